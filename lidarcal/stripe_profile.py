"""Sub-pixel centre line of a laser stripe in one image (section 1.3, the detection step).

Column (or row) profiles across the stripe inside a mask: robust noise level, a coarse
line from the brightest pixels, per-profile background and an iterated symmetric-window
centroid, the squares' albedo divided out (:func:`reflectance_ratio`), outliers rejected
against a smooth curve; :func:`stripe_centres` lists the steps. The board-level use
(both boards of the V, the laser plane) is :mod:`lidarcal.stripe`.
"""

from __future__ import annotations

import cv2
import numpy as np

from .camera import undistort_pixels
from .geometry import MAD_TO_SIGMA
from .io.dataset import CameraModel
from .laser_colour import SATURATED_DN
from .stripe_quality import quality_problem, stripe_quality


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
