"""Chessboard corners to sub-pixel accuracy (section 1.2's corner measurements).

OpenCV finds the board (:func:`detect_chessboard`: ``findChessboardCorners``, then
``findChessboardCornersSB``); each corner is refined in a window sized from the local square
size in pixels (:func:`local_square_px`, :func:`refine_corners`), checked against the grid's
prediction from its neighbours (:func:`corner_outliers`), and may be replaced by the saddle
point of the smoothed image (:func:`saddle_corners`) or OpenCV's SB detector in its accuracy
mode (:func:`sb_accuracy_corners`). Pixels are raw (distorted) image pixels.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from .geometry import MAD_TO_SIGMA


def detect_chessboard(image: np.ndarray, pattern_size: tuple[int, int],
                      exhaustive: bool = False, downscale: float = 1.0) -> np.ndarray | None:
    """Inner corners of one chessboard, OpenCV order, sub-pixel (N, 2) float64, or None.

    ``cv2.findChessboardCornersSB`` (``exhaustive`` adds ``CALIB_CB_EXHAUSTIVE``)
    finds the board, :func:`refine_corners` refines it (``cv2.cornerSubPix`` with a
    window from each corner's local square size, per-corner outlier check); the
    classic ``cv2.findChessboardCorners`` is the fallback, and so are SB with
    ``CALIB_CB_NORMALIZE_IMAGE`` and the classic detector where the refinement rejects the
    board SB found (:func:`_board_candidates`). Measured on the rendered
    wide-angle rig's 18 intrinsics views (seed 37) against their true corners:
    0.035 px rms, against 0.049 px for one window of a quarter of the smallest square
    (capped at 11 px) and 0.057 px for SB's ``CALIB_CB_ACCURACY`` mode;
    ``CALIB_CB_NORMALIZE_IMAGE`` costs SB 0.1-0.2 px and is not used. None also when
    a corner fails the outlier check twice.

    ``downscale`` < 1 first looks for the board in an image resized by that
    factor (``INTER_AREA``; SB's cost scales with the pixel count), then by half of it,
    then with the classic detector at that factor, maps its corners back and refines them
    with ``cornerSubPix`` at full resolution as usual; only when that fails is the full
    image searched. On 4000 x 3000 photos (OpenCV's left*.jpg upscaled) SB at full size
    found 9 of 13 boards in 110 s; reduced to 2000 x 1500 first, all 13.
    """
    gray = _gray(image)
    for corners, trust in _board_candidates(gray, tuple(pattern_size), exhaustive, downscale):
        refined = refine_corners(gray, corners, pattern_size, trust)
        if refined is not None:
            return refined
    return None


def _board_candidates(gray: np.ndarray, pattern_size: tuple[int, int], exhaustive: bool,
                      downscale: float):
    """The detectors' boards for :func:`detect_chessboard`, in its order, each as
    ``(corners (N, 2) at full size, trust_px)`` (how far the refinement may move them: SB's
    are accurate to ~2 px at the size searched, the classic detector's only to a pixel:
    None). The next detector is tried only when the refinement rejects the board before:
    SB can return a grid shifted by a row onto the board's border (seen on OpenCV's
    right11/right14.jpg with vignetting), which :func:`refine_corners` refuses."""
    sb_flags = cv2.CALIB_CB_EXHAUSTIVE if exhaustive else 0
    classic = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    tries = []
    if 0 < downscale < 1:
        # SB at the reduced size, then at half of it (on soft, upscaled photos SB misses the
        # board at some sizes and finds it at others), then the classic detector reduced
        tries += [(downscale, sb_flags, True), (downscale / 2, sb_flags, True),
                  (downscale, classic, False)]
    tries += [(1.0, sb_flags, True), (1.0, sb_flags | cv2.CALIB_CB_NORMALIZE_IMAGE, True),
              (1.0, classic, False)]
    for f, flags, sb in tries:
        small = gray if f == 1.0 else cv2.resize(gray, None, fx=f, fy=f,
                                                  interpolation=cv2.INTER_AREA)
        find = cv2.findChessboardCornersSB if sb else cv2.findChessboardCorners
        ok, corners = find(small, pattern_size, flags=flags)
        if not ok or corners is None:
            continue
        corners = corners.reshape(-1, 2)
        if f != 1.0:
            sx, sy = gray.shape[1] / small.shape[1], gray.shape[0] / small.shape[0]
            corners = (corners + 0.5) * np.array([sx, sy], np.float32) - 0.5
        yield corners, (SB_TRUST_PX / f if sb else None)


#: cornerSubPix half window as a share of the local square side (px): large enough to
#: average many gradient samples, small enough never to reach a neighbouring corner (the
#: window spans +-0.3 side). Measured (corner rms against truth on the rendered wide rig's
#: intrinsics views, seed 37; held-out reprojection on OpenCV's left*.jpg photos):
#: 0.2: 0.048 / 0.187 px, 0.3: 0.044 / 0.179 px, 0.4: 0.042 / 0.253 px (real photos degrade)
SUBPIX_WINDOW_SHARE = 0.3
MIN_SUBPIX_HALF_WINDOW = 2
#: Gaussian pre-smoothing before cornerSubPix: sigma = this share of the median square side,
#: at most SUBPIX_SMOOTH_MAX_PX. Measured: corner rms against truth 0.044 -> 0.035 px on the
#: wide rig's intrinsics views, 0.074 -> 0.064 (wide) and 0.084 -> 0.072 px (bundled paper
#: rig) on the V boards; held-out reprojection on OpenCV's left*.jpg 0.179 -> 0.176 px
SUBPIX_SMOOTH_SHARE = 0.05
#: how far (px) the refinement may move a corner of OpenCV's SB detector (itself accurate
#: to ~0.1-0.5 px on real photos) before it counts as dragged
SB_TRUST_PX = 2.0
SUBPIX_SMOOTH_MAX_PX = 1.2
#: a corner further than this many robust sigmas (and 0.5 px) from the position its grid
#: neighbours predict is an outlier (a marker, a glint, the laser on it)
CORNER_OUTLIER_K = 6.0


def local_square_px(corners: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray:
    """Per corner, the shortest distance (px) to a grid neighbour: the local square side."""
    cols, rows = pattern_size
    g = np.asarray(corners, float).reshape(rows, cols, 2)
    m = np.full((rows, cols), np.inf)
    if cols > 1:
        dx = np.linalg.norm(np.diff(g, axis=1), axis=2)
        m[:, 1:] = np.minimum(m[:, 1:], dx)
        m[:, :-1] = np.minimum(m[:, :-1], dx)
    if rows > 1:
        dy = np.linalg.norm(np.diff(g, axis=0), axis=2)
        m[1:] = np.minimum(m[1:], dy)
        m[:-1] = np.minimum(m[:-1], dy)
    return m.ravel()


def _subpix(gray: np.ndarray, corners: np.ndarray, half: np.ndarray) -> np.ndarray:
    """``cv2.cornerSubPix`` with a per-corner half window (one call per distinct size)."""
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    out = np.asarray(corners, np.float32).reshape(-1, 2).copy()
    for w in np.unique(half):
        sel = np.flatnonzero(half == w)
        out[sel] = cv2.cornerSubPix(gray, out[sel].reshape(-1, 1, 2).copy(), (int(w), int(w)),
                                    (-1, -1), crit).reshape(-1, 2)
    return out.astype(np.float64)


def grid_prediction(corners: np.ndarray, pattern_size: tuple[int, int],
                    reach: int = 2, valid: np.ndarray | None = None) -> np.ndarray:
    """See :func:`grid_prediction_scaled` (the predictions alone)."""
    return grid_prediction_scaled(corners, pattern_size, reach, valid)[0]


def grid_prediction_scaled(corners: np.ndarray, pattern_size: tuple[int, int],
                           reach: int = 2, valid: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Each corner predicted from its grid neighbours alone (leave-one-out): a quadratic
    map grid (i, j) -> pixel fitted by least squares to the corners within ``reach`` grid
    steps, the corner itself (and any not ``valid``) excluded (NaN with fewer than 8). Perspective and
    lens distortion are smooth over a few squares: on the rendered wide-angle views
    (k1 = -0.30) the prediction is within 0.05-0.2 px (median), where a local homography
    is 0.4-0.9 px off. Also returns each residual's scale ``sqrt(1 + a0' (A'A)^-1 a0)``
    (the prediction's noise gain: larger where a corner is extrapolated, at the board's
    corners and edges), so residuals divided by it are comparable."""
    cols, rows = pattern_size
    n = rows * cols
    P = np.asarray(corners, float).reshape(n, 2)
    ok = np.ones(n, bool) if valid is None else np.asarray(valid, bool).reshape(n)
    out = np.full((n, 2), np.nan)
    scale = np.full(n, np.nan)
    # every corner's neighbourhood at once: the grid offsets within ``reach`` in row-major
    # order (dj, then di), used where the neighbour is on the board, valid and not the corner
    dj, di = (d.ravel() for d in np.mgrid[-reach:reach + 1, -reach:reach + 1])
    j, i = np.divmod(np.arange(n), cols)
    nj, ni = j[:, None] + dj, i[:, None] + di  # (n, K) neighbour rows and columns
    on_board = (nj >= 0) & (nj < rows) & (ni >= 0) & (ni < cols)
    nbr = np.where(on_board, nj * cols + ni, 0)
    use = on_board & ok[nbr] & ((dj != 0) | (di != 0))
    fitted = np.flatnonzero(use.sum(axis=1) >= 8)
    # the least-squares operator depends only on which grid offsets are used: corners with
    # the same neighbourhood (all interior ones of a clean board) share one pseudo-inverse
    masks, group = np.unique(use[fitted], axis=0, return_inverse=True)
    group = group.reshape(-1)
    for g, m in enumerate(masks):
        idx = fitted[group == g]
        row0, gain = _grid_operator(reach, m.tobytes())
        out[idx] = np.einsum("n,knd->kd", row0, P[nbr[idx][:, m]])
        scale[idx] = gain
    return out, scale


@lru_cache(maxsize=512)
def _grid_operator(reach: int, used: bytes) -> tuple[np.ndarray, float]:
    """:func:`grid_prediction_scaled`'s operator for one neighbourhood (the offsets within
    ``reach``, row-major, where the bool mask ``used`` is set): the quadratic map's constant
    term as weights, ``pinv(A)[0]``, and the noise gain ``sqrt(1 + (A'A)^-1 [0, 0])``; it
    depends on the offsets alone, so it is computed once per process."""
    dj, di = (d.ravel() for d in np.mgrid[-reach:reach + 1, -reach:reach + 1])
    m = np.frombuffer(used, dtype=bool)
    u, v = di[m].astype(float), dj[m].astype(float)
    A = np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
    # the map at (u, v) = (0, 0): the constant term of the least-squares fit
    row0 = np.linalg.pinv(A)[0]
    row0.flags.writeable = False
    return row0, float(np.sqrt(1.0 + np.linalg.pinv(A.T @ A)[0, 0]))


def corner_outliers(corners: np.ndarray, pattern_size: tuple[int, int]) -> np.ndarray:
    """Outlier mask of detected corners against the board's smooth grid: leave-one-out
    (:func:`grid_prediction`), worst first, each outlier then left out of its neighbours'
    predictions; an outlier lies further than ``CORNER_OUTLIER_K`` robust sigmas and 0.5 px
    from its prediction (residuals divided by the prediction's noise gain)."""
    cols, rows = pattern_size
    flagged = np.zeros(cols * rows, bool)
    if min(cols, rows) < 3:
        return flagged
    for _ in range(cols * rows // 4):
        pred, gain = grid_prediction_scaled(corners, pattern_size, valid=~flagged)
        r = np.linalg.norm(corners - pred, axis=1) / gain
        r[flagged] = np.nan
        bad = _outlier_mask(r)
        if not bad.any():
            break
        flagged[int(np.nanargmax(np.where(bad, r, -1.0)))] = True
    return flagged


def _outlier_mask(r: np.ndarray) -> np.ndarray:
    """Residuals (px) beyond ``CORNER_OUTLIER_K`` robust sigmas and 0.5 px (NaN: not judged)."""
    ok = np.isfinite(r)
    if not ok.any():
        return np.zeros(len(r), bool)
    s = MAD_TO_SIGMA * np.median(r[ok])
    return ok & (r > max(CORNER_OUTLIER_K * s, 0.5))


def refine_corners(gray: np.ndarray, corners: np.ndarray, pattern_size: tuple[int, int],
                   trust_px: float | None = None) -> np.ndarray | None:
    """Sub-pixel corners with a window from the LOCAL square size, outliers checked.

    Each corner's half window is ``SUBPIX_WINDOW_SHARE`` of its shortest grid edge in
    pixels (at least ``MIN_SUBPIX_HALF_WINDOW``): the window never reaches a neighbouring
    corner, and a small square far away gets a small window while a near one a large one.
    A corner its neighbours disagree with (:func:`corner_outliers`) is refined again from
    its predicted position with half that window, or else falls back to the detector's own
    (unrefined) corner; if neither agrees, or more than 10 % of the corners (at least 3)
    are outliers, the view is rejected (None): a wrong corner is never passed on. With
    ``trust_px`` (the detector's corners are that accurate: OpenCV's SB detector), a corner
    the refinement moved further than that (and 1/20 of its square) counts as an outlier too
    (a marker or glint inside the window drags it). On the bundled real TAPAS views the fiducial rings beside the
    board's outer corners drag those corners by 12-14 px; they are caught here.
    """
    side = local_square_px(corners, pattern_size)
    half = np.maximum(np.floor(SUBPIX_WINDOW_SHARE * side), MIN_SUBPIX_HALF_WINDOW).astype(int)
    # a light Gaussian pre-smoothing (symmetric: it does not move a corner) lowers the
    # gradients' noise; ~1/20 of a square, at most SUBPIX_SMOOTH_MAX_PX
    sigma = min(SUBPIX_SMOOTH_SHARE * float(np.median(side)), SUBPIX_SMOOTH_MAX_PX)
    if sigma >= 0.3:
        gray = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), sigma)
    out = _subpix(gray, corners, half)
    off_grid = corner_outliers(out, pattern_size)
    bad = off_grid.copy()
    if trust_px is not None:  # refined far from an accurate detector's corner: dragged?
        bad |= np.linalg.norm(out - corners, axis=1) > np.maximum(trust_px, 0.05 * side)
    if not bad.any():
        return out
    if bad.sum() > max(2, 0.1 * len(out)):
        return None  # not a few stray corners: the view is not trusted
    pred, gain = grid_prediction_scaled(out, pattern_size, valid=~bad)
    if not np.all(np.isfinite(pred[bad])):
        return None
    r_good = (np.linalg.norm(out - pred, axis=1) / gain)[~bad]
    limit = max(CORNER_OUTLIER_K * MAD_TO_SIGMA * float(np.median(r_good)), 0.5)
    small = np.maximum(half // 2, MIN_SUBPIX_HALF_WINDOW)
    retry = _subpix(gray, pred[bad], small[bad])
    detector = np.asarray(corners, float)[bad]
    for n, k in enumerate(np.flatnonzero(bad)):
        # the re-refined corner, the detector's own, or (when its neighbours agreed with it)
        # the first refinement: whichever its neighbours agree with best
        cands = [retry[n], detector[n]] + ([] if off_grid[k] else [out[k].copy()])
        errs = [float(np.linalg.norm(c - pred[k]) / gain[k]) for c in cands]
        best = int(np.argmin(errs))
        if errs[best] > limit:
            return None
        out[k] = cands[best]
    return out


#: :func:`sb_accuracy_corners` is not run on a board crop larger than this (px): its upsampled
#: search took 4-15 s per board on 4000 x 3000 photos, where the board's squares are large
#: and ``cornerSubPix`` with a window from them is accurate anyway
SB_ACCURACY_MAX_PIXELS = 4_000_000


def sb_accuracy_corners(gray: np.ndarray, corners: np.ndarray, pattern_size: tuple[int, int]
                        ) -> np.ndarray | None:
    """The same board's corners by ``cv2.findChessboardCornersSB`` with ``CALIB_CB_ACCURACY``
    (its own sub-pixel model on an upsampled image), searched in a crop 1.5 squares beyond
    ``corners`` and put in their order; None when not found, not the same corners (each
    within a fifth of a square of one of ``corners``) or off the board's smooth grid
    (:func:`corner_outliers`), or when the crop exceeds ``SB_ACCURACY_MAX_PIXELS``."""
    c = np.asarray(corners, float).reshape(-1, 2)
    side = float(np.median(local_square_px(c, pattern_size)))
    gray = _gray(gray)
    H, W = gray.shape[:2]
    x0, y0 = np.floor(c.min(0) - 1.5 * side).astype(int).clip(0)
    x1, y1 = np.minimum(np.ceil(c.max(0) + 1.5 * side).astype(int) + 1, [W, H])
    if (x1 - x0) * (y1 - y0) > SB_ACCURACY_MAX_PIXELS:
        return None
    ok, sb = cv2.findChessboardCornersSB(np.ascontiguousarray(gray[y0:y1, x0:x1]),
                                         tuple(pattern_size), flags=cv2.CALIB_CB_ACCURACY)
    if not ok or sb is None:
        return None
    sb = sb.reshape(-1, 2).astype(float) + [x0, y0]
    d = np.linalg.norm(c[:, None] - sb[None], axis=2)
    near = np.argmin(d, axis=1)
    if len(np.unique(near)) != len(c) or np.max(d[np.arange(len(c)), near]) > 0.2 * side:
        return None
    sb = sb[near]
    return None if corner_outliers(sb, pattern_size).any() else sb


#: Saddle-point refinement (:func:`saddle_corners`): Gaussian smoothing sigma and half window
#: of the quadratic fit as shares of each corner's local square side. Measured (corner rms
#: against truth on board.png, both boards; scripts/camera_truth.py's true projections):
#: sigma/window 0.10/0.25: 0.026 px mean over bundled paper rig, paper seed 11, wide seed 37;
#: 0.15/0.25: 0.024; 0.15/0.35: 0.023; 0.20/0.40: 0.022 (SB accuracy mode 0.035, the
#: cornerSubPix refinement 0.058). The middle value is kept: the blur must not reach
#: the neighbouring corners (0.35 + 4 x 0.15 < 1 square).
SADDLE_SMOOTH_SHARE = 0.15
SADDLE_WINDOW_SHARE = 0.35
#: re-centred fits per corner (each moves the window onto the last estimate)
SADDLE_ITERATIONS = 3
#: a saddle further than this from the given (cornerSubPix) corner, px and share of the local
#: square, was dragged (on the bundled real TAPAS views the fiducial rings beside the board's
#: outer corners pull the smoothed saddles 5-9 px; on the simulated V boards no saddle
#: moved more than 0.2 px): that corner keeps the given position
SADDLE_TRUST_PX = 1.0
SADDLE_TRUST_SHARE = 0.05
#: a corner's fitted saddle must span at least this share of the board's intensity range over
#: its window (measured, median per board: 0.35-0.38 on the simulated V boards, 0.16-0.28 on
#: the real TAPAS views; 0 on a blank or noise-only image)
SADDLE_MIN_CONTRAST = 0.1


def saddle_corners(gray: np.ndarray, corners: np.ndarray, pattern_size: tuple[int, int]
                   ) -> np.ndarray | None:
    """Sub-pixel chessboard corners as saddle points of the smoothed image (Lucchese and
    Mitra 2002, "Using saddle points for subpixel feature detection in camera calibration
    targets"; the same idea as ROCHADE, Placht et al. 2014).

    The board's region is smoothed with a Gaussian (sigma ``SADDLE_SMOOTH_SHARE`` of the
    median square side); around each corner a quadratic ``I = a x^2 + b xy + c y^2 + d x +
    e y + f`` is fitted by Gaussian-weighted least squares over a half window of
    ``SADDLE_WINDOW_SHARE`` of its local square side, and the corner moves to the
    quadric's stationary point ``[2a b; b 2c] p = -[d e]``; ``SADDLE_ITERATIONS`` times,
    the window re-centred (bilinear samples, :func:`_bilinear_patches`). An ideal
    corner is point-symmetric (``I(-x) = I(x)``), and so is its blurred image under any
    affine view, so its saddle is the corner itself; the smoothing averages the noise over
    a large part of the square. A corner whose fit is no saddle of the board's contrast
    (``SADDLE_MIN_CONTRAST``), that moved further than ``SADDLE_TRUST_PX`` and
    ``SADDLE_TRUST_SHARE`` of its square from ``corners`` (dragged by a marker), or that is
    off the board's smooth grid (:func:`corner_outliers`) keeps its position in ``corners``;
    None when more than 10 % of the corners (at least 3) do.
    """
    c = np.asarray(corners, float).reshape(-1, 2)
    side = local_square_px(c, pattern_size)
    sigma = SADDLE_SMOOTH_SHARE * float(np.median(side))
    half = np.maximum(np.round(SADDLE_WINDOW_SHARE * side), 2).astype(int)
    # smooth only the board's region (plus the reach of the windows and the kernel)
    g = _gray(gray)
    H, W = g.shape[:2]
    pad = int(np.ceil(half.max() + 4 * sigma + 2))
    x0, y0 = np.floor(c.min(0) - pad).astype(int).clip(0)
    x1, y1 = np.minimum(np.ceil(c.max(0) + pad).astype(int) + 1, [W, H])
    img = cv2.GaussianBlur(g[y0:y1, x0:x1].astype(np.float32), (0, 0), sigma)
    # the board's contrast: the smoothed region's 1st-99th percentile range (subsampled;
    # at least one grey level, so a blank image has none of the saddles asked for)
    lo, hi = np.percentile(img[::4, ::4], [1, 99])
    contrast = max(float(hi - lo), 1.0)
    out = c - [x0, y0]
    saddle = np.ones(len(c), bool)
    for w in np.unique(half):
        sel = np.flatnonzero(half == w)
        yy, xx = np.mgrid[-w:w + 1, -w:w + 1].astype(float)
        x, y = xx.ravel(), yy.ravel()
        sw = np.exp(-(x * x + y * y) / (4 * (0.6 * w) ** 2))  # sqrt of the Gaussian weight
        A = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
        fit = np.linalg.pinv(A * sw[:, None]) * sw[None, :]  # (6, n) weighted least squares
        for _ in range(SADDLE_ITERATIONS):
            p = out[sel]
            Z = _bilinear_patches(img, p, w).reshape(len(sel), -1)
            # einsum, not BLAS: a product this small costs less than waking BLAS threads
            a, b, cc, d, e, _ = np.einsum("kn,mn->km", fit, Z)
            det = 4 * a * cc - b * b
            # a saddle whose curvature spans a share of the board's contrast over the window
            # (the quadric's geometric-mean |eigenvalue| sqrt(-det) / 2, times w^2); else no
            # chessboard corner there (a flat or noisy patch)
            ok = np.sqrt(np.maximum(-det, 0.0)) / 2 * w * w > SADDLE_MIN_CONTRAST * contrast
            saddle[sel] &= ok
            det = np.where(ok, det, -1.0)
            step = np.column_stack([(b * e - 2 * cc * d) / det, (b * d - 2 * a * e) / det])
            out[sel] = p + np.where(ok[:, None], step, 0.0)
    out = out + [x0, y0]
    moved = np.linalg.norm(out - c, axis=1)
    bad = ~saddle | ~(moved <= np.maximum(SADDLE_TRUST_PX, SADDLE_TRUST_SHARE * side))
    bad |= corner_outliers(np.where(bad[:, None], c, out), pattern_size)
    if bad.sum() > max(2, 0.1 * len(c)):
        return None
    return np.where(bad[:, None], c, out)


def _bilinear_patches(img: np.ndarray, centres: np.ndarray, w: int) -> np.ndarray:
    """Bilinear samples (n, 2w+1, 2w+1) of ``img`` on the pixel grid offsets -w..w around each
    centre (n, 2) (x, y); indices beyond the image repeat its edge. All samples of a patch
    share the centre's fractional part, so one (2w+2)^2 integer patch and four weights do
    (interpolated along x on every row of the patch, then along y).
    Exact weights, not ``cv2.remap``'s: it rounds every sample position to 1/32 px, as
    large as the saddle shifts being measured."""
    base = np.floor(centres).astype(int)
    f = (centres - base)[:, :, None, None]
    H, W = img.shape[:2]
    x0, y0 = base[:, 0] - w, base[:, 1] - w  # each patch's top-left pixel
    if len(base) and x0.min() >= 0 and y0.min() >= 0 and x0.max() + 2 * w + 2 <= W \
            and y0.max() + 2 * w + 2 <= H:
        # every patch inside the image: cut from a strided view of all (2w+2)^2 windows
        # (5x faster than indexing every pixel)
        P = sliding_window_view(img, (2 * w + 2, 2 * w + 2))[y0, x0].astype(np.float64)
    else:
        r = np.arange(-w, w + 2)
        rows = np.clip(base[:, 1, None] + r, 0, H - 1)
        cols = np.clip(base[:, 0, None] + r, 0, W - 1)
        P = img[rows[:, :, None], cols[:, None, :]].astype(np.float64)
    fx, fy = f[:, 0], f[:, 1]
    along_x = (1 - fx) * P[:, :, :-1] + fx * P[:, :, 1:]  # every row once, (n, 2w+2, 2w+1)
    return (1 - fy) * along_x[:, :-1] + fy * along_x[:, 1:]


def _gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img
