"""Sub-pixel centre line of a laser stripe in one image (section 1.3, the detection step).

Column (or row) profiles across the stripe inside a mask: robust noise level, a coarse
line from the brightest pixels, per-profile background and an iterated symmetric-window
centroid, the squares' albedo divided out (:func:`reflectance_ratio`), outliers rejected
against a smooth curve; :func:`stripe_centres` lists the steps. The board-level use
(both boards of the V, the laser plane) is :mod:`lidarcal.stripe`.
"""

from __future__ import annotations

import functools

import cv2
import numpy as np

from .camera import undistort_pixels
from .geometry import MAD_TO_SIGMA, median
from .io.dataset import CameraModel
from .stripe_albedo import reflectance_ratio
from .stripe_clipped import _saturated_centres, clipped_core_pixels, fwhm_run
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
        return _hist_percentile(_hist(np.ascontiguousarray(v).reshape(-1, 1)), q)
    return _hist_percentile(np.bincount(v.ravel()), q)


def _noise_rows(shape: tuple[int, ...]) -> int:
    """Row step of :func:`_noise_sigma`: every other row, sparser on large crops so that
    at least some 60 000 differences remain (a MAD needs no more)."""
    return 2 * min(max((shape[0] * shape[1]) // 120_000, 1), 8)


def _noise_sigma(img: np.ndarray, mask: np.ndarray, raw8: np.ndarray | None = None) -> float:
    """Robust sensor-noise sigma (DN) from horizontal pixel differences inside ``mask``.

    The differences of every ``k``-th row (:func:`_noise_rows`). ``raw8``: the same image
    as uint8; the medians are then taken exactly from a histogram of the (integer)
    differences, in O(n), computed in 8 bits (``d + 128`` saturated: the tails beyond
    +-127 DN stay beyond the median and its MAD; otherwise the 9-bit histogram is used).
    """
    k = _noise_rows(mask.shape)
    m = _derived(mask, ("noise", k), lambda: mask[::k, 1:] & mask[::k, :-1])
    if raw8 is not None:
        a = raw8[::k]
        masked = _derived(mask, ("noise_n", k), lambda: np.count_nonzero(m) >= 10)
        v = cv2.addWeighted(a[:, 1:], 1.0, a[:, :-1], -1.0, 128.0)  # saturate(d + 128)
        hist = _masked_hist(v, m) if masked else _hist(v)
        if hist.sum() == 0:
            return 0.5
        med2 = round(2 * _hist_percentile(hist, 50.0)) - 256  # 2 x median, an integer
        # histogram of 2 |d - median| folded from the one of d
        dev = np.abs(2 * (np.arange(256) - 128) - med2)
        mad = _hist_percentile(np.bincount(dev, weights=hist).astype(np.int64), 50.0) / 2.0
        if abs(med2) / 2.0 + mad < 120.0:
            return float(max(MAD_TO_SIGMA * mad / np.sqrt(2.0), 0.5))
        key = a[:, 1:].astype(np.uint16) + np.uint16(256) - a[:, :-1]  # d + 256, in 1..511
        if masked:
            key *= m  # 0 = outside the mask
        hist = cv2.calcHist([key], [0], None, [512], [0, 512]).ravel().astype(np.int64)[1:]
        med2 = round(2 * _hist_percentile(hist, 50.0)) - 510
        dev = np.abs(2 * (np.arange(511) - 255) - med2)
        mad = _hist_percentile(np.bincount(dev, weights=hist).astype(np.int64), 50.0) / 2.0
        return float(max(MAD_TO_SIGMA * mad / np.sqrt(2.0), 0.5))
    d = np.diff(img[::k], axis=1)
    v = d[m]
    if v.size < 10:
        v = d.ravel()
    mad = np.median(np.abs(v - np.median(v)))
    return float(max(MAD_TO_SIGMA * mad / np.sqrt(2.0), 0.5))


def _hist(img8: np.ndarray) -> np.ndarray:
    """Histogram (256,) int64 of a uint8 image (``cv2.calcHist``; exact counts)."""
    return cv2.calcHist([img8], [0], None, [256], [0, 256]).ravel().astype(np.int64)


def _masked_hist(img8: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Histogram (256,) int64 of the uint8 image's pixels where ``mask`` (bool, its shape).

    The counts of ``cv2.calcHist`` with the mask, from its plain histogram of the image
    ANDed with the mask (a pixel outside counts at 0) with the pixels outside taken off
    bin 0 again: OpenCV's masked loop costs several times its plain one.
    """
    m255, n_out = _derived(mask, "hist255", lambda: (
        np.ascontiguousarray(mask).view(np.uint8) * np.uint8(255),
        mask.size - np.count_nonzero(mask)))
    hist = _hist(cv2.bitwise_and(img8, m255))
    hist[0] -= n_out
    return hist


_DERIVED: list = []  # [(mask, key, value)]: arrays derived from the read-only board masks


def _derived(mask: np.ndarray, key, make):
    """``make()``, kept for the next image when ``mask`` is a view of a read-only array (the
    cached board masks of :func:`lidarcal.stripe._board_crop` serve every stripe image)."""
    root = mask
    while isinstance(root.base, np.ndarray):
        root = root.base
    if root.flags.writeable or mask.flags.writeable:
        return make()
    key = (key, mask.shape, mask.strides, mask.__array_interface__["data"][0])
    for m, k, v in _DERIVED:
        if m is root and k == key:
            return v
    v = make()
    if isinstance(v, np.ndarray):
        v.flags.writeable = False
    _DERIVED.insert(0, (root, key, v))
    del _DERIVED[32:]
    return v


def _coarse_line(img: np.ndarray, mask: np.ndarray, noise: float,
                 raw8: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """Rough stripe line (point, unit direction) in pixels from the brightest pixels, or None.

    Pixels well above the local background (a wide median along both axes)
    are fitted by PCA, with two rounds of rejection by the median absolute
    perpendicular residual. With ``raw8`` (the image as uint8) this is done
    in 8 bits on the image halved (``INTER_AREA``) first, and at full
    resolution only when that finds no line: the line only guides the
    column windows of :func:`_centres_by_column`, which re-centre on the stripe.
    (Halved again, a lit chessboard without a laser can pass for a stripe.) The halved
    image is made of the mask's bounding box only (:func:`_even_box`: the same pixels).
    """
    if raw8 is not None and min(raw8.shape) >= 64:
        y0, y1, x0, x1 = _derived(mask, "box", lambda: _even_box(mask))
        m8 = mask[y0:y1, x0:x1]
        small = _halved(raw8[y0:y1, x0:x1])
        h, w = small.shape
        msmall = _derived(m8, "halved", lambda: m8[:2 * h:2, :2 * w:2]
                          & m8[1:2 * h:2, 1:2 * w:2])
        found = _bright_line(_coarse_blur(small), msmall, noise, scale=2.0)
        if found is not None:
            return found[0] + np.array([x0, y0], float), found[1]
    found = _bright_line(_gaussian_blur(img if raw8 is None else raw8, 1.5), mask, noise)
    if found is not None:
        return found
    # a clipped stripe on a lit board: its clipped core (stripe_clipped.clipped_core_pixels)
    P = clipped_core_pixels(img if raw8 is None else raw8, mask)
    line = None if P is None else _pca_line(P, 1.0)
    return None if line is None or line[2] > BLOB_SPREAD_PX else line[:2]


#: Kernel sizes for ``cv2.GaussianBlur`` of uint8 images that give the very result of the
#: size OpenCV derives from sigma (``round(6 sigma + 1) | 1``: 7 and 11 px): their outer
#: taps round to 0 in OpenCV's bit-exact 8-bit fixed-point kernel, but cost as much as the
#: others (half the blur's time for sigma 0.75). tests/test_stripe_kernels.py checks it.
_UINT8_BLUR_KSIZE = {0.75: 5, 1.5: 9}


def _gaussian_blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """``cv2.GaussianBlur(img, (0, 0), sigma)``, with the smaller equal kernel of
    :data:`_UINT8_BLUR_KSIZE` on uint8 images."""
    k = _UINT8_BLUR_KSIZE.get(sigma, 0) if img.dtype == np.uint8 else 0
    return cv2.GaussianBlur(img, (k, k), sigma)


def _coarse_blur(small: np.ndarray) -> np.ndarray:
    """Smoothing of the halved uint8 image for :func:`_bright_line`: a Gaussian of sigma
    0.75 px truncated to 3 x 3 taps (its outer taps of the 5 x 5 kernel hold 3 % of the
    weight; a quarter of the 5 x 5 blur's cost). The pixels it finds above the threshold
    only guide the column windows of :func:`_centres_by_column`, which re-centre on the
    stripe (tests/test_stripe_coarse.py: the coarse line moves by at most a few tenths of a
    px, against the 5 x 5 blur)."""
    return cv2.GaussianBlur(small, (3, 3), 0.75)


def _even_box(mask: np.ndarray, margin: int = 6) -> tuple[int, int, int, int]:
    """``(y0, y1, x0, x1)``: the bounding box of ``mask`` plus ``margin`` px, clipped to it,
    starting at even rows and columns: its halved image (:func:`_halved`) holds the very
    2 x 2 blocks of the whole one's, and their 3 x 3 blur (:func:`_coarse_blur`) is the same
    wherever the halved mask is (its border lies ``margin / 2`` halved px beyond it)."""
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return 0, mask.shape[0], 0, mask.shape[1]
    y0, x0 = max(rows[0] - margin, 0) // 2 * 2, max(cols[0] - margin, 0) // 2 * 2
    return (int(y0), int(min(rows[-1] + 1 + margin, mask.shape[0])),
            int(x0), int(min(cols[-1] + 1 + margin, mask.shape[1])))


def _halved(img: np.ndarray) -> np.ndarray:
    """``img`` reduced 2 times by averaging 2 x 2 blocks (``INTER_AREA``; an odd last row or
    column is dropped)."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    return cv2.resize(img[:2 * h, :2 * w], (w, h), interpolation=cv2.INTER_AREA)


def _bright_line(sm: np.ndarray, mask: np.ndarray, noise: float, scale: float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """PCA line of the pixels of a smoothed image ``sm`` well above its background, in
    full-resolution pixels (``sm`` is the image reduced by ``scale``).

    Above the background: brighter than ``base + max(0.35 (peak - base), 6 noise)``, with
    ``base`` the median and ``peak`` the 99.9th percentile of the masked pixels (a uint8
    image: both from one histogram of them; a float one: the median of every 7th). When
    those pixels spread more than ``BLOB_SPREAD_PX`` about their line (a bright reflection
    wider than the stripe took it), the line is found again without the regions thicker than
    a stripe, and kept when those pixels spread as a stripe's do (else the first line stands)."""
    if sm.dtype == np.uint8 and sm.flags.c_contiguous:
        hist = _masked_hist(sm, mask)  # the masked pixels' histogram
        if hist.sum() < 20:
            return None
        base = _hist_percentile(hist, 50.0)
        peak = _hist_percentile(hist, 99.9)
    elif (vals := sm[mask]).size < 20:
        return None
    elif sm.dtype == np.uint8:
        base = _int_percentile(vals, 50.0)
        peak = _int_percentile(vals, 99.9)
    else:
        base = np.median(vals[::7])
        peak = np.percentile(vals, 99.9)
    thr = base + max(0.35 * (peak - base), 6.0 * noise)
    if sm.dtype == np.uint8:  # integers: v > thr is v > floor(thr), as cv2.threshold tests
        hot = cv2.threshold(sm, thr, 1, cv2.THRESH_BINARY)[1]
        hot &= np.ascontiguousarray(mask).view(np.uint8)
        found = cv2.findNonZero(hot)  # (x, y) in row-major order, as np.nonzero
        if found is None or len(found) < 10:
            return None
        P = found.reshape(-1, 2).astype(float)
    else:
        ys, xs = np.nonzero(mask & (sm > thr))
        if xs.size < 10:
            return None
        P = np.column_stack([xs, ys]).astype(float)
    found = _pca_line(P, scale)
    if found is None or found[2] <= BLOB_SPREAD_PX:
        return None if found is None else found[:2]
    # the bright pixels spread far about their line: a reflection or glint brighter and
    # wider than the stripe holds the fit. The same bright pixels without the regions
    # thicker than any stripe (they survive an opening by a disc ~2 BLOB_SPREAD_PX wide)
    # give the stripe's line, taken when they spread as a stripe's do.
    hot8 = cv2.threshold(sm, thr, 1, cv2.THRESH_BINARY)[1] if sm.dtype == np.uint8 else \
        (sm > thr).astype(np.uint8)
    hot8 &= np.ascontiguousarray(mask).view(np.uint8)
    k = 2 * round(BLOB_SPREAD_PX / scale) + 1
    thick = cv2.morphologyEx(hot8, cv2.MORPH_OPEN,
                             cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    rest = cv2.findNonZero(hot8 & (1 - thick))
    if rest is None or len(rest) < 10:
        return found[:2]
    thin = _pca_line(rest.reshape(-1, 2).astype(float), scale)
    return thin[:2] if thin is not None and thin[2] <= BLOB_SPREAD_PX else found[:2]


#: A coarse line whose bright pixels spread more than this (px, robust sigma across it) is
#: held by something wider than a stripe (a reflection): see :func:`_bright_line`. Stripes
#: spread 2-3 px on the paper, harsh and wide rigs (lights on, saturated, blooming); a bright
#: reflection blob 25-30 px.
BLOB_SPREAD_PX = 8.0


def _pca_line(P: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray, float] | None:
    """PCA line (point, unit direction) of the pixels ``P`` (N, 2) of an image reduced by
    ``scale``, in full-resolution pixels, with two rounds of rejection by the median absolute
    perpendicular residual, and the robust sigma (px) of the pixels about it."""
    if scale != 1.0:
        P = scale * P + 0.5 * (scale - 1)
    x, y = np.ascontiguousarray(P.T)  # the two coordinates, each contiguous
    keep = np.ones(len(P), bool)
    for _ in range(3):
        xk, yk = x[keep], y[keep]
        c = np.array([_mean(xk), _mean(yk)])
        t = _principal_direction_xy(xk - c[0], yk - c[1])
        r = (y - c[1]) * t[0] - (x - c[0]) * t[1]  # distance from the line
        s = MAD_TO_SIGMA * median(np.abs(r[keep]))
        new = np.abs(r) <= max(3 * s, 2.0)
        if np.count_nonzero(new) < 10:
            return None
        if np.array_equal(new, keep):
            break  # the next round would fit the same points again
        keep = new
    return c, t, s


def _principal_direction(q: np.ndarray) -> np.ndarray:
    """Unit direction of largest spread of centred 2D points (N, 2): the first principal
    axis (the leading right singular vector), in closed form from the 2 x 2 scatter."""
    return _principal_direction_xy(q[:, 0], q[:, 1])


def _principal_direction_xy(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """:func:`_principal_direction` of the points ``(dx, dy)`` given as two coordinate arrays."""
    sxx, syy, sxy = dx @ dx, dy @ dy, dx @ dy
    a = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    return np.array([np.cos(a), np.sin(a)])


def _window_centroid(prof: np.ndarray, start: np.ndarray, half: float, iters: int = 6,
                     tol: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """Iterated centroid of background-free profiles (M, W) in a window ``start +- half``.

    Returns centres (profile index units) and the summed signal in the window.
    Symmetric windows make the fixed point the centre of a symmetric stripe
    profile, including one clipped at saturation. Stops early once no centre
    moves by more than ``tol`` px. Sample ``j`` weighs the overlap of its cell
    ``[j - 1/2, j + 1/2]`` with the window (fractional at the edges: the centroid is
    continuous in c), so both window sums are differences of running sums of the
    profile, O(1) per profile and step (``half >= 1/2``).
    """
    n_rows, n = prof.shape
    s = np.maximum(prof, 0, dtype=np.float64)  # clipped at 0, in float64
    # running sums along each profile from integral images (row r + 1 minus row r)
    cs = cv2.integral(s, sdepth=cv2.CV_64F)
    cj = cv2.integral(s * np.arange(n), sdepth=cv2.CV_64F)
    cs, cj = (cs[1:] - cs[:-1]).ravel(), (cj[1:] - cj[:-1]).ravel()  # (n_rows, n + 1)
    sf = np.concatenate([s, np.zeros((n_rows, 1))], axis=1).ravel()
    c = start.astype(float).copy()
    mass = np.zeros(n_rows)
    act = np.arange(n_rows)  # rows still moving; converged rows are left alone
    base = act * (n + 1)
    edges = np.array([[half + 0.5], [0.5 - half]])  # window ends, + 1/2: cells from -1/2
    with np.errstate(invalid="ignore", divide="ignore"):
        for _ in range(iters):
            ca = c[act]
            # integrals of s and of j s from -1/2 up to both window ends (clipped)
            x = np.clip(ca + edges, 0.0, n)
            k = x.astype(np.intp)  # floor (x >= 0)
            i = k + base[act]
            sk = sf[i] * (x - k)
            m2 = cs[i] + sk
            j2 = cj[i] + k * sk
            m = m2[0] - m2[1]
            c_new = np.where(m > 0, (j2[0] - j2[1]) / m, np.nan)
            moving = np.abs(c_new - ca) > tol  # False for NaN: such rows stay NaN
            c[act], mass[act] = c_new, m
            act = act[moving]
            if act.size == 0:
                break
    return c, mass


def _profiles(img: np.ndarray, xs: np.ndarray, y0: np.ndarray, L: int) -> tuple[np.ndarray,
                                                                               np.ndarray]:
    """Column profiles ``img[y0 + k, x]`` for ``k = -L..L`` (M, 2L+1), clipped to the image."""
    top = _profile_top(y0, L, img.shape[0])
    return _profiles_at(img, xs, top, 2 * L + 1), top


def _profiles_at(img: np.ndarray, xs: np.ndarray, top: np.ndarray, n: int) -> np.ndarray:
    """Column profiles ``img[top + k, x]`` for ``k = 0..n-1`` (M, n), float32; ``top`` as
    :func:`_profile_top` gives it (in the image when it has ``n`` rows)."""
    H = img.shape[0]
    if H >= n:  # windows of n rows: one gather of M runs, not M x n single pixels
        s0, s1 = img.strides
        win = np.lib.stride_tricks.as_strided(img, (H - n + 1, img.shape[1], n), (s0, s1, s0),
                                              writeable=False)
        return win[top, xs].astype(np.float32, copy=False)
    rows = np.clip(top[:, None] + np.arange(n)[None, :], 0, H - 1)
    return img[rows, xs[:, None]].astype(np.float32, copy=False)


def stripe_centres(image: np.ndarray, mask: np.ndarray, camera: CameraModel | None = None,
                   min_snr: float = 8.0, blackness: np.ndarray | None = None,
                   rho: float | None = None, return_info: bool = False):
    """Sub-pixel centre line of a laser stripe inside ``mask`` (section 1.3), pixels (N, 2).

    1. Robust noise level (MAD of pixel differences) and a coarse stripe line
       (PCA of the brightest pixels): its direction decides whether the
       stripe is sampled by columns (|slope| <= 1) or by rows.
    2. Stripe width from the median profile (with ``blackness``: of the profiles less
       their background, the run above half the peak, so a lit square beside the stripe
       does not widen it); per column, a window of a few widths around the predicted
       centre; background from the window's two
       outer thirds (a straight line; with ``blackness``, ambient light
       reflected by the squares: ``b0 + b1 * blackness``).
    3. Centre = iterated symmetric-window centroid; a clipped profile's centre is the
       midpoint of its run above half the smaller headroom of its two flanks
       (:func:`_saturated_centres`; on a lit board the white squares leave less room
       below the clip than the black ones), dropped where the albedo changes under that
       run; columns whose peak is below ``min_snr`` noise sigmas are dropped.
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
    ``n_rejected``, ``samples`` (x, signal mass, effective blackness per
    column, for a joint :func:`reflectance_ratio`) and ``normalised`` (the centres
    undistorted to normalised coordinates, (N, 2), when ``camera`` is given).
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
                     clean: bool = False, samples_only: bool = False):
    """:func:`stripe_centres` on a crop (origin ``(x0, y0)`` in the image) holding the mask.

    ``clean``: ``bsub`` is already finite float32 (from :func:`_board_crop`).
    ``samples_only``: the caller wants ``info["samples"]`` alone (the reflectance ratio):
    the centres' outlier test and quality gates are skipped."""
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
    res = _centres_by_column(sub, msub, c0, slope, noise, min_snr, bsub, rho,
                             want_samples=want_samples or rho is None)
    if res is None:
        return _empty(return_info)
    pts, snr, width, rho_used, samples = res
    if samples_only:
        return pts, {"samples": samples, "rho": rho_used}
    if transpose:
        pts = pts[:, ::-1]
    pts = pts + np.array([x_lo, y_lo], float)
    keep, fit_rms, xy = _reject_outliers(pts, camera)
    pts = pts[keep]
    if not return_info:
        return pts
    snr, n_rejected = snr[keep], len(keep) - len(pts)
    quality = stripe_quality(pts, n_rejected, fit_rms, width, snr, mask_img, (x_lo, y_lo))
    info = {"snr": snr, "width_px": width, "noise_dn": noise, "rho": rho_used,
            "fit_rms_px": fit_rms, "n_rejected": n_rejected, "samples": samples,
            "quality": quality, "problem": quality_problem(quality),
            "normalised": None if xy is None else xy[keep]}
    return pts, info


def _mean(v: np.ndarray) -> float:
    """``v.mean()`` of a 1-D float64 array (the same sum and division), without the
    wrapper's checks."""
    return v.sum() / v.size


def _row_median(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` for finite data, by one partition (odd rows) or one sort
    (even rows of several: a partition at two ranks costs several times a sort there; both
    give the same order statistics, so the same medians)."""
    n = a.shape[1]
    k = n // 2
    if n % 2:
        return np.partition(a, k, axis=1)[:, k]
    p = np.partition(a, [k - 1, k], axis=1) if a.shape[0] == 1 else np.sort(a, axis=1)
    return 0.5 * (p[:, k - 1] + p[:, k])


def _row_max(a: np.ndarray) -> np.ndarray:
    """``a.max(axis=1)`` (the same maxima) as a reduction across the rows of the transposed
    copy: numpy reduces short rows one at a time, but vectorises across rows."""
    return np.ascontiguousarray(a.T).max(axis=0)


def _background(prof: np.ndarray, bprof: np.ndarray | None) -> np.ndarray:
    """Background of each profile (M, W) fitted to its two outer thirds.

    A straight line through the medians of the two thirds; where the
    blackness differs between the two thirds, ``b0 + b1 * blackness``
    (ambient light is reflected in proportion to the squares' albedo).
    """
    m, n = prof.shape
    third = max(n // 3, 2)
    parts = [prof[:, :third], prof[:, -third:]]
    if bprof is not None and bprof.dtype == prof.dtype:
        parts += [bprof[:, :third], bprof[:, -third:]]
    med = _row_median(np.concatenate(parts))  # all the thirds' medians at once
    left, right = med[:m], med[m:2 * m]
    xl, xr = (third - 1) / 2.0, n - 1 - (third - 1) / 2.0
    u = (np.arange(n)[None, :] - xl) / (xr - xl)
    if bprof is None:
        return left[:, None] + (right - left)[:, None] * u
    if len(med) > 2 * m:
        bl, br = med[2 * m:3 * m], med[3 * m:]
    else:
        bl, br = _row_median(bprof[:, :third]), _row_median(bprof[:, -third:])
    db = br - bl
    is_step = np.abs(db) > 0.3
    if not is_step.any():
        return left[:, None] + (right - left)[:, None] * u
    # each row by its own model (most rows of a stripe across the squares are steps)
    bg = np.empty((m, n), np.result_type(left, u))
    flat, step = np.flatnonzero(~is_step), np.flatnonzero(is_step)
    bg[flat] = left[flat, None] + (right[flat] - left[flat])[:, None] * u
    slope = (right[step] - left[step]) / db[step]
    bg[step] = left[step, None] + slope[:, None] * (bprof[step] - bl[step, None])
    return bg


def _centres_by_column(img: np.ndarray, mask: np.ndarray, c0: np.ndarray, slope: float,
                       noise: float, min_snr: float, blk: np.ndarray | None = None,
                       rho: float | None = None, want_samples: bool = True):
    """Column-wise centres; returns (points (N, 2), snr, width, rho used, samples) or None."""
    cols = _derived(mask, "cols", lambda: np.flatnonzero(mask.any(axis=0)))
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
    if blk is not None:  # a lit board: its squares' steps are background, not stripe
        bprof0 = np.clip(_profiles_at(blk, cols, top, 2 * L0 + 1), 0.0, 1.0)
        width = fwhm_run(prof - _background(prof, bprof0), noise)
    else:
        width = _fwhm(prof, noise)
    L = int(min(max(np.ceil(4 * width) + 6, 10), (H - 1) // 2))
    half = max(1.5 * width, 2.0)
    y_cur = y_pred
    samples = None
    rho_used = rho
    # with blackness, passes with the albedo divided out; rho (when not given) is estimated
    # from a plain pass 0 and re-estimated after each pass, as the centres it weights by
    # move. A column whose window did not move since the last pass with the same albedo
    # division gives the same centre again: only the columns whose window moved are
    # recomputed. (With rho given, a plain pass 0 only placed the windows: dividing from the
    # start gave the same centres on the paper and p11 rigs, within 0.1 px (median) on the
    # harsh one, with the same error against the truth.)
    n_pass = 2 if blk is None else 4
    idx = np.arange(2 * L + 1)[None, :]
    sig_smooth = max(width / 2.355, 0.8)
    st = None  # per column: prof, bprof, s_raw, start, peak, cen (the last pass's)
    divided_by = None
    for it in range(n_pass):
        divide = rho_used if blk is not None and (it > 0 or rho is not None) else None
        if st is None or divide != divided_by:
            top = _profile_top(y_cur, L, H)
            st = list(_column_pass(img, blk, cols, top, L, sig_smooth, divide, half))
        else:
            new_top = _profile_top(y_cur, L, H)
            moved = np.flatnonzero(new_top != top)
            top = new_top
            if moved.size:
                for arr, part in zip(st, _column_pass(img, blk, cols[moved], top[moved], L,
                                                      sig_smooth, divide, half)):
                    if arr is not None:
                        arr[moved] = part
        divided_by = divide
        prof, bprof, s_raw, _, peak, cen = st
        ok = np.isfinite(cen) & (peak >= min_snr * noise)
        y_cur = np.where(ok, top + cen, y_cur)
        # (with rho given, only the last of these passes' samples is returned)
        if bprof is not None and want_samples and (it == n_pass - 2 or
                                                   (rho is None and it < n_pass - 1)):
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
    cen, peak = _saturated_centres(prof, s_raw, cen, peak, bprof, noise)
    yc = top + cen
    ok = np.isfinite(cen) & (peak >= min_snr * noise) & (cen > half) & (cen < n - 1 - half)
    xi, yi = cols[ok], yc[ok]
    inmask = mask[np.clip(np.round(yi).astype(int), 0, H - 1), xi]
    xi, yi, snr = xi[inmask], yi[inmask], (peak[ok] / noise)[inmask]
    if xi.size < 5:
        return None
    return np.column_stack([xi.astype(float), yi]), snr, width, rho_used, samples


def _profile_top(y: np.ndarray, L: int, H: int) -> np.ndarray:
    """First row of the profile windows ``round(y) - L`` (:func:`_profiles`), in the image."""
    return np.clip(np.round(y).astype(np.intp) - L, 0, max(H - 2 * L - 1, 0))


def _column_pass(img: np.ndarray, blk: np.ndarray | None, cols: np.ndarray, top: np.ndarray,
                 L: int, sig_smooth: float, divide: float | None, half: float):
    """One pass of :func:`_centres_by_column` over the columns ``cols`` with windows from
    row ``top``: profiles, blackness profiles (or None), background-free profiles, start
    of the centroid, peak, centre (in window rows; the albedo ``1 - (1 - divide) b`` divided
    out when ``divide`` is given)."""
    prof = _profiles_at(img, cols, top, 2 * L + 1)
    bprof = None if blk is None else np.clip(_profiles_at(blk, cols, top, 2 * L + 1), 0.0, 1.0)
    s = prof - _background(prof, bprof)
    start = np.argmax(_smooth_rows(s, sig_smooth), axis=1)
    peak = s[np.arange(len(s)), start]
    # (rho = 1: the albedo is 1 everywhere and the division leaves s as it is)
    s_div = s if divide is None or divide == 1.0 else s / (1.0 - (1.0 - divide) * bprof)
    cen, _ = _window_centroid(s_div, start.astype(float), half)
    return prof, bprof, s, start, peak, cen


def _smooth_rows(s: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of each profile (along axis 1)."""
    return cv2.filter2D(s.astype(np.float32), -1, _gauss_kernel(sigma),
                        borderType=cv2.BORDER_REPLICATE)


@functools.lru_cache(maxsize=8)
def _gauss_kernel(sigma: float) -> np.ndarray:
    """The normalised Gaussian (1, 2r + 1), float32, ``r = ceil(3 sigma)``, of :func:`_smooth_rows`."""
    r = int(np.ceil(3 * sigma))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    return k[None, :].astype(np.float32)


def _fwhm(prof: np.ndarray, noise: float) -> float:
    """Median full width at half maximum (px) of the profiles with a clear peak."""
    # (M, W) profiles handled as (W, M): the per-profile max and count of samples above
    # half of it are reductions across profiles, which numpy vectorises (same numbers)
    s = np.ascontiguousarray(prof.T) - _row_median(prof)
    pk = s.max(axis=0)
    good = pk > 8 * noise
    if good.sum() < 3:
        return 3.0
    widths = np.add.reduce(s > 0.5 * pk, axis=0, dtype=np.intp)[good]
    return min(max(median(widths), 1.0), 30.0)


def _reject_outliers(pts: np.ndarray, camera: CameraModel | None,
                     k: float = 3.5, iters: int = 5) -> tuple[np.ndarray, float, np.ndarray | None]:
    """Inlier mask of stripe centres against a smooth curve, the inliers' rms (px), and the
    centres' undistorted normalised coordinates (N, 2) when ``camera`` is given (else None).
    """
    n = len(pts)
    keep = np.ones(n, bool)
    if n < 5:
        return keep, float("nan"), None
    if camera is not None:
        xy = undistort_pixels(camera, pts)
        f = 0.5 * (float(camera.K[0][0]) + float(camera.K[1][1]))  # mean focal length
        keep &= np.all(np.isfinite(xy), axis=1)
        u, v = np.ascontiguousarray(xy.T)  # the two coordinates, each contiguous
    else:
        xy, f = pts, 1.0
    r = np.zeros(n)
    for _ in range(iters):
        if keep.sum() < 5:
            break
        if camera is not None:
            uk, vk = u[keep], v[keep]
            cu, cv = _mean(uk), _mean(vk)
            t = _principal_direction_xy(uk - cu, vk - cv)
            r = ((v - cv) * t[0] - (u - cu) * t[1]) * f  # distance from the line, x f
        else:
            c = pts[keep].mean(0)
            t = _principal_direction(pts[keep] - c)
            u, v = (pts - c) @ t, (pts - c) @ np.array([-t[1], t[0]])
            A = np.column_stack([np.ones(n), u, u * u])
            coef, *_ = np.linalg.lstsq(A[keep], v[keep], rcond=None)
            r = v - A @ coef
        rk = r[keep]
        sig = MAD_TO_SIGMA * median(np.abs(rk - median(rk)))
        new = np.isfinite(r) & (np.abs(r) <= max(k * sig, 0.05))
        if np.array_equal(new, keep):
            break
        keep = new
    rms = float(np.sqrt(np.mean(r[keep] ** 2))) if keep.any() else float("nan")
    return keep, rms, (xy if camera is not None else None)
