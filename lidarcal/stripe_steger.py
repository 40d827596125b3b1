"""Sub-pixel stripe centres by Steger's line detector (section 1.3, the detection step).

C. Steger, "An unbiased detector of curvilinear structures", IEEE PAMI 20(2), 1998:
the image is convolved with the derivatives of a Gaussian of scale ``sigma``; at each
pixel the Hessian's eigenvector of the most negative eigenvalue is the line's normal
``n``, and the second-order Taylor expansion along ``n`` puts the line's centre at
``p + t n`` with ``t = -(r_x n_x + r_y n_y) / (r_xx n_x^2 + 2 r_xy n_x n_y + r_yy n_y^2)``
(eq. 14 of the paper); a pixel holds a line point when ``|t n_x|, |t n_y| <= 1/2``.
A bar-shaped line of half-width ``w`` (a saturated core is one) has a single centre
only for ``sigma >= w / sqrt(3)`` (eq. 9): ``sigma`` is taken from the stripe's measured
width. The Gaussian also averages the stripe's speckle over ``sigma`` along it.

Used by :mod:`lidarcal.laserplane` on the colour-excess image already averaged along
the stripe (:func:`lidarcal.laser_colour.along_stripe`), guided by the centroid
centres of :func:`lidarcal.stripe_profile.stripe_centres` (one Steger point per column,
or row, of the stripe near them).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

#: Steger's eq. (9): a bar of half-width w has one centre for sigma >= w / sqrt(3)
SQRT3 = float(np.sqrt(3.0))
#: the smallest scale (px): below ~half a pixel the Gaussian's sampled derivatives are poor
MIN_SIGMA_PX = 0.5
#: a line point's second derivative across the line must exceed this many times its noise
#: (:func:`ridge_noise`): the SNR the centroid asks of a profile's peak (``min_snr``)
MIN_RIDGE_SNR = 8.0


def ridge_noise(noise_dn: float, sigma: float) -> float:
    """The standard deviation of a Gaussian second derivative of scale ``sigma`` (px) of
    white noise of ``noise_dn``: ``noise_dn sqrt(3 / (16 pi sigma^6))`` (the squared
    kernel's integral)."""
    return float(noise_dn) * float(np.sqrt(3.0 / (16.0 * np.pi * sigma ** 6)))


def steger_sigma(width_px: float) -> float:
    """Steger's scale for a stripe of full width at half maximum ``width_px``: its half
    width ``w = width_px / 2`` over ``sqrt(3)`` (eq. 9), at least ``MIN_SIGMA_PX``."""
    return max(0.5 * float(width_px) / SQRT3, MIN_SIGMA_PX)


def hessian_line_points(img: np.ndarray, sigma: float, cand: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steger's line points (eq. 14) at the candidate pixels ``cand`` (N, 2) (x, y ints).

    Returns (points (M, 2) sub-pixel x, y; the second directional derivative across the
    line there, ``-lambda`` > 0 for a bright line; the index into ``cand`` of each point;
    the unit normals (M, 2)).
    """
    f = np.asarray(img, np.float32)
    d = {o: ndimage.gaussian_filter(f, sigma, order=o, mode="nearest")
         for o in ((0, 1), (1, 0), (0, 2), (1, 1), (2, 0))}  # (y order, x order)
    xs, ys = cand[:, 0], cand[:, 1]
    rx, ry = d[(0, 1)][ys, xs], d[(1, 0)][ys, xs]
    rxx, rxy, ryy = d[(0, 2)][ys, xs], d[(1, 1)][ys, xs], d[(2, 0)][ys, xs]
    half_tr = 0.5 * (rxx + ryy)
    rad = np.sqrt((0.5 * (rxx - ryy)) ** 2 + rxy ** 2)
    lam = half_tr - rad  # the most negative eigenvalue: across a bright line
    # its eigenvector, from the better conditioned of the two rows of H - lam I
    a = np.column_stack([rxy, lam - rxx])
    b = np.column_stack([lam - ryy, rxy])
    v = np.where((np.abs(a).sum(1) >= np.abs(b).sum(1))[:, None], a, b)
    norm = np.linalg.norm(v, axis=1)
    ok = (norm > 0) & (lam < 0)
    n = v / np.where(norm > 0, norm, 1.0)[:, None]
    nx, ny = n[:, 0], n[:, 1]
    den = rxx * nx * nx + 2 * rxy * nx * ny + ryy * ny * ny
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -(rx * nx + ry * ny) / den
    ok &= np.isfinite(t) & (np.abs(t * nx) <= 0.5) & (np.abs(t * ny) <= 0.5)
    idx = np.flatnonzero(ok)
    pts = np.column_stack([xs[idx] + t[idx] * nx[idx], ys[idx] + t[idx] * ny[idx]])
    return pts, -lam[idx], idx, n[idx]


def steger_centres(response: np.ndarray, mask: np.ndarray, guide_px: np.ndarray,
                   width_px: float, band_px: float | None = None,
                   saturated: np.ndarray | None = None, noise_dn: float = 0.0
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Steger centres of the stripe near the guide centres ``guide_px`` (N, 2), inside
    ``mask``: (points (M, 2), their strength ``-lambda``, sigma used).

    The candidates are the mask's pixels within ``band_px`` (default: the stripe's width,
    at least 2 px) of the guide polyline (the centroid centres, sorted along the stripe);
    the Hessian is computed on the mask's box only. Of the pixels of one column (a stripe
    sampled by columns, |slope| <= 1; else of one row) that hold a line point, the one with
    the strongest ``-lambda`` is kept: one centre per column, as the centroid gives.
    ``saturated`` (bool, the image's shape): where the laser's channel clips; a point there
    lies on a filled core (:func:`lidarcal.laser_colour.laser_response`), whose flat top
    is not a smooth bar: its centre is the midpoint of the run above half the peak along
    the normal (:func:`half_max_midpoints`), as :mod:`lidarcal.stripe_profile` centres
    clipped profiles. Points whose ``-lambda`` is below ``MIN_RIDGE_SNR`` times its noise
    (:func:`ridge_noise` of ``noise_dn``, the image's noise) are not line points.
    """
    guide = np.asarray(guide_px, float)
    if len(guide) < 2:
        return np.empty((0, 2)), np.empty(0), float("nan")
    sigma = steger_sigma(width_px)
    band = max(float(width_px), 2.0) if band_px is None else float(band_px)
    c = guide.mean(0)
    _, _, vt = np.linalg.svd(guide - c, full_matrices=False)
    by_cols = abs(vt[0][0]) >= abs(vt[0][1])
    order = np.argsort((guide - c) @ vt[0])
    H, W = mask.shape
    pad = int(np.ceil(4 * sigma + band)) + 2
    x0 = max(int(np.floor(guide[:, 0].min())) - pad, 0)
    x1 = min(int(np.ceil(guide[:, 0].max())) + pad + 1, W)
    y0 = max(int(np.floor(guide[:, 1].min())) - pad, 0)
    y1 = min(int(np.ceil(guide[:, 1].max())) + pad + 1, H)
    near = np.zeros((y1 - y0, x1 - x0), np.uint8)
    poly = np.round((guide[order] - [x0, y0]) * 16).astype(np.int32)
    cv2.polylines(near, [poly], False, 1, thickness=int(2 * np.ceil(band) + 1),
                  shift=4)
    near &= np.asarray(mask[y0:y1, x0:x1], np.uint8)
    ys, xs = np.nonzero(near)
    if xs.size == 0:
        return np.empty((0, 2)), np.empty(0), sigma
    crop = np.asarray(response[y0:y1, x0:x1], np.float32)
    pts, strength, idx, normals = hessian_line_points(crop, sigma, np.column_stack([xs, ys]))
    strong = strength >= MIN_RIDGE_SNR * ridge_noise(noise_dn, sigma)
    pts, strength, idx, normals = pts[strong], strength[strong], idx[strong], normals[strong]
    if len(pts) == 0:
        return np.empty((0, 2)), np.empty(0), sigma
    key = xs[idx] if by_cols else ys[idx]
    # strongest point per column (row): sort by key, then by -strength, keep the first
    o = np.lexsort((-strength, key))
    first = np.ones(len(o), bool)
    first[1:] = key[o][1:] != key[o][:-1]
    keep = o[first]
    pts, normals = pts[keep], normals[keep]
    if saturated is not None and len(pts):
        on = np.asarray(saturated, bool)[y0:y1, x0:x1][ys[idx[keep]], xs[idx[keep]]]
        if on.any():
            pts[on] = half_max_midpoints(crop, pts[on], normals[on], 1.5 * max(width_px, 2.0))
    return pts + [x0, y0], strength[keep], sigma


def half_max_midpoints(img: np.ndarray, pts: np.ndarray, normals: np.ndarray,
                       reach_px: float) -> np.ndarray:
    """Each point moved along its normal to the midpoint of the run above half the peak
    (over the lower of the two ends) of the profile through it, sampled every 1/4 px out
    to ``reach_px`` each way (bilinear, ``cv2.remap``); the two edges interpolated
    linearly. A point whose run reaches an end keeps its place."""
    s = np.arange(-reach_px, reach_px + 1e-9, 0.25, dtype=np.float32)
    X = (pts[:, 0, None] + s[None, :] * normals[:, 0, None]).astype(np.float32)
    Y = (pts[:, 1, None] + s[None, :] * normals[:, 1, None]).astype(np.float32)
    prof = cv2.remap(np.asarray(img, np.float32), X, Y, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE).astype(float)
    n = len(s)
    q = max(n // 8, 1)
    base = np.minimum(np.median(prof[:, :q], 1), np.median(prof[:, -q:], 1))
    half = base + 0.5 * (prof.max(1) - base)
    above = prof >= half[:, None]
    k0 = n // 2  # s = 0: the Steger point
    idx = np.arange(n)[None, :]
    below = ~above
    a = np.max(np.where(below & (idx < k0), idx, -1), axis=1)       # last below, left
    b = np.min(np.where(below & (idx > k0), idx, n), axis=1)        # first below, right
    ok = above[:, k0] & (a >= 0) & (b < n)
    out = pts.copy()
    r = np.flatnonzero(ok)
    a, b, h = a[r], b[r], half[r]
    P = prof[r]
    j = np.arange(len(r))
    left = s[a] + 0.25 * (h - P[j, a]) / np.maximum(P[j, a + 1] - P[j, a], 1e-6)
    right = s[b - 1] + 0.25 * (P[j, b - 1] - h) / np.maximum(P[j, b - 1] - P[j, b], 1e-6)
    out[r] = pts[r] + (0.5 * (left + right))[:, None] * normals[r]
    return out


def steger_stripe(response: np.ndarray, mask: np.ndarray, camera, guide_px: np.ndarray,
                  guide_info: dict, saturated: np.ndarray | None = None
                  ) -> tuple[np.ndarray, dict]:
    """The stripe's centres by :func:`steger_centres` near the centroid centres
    ``guide_px`` of :func:`lidarcal.stripe_profile.stripe_centres` (with its
    ``return_info`` dict ``guide_info``), outliers rejected and judged by the same gates
    (:func:`lidarcal.stripe_quality.stripe_quality`): (centres (N, 2), info with
    ``fit_rms_px``, ``quality``, ``problem``, ``sigma_px``).

    A column whose profile only shows the flank of a stripe hidden in an area left out of
    ``mask`` (an overexposed square beside it) has no ridge there and gives no Steger
    point (the centroid puts a centre on the flank, which the outlier test then counts
    against the stripe). Each point's SNR is its column's centroid SNR (the peak over
    the noise, ``guide_info["snr"]``) of the nearest guide centre along the stripe.
    The centres are correlated along the stripe over about ``sigma_px`` (and over the
    along-stripe averaging of the response): their residual rms is not that of
    independent points.
    """
    from .stripe_profile import _reject_outliers
    from .stripe_quality import quality_problem, stripe_quality

    width = float(guide_info.get("width_px", np.nan))
    pts, _strength, sigma = steger_centres(response, mask, guide_px, width,
                                           saturated=saturated,
                                           noise_dn=guide_info.get("noise_dn") or 0.0)
    info = {"width_px": width, "sigma_px": sigma, "noise_dn": guide_info.get("noise_dn")}
    if len(pts) < 5:
        info.update(fit_rms_px=float("nan"), problem="no laser stripe found (Steger)")
        return np.empty((0, 2)), info
    keep, fit_rms, _ = _reject_outliers(pts, camera)
    g = np.asarray(guide_px, float)
    c = g.mean(0)
    t = np.linalg.svd(g - c, full_matrices=False)[2][0]
    gs, ps = (g - c) @ t, (pts - c) @ t
    o = np.argsort(gs)
    j = np.clip(np.searchsorted(gs[o], ps), 0, len(o) - 1)
    j_prev = np.clip(j - 1, 0, len(o) - 1)
    nearest = np.where(np.abs(gs[o][j_prev] - ps) < np.abs(gs[o][j] - ps), j_prev, j)
    snr = np.asarray(guide_info["snr"], float)[o][nearest]
    pts, snr = pts[keep], snr[keep]
    quality = stripe_quality(pts, int(len(keep) - keep.sum()), fit_rms, width, snr,
                             np.asarray(mask, bool))
    info.update(fit_rms_px=fit_rms, quality=quality, problem=quality_problem(quality))
    return pts, info
