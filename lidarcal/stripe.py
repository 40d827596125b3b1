"""Laser stripes on the V: centre lines, 3D stripe points, laser plane, E, l1, l2, alpha (section 1.3).

The LiDAR's scan plane ``Pi_L`` cuts each board of the V in a straight line
(``L1``, ``L2``). Its red laser is visible to the camera: the stripe centres
are extracted with sub-pixel precision inside each board's outline, cast as
rays and met with that board's plane (eqs. 3, 5), and ``Pi_L`` is fitted to
the 3D points of both stripes (eq. 4). ``E`` is the common point of
``Pi_1, Pi_2, Pi_L``; ``l_k = n_k x n_L`` (oriented towards stripe ``k``),
``alpha = arccos(l1 . l2)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from .board import BoardView
from .camera import backproject_to_plane, undistort_pixels
from .dataset import CameraModel
from .geometry import Plane, fit_plane, fit_plane_algebraic, intersect_planes, unit
from .laser_colour import (  # noqa: F401  (re-exported: the stripe's public API)
    LASER_COLOURS,
    SATURATED_DN,
    detect_laser_colour,
    laser_response,
)
from .stripe_quality import (  # noqa: F401  (re-exported)
    DEFAULT_GATES,
    StripeGates,
    quality_problem,
    stripe_quality,
)

MAD_TO_SIGMA = 1.4826

def _hist_percentile(hist: np.ndarray, q: float) -> float:
    """``np.percentile`` (linear interpolation) of the integers ``0..len(hist)-1`` counted in
    ``hist`` (value ``k`` occurs ``hist[k]`` times)."""
    cum = np.cumsum(hist)
    pos = (cum[-1] - 1) * q / 100.0
    lo, hi = int(np.floor(pos)), int(np.ceil(pos))
    a, b = np.searchsorted(cum, [lo, hi], side="right").astype(float)
    return float(a + (b - a) * (pos - lo))


def _int_percentile(v: np.ndarray, q: float) -> float:
    """``np.percentile(v, q)`` (linear interpolation) of non-negative integers, in O(n)."""
    if v.dtype == np.uint8:
        hist = cv2.calcHist([np.ascontiguousarray(v).reshape(-1, 1)], [0], None, [256], [0, 256])
        return _hist_percentile(hist.ravel().astype(np.int64), q)
    return _hist_percentile(np.bincount(v.ravel()), q)


def _noise_sigma(img: np.ndarray, mask: np.ndarray, raw8: np.ndarray | None = None) -> float:
    """Robust sensor-noise sigma (DN) from horizontal pixel differences inside ``mask``.

    ``raw8``: the same image as uint8; the medians are then taken exactly from a
    histogram of the (integer) differences, in O(n).
    """
    m = mask[::2, 1:] & mask[::2, :-1]
    if raw8 is not None:
        a = raw8[::2]
        key = a[:, 1:].astype(np.uint16) + np.uint16(256) - a[:, :-1]  # d + 256, in 1..511
        if np.count_nonzero(m) >= 10:
            key *= m  # 0 = outside the mask
        hist = cv2.calcHist([key], [0], None, [512], [0, 512]).ravel().astype(np.int64)[1:]
        if hist.sum() == 0:
            return 0.5
        med2 = round(2 * _hist_percentile(hist, 50.0)) - 510  # 2 x median, an integer
        # histogram of 2 |d - median| folded from the one of d
        dev = np.abs(2 * (np.arange(511) - 255) - med2)
        mad = _hist_percentile(np.bincount(dev, weights=hist).astype(np.int64), 50.0) / 2.0
        return float(max(MAD_TO_SIGMA * mad / np.sqrt(2.0), 0.5))
    d = np.diff(img[::2], axis=1)  # every other row is plenty for a MAD
    v = d[m]
    if v.size < 10:
        v = d.ravel()
    mad = np.median(np.abs(v - np.median(v)))
    return float(max(MAD_TO_SIGMA * mad / np.sqrt(2.0), 0.5))


def _coarse_line(img: np.ndarray, mask: np.ndarray, noise: float,
                 raw8: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Rough stripe line (point, unit direction) in pixels from the brightest pixels, or None.

    Pixels well above the local background (a wide median along both axes)
    are fitted by PCA, with two rounds of rejection by the median absolute
    perpendicular residual. With ``raw8`` (the image as uint8) this is done
    in 8 bits on the image halved (``INTER_AREA``) first, and at full
    resolution only when that finds no line: the line only guides the
    column windows of :func:`_centres_by_column`, which re-centre on the stripe.
    """
    if raw8 is not None and min(raw8.shape) >= 64:
        h, w = raw8.shape[0] // 2, raw8.shape[1] // 2
        small = cv2.resize(raw8[:2 * h, :2 * w], (w, h), interpolation=cv2.INTER_AREA)
        msmall = mask[:2 * h:2, :2 * w:2] & mask[1:2 * h:2, 1:2 * w:2]
        found = _bright_line(cv2.GaussianBlur(small, (0, 0), 0.75), msmall, noise, scale=2.0)
        if found is not None:
            return found
    if raw8 is not None:
        return _bright_line(cv2.GaussianBlur(raw8, (0, 0), 1.5), mask, noise)
    return _bright_line(cv2.GaussianBlur(img, (0, 0), 1.5), mask, noise)


def _bright_line(sm: np.ndarray, mask: np.ndarray, noise: float, scale: float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """PCA line of the pixels of a smoothed image ``sm`` well above its background, in
    full-resolution pixels (``sm`` is the image reduced by ``scale``)."""
    vals = sm[mask]
    if vals.size < 20:
        return None
    if sm.dtype == np.uint8:
        base = _int_percentile(vals[::7], 50.0)
        peak = _int_percentile(vals, 99.9)
    else:
        base = np.median(vals[::7])
        peak = np.percentile(vals, 99.9)
    thr = base + max(0.35 * (peak - base), 6.0 * noise)
    ys, xs = np.nonzero(mask & (sm > thr))
    if xs.size < 10:
        return None
    if scale != 1.0:
        xs, ys = scale * xs + 0.5 * (scale - 1), scale * ys + 0.5 * (scale - 1)
    P = np.column_stack([xs, ys]).astype(float)
    keep = np.ones(len(P), bool)
    for _ in range(3):
        c = P[keep].mean(0)
        _, _, vt = np.linalg.svd(P[keep] - c, full_matrices=False)
        t = vt[0]
        nrm = np.array([-t[1], t[0]])
        r = (P - c) @ nrm
        s = MAD_TO_SIGMA * np.median(np.abs(r[keep]))
        keep = np.abs(r) <= max(3 * s, 2.0)
        if keep.sum() < 10:
            return None
    return c, t


def _window_centroid(prof: np.ndarray, start: np.ndarray, half: float, iters: int = 6,
                     tol: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Iterated centroid of background-free profiles (M, W) in a window ``start +- half``.

    Returns centres (profile index units) and the summed signal in the window.
    Symmetric windows make the fixed point the centre of a symmetric stripe
    profile, including one clipped at saturation. Stops early once no centre
    moves by more than ``tol`` px.
    """
    idx = np.arange(prof.shape[1])[None, :]
    c = start.astype(float).copy()
    s = np.clip(prof, 0, None)
    mass = np.zeros(len(c))
    act = np.arange(len(c))  # rows still moving; converged rows are left alone
    for _ in range(iters):
        # fractional weights at the window edges keep the centroid continuous in c
        w = np.clip(half + 0.5 - np.abs(idx - c[act, None]), 0.0, 1.0)
        ws = w * s[act]
        m = ws.sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            c_new = (ws * idx).sum(1) / m
        c_new = np.where(m > 0, c_new, np.nan)
        moving = np.abs(c_new - c[act]) > tol  # False for NaN: such rows stay NaN
        c[act], mass[act] = c_new, m
        act = act[moving]
        if act.size == 0:
            break
    return c, mass


def _profiles(img: np.ndarray, xs: np.ndarray, y0: np.ndarray, L: int) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Column profiles ``img[y0 + k, x]`` for ``k = -L..L`` (M, 2L+1), clipped to the image."""
    H = img.shape[0]
    top = np.clip(np.round(y0).astype(int) - L, 0, max(H - 2 * L - 1, 0))
    rows = top[:, None] + np.arange(2 * L + 1)[None, :]
    rows = np.clip(rows, 0, H - 1)
    return img[rows, xs[:, None]].astype(np.float32, copy=False), top


def stripe_centres(image: np.ndarray, mask: np.ndarray, camera: CameraModel | None = None,
                   min_snr: float = 8.0, blackness: np.ndarray | None = None,
                   rho: float | None = None, return_info: bool = False):
    """Sub-pixel centre line of a laser stripe inside ``mask`` (section 1.3), pixels (N, 2).

    1. Robust noise level (MAD of pixel differences) and a coarse stripe line
       (PCA of the brightest pixels): its direction decides whether the
       stripe is sampled by columns (|slope| <= 1) or by rows.
    2. Stripe width from the median profile; per column, a window of a few
       widths around the predicted centre; background from the window's two
       outer thirds (a straight line; with ``blackness``, ambient light
       reflected by the squares: ``b0 + b1 * blackness``).
    3. Centre = iterated symmetric-window centroid (robust to saturation);
       columns whose peak is below ``min_snr`` noise sigmas are dropped.
    4. With ``blackness`` (0 on white, 1 on black squares, as seen in the
       bright image; :meth:`lidarcal.board.BoardView.blackness_map`) each
       profile is divided by the stripe's albedo ``1 - (1 - rho) blackness``
       before the centroid. Without this, a stripe running along a square
       edge is pulled towards the white square by up to half its width.
       ``rho`` (the stripe's black/white reflectance ratio) is estimated from
       this stripe's brightness when not given (:func:`reflectance_ratio`);
       when it cannot be (no contrast along the stripe) no division is made.
    5. Outliers (speckle, glints, edges) are rejected against a smooth curve:
       a straight line in undistorted normalised coordinates when ``camera``
       is given (a straight stripe on the board seen through the lens), else
       a quadratic in the image; 3.5 robust sigmas, iterated.

    With ``return_info`` a dict comes back as a second value: ``snr``,
    ``width_px``, ``noise_dn``, ``rho`` (used), ``fit_rms_px``,
    ``n_rejected`` and ``samples`` (x, signal mass, effective blackness per
    column, for a joint :func:`reflectance_ratio`).
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    mask = np.asarray(mask, bool)
    if mask.shape != img.shape:
        raise ValueError(f"mask shape {mask.shape} differs from image shape {img.shape}")
    if blackness is not None and np.shape(blackness) != img.shape:
        raise ValueError(f"blackness shape {np.shape(blackness)} differs from image shape "
                         f"{img.shape}")
    if not mask.any():
        return _empty(return_info)
    y_lo, y_hi, x_lo, x_hi = _crop_box(mask, img.shape)
    bsub = None if blackness is None else np.asarray(blackness)[y_lo:y_hi, x_lo:x_hi]
    return _centres_in_crop(img[y_lo:y_hi, x_lo:x_hi], mask[y_lo:y_hi, x_lo:x_hi], bsub,
                            (x_lo, y_lo), camera, min_snr, rho, return_info, return_info)


_CROP_PAD = 40  # px around a mask's bounding box: room for the background windows


def _empty(return_info: bool):
    pts = np.empty((0, 2))
    return (pts, {"snr": np.empty(0), "n_rejected": 0, "rho": None, "samples": None,
                  "problem": "no laser stripe found"}) if return_info else pts


def _crop_box(mask: np.ndarray, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """``(y_lo, y_hi, x_lo, x_hi)``: bounding box of ``mask`` plus ``_CROP_PAD``, in the image."""
    ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    y_lo, y_hi, x_lo, x_hi = ys[0], ys[-1] + 1, xs[0], xs[-1] + 1
    return (max(y_lo - _CROP_PAD, 0), min(y_hi + _CROP_PAD, shape[0]),
            max(x_lo - _CROP_PAD, 0), min(x_hi + _CROP_PAD, shape[1]))


def _centres_in_crop(sub: np.ndarray, msub: np.ndarray, bsub: np.ndarray | None,
                     origin: tuple[int, int], camera: CameraModel | None, min_snr: float,
                     rho: float | None, return_info: bool, want_samples: bool,
                     clean: bool = False):
    """:func:`stripe_centres` on a crop (origin ``(x0, y0)`` in the image) holding the mask.

    ``clean``: ``bsub`` is already finite float32 (from :func:`_board_crop`)."""
    x_lo, y_lo = origin
    sub = np.asarray(sub)
    raw8 = sub if sub.dtype == np.uint8 else None
    if raw8 is None:
        sub = sub.astype(np.float32)
    # (uint8 crops stay uint8: profiles are gathered from them and then converted)
    if bsub is not None and not clean:
        bsub = np.asarray(bsub, np.float32)
        if not np.isfinite(bsub).all():
            bsub = np.nan_to_num(bsub, nan=0.0)
    if not msub.any():
        return _empty(return_info)
    noise = _noise_sigma(sub, msub, raw8)
    coarse = _coarse_line(sub, msub, noise, raw8)
    if coarse is None:
        return _empty(return_info)
    c0, t0 = coarse
    transpose = abs(t0[0]) < abs(t0[1])
    mask_img = msub  # in image axes, for the quality gate
    if transpose:  # sample by rows: swap axes, solve as by columns, swap back
        sub, msub = sub.T, msub.T
        bsub = None if bsub is None else bsub.T
        c0, t0 = c0[::-1], t0[::-1]
    slope = t0[1] / t0[0]
    res = _centres_by_column(np.ascontiguousarray(sub), msub, c0, slope, noise, min_snr,
                             None if bsub is None else np.ascontiguousarray(bsub), rho,
                             want_samples=want_samples or rho is None)
    if res is None:
        return _empty(return_info)
    pts, snr, width, rho_used, samples = res
    if transpose:
        pts = pts[:, ::-1]
    pts = pts + np.array([x_lo, y_lo], float)
    keep, fit_rms = _reject_outliers(pts, camera)
    if not return_info:
        return pts[keep]
    quality = stripe_quality(pts[keep], int((~keep).sum()), fit_rms, width, snr[keep],
                             mask_img, (x_lo, y_lo))
    info = {"snr": snr[keep], "width_px": width, "noise_dn": noise, "rho": rho_used,
            "fit_rms_px": fit_rms, "n_rejected": int((~keep).sum()), "samples": samples,
            "quality": quality, "problem": quality_problem(quality)}
    return pts[keep], info


def _row_median(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` for finite data, by one partition."""
    n = a.shape[1]
    k = n // 2
    if n % 2:
        return np.partition(a, k, axis=1)[:, k]
    p = np.partition(a, [k - 1, k], axis=1)
    return 0.5 * (p[:, k - 1] + p[:, k])


def _background(prof: np.ndarray, bprof: np.ndarray | None) -> np.ndarray:
    """Background of each profile (M, W) fitted to its two outer thirds.

    A straight line through the medians of the two thirds; where the
    blackness differs between the two thirds, ``b0 + b1 * blackness``
    (ambient light is reflected in proportion to the squares' albedo).
    """
    n = prof.shape[1]
    third = max(n // 3, 2)
    left = _row_median(prof[:, :third])
    right = _row_median(prof[:, -third:])
    xl, xr = (third - 1) / 2.0, n - 1 - (third - 1) / 2.0
    k = np.arange(n)[None, :]
    bg = left[:, None] + (right - left)[:, None] * (k - xl) / (xr - xl)
    if bprof is None:
        return bg
    bl = _row_median(bprof[:, :third])
    br = _row_median(bprof[:, -third:])
    db = br - bl
    step = np.abs(db) > 0.3
    if np.any(step):
        slope = np.where(step, (right - left) / np.where(step, db, 1.0), 0.0)
        bg_b = left[:, None] + slope[:, None] * (bprof - bl[:, None])
        bg = np.where(step[:, None], bg_b, bg)
    return bg


def _centres_by_column(img: np.ndarray, mask: np.ndarray, c0: np.ndarray, slope: float,
                       noise: float, min_snr: float, blk: np.ndarray | None = None,
                       rho: float | None = None, want_samples: bool = True):
    """Column-wise centres; returns (points (N, 2), snr, width, rho used, samples) or None."""
    cols = np.nonzero(mask.any(axis=0))[0]
    if cols.size < 5:
        return None
    H = img.shape[0]
    y_pred = c0[1] + slope * (cols - c0[0])
    inside = (y_pred >= 0) & (y_pred < H)
    cols, y_pred = cols[inside], y_pred[inside]
    if cols.size < 5:
        return None
    # stripe width from a first look: median FWHM of the profiles
    L0 = min(30, (H - 1) // 2)
    prof, top = _profiles(img, cols, y_pred, L0)
    width = _fwhm(prof, noise)
    L = int(min(max(np.ceil(4 * width) + 6, 10), (H - 1) // 2))
    half = max(1.5 * width, 2.0)
    y_cur = y_pred
    samples = None
    rho_used = rho
    # with blackness: pass 0 plain, then passes with the albedo divided out; rho (when not
    # given) is re-estimated after each pass, as the centres it weights by move
    n_pass = 2 if blk is None else 4
    idx = np.arange(2 * L + 1)[None, :]
    for it in range(n_pass):
        prof, top = _profiles(img, cols, y_cur, L)
        bprof = None if blk is None else np.clip(_profiles(blk, cols, y_cur, L)[0], 0.0, 1.0)
        s = prof - _background(prof, bprof)
        start = np.argmax(_smooth_rows(s, max(width / 2.355, 0.8)), axis=1)
        peak = s[np.arange(len(s)), start]
        s_raw = s
        if bprof is not None and rho_used is not None and it > 0:
            s = s / (1.0 - (1.0 - rho_used) * bprof)
        cen, _ = _window_centroid(s, start.astype(float), half)
        ok = np.isfinite(cen) & (peak >= min_snr * noise)
        y_cur = np.where(ok, top + cen, y_cur)
        if bprof is not None and it < n_pass - 1 and want_samples:
            # raw signal mass and effective blackness in a window about the current centre
            sig = max(width / 2.355, 0.7)
            cc = np.nan_to_num(cen)[:, None]
            win = np.clip(half + 0.5 - np.abs(idx - cc), 0.0, 1.0)
            mass = (win * np.clip(s_raw, 0, None)).sum(1)
            g = np.exp(-0.5 * ((idx - cc) / sig) ** 2) * win
            b_eff = (g * bprof).sum(1) / np.maximum(g.sum(1), 1e-12)
            use = ok & (prof.max(axis=1) < 254)  # saturated profiles lose signal mass
            samples = (cols[use].astype(float), mass[use], b_eff[use])
            if rho is None:
                rho_used = reflectance_ratio([samples])
    n = prof.shape[1]
    cen = _saturated_centres(prof, s_raw, cen)
    yc = top + cen
    ok = np.isfinite(cen) & (peak >= min_snr * noise) & (cen > half) & (cen < n - 1 - half)
    xi, yi = cols[ok], yc[ok]
    inmask = mask[np.clip(np.round(yi).astype(int), 0, H - 1), xi]
    xi, yi, snr = xi[inmask], yi[inmask], (peak[ok] / noise)[inmask]
    if xi.size < 5:
        return None
    return np.column_stack([xi.astype(float), yi]), snr, width, rho_used, samples


def _saturated_centres(prof: np.ndarray, s: np.ndarray, cen: np.ndarray) -> np.ndarray:
    """Centres of clipped profiles: the midpoint of the run above half the peak, its two
    edges interpolated linearly (sub-pixel) on the unsaturated flanks.

    A profile is clipped when at least 3 samples lie within 1 DN of its maximum and
    that maximum is ``SATURATED_DN`` or more (a saturated laser core is a flat top).
    Other profiles keep their centroid ``cen``.
    """
    top = prof.max(axis=1)
    flat = (prof >= top[:, None] - 1).sum(axis=1) >= 3
    rows = np.flatnonzero(flat & (top >= SATURATED_DN) & np.isfinite(cen))
    out = cen.copy()
    n = s.shape[1]
    for i in rows:
        row = s[i]
        k = int(np.clip(np.rint(cen[i]), 0, n - 1))
        half = 0.5 * row.max()
        if row[k] < half:
            continue
        a = k
        while a > 0 and row[a - 1] >= half:
            a -= 1
        b = k
        while b < n - 1 and row[b + 1] >= half:
            b += 1
        if a == 0 or b == n - 1:
            continue  # an edge outside the window: keep the centroid
        left = a - (row[a] - half) / max(row[a] - row[a - 1], 1e-6)
        right = b + (row[b] - half) / max(row[b] - row[b + 1], 1e-6)
        out[i] = 0.5 * (left + right)
    return out


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
    groups = [(x, m, b) for x, m, b in samples if x is not None and len(x) >= 10]
    if not groups:
        return None
    ball = np.concatenate([b for _, _, b in groups])
    if np.percentile(ball, 95) - np.percentile(ball, 5) < min_contrast:
        return None
    grid = np.linspace(0.02, 1.0, 99)
    cost = np.zeros(len(grid))
    for x, m, b in groups:
        ok = m > 0
        x, lm, b = x[ok], np.log(m[ok]), b[ok]
        u = (x - x.mean()) / max(np.ptp(x), 1.0)
        A = np.column_stack([np.ones_like(u), u, u * u])
        pinv = np.linalg.pinv(A)
        # all grid values at once: column g of Y is the model's left side for rho = grid[g]
        Y = lm[:, None] - np.log(1.0 - (1.0 - grid)[None, :] * b[:, None])
        res = Y - A @ (pinv @ Y)
        # one reweighting step towards an L1 fit (weighted normal equations, 3 x 3 per column)
        w = 1.0 / np.maximum(np.abs(res), 1e-3)
        M = np.einsum("ni,nj,ng->gij", A, A, w)
        rhs = np.einsum("ni,ng->gi", A, w * Y)
        coef = np.linalg.solve(M, rhs[:, :, None])[:, :, 0]
        cost += np.abs(Y - A @ coef.T).sum(0)
    i = int(np.argmin(cost))
    if 0 < i < len(grid) - 1:  # parabolic refinement
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        den = c0 - 2 * c1 + c2
        step = 0.5 * (c0 - c2) / den if den > 0 else 0.0
        return float(grid[i] + np.clip(step, -1, 1) * (grid[1] - grid[0]))
    return float(grid[i])


def _smooth_rows(s: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of each profile (along axis 1)."""
    r = int(np.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    return cv2.filter2D(s.astype(np.float32), -1, k[None, :].astype(np.float32),
                        borderType=cv2.BORDER_REPLICATE)


def _fwhm(prof: np.ndarray, noise: float) -> float:
    """Median full width at half maximum (px) of the profiles with a clear peak."""
    base = np.median(prof, axis=1, keepdims=True)
    s = prof - base
    pk = s.max(axis=1)
    good = pk > 8 * noise
    if good.sum() < 3:
        return 3.0
    above = s[good] > 0.5 * pk[good, None]
    widths = above.sum(axis=1)
    return float(np.clip(np.median(widths), 1.0, 30.0))


def _reject_outliers(pts: np.ndarray, camera: CameraModel | None,
                     k: float = 3.5, iters: int = 5) -> tuple[np.ndarray, float]:
    """Inlier mask of stripe centres against a smooth curve, and the inliers' rms (px)."""
    n = len(pts)
    keep = np.ones(n, bool)
    if n < 5:
        return keep, float("nan")
    if camera is not None:
        xy = undistort_pixels(camera, pts)
        f = float(np.mean(np.diag(camera.K)[:2]))
        keep &= np.all(np.isfinite(xy), axis=1)
    else:
        xy, f = pts, 1.0
    r = np.zeros(n)
    for _ in range(iters):
        if keep.sum() < 5:
            break
        if camera is not None:
            c = xy[keep].mean(0)
            _, _, vt = np.linalg.svd(xy[keep] - c, full_matrices=False)
            r = ((xy - c) @ vt[1]) * f
        else:
            c = pts[keep].mean(0)
            _, _, vt = np.linalg.svd(pts[keep] - c, full_matrices=False)
            u, v = (pts - c) @ vt[0], (pts - c) @ vt[1]
            A = np.column_stack([np.ones(n), u, u * u])
            coef, *_ = np.linalg.lstsq(A[keep], v[keep], rcond=None)
            r = v - A @ coef
        sig = MAD_TO_SIGMA * np.median(np.abs(r[keep] - np.median(r[keep])))
        new = np.isfinite(r) & (np.abs(r) <= max(k * sig, 0.05))
        if np.array_equal(new, keep):
            break
        keep = new
    rms = float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float("nan")
    return keep, rms


def stripe_points_3d(camera: CameraModel, centres_px: np.ndarray, plane: Plane) -> np.ndarray:
    """3D stripe points (N, 3), mm: rays through the centres meet that board's plane (eq. 5)."""
    return backproject_to_plane(camera, centres_px, plane)


@dataclass(frozen=True)
class CameraLines:
    """The camera side of one position (section 1.3).

    ``laser_plane`` is the total-least-squares fit of eq. (4) to both boards'
    stripe points; ``laser_plane_algebraic`` the paper's ``ax + by + cz = 1``
    least squares, for comparison; ``laser_plane_lines`` the plane through
    the two stripe lines fitted in their board planes (beyond the paper).
    ``E`` (3,) = Pi_1 ^ Pi_2 ^ Pi_L, mm. ``l[k]`` is the unit direction of
    the stripe on board ``k`` (``n_k x n_L``), oriented from ``E`` towards
    that stripe's points; ``alpha = arccos(l0 . l1)``, rad.
    ``residual_rms_mm`` is the rms distance of the stripe points to
    ``laser_plane``; ``rho`` the stripe's black/white reflectance ratio used
    to correct the centres (None: no correction).
    """

    laser_plane: Plane
    laser_plane_algebraic: Plane
    E: np.ndarray
    l: np.ndarray  # (2, 3)
    alpha: float
    centres_px: tuple[np.ndarray, np.ndarray]
    points_3d: tuple[np.ndarray, np.ndarray]
    residual_rms_mm: float
    board_planes: tuple[Plane, Plane]
    laser_plane_lines: Plane | None = None
    rho: float | None = None

    @property
    def alpha_deg(self) -> float:
        return float(np.degrees(self.alpha))


def laser_plane_from_lines(points: tuple[np.ndarray, np.ndarray],
                           planes: tuple[Plane, Plane]) -> Plane:
    """Laser plane through the two 3D stripe lines (beyond the paper).

    Each stripe is fitted as a line inside its own board plane (TLS on the
    points projected onto the plane); the laser plane is then the TLS plane
    of the two fitted lines, each sampled over the extent of its points and
    weighted by its point count.
    """
    samples, weights = [], []
    for P, pl in zip(points, planes):
        Q = pl.project(P)
        c = Q.mean(0)
        _, _, vt = np.linalg.svd(Q - c, full_matrices=False)
        d = vt[0]
        t = (Q - c) @ d
        ts = np.linspace(t.min(), t.max(), 9)
        samples.append(c + ts[:, None] * d)
        weights.append(np.full(9, len(P) / 9.0))
    return fit_plane(np.vstack(samples), np.concatenate(weights))


_CROP_CACHE: list = []  # [(board, other board, (shape, albedo), geometry)]: the same boards serve every image


def _board_crop(img: np.ndarray, board: BoardView, albedo: bool, other: BoardView | None = None):
    """The crop of ``img`` around one board's outline that :func:`stripe_centres` would use
    with the full mask ``board.mask``: (image crop, mask crop, blackness crop or None, origin).

    Only the crop is rasterised and sliced (no full-size mask or blackness map); the
    mask and blackness crops depend on the boards alone and are kept for the next image.
    The mask is ``board.stripe_outline_px`` (the pattern and half a square of its white
    border; ``outline_px`` when absent) minus the ``other`` board's ``outline_px``.
    """
    key = (img.shape[:2], albedo)
    for b, o, k, geo in _CROP_CACHE:
        if b is board and o is other and k == key:
            break
    else:
        geo = _board_crop_geometry(img.shape[:2], board, albedo, other)
        _CROP_CACHE.insert(0, (board, other, key, geo))
        del _CROP_CACHE[4:]
    if geo is None:
        return None
    msub, bsub, (x_lo, y_lo) = geo
    h, w = msub.shape
    return img[y_lo:y_lo + h, x_lo:x_lo + w], msub, bsub, (x_lo, y_lo)


def _board_crop_geometry(shape: tuple[int, int], board: BoardView, albedo: bool,
                         other: BoardView | None = None):
    """Mask crop, blackness crop (finite, float32) or None, and origin for :func:`_board_crop`."""
    H, W = shape
    outline = getattr(board, "stripe_outline_px", None)
    poly = np.round(board.outline_px if outline is None else outline).astype(np.int32)
    bx0, by0 = np.clip(poly.min(0), 0, [W - 1, H - 1])
    bx1, by1 = np.clip(poly.max(0) + 1, 1, [W, H])
    small = np.zeros((by1 - by0, bx1 - bx0), np.uint8)
    cv2.fillPoly(small, [poly], 1, offset=(-int(bx0), -int(by0)))
    if other is not None and outline is not None:
        cv2.fillPoly(small, [np.round(other.outline_px).astype(np.int32)], 0,
                     offset=(-int(bx0), -int(by0)))
    small = small.astype(bool)
    if not small.any():
        return None
    ys, xs = np.flatnonzero(small.any(axis=1)), np.flatnonzero(small.any(axis=0))
    y_lo, y_hi = max(by0 + ys[0] - _CROP_PAD, 0), min(by0 + ys[-1] + 1 + _CROP_PAD, H)
    x_lo, x_hi = max(bx0 + xs[0] - _CROP_PAD, 0), min(bx0 + xs[-1] + 1 + _CROP_PAD, W)
    msub = np.zeros((y_hi - y_lo, x_hi - x_lo), bool)
    msub[by0 - y_lo:by1 - y_lo, bx0 - x_lo:bx1 - x_lo] = small
    bsub = None
    if albedo and board.blackness is not None:
        bsub = np.zeros(msub.shape, np.float32)  # as blackness_map: 0 outside the stored crop
        ox, oy = board.blackness_origin
        h, w = board.blackness.shape
        h, w = min(h, H - oy), min(w, W - ox)
        sx0, sy0 = max(x_lo, ox), max(y_lo, oy)
        sx1, sy1 = min(x_hi, ox + w), min(y_hi, oy + h)
        if sx1 > sx0 and sy1 > sy0:
            bsub[sy0 - y_lo:sy1 - y_lo, sx0 - x_lo:sx1 - x_lo] = \
                board.blackness[sy0 - oy:sy1 - oy, sx0 - ox:sx1 - ox]
        bsub = np.nan_to_num(bsub, nan=0.0)
        bsub.flags.writeable = False  # shared by every image: never modified
    msub.flags.writeable = False
    return msub, bsub, (int(x_lo), int(y_lo))


def _board_inputs(img: np.ndarray, boards: tuple[BoardView, BoardView], albedo: bool):
    return [_board_crop(img, b, albedo, boards[1 - k]) for k, b in enumerate(boards)]


def _crop_centres(crop, camera: CameraModel, min_snr: float, rho: float | None,
                  return_info: bool = False, want_samples: bool | None = None):
    if crop is None:
        return _empty(return_info)
    sub, msub, bsub, origin = crop
    return _centres_in_crop(sub, msub, bsub, origin, camera, min_snr, rho, return_info,
                            return_info if want_samples is None else want_samples, clean=True)


def estimate_reflectance_ratio(camera: CameraModel, stripe_images: list[np.ndarray],
                               boards: tuple[BoardView, BoardView],
                               min_snr: float = 8.0) -> float | None:
    """The stripe's black/white reflectance ratio from several stripe images at once.

    A property of the board and the laser, the same at every position: pooling
    positions sees the stripe on pure white and pure black squares even when
    at some position it runs along a square edge. None without blackness maps
    or contrast.
    """
    samples = []
    for img in stripe_images:
        got = reflectance_samples(camera, img, boards, min_snr)
        if got is None:
            return None
        samples += got
    return reflectance_ratio(samples)


def reflectance_samples(camera: CameraModel, stripe_image: np.ndarray,
                        boards: tuple[BoardView, BoardView], min_snr: float = 8.0
                        ) -> list | None:
    """One image's share of :func:`estimate_reflectance_ratio`: the ``samples`` of its two
    stripes for :func:`reflectance_ratio` (None when the boards carry no blackness maps)."""
    img = np.asarray(stripe_image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    out = []
    for crop in _board_inputs(img, boards, True):
        if crop is not None and crop[2] is None:
            return None
        _, info = _crop_centres(crop, camera, min_snr, 1.0, return_info=True)
        if info.get("samples") is not None:
            out.append(info["samples"])
    return out


#: Fewer stripe centres than this on a board: no usable stripe there (section 1.3).
MIN_STRIPE_CENTRES = 10


def board_stripe_centres(camera: CameraModel, stripe_image: np.ndarray,
                         boards: tuple[BoardView, BoardView], min_snr: float = 8.0,
                         rho: float | None = None, albedo_correction: bool = True,
                         laser_colour: str = "auto"
                         ) -> tuple[list[np.ndarray], float | None, list[str | None]]:
    """Sub-pixel laser-stripe centres (raw pixels, (N, 2) per board) on each board of the V,
    the detection step of section 1.3 before any fit, the reflectance ratio used, and per
    board the quality problem (None when the stripe passes the gates of :class:`StripeGates`
    and has at least :data:`MIN_STRIPE_CENTRES` centres).

    With ``albedo_correction`` (and boards found by :func:`lidarcal.board.find_v_boards`,
    which carry blackness maps) the centres are corrected for the squares' reflectance
    (:func:`stripe_centres`); ``rho`` is the stripe's black/white reflectance ratio,
    estimated from this image's two stripes when not given (better: once per dataset with
    :func:`estimate_reflectance_ratio`). A colour image is turned into the laser's response
    by ``laser_colour`` (:func:`laser_response`).
    """
    img = np.asarray(stripe_image)
    if img.ndim == 3:
        img = laser_response(img, laser_colour)
    crops = _board_inputs(img, boards, albedo_correction)
    use_albedo = albedo_correction and all(b.blackness is not None for b in boards)
    if not use_albedo:
        crops = [None if c is None else (c[0], c[1], None, c[3]) for c in crops]
        rho = None
    elif rho is None:
        samples = []
        for crop in crops:
            _, info = _crop_centres(crop, camera, min_snr, 1.0, return_info=True)
            if info.get("samples") is not None:
                samples.append(info["samples"])
        rho = reflectance_ratio(samples)
        if rho is None:
            rho = 1.0  # not seen in this image: no division (background still uses blackness)
    centres, problems = [], []
    for k in range(2):
        c, info = _crop_centres(crops[k], camera, min_snr, rho, return_info=True,
                                want_samples=False)
        centres.append(c)
        problems.append(info.get("problem") or (
            None if len(c) >= MIN_STRIPE_CENTRES
            else f"{len(c)} stripe centres found, need at least {MIN_STRIPE_CENTRES}"))
    return centres, rho, problems


def camera_lines(camera: CameraModel, stripe_image: np.ndarray,
                 boards: tuple[BoardView, BoardView], use_pnp: bool = True,
                 min_snr: float = 8.0, rho: float | None = None,
                 albedo_correction: bool = True, laser_colour: str = "auto") -> CameraLines:
    """Laser plane (eq. 4), E, l1, l2 and alpha from one stripe image (section 1.3).

    ``use_pnp`` (default) takes the board planes from ``cv2.solvePnP`` (the
    maximum-likelihood pose, started from the homography's) instead of the
    homography alone (eqs. 2-3). Measured on the rendered wide rig (seed 37, true
    camera): board-plane offset 0.01-0.04 mm with PnP against 0.14-0.32 mm with the
    homography (normals 0.016-0.030 against 0.021-0.066 deg). The stripe centres are
    :func:`board_stripe_centres` (``rho``, ``albedo_correction``, ``laser_colour`` as there).

    Raises
    ------
    ValueError
        When a board's stripe fails the quality gates (:class:`StripeGates`: too few
        centres, not one smooth curve, too little of the board crossed, too faint); the
        caller names the file. Never wrong points instead.
    """
    planes = tuple(b.plane_pnp if use_pnp else b.plane for b in boards)
    centres, rho, problems = board_stripe_centres(camera, stripe_image, boards, min_snr, rho,
                                                  albedo_correction, laser_colour)
    for k, problem in enumerate(problems):
        if problem:
            raise ValueError(f"board {k}: {problem}; is the stripe on both boards, bright "
                             "enough, and lidar.laser_colour right?")
    return camera_lines_from_centres(camera, centres, planes, rho)


def camera_lines_from_centres(camera: CameraModel, centres: Sequence[np.ndarray],
                              planes: Sequence[Plane], rho: float | None = None) -> CameraLines:
    """Section 1.3 after centre extraction: eq. (4), E, l1, l2, alpha.

    Rays through each board's stripe centres meet that board's plane (eq. 5);
    the laser plane is the TLS fit of both boards' points (the paper's algebraic
    ``ax + by + cz = 1`` fit is kept for comparison); ``E = Pi_1 ^ Pi_2 ^ Pi_L``;
    ``l_k = n_k x n_L`` oriented from E towards stripe ``k``.
    """
    pts = [stripe_points_3d(camera, c, pl) for c, pl in zip(centres, planes)]
    allp = np.vstack(pts)
    laser = fit_plane(allp)
    E = intersect_planes(planes[0], planes[1], laser)
    ls = []
    for k in range(2):
        lk = unit(np.cross(planes[k].normal, laser.normal))
        if (pts[k].mean(0) - E) @ lk < 0:
            lk = -lk
        ls.append(lk)
    l = np.vstack(ls)
    alpha = float(np.arccos(np.clip(l[0] @ l[1], -1.0, 1.0)))
    rms = float(np.sqrt(np.mean(laser.distance(allp) ** 2)))
    return CameraLines(laser, fit_plane_algebraic(allp), E, l, alpha, (centres[0], centres[1]),
                       (pts[0], pts[1]), rms, (planes[0], planes[1]),
                       laser_plane_from_lines((pts[0], pts[1]), tuple(planes)), rho)
