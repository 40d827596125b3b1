"""The stripe's brightness along itself: the squares' black/white reflectance ratio and the
stripe frames' blur beyond board.png's (section 1.3 on real captures).

:func:`reflectance_ratio` finds how much darker the stripe is on black squares than on white
ones, so that the stripe centres can divide the squares' albedo out
(:mod:`lidarcal.stripe_profile`).

The stripe centres divide out the squares' albedo with a blackness map taken from
``board.png`` (:func:`lidarcal.board.board_blackness`), whose edges carry that image's own
blur. Stripe frames are often blurrier: taken in the dark with the aperture opened (less
depth of field), refocused, or smeared by a long exposure. The stripe's brightness then
changes more gently across a square edge than the map says, and dividing by the sharp map
pulls every centre near an edge (0.26 mm of centre error on a harsh rig with 2 px of extra
blur, against 0.06 mm). The extra blur is seen in the stripe's brightness along itself:
:func:`albedo_blur` fits the reflectance model of :func:`lidarcal.stripe.reflectance_ratio`
with the blackness under the stripe smoothed along it by a Gaussian, over a grid of widths,
and :func:`blur_blackness` gives the boards' maps that blur.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np


def reflectance_ratio(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                      min_contrast: float = 0.5) -> float | None:
    """The stripe's black/white reflectance ratio ``rho`` from its brightness along the stripe.

    Each element of ``samples`` is one stripe: column position ``x``, signal
    mass of the column profile and the effective blackness ``b`` under it.
    Model: ``log mass = p(x) + log(1 - (1 - rho) b)`` with a quadratic
    ``p`` per stripe (range and incidence change slowly along it); ``rho``
    by a grid search minimising the sum of absolute residuals (speckle and
    albedo noise are heavy-tailed). None when the blackness under the
    stripes spans less than ``min_contrast`` (the ratio is then not seen).
    """
    groups = _seen(samples, min_contrast)
    return None if groups is None else grid_minimum(RATIO_GRID, ratio_costs(groups, RATIO_GRID))


def _seen(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]], min_contrast: float
          ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None:
    """The stripes of ``samples`` with at least 10 samples, or None when there are none or the
    blackness under them spans less than ``min_contrast`` (5-95 %: the ratio is not seen)."""
    groups = [(x, m, b) for x, m, b in samples if x is not None and len(x) >= 10]
    if not groups:
        return None
    b5, b95 = np.percentile(np.concatenate([b for _, _, b in groups]), [5, 95])
    return groups if b95 - b5 >= min_contrast else None


def grid_minimum(grid: np.ndarray, cost: np.ndarray) -> float:
    """The minimum of ``cost`` over the evenly spaced ``grid``, refined by a parabola through
    the lowest point and its neighbours (a step of at most one grid spacing)."""
    i = int(np.argmin(cost))
    if 0 < i < len(grid) - 1:  # parabolic refinement
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        den = c0 - 2 * c1 + c2
        step = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        return float(grid[i] + np.clip(step, -1, 1) * (grid[1] - grid[0]))
    return float(grid[i])


#: the grid of black/white reflectance ratios :func:`reflectance_ratio` searches
RATIO_GRID = np.linspace(0.02, 1.0, 99)


def ratio_costs(groups: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                grid: np.ndarray = RATIO_GRID) -> np.ndarray:
    """The L1 cost of :func:`reflectance_ratio`'s model at each ratio of ``grid`` (summed over
    the stripes ``groups``: ``(x, mass, blackness)``, at least a few samples each)."""
    cost = np.zeros(len(grid))
    for x, m, b in groups:
        ok = m > 0
        x, lm, b = x[ok], np.log(m[ok]), b[ok]
        u = (x - x.mean()) / max(np.ptp(x), 1.0)
        A = np.column_stack([np.ones_like(u), u, u * u])
        pinv = np.linalg.pinv(A)
        # all grid values at once: column g of Y is the model's left side for rho = grid[g]
        Y = lm[:, None] - np.log(1.0 - (1.0 - grid)[None, :] * b[:, None])
        res = Y - _times(A, _times(pinv, Y))
        # one reweighting step towards an L1 fit (weighted normal equations, 3 x 3 per column)
        w = 1.0 / np.maximum(np.abs(res), 1e-3)
        M = np.empty((len(grid), 3, 3))
        for i in range(3):
            for j in range(i, 3):
                M[:, i, j] = M[:, j, i] = _times((A[:, i] * A[:, j])[None, :], w)[0]
        rhs = _times(A.T, w * Y).T
        coef = np.linalg.solve(M, rhs[:, :, None])[:, :, 0]
        cost += np.abs(Y - _times(A, coef.T)).sum(0)
    return cost


def _times(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for a short inner or outer dimension (``a`` (p, n), ``b`` (n, q), p or n
    at most a few) by ``np.einsum``'s own loops on contiguous operands (the sums in the
    order of broadcast sums, bit for bit): no multi-threaded BLAS call, whose spinning
    threads cost more CPU than these small products."""
    return np.einsum("ij,jk->ik", np.ascontiguousarray(a), np.ascontiguousarray(b))


#: Gaussian sigmas (px) of extra blur tried by :func:`albedo_blur`
BLUR_GRID_PX = np.arange(0.0, 4.01, 0.5)
#: blur below this (px) is left alone: the map is used as it is
MIN_BLUR_PX = 0.75
#: the model with blur must lower the fit's L1 cost by at least this share to be taken
MIN_COST_GAIN = 0.01
#: the ratios searched while the blur is chosen (every 4th of the full grid)
_COARSE = RATIO_GRID[::4]


def smooth_along(x: np.ndarray, b: np.ndarray, sigma: float) -> np.ndarray:
    """``b`` sampled at the integer positions ``x`` (ascending, gaps allowed) smoothed by a
    Gaussian of ``sigma`` samples along ``x`` (normalised convolution: gaps do not count)."""
    if sigma <= 0 or len(x) == 0:
        return b
    k = np.rint(x - x.min()).astype(int)
    val = np.zeros((1, k.max() + 1), np.float32)
    w = np.zeros_like(val)
    val[0, k], w[0, k] = b, 1.0
    sv = cv2.GaussianBlur(val, (0, 0), sigmaX=sigma, sigmaY=1e-6, borderType=cv2.BORDER_CONSTANT)
    sw = cv2.GaussianBlur(w, (0, 0), sigmaX=sigma, sigmaY=1e-6, borderType=cv2.BORDER_CONSTANT)
    return (sv[0, k] / np.maximum(sw[0, k], 1e-6)).astype(np.float64)


def _groups(samples: list, sigma: float) -> list:
    return [(x, m, smooth_along(x, b, sigma)) for x, m, b in samples]


def albedo_blur(samples: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
                min_contrast: float = 0.5) -> tuple[float | None, float]:
    """``(rho, blur_px)``: the stripe's black/white reflectance ratio and the stripe frames'
    Gaussian blur (sigma, px) beyond the blackness map's.

    ``samples`` as for :func:`lidarcal.stripe.reflectance_ratio` (per stripe: position along
    it, signal mass, blackness under it). Model: ``log mass = p(x) + log(1 - (1 - rho)
    (G_s * b))``, ``G_s *`` a Gaussian of sigma ``s`` along the stripe; ``s`` on
    ``BLUR_GRID_PX`` (each with its best ``rho``), refined by a parabola,
    then ``rho`` on the full grid at that ``s``. The blur is 0 unless it lowers the L1 cost
    by ``MIN_COST_GAIN`` (checked first at 1.5 px, so a sharp capture costs two evaluations)
    and reaches ``MIN_BLUR_PX``. ``rho`` is None when the ratio is not seen (as there).
    """
    groups = _seen(samples, min_contrast)
    if groups is None:
        return None, 0.0

    def cost(s: float, grid: np.ndarray = _COARSE) -> float:
        return float(ratio_costs(_groups(groups, s), grid).min())

    c0 = cost(0.0)
    blur = 0.0
    if cost(1.5) < (1.0 - MIN_COST_GAIN) * c0:
        # each width with its best ratio on the full grid (the coarse one's steps are as
        # large as the differences between neighbouring widths on a speckled stripe)
        costs = np.array([cost(s, RATIO_GRID) for s in BLUR_GRID_PX])
        c0 = costs[0]
        s = grid_minimum(BLUR_GRID_PX, costs)
        if s >= MIN_BLUR_PX and costs.min() < (1.0 - MIN_COST_GAIN) * c0:
            blur = s
    g = _groups(groups, blur)
    return grid_minimum(RATIO_GRID, ratio_costs(g, RATIO_GRID)), blur


def blur_blackness(boards: tuple, sigma: float) -> tuple:
    """The boards (:class:`lidarcal.board.BoardView`) with their blackness maps blurred by a
    Gaussian of ``sigma`` px (the stripe frames' extra blur, :func:`albedo_blur`); as they
    are when ``sigma`` is 0 or a board has no map."""
    if sigma <= 0:
        return boards
    return tuple(b if b.blackness is None else
                 replace(b, blackness=cv2.GaussianBlur(b.blackness, (0, 0), sigma))
                 for b in boards)
