"""The LiDAR's beam spot at a disc's rim, read from the sweep's own mixed returns (beyond the paper).

A beam whose spot straddles the disc's rim returns a range between the disc and the background
(energy-mixing scanners). With a spot about one beam spacing wide that touches one or two
beams per rim crossing; with a wide spot (large exit window or divergence) the *mixed band*
around the disc is many beams and scan lines wide, and :func:`lidarcal.measure.measure_disc`
must look that far for the rim and the background behind it. Nothing here is a rig constant:

* :func:`grid_spacing_mm` -- the spacing of the beams on the disc plane along the grid's two
  axes (scan lines, beams), from the disc's own hits;
* :func:`background_plane` -- the background behind the disc (RANSAC plane of the returns
  behind the disc plane in a ring as wide as the disc), so a mixed beam's background range is
  its ray's range to that plane, even where the sweep ends inside the mixed band;
* :func:`mixed_band_mm` -- how far from the disc hits the returns stay mixed (in front of the
  background by more than the noise, on at least half the beams at that distance);
* :func:`spot_sigma_mm` -- the spot's 1-sigma across the beam, from the mixed returns' disc
  fraction ``f`` against their distance ``x`` from the fitted rim: for a Gaussian spot the edge
  spread function is ``f = Phi(-x / sigma_r)``, so ``x = x0 - sigma_r Phi^-1(f)`` (probit
  regression); ``sigma_r`` is the spot's sigma ``sigma0`` stretched on the tilted disc plane;
* :func:`curvature_offset_mm` -- a spot centred on a convex rim has less than half of itself on
  the disc: the half-share contour of a disc of radius ``R`` lies ``delta = sigma_t^2 / (2 R)``
  inside the rim (``sigma_t`` the spot's sigma along the rim on the disc plane; first order in
  ``sigma / R``, from ``P(X < -Y^2 / (2R)) = 1/2 - phi(0) E[Y^2] / (2 R sigma_r)``).

The spot on the disc plane: a round spot of sigma ``sigma0`` across the beam ``b`` maps onto a
plane with basis ``B`` (2, 3) with covariance ``sigma0^2 M^-1``, ``M = I - c c^T``, ``c = B b``;
``M^-1 = I + c c^T / (1 - |c|^2)`` (Sherman-Morrison), ``1 - |c|^2 = cos^2(incidence)``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.special import ndtri

from .geometry import MAD_TO_SIGMA, Plane

#: a background plane needs this share of the ring's returns behind the disc within its noise
#: band (the rest: mixed returns in front of it) ...
BACKGROUND_MIN_SHARE = 0.25
#: ... and at most this share beyond it (a background that is not one plane; spurious ranges)
BACKGROUND_MAX_BEYOND = 0.1
#: the mixed band ends at the first distance where fewer than this share of the beams are mixed
BAND_MIN_SHARE = 0.5
#: a spot sigma beyond this share of the disc's radius is not trusted (module docstring)
MAX_SIGMA_RADIUS = 0.25
#: disc fractions used by the probit regression (beyond them Phi^-1 amplifies range noise)
F_RANGE = (0.05, 0.95)


def grid_spacing_mm(points: np.ndarray, hits: np.ndarray) -> tuple[float, float]:
    """Median spacing (mm) of the disc hits' points (P, B, 3) between scan lines and between beams."""
    out = []
    for axis in (0, 1):
        a = hits & np.roll(hits, -1, axis=axis)
        if axis == 0:
            a[-1] = False
        else:
            a[:, -1] = False
        d = np.linalg.norm(np.roll(points, -1, axis=axis)[a] - points[a], axis=-1)
        out.append(float(np.median(d)) if len(d) else float("nan"))
    return out[0], out[1]


def ray_range_to_plane(origin: np.ndarray, direction: np.ndarray, plane: Plane) -> np.ndarray:
    """Range (P, B) along every beam ``origin[i] + s direction[i, j]`` to ``plane`` (NaN if behind)."""
    den = np.einsum("pbi,i->pb", direction, plane.normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (plane.d - origin @ plane.normal)[:, None] / den
    return np.where((np.abs(den) > 1e-9) & (s > 0), s, np.nan)


def ring(hits: np.ndarray, cells: tuple[int, int]) -> np.ndarray:
    """Cells within ``cells`` (rows, columns) of a disc hit (a box dilation), hits excluded."""
    ni, nj = (max(int(c), 1) for c in cells)
    box = ndimage.maximum_filter(hits.astype(np.uint8), size=(2 * ni + 1, 2 * nj + 1), mode="constant")
    return (box > 0) & ~hits


def background_plane(points: np.ndarray, behind: np.ndarray, hits: np.ndarray, spacing_mm: tuple[float, float],
                     tol_mm: float, fit, viewpoint: np.ndarray) -> Plane | None:
    """The background behind the disc, a plane through the returns behind it in a ring as wide as
    the disc's radius (``fit``: a robust plane fit ``fit(points, tol) -> Plane``). Mixed returns
    lie between the disc and it, never beyond (seen from ``viewpoint``, the LiDAR): ``None``
    (no planar background) when fewer than :data:`BACKGROUND_MIN_SHARE` of the returns lie on
    it or more than :data:`BACKGROUND_MAX_BEYOND` beyond it."""
    radius = np.sqrt(hits.sum() * spacing_mm[0] * spacing_mm[1] / np.pi)
    cells = tuple(int(np.ceil(radius / s)) if np.isfinite(s) and s > 0 else 1 for s in spacing_mm)
    pts = points[behind & ring(hits, cells)]
    if len(pts) < 30:
        return None
    try:
        pl = fit(pts, tol_mm)
    except ValueError:
        return None
    d = pl.distance(pts) * -np.sign(pl.distance(np.asarray(viewpoint, float)[None])[0])  # + = beyond
    on, beyond = np.mean(np.abs(d) < tol_mm), np.mean(d >= tol_mm)
    return pl if on >= BACKGROUND_MIN_SHARE and beyond <= BACKGROUND_MAX_BEYOND else None


def mixed_band_mm(mixed: np.ndarray, in_sweep: np.ndarray, hits: np.ndarray,
                  spacing_mm: tuple[float, float]) -> float:
    """How far (mm, on the disc plane's grid) from the disc hits the returns stay mixed: the
    distance bins (one grid spacing wide) from the hits outwards while at least
    :data:`BAND_MIN_SHARE` of the sweep's beams in the bin are mixed (module docstring)."""
    if not np.all(np.isfinite(spacing_mm)):
        return 0.0
    dist = ndimage.distance_transform_edt(~hits, sampling=spacing_mm)
    h = max(spacing_mm)
    extent = 0.0
    for b in range(1000):
        sel = in_sweep & ~hits & (dist > b * h) & (dist <= (b + 1) * h)
        if not sel.any() or np.mean(mixed[sel]) < BAND_MIN_SHARE:
            break
        extent = (b + 1) * h
    return extent


def _c(basis: np.ndarray, beam: np.ndarray) -> np.ndarray:
    return beam @ basis.T  # (n, 2): the beam's components along the disc plane's axes


def stretch2(direction: np.ndarray, basis: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """``e^T M^-1 e`` per row: the squared stretch, on the disc plane along unit ``direction``
    (n, 2), of a spot round across unit ``beam`` (n, 3) (module docstring)."""
    c = _c(basis, beam)
    cos2 = np.maximum(1.0 - np.sum(c * c, axis=1), 1e-3)
    return 1.0 + np.einsum("ki,ki->k", c, direction) ** 2 / cos2


def spot_sigma_mm(f: np.ndarray, xy: np.ndarray, beam: np.ndarray, basis: np.ndarray,
                  centre: np.ndarray, radius: float, min_returns: int = 20) -> tuple[float, int]:
    """The spot's 1-sigma across the beam (mm) and the number of mixed returns it rests on.

    ``f`` (n,): the mixed returns' disc fractions; ``xy`` (n, 2): their beams' points on the disc
    plane; ``beam`` (n, 3): their directions. Probit regression ``x = x0 - sigma0 a Phi^-1(f)``,
    ``x`` the distance outside the circle (``centre``, ``radius``), ``a`` the radial stretch
    (:func:`stretch2`); refitted once without residuals beyond 4 robust sigmas. NaN (no spot
    seen) with fewer than ``min_returns`` usable returns (a first-echo scanner's few stray
    mixed ranges), a non-positive slope, or a sigma beyond :data:`MAX_SIGMA_RADIUS` of the
    radius (the first-order curvature term no longer holds).
    """
    ok = (f > F_RANGE[0]) & (f < F_RANGE[1])
    if ok.sum() < max(min_returns, 20):
        return float("nan"), int(ok.sum())
    v = xy[ok] - centre
    rho = np.linalg.norm(v, axis=1)
    x = rho - radius
    a = np.sqrt(stretch2(v / np.maximum(rho, 1e-12)[:, None], basis, beam[ok]))
    A = np.column_stack([np.ones(len(x)), -a * ndtri(f[ok])])
    keep = np.ones(len(x), bool)
    for _ in range(2):
        coef = np.linalg.lstsq(A[keep], x[keep], rcond=None)[0]
        res = x - A @ coef
        keep = np.abs(res) <= 4.0 * max(MAD_TO_SIGMA * np.median(np.abs(res[keep])), 1e-9)
    sigma0 = float(coef[1])
    return (sigma0 if 0 < sigma0 <= MAX_SIGMA_RADIUS * radius else float("nan")), int(keep.sum())


def curvature_offset_mm(sigma0: float, radial: np.ndarray, beam: np.ndarray, basis: np.ndarray,
                        radius: float, weights: np.ndarray) -> float:
    """``delta = mean(sigma_t^2) / (2 R)``: how far inside the rim the half-share contour lies
    (module docstring); ``sigma_t^2 = sigma0^2 t^T M^-1 t`` at each rim crossing (``radial``
    (n, 2) its unit radial direction, ``t`` the tangent), averaged with the circle fit's
    ``weights``. 0 when the spot was not seen (``sigma0`` NaN)."""
    if not np.isfinite(sigma0) or radius <= 0 or len(radial) == 0:
        return 0.0
    t = np.column_stack([-radial[:, 1], radial[:, 0]])
    st2 = sigma0 ** 2 * stretch2(t, basis, beam)
    return float(np.sum(weights * st2) / np.sum(weights) / (2.0 * radius))
