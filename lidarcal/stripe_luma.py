"""The laser stripe on the photo's full-resolution luma, the lit board predicted and removed.

A colour photo's laser response (:func:`lidarcal.laser_colour.laser_response`, the
colour excess ``R - (G + B) / 2`` of a red laser) is made of chroma only: JPEG stores
chroma at half resolution (4:2:0) and quantises it coarsely in 16 x 16 px blocks, and a
Bayer sensor samples red on a quarter of its pixels. The luma ``Y`` (ITU-R BT.601, what
JPEG stores at full resolution) sees the laser too, but also the lit chessboard's black
and white squares. Here that board is predicted and subtracted:

(L1) board coordinates ``(u, v)`` (squares) of each pixel near the stripe: its ray meets
     the board's plane (eq. 5, the PnP pose), the detected corners' residuals to that pose
     removed first (bilinear over the corner grid): the squares' edges pass through the
     detected corners;
(L2) the white share of a chessboard blurred by a separable Gaussian of scale
     ``sigma_e``: ``W = 1/2 + 1/2 p erf(d_u / (sqrt 2 sigma_e)) erf(d_v / (sqrt 2
     sigma_e))``, ``d_u, d_v`` the signed px distances to the nearest edge lines, ``p =
     +-1`` by the squares' parity; white beyond the pattern (the printed border);
(L3) ``Y = a(t, s) + c(t, s) W + g1 W (1 - W) + g2 W (1 - W) (2 W - 1) + sum_k e_k dW/dn_k
     + h1 LoG1(W) + h2 LoG2(W)``: black level ``a`` and contrast ``c`` linear across the
     stripe (``s``) and piecewise linear along it (``t``, knots half a square apart); the
     camera's tone curve at the edges (``g``); a shift ``e_k`` of each edge line ``k`` along
     its image normal (the corners' sub-pixel error between them); the camera's sharpening
     (``h``, Laplacians of the blurred ``W``, an unsharp mask). Linear least squares over
     the pixels of a band about the stripe outside its core (``|s| >= r_in``), one robust
     re-fit; the parity and ``sigma_e`` are chosen by the fit's rms;
(L4) the luma response ``Y - model`` in the band (zero elsewhere), averaged along the
     stripe as the colour response is, gives the centres by the same detector and gates
     (:func:`luma_stripe`).

Measured on the semi-real JPEG photos (q 90, 4:2:0, Bayer; scripts/semireal_laser.py): the
centres' error against the true stripe 0.225 px on the colour response, 0.141 px on the
luma response read at the colour stripe's width, 0.124 px at its own (:func:`luma_width`);
the board model fits the luma beside the stripe to ~2-3 DN rms.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import sparse
from scipy.ndimage import map_coordinates

from .camera import backproject_to_plane, project_points
from .geometry import MAD_TO_SIGMA
from .io.dataset import BoardSpec, CameraModel

#: edge spread scales tried (px): the Gaussian that with the pixel's box blurs an edge
EDGE_SIGMAS = (0.3, 0.45, 0.6, 0.8, 1.1, 1.5, 2.0, 3.0)
#: at most this many pixels enter the board model's fit (evenly spaced), and every
#: SELECT_STRIDE-th of them the choice of the squares' parity and the edge spread
MAX_FIT_PX = 60_000
SELECT_STRIDE = 4


@dataclass
class LumaBackground:
    """The luma response (float32, image shape, zero off the band), the board model's fit
    rms (DN) outside the stripe's core, the edge scale used (px), and the band (bool)."""

    response: np.ndarray
    fit_rms_dn: float
    sigma_e_px: float
    band: np.ndarray


def luma(image: np.ndarray) -> np.ndarray:
    """``Y`` of ITU-R BT.601 (JPEG's luma), float32, of a BGR image; a gray image as is."""
    img = np.asarray(image)
    if img.ndim == 2:
        return img.astype(np.float32)
    return cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2YCrCb)[..., 0].astype(np.float32)


def _stripe_frame(centres: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(centre point, unit direction t, unit normal n, quadratic coefficients of s(t))
    of the centres (N, 2): the stripe as ``s = q(t)`` in the frame of its principal axis."""
    c = centres.mean(0)
    _, _, vt = np.linalg.svd(centres - c, full_matrices=False)
    t_hat = vt[0]
    n_hat = np.array([-t_hat[1], t_hat[0]])
    t = (centres - c) @ t_hat
    s = (centres - c) @ n_hat
    q = np.polyfit(t, s, 2 if len(t) >= 10 else 1)
    return c, t_hat, n_hat, q


def _corner_residual_field(camera: CameraModel, view, board: BoardSpec) -> np.ndarray:
    """The detected corners' residual to the PnP pose's projection, (rows, cols, 2) px, for
    its bilinear interpolation over the corner grid (L1)."""
    obj = board.object_points()
    proj = project_points(camera, obj @ view.R_pnp.T + view.T_pnp)
    c, r = board.inner_corners
    return (np.asarray(view.corners_px, float) - proj).reshape(r, c, 2)


def _bilinear(grid: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``grid`` (rows, cols, 2) at fractional corner indices (u: column, v: row), bilinear,
    clamped to the grid (``scipy.ndimage.map_coordinates``, order 1, mode nearest)."""
    at = np.vstack([np.asarray(v, float), np.asarray(u, float)])
    return np.column_stack([map_coordinates(grid[..., k], at, order=1, mode="nearest")
                            for k in range(grid.shape[2])])


def board_coordinates(camera: CameraModel, view, board: BoardSpec, px: np.ndarray
                      ) -> np.ndarray:
    """(L1) board coordinates (N, 2) in squares of the pixels ``px`` (N, 2): rays met with
    the board's plane (PnP pose), the corners' residuals to that pose removed first
    (bilinear over the corner grid, two fixed-point steps)."""
    field = _corner_residual_field(camera, view, board)
    R, T, sq = view.R_pnp, np.ravel(view.T_pnp), board.square_mm
    p = np.asarray(px, float)
    uv = None
    for _ in range(3):
        q = p if uv is None else p - _bilinear(field, uv[:, 0], uv[:, 1])
        X = backproject_to_plane(camera, q, view.plane_pnp)
        uv = ((X - T) @ R)[:, :2] / sq
    return uv


def _hat_basis(t: np.ndarray, knots: np.ndarray) -> sparse.csr_matrix:
    """Piecewise-linear (hat) functions of ``t`` on ``knots`` (N, K, sparse: two per row),
    a partition of unity."""
    k = np.clip(np.searchsorted(knots, t) - 1, 0, len(knots) - 2)
    f = np.clip((t - knots[k]) / (knots[k + 1] - knots[k]), 0.0, 1.0)
    n = len(t)
    rows = np.repeat(np.arange(n), 2)
    cols = np.column_stack([k, k + 1]).ravel()
    vals = np.column_stack([1 - f, f]).ravel()
    return sparse.csr_matrix((vals, (rows, cols)), shape=(n, len(knots)))


def luma_background(image: np.ndarray, camera: CameraModel, view, board: BoardSpec,
                    centres: np.ndarray, width_px: float, side_px: float,
                    mask: np.ndarray) -> LumaBackground | None:
    """(L1)-(L4): the luma response about the stripe through ``centres`` (N, 2), or None
    when too few board pixels lie beside it.

    ``width_px``: the stripe's width (FWHM); the core ``|s| < r_in`` with
    ``r_in = 2 width + 1`` is left out of the fit, the band reaches ``r_in + max(2 width,
    side / 4)``; ``side_px``: a square's side (knots along the stripe half of it).
    """
    Y = luma(image)
    H, W_img = Y.shape
    c0, t_hat, n_hat, q = _stripe_frame(np.asarray(centres, float))
    r_in = 2.0 * float(width_px) + 1.0
    r_out = r_in + max(2.0 * float(width_px), side_px / 4.0)
    t_c = (centres - c0) @ t_hat
    t_lo, t_hi = t_c.min() - 2.0, t_c.max() + 2.0
    pad = int(np.ceil(r_out)) + 4
    x0 = max(int(np.floor(centres[:, 0].min())) - pad, 0)
    x1 = min(int(np.ceil(centres[:, 0].max())) + pad + 1, W_img)
    y0 = max(int(np.floor(centres[:, 1].min())) - pad, 0)
    y1 = min(int(np.ceil(centres[:, 1].max())) + pad + 1, H)
    ys, xs = np.mgrid[y0:y1, x0:x1]
    P = np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    t = (P - c0) @ t_hat
    s = (P - c0) @ n_hat - np.polyval(q, t)
    reach = r_out + 3 * max(EDGE_SIGMAS) + 2
    near = (np.abs(s) <= reach) & (t >= t_lo - reach) & (t <= t_hi + reach)
    crop_m = np.asarray(mask, bool)[y0:y1, x0:x1].ravel()
    band = near & (np.abs(s) <= r_out) & (t >= t_lo) & (t <= t_hi) & crop_m
    fit = band & (np.abs(s) >= r_in)
    yv = Y[y0:y1, x0:x1].ravel()
    if fit.sum() < 50:
        return None
    # (L1): board coordinates (squares) of the pixels near the stripe and their image
    # gradients (the image normals of the two families of edge lines, px per square)
    uv = board_coordinates(camera, view, board, P[near])
    U = np.full(ys.shape, np.nan)
    V = np.full(ys.shape, np.nan)
    U.ravel()[near], V.ravel()[near] = uv[:, 0], uv[:, 1]
    gu = np.stack(np.gradient(U)[::-1], -1).reshape(-1, 2)[near]  # (d/dx, d/dy)
    gv = np.stack(np.gradient(V)[::-1], -1).reshape(-1, 2)[near]
    ok = np.isfinite(gu).all(1) & np.isfinite(gv).all(1)
    band &= _scatter(ok, near, ys.size)
    fit &= band
    knots = np.arange(t_lo, t_hi + side_px / 2, side_px / 2) if t_hi - t_lo > side_px / 2 \
        else np.array([t_lo, t_hi])
    if knots[-1] < t_hi:
        knots = np.append(knots, t_hi)
    gu, gv = np.nan_to_num(gu), np.nan_to_num(gv)
    labels = _edge_labels(uv, gu, gv, board)
    at = np.full(ys.size, -1)
    at[near] = np.arange(int(near.sum()))  # crop pixel -> its row in uv, gu, gv
    lines = np.unique(labels[at[band]])
    lines = lines[lines >= 0]
    n_u = board.inner_corners[0] + 2
    uv_mid = np.array(board.inner_corners, float) / 2 - 0.5

    def design(idx: np.ndarray, parity: int, sig: float, lap: list[np.ndarray]) -> np.ndarray:
        j = at[idx]
        w, dwu, dwv, out = white_share_blurred(uv[j], gu[j], gv[j], board, parity, sig)
        E = _edge_design(dwu, dwv, uv[j] - uv_mid, labels[j], lines, n_u)
        return sparse.hstack([_design(t[idx], s[idx], w, knots, r_out), E,
                              sparse.csr_matrix(np.column_stack([v[idx] for v in lap] + [out]))],
                             format="csr")

    def laplacians(parity: int, sig: float) -> list[np.ndarray]:
        # the camera's sharpening: an unsharp mask adds the (negative) Laplacian of the
        # blurred edges, at the edge scale and twice it
        w, _, _, out = white_share_blurred(uv, gu, gv, board, parity, sig)
        img_w = _scatter((w + out).astype(np.float32), near, ys.size).reshape(ys.shape)
        return [cv2.Laplacian(cv2.GaussianBlur(img_w, (0, 0), f * sig), cv2.CV_32F).ravel()
                for f in (0.7, 1.5)]

    fit_idx = np.flatnonzero(fit)
    fit_idx = fit_idx[::max(1, len(fit_idx) // MAX_FIT_PX)]
    pick = fit_idx[::SELECT_STRIDE] if len(fit_idx) >= 50 * SELECT_STRIDE else fit_idx
    best = None
    for parity in (0, 1):  # the squares' colours, and the edge spread: least squares
        for sig in EDGE_SIGMAS:
            lap = laplacians(parity, sig)
            A = design(pick, parity, sig, lap)
            coef, keep = _robust_lstsq(A, yv[pick], _smoothness(len(knots), len(lines), A.shape[1]))
            r = yv[pick] - design(pick, parity, sig, lap) @ coef
            rms = float(np.sqrt(np.mean(r[keep] ** 2)))
            if best is None or rms < best[0]:
                best = (rms, parity, sig)
    _, parity, sig = best
    lap = laplacians(parity, sig)
    A = design(fit_idx, parity, sig, lap)
    coef, keep = _robust_lstsq(A, yv[fit_idx], _smoothness(len(knots), len(lines), A.shape[1]))
    rms = float(np.sqrt(np.mean((yv[fit_idx][keep] - A[keep] @ coef) ** 2)))
    resp = np.zeros((H, W_img), np.float32)
    bandimg = np.zeros((H, W_img), bool)
    rc = np.zeros(ys.size, np.float32)
    b_idx = np.flatnonzero(band)
    for k0 in range(0, len(b_idx), MAX_FIT_PX):  # (L4), in chunks
        idx = b_idx[k0:k0 + MAX_FIT_PX]
        rc[idx] = yv[idx] - design(idx, parity, sig, lap) @ coef
    resp[y0:y1, x0:x1] = rc.reshape(ys.shape)
    bandimg[y0:y1, x0:x1] = band.reshape(ys.shape)
    return LumaBackground(resp, rms, sig, bandimg)


def _scatter(values: np.ndarray, where: np.ndarray, n: int) -> np.ndarray:
    out = np.zeros(n, np.asarray(values).dtype)
    out[where] = values
    return out


def white_share_blurred(uv: np.ndarray, gu: np.ndarray, gv: np.ndarray, board: BoardSpec,
                        white_parity: int, sigma_px: float
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(L2) the white share of pixels at board coordinates ``uv`` (squares) under a Gaussian
    edge spread of ``sigma_px``, its derivatives for a shift (px) of the nearest ``u`` and
    ``v`` edge lines along their image normals, and the share beyond the pattern.

    Near a corner the chessboard is ``1/2 + 1/2 p sgn(d_u) sgn(d_v)`` (``d``: signed px
    distances to the nearest lines, ``(u - round u) / |grad u|``, ``p = +-1`` by the
    squares' parity); a separable Gaussian turns each sign into ``erf(d / (sqrt 2
    sigma))``. Beyond the pattern's outer squares lies the board's border (its own level,
    not always white: the last array, blurred alike).
    """
    from scipy.special import erf

    c, r = board.inner_corners
    nu = np.maximum(np.linalg.norm(gu, axis=1), 1e-9)
    nv = np.maximum(np.linalg.norm(gv, axis=1), 1e-9)
    ru, rv = np.round(uv[:, 0]), np.round(uv[:, 1])
    du, dv = (uv[:, 0] - ru) / nu, (uv[:, 1] - rv) / nv
    k = 1.0 / (np.sqrt(2.0) * sigma_px)
    gu_, gv_ = erf(k * du), erf(k * dv)
    p = np.where((ru + rv + white_parity) % 2 == 0, 1.0, -1.0)
    w = 0.5 + 0.5 * p * gu_ * gv_
    dg = lambda d: (2 * k / np.sqrt(np.pi)) * np.exp(-(k * d) ** 2)
    dwu, dwv = 0.5 * p * dg(du) * gv_, 0.5 * p * gu_ * dg(dv)
    # inside the pattern (soft): its outer lines u = -1, u = c, v = -1, v = r
    ins = (0.5 * (1 + erf(k * (uv[:, 0] + 1) / nu)) * 0.5 * (1 + erf(k * (c - uv[:, 0]) / nu))
           * 0.5 * (1 + erf(k * (uv[:, 1] + 1) / nv)) * 0.5 * (1 + erf(k * (r - uv[:, 1]) / nv)))
    return ins * w, ins * dwu, ins * dwv, 1.0 - ins


def _edge_labels(uv: np.ndarray, gu: np.ndarray, gv: np.ndarray, board: BoardSpec
                 ) -> np.ndarray:
    """Per pixel, the edge line it lies nearest (in px) as an index into the lines
    ``u = -1..c`` then ``v = -1..r`` of the pattern, or -1 when none is within 3 px."""
    c, r = board.inner_corners
    du = np.abs(uv[:, 0] - np.round(uv[:, 0])) / np.maximum(np.linalg.norm(gu, axis=1), 1e-9)
    dv = np.abs(uv[:, 1] - np.round(uv[:, 1])) / np.maximum(np.linalg.norm(gv, axis=1), 1e-9)
    ku, kv = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    lab = np.where(du <= dv, ku + 1, (c + 2) + kv + 1)
    ok = np.where(du <= dv, (ku >= -1) & (ku <= c) & (du < 3), (kv >= -1) & (kv <= r) & (dv < 3))
    ok &= np.isfinite(du) & np.isfinite(dv)
    return np.where(ok, lab, -1)


def _edge_design(dwu: np.ndarray, dwv: np.ndarray, uv: np.ndarray, labels: np.ndarray,
                 lines: np.ndarray, n_u_lines: int) -> sparse.csr_matrix:
    """Columns of a shift and a turn of each edge line along its image normal (the white
    share's derivative there, and that times the position along the line, in squares
    from the pattern's middle): two columns per line of ``lines`` (:func:`_edge_labels`),
    sparse."""
    col = np.searchsorted(lines, labels)
    on = (labels >= 0) & (col < len(lines))
    on[on] &= lines[col[on]] == labels[on]
    rows = np.flatnonzero(on)
    is_u = labels[rows] < n_u_lines
    vals = np.where(is_u, dwu[rows], dwv[rows])
    along = np.where(is_u, uv[rows, 1], uv[rows, 0])
    n = len(lines)
    return sparse.csr_matrix((np.concatenate([vals, vals * (along - along.mean() if len(along)
                                                            else along)]),
                              (np.concatenate([rows, rows]),
                               np.concatenate([col[rows], n + col[rows]]))),
                             shape=(len(labels), 2 * n))


def _design(t: np.ndarray, s: np.ndarray, w: np.ndarray, knots: np.ndarray,
            r_out: float) -> sparse.csr_matrix:
    """(L3) the design matrix of ``a(t, s) + c(t, s) W`` (hats in ``t`` times (1, s)) and
    the edges' tone curve (``W (1 - W)``, ``W (1 - W) (2 W - 1)``, global), sparse."""
    B = _hat_basis(t, knots)
    sn = s / r_out
    tone = np.column_stack([w * (1 - w), w * (1 - w) * (2 * w - 1)])
    return sparse.hstack([B, sparse.diags(sn) @ B, sparse.diags(w) @ B,
                          sparse.diags(w * sn) @ B, sparse.csr_matrix(tone)], format="csr")


def _smoothness(n_knots: int, n_lines: int, n_cols: int) -> sparse.csr_matrix:
    """Prior rows (weight 1, i.e. one pixel's residual of 1 DN) on the hat coefficients of
    :func:`_design`: their second differences along the stripe vanish, and the terms
    linear across it (``s``) vanish; and on the edge lines' shifts (they vanish: the edge
    through the corners). Where the band's pixels fix them (hundreds per knot) the prior
    does not count; a knot the band leaves without pixels beside the stripe (its end, the
    board's edge on one side), or an edge hidden under the stripe's core (it runs along the
    stripe), follows its neighbours or the corners instead of taking any value in the
    core."""
    K = n_knots
    D = sparse.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(K - 2, 0), K))
    Z = sparse.csr_matrix((D.shape[0], K))
    I0, I1 = sparse.csr_matrix((K, K)), sparse.identity(K)
    rows = [sparse.hstack([D if g == j else Z for j in range(4)]) for g in range(4)]
    rows += [sparse.hstack([I1 if g == j else I0 for j in range(4)]) for g in (1, 3)]
    P = sparse.vstack(rows).tocsr()
    P = sparse.hstack([P, sparse.csr_matrix((P.shape[0], n_cols - 4 * K))], format="csr")
    e0 = 4 * K + 2  # the edge shifts follow the hats and the two tone terms
    E = sparse.csr_matrix((np.ones(2 * n_lines), (np.arange(2 * n_lines),
                                                  e0 + np.arange(2 * n_lines))),
                          shape=(2 * n_lines, n_cols))
    return sparse.vstack([P, E], format="csr")


def _robust_lstsq(A: sparse.csr_matrix, y: np.ndarray, prior: sparse.csr_matrix | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Least squares by the normal equations (columns scaled to unit norm; ``prior``: rows
    with zero targets added), then again without the points beyond 3.5 robust sigmas;
    (coefficients, points kept)."""
    keep = np.ones(len(y), bool)
    coef = np.zeros(A.shape[1])
    for _ in range(2):
        Ak = A[keep]
        scale = np.sqrt(np.asarray(Ak.multiply(Ak).sum(axis=0)).ravel())
        scale[scale == 0] = 1.0
        As = Ak @ sparse.diags(1.0 / scale)
        N = (As.T @ As).toarray()
        if prior is not None:
            Ps = prior @ sparse.diags(1.0 / scale)
            N += (Ps.T @ Ps).toarray()
        N[np.diag_indices_from(N)] += 1e-10
        try:
            coef = np.linalg.solve(N, As.T @ y[keep]) / scale
        except np.linalg.LinAlgError:
            coef = np.linalg.lstsq(N, As.T @ y[keep], rcond=None)[0] / scale
        r = y - A @ coef
        sig = MAD_TO_SIGMA * np.median(np.abs(r[keep] - np.median(r[keep])))
        keep = np.abs(r) <= max(3.5 * sig, 1.0)
    return coef, keep


def luma_width(response: np.ndarray, mask: np.ndarray, camera: CameraModel | None,
               guide_width_px: float) -> float:
    """The stripe's width (FWHM, px) on the luma response itself, for Steger's scale
    (eq. 9 of :mod:`lidarcal.stripe_steger`): the median profile's run above half its peak
    (:func:`lidarcal.stripe_profile.stripe_centres`). The colour pass's width is wider
    (JPEG's half-resolution chroma, demosaicing), and a scale set by it reaches further
    into the stripe's uneven flanks (measured on the semi-real JPEG photos: the centres'
    error against the true stripe 0.261 mm rms with the colour width, 0.247 mm with the
    luma's own). The guide's width when the luma's cannot be measured (fewer than 5
    centres there) or is wider."""
    from .stripe_profile import stripe_centres

    pts, info = stripe_centres(response, mask, camera, return_info=True)
    w = float(info.get("width_px", np.nan)) if len(pts) >= 5 else float("nan")
    return w if np.isfinite(w) and 0 < w <= guide_width_px else float(guide_width_px)


def luma_stripe(image: np.ndarray, camera: CameraModel, view, board: BoardSpec,
                centres: np.ndarray, guide_px: np.ndarray, guide_info: dict, mask: np.ndarray,
                side_px: float, along_deg: float, saturated: np.ndarray | None = None
                ) -> tuple[np.ndarray, dict]:
    """(L4) the stripe's centres on the luma response (:func:`luma_background` about the
    colour centres ``centres``): averaged along the stripe's direction ``along_deg`` over
    ``side_px`` (as :func:`lidarcal.laser_colour.along_stripe` does the colour response),
    then Steger's detector guided by the colour pass's centroid centres ``guide_px``
    (:func:`lidarcal.stripe_steger.steger_stripe`, its outlier test and quality gates; the
    noise measured on this response). Returns (centres, info) as ``steger_stripe``, info
    with ``board_fit_dn`` (the board model's rms) and ``problem`` when it cannot be made.
    """
    from .laser_colour import _line_kernel
    from .stripe_profile import _noise_sigma
    from .stripe_steger import steger_stripe

    width = float(guide_info.get("width_px", np.nan))
    lb = luma_background(image, camera, view, board, np.asarray(centres, float), width,
                         side_px, mask) if np.isfinite(width) else None
    if lb is None:
        return np.empty((0, 2)), {"problem": "too few board pixels beside the stripe"}
    f = cv2.filter2D(lb.response, -1, _line_kernel(np.radians(along_deg), side_px))
    resp = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    m = np.asarray(mask, bool) & lb.band
    gi = dict(guide_info)
    gi["noise_dn"] = _noise_sigma(resp, m, resp)
    gi["width_px"] = luma_width(resp, m, camera, width)
    pts, info = steger_stripe(resp, m, camera, guide_px, gi, saturated)
    info["board_fit_dn"] = lb.fit_rms_dn
    return pts, info
