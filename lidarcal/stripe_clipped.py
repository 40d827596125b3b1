"""Clipped laser stripes on lit boards (section 1.3 on real captures): the stripe frames of a
lab that works with the room lights on and the laser overexposed.

The lit board adds the squares' albedo to every profile (white squares far brighter than
black ones), the laser's core clips at the sensor's top level, and blooming widens it. On
the white squares the clip leaves only a few noise sigmas above the lit background, on the
black ones far more. :mod:`lidarcal.stripe_profile` uses these pieces: the stripe's width
measured on profiles less their (albedo) background (:func:`fwhm_run`), the centre of a
clipped profile from the flanks below both of their headrooms, dropped where the albedo
changes under the run (:func:`_saturated_centres`), and the coarse line of a stripe whose
clipped core is the only thing brighter than the lit squares (:func:`clipped_core_pixels`).
Measured on the harsh rig (scripts/capture_sweep.py, lit120_sat_hot: gain 3, bloom 0.3,
lights at 120 DN, 300 hot pixels): stripe centres 0.40 px rms from the true stripe, where
they were 5-9 px off (every board failing "one smooth curve").
"""

from __future__ import annotations

import cv2
import numpy as np

from .geometry import median
from .laser_colour import SATURATED_DN


def fwhm_run(s: np.ndarray, noise: float) -> float:
    """Median FWHM (px) of background-free profiles (M, W) with a clear peak (above 8
    noise sigmas): the run of samples above half the peak through the peak.

    :func:`lidarcal.stripe_profile._fwhm` counts every sample above half the peak over the
    profile's median: on a lit board a white square beside the stripe counts as stripe
    (the harsh rig with the lights at 120 DN and the laser 3 x overexposed: 17-21 px for a
    4-5 px stripe, and windows so wide that the centres locked onto square edges)."""
    n = s.shape[1]
    k = np.argmax(s, axis=1)
    pk = s[np.arange(len(s)), k]
    good = pk > 8 * noise
    if good.sum() < 3:
        return 3.0
    s, k, pk = s[good], k[good], pk[good]
    idx = np.arange(n)[None, :]
    below = s <= 0.5 * pk[:, None]
    a = np.max(np.where(below & (idx < k[:, None]), idx, -1), axis=1) + 1
    b = np.min(np.where(below & (idx > k[:, None]), idx, n), axis=1) - 1
    return min(max(median((b - a + 1).astype(float)), 1.0), 30.0)


def clipped_core_pixels(img: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """Pixels (N, 2) ``(x, y)`` of a clipped stripe's core on a lit board, or None.

    With the room lights on and the laser overexposed, the stripe's core is clipped at the
    image's top level while the lit white squares lie only a few noise sigmas below it: no
    threshold above the background tells them apart, but the clipped core does. The pixels
    whose 2 x 2 block is all within 1 DN of the masked maximum (the clip level; noise clips
    single pixels of a bright square, and a hot pixel is one pixel), at the blocks' centres;
    None when fewer than 10. (:func:`lidarcal.stripe_profile._coarse_line` fits them by PCA
    and rejects them when they spread wider than a stripe: clipped squares, a lamp.)
    """
    vals = img[mask]
    if vals.size < 20:
        return None
    top = int(vals.max())  # a Python int: top - 1 must not wrap at 0 (uint8)
    clipped = ((img >= top - 1) & mask).astype(np.uint8)
    blocks = cv2.erode(clipped, np.ones((2, 2), np.uint8), anchor=(0, 0),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    found = cv2.findNonZero(blocks)
    if found is None or len(found) < 10:
        return None
    return found.reshape(-1, 2).astype(float) + 0.5


def _saturated_centres(prof: np.ndarray, s: np.ndarray, cen: np.ndarray, peak: np.ndarray,
                       bprof: np.ndarray | None = None, noise: float = 0.0
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Centres and peaks of clipped profiles: the midpoint of the run above a level ``h``
    through the clipped plateau, its two edges interpolated linearly (sub-pixel) on the
    unclipped flanks.

    A profile is clipped when its maximum is ``SATURATED_DN`` or more and at least 3
    consecutive samples lie within 1 DN of it (a saturated laser core is a flat top: that
    maximum is the clip level, read from the profile). ``s`` is the background-free
    profile; the clip leaves ``s`` at most ``top - background`` (the headroom), which on a
    lit board differs between white and black squares: ``h`` is half the smaller headroom
    at the plateau's two ends, so both edges lie on samples that are not clipped and a
    symmetric stripe's midpoint is its centre. The peak of a clipped profile (a lower
    bound of its signal) is that headroom times the square root of the plateau's length
    (the plateau's samples are all at least that far above the background).

    Without ``bprof`` (no albedo map: :func:`lidarcal.laserplane.laser_plane`'s photos)
    the run through the centroid is taken as before (:func:`_run_centres`), the peaks
    left alone: a run over a square edge cannot be told there, and a raised peak would
    let such runs through the gates.

    With ``bprof`` (blackness under the profile, 0 white to 1 black) a clipped profile
    whose blackness changes over the run and its edge samples by more than ``noise / h``
    (an albedo change that moves an edge by more than the noise would, for a black/white
    reflectance ratio of 0: the ratio estimated from clipped frames is not trusted) is
    dropped (centre NaN): its flanks see two albedos (and a blooming halo that does not
    follow the albedo), so the run is not symmetric about the stripe, and the clip hides
    the core that would tell (on the harsh rig under lit120_sat_hot of
    scripts/capture_sweep.py such runs were the white square's clipped tail of a stripe on
    the black one, 2-3 px off). Other profiles keep their centroid ``cen`` and ``peak``.
    """
    if bprof is None:
        return _run_centres(prof, s, cen), peak
    top = np.ascontiguousarray(prof.T).max(axis=0)
    rows = np.flatnonzero((top >= SATURATED_DN) & np.isfinite(cen))
    out, pk = cen.copy(), peak.copy()
    if rows.size == 0:
        return out, pk
    flat = prof[rows] >= top[rows, None] - 1
    m, n = flat.shape
    run = np.zeros(m, np.intp)
    best = np.zeros(m, np.intp)
    end = np.zeros(m, np.intp)
    for j in range(n):  # the longest run of flat samples (a hot pixel is one sample)
        run = np.where(flat[:, j], run + 1, 0)
        longer = run > best
        best[longer], end[longer] = run[longer], j
    use = best >= 3
    rows, p1, best = rows[use], end[use], best[use]
    if rows.size == 0:
        return out, pk
    p0 = p1 - best + 1
    S = s[rows]
    r = np.arange(len(rows))
    head = np.minimum(S[r, p0], S[r, p1])
    h = 0.5 * head
    idx = np.arange(n)[None, :]
    below = S < h[:, None]
    # the run of samples >= h through the plateau: from after the last one below h on the
    # left to before the first one below h on the right
    a = np.max(np.where(below & (idx < p0[:, None]), idx, -1), axis=1) + 1
    b = np.min(np.where(below & (idx > p1[:, None]), idx, n), axis=1) - 1
    inside = (head > 0) & (a > 0) & (b < n - 1)  # an edge outside the window: keep the centroid
    r, a, b, h, head = r[inside], a[inside], b[inside], h[inside], head[inside]
    left = a - (S[r, a] - h) / np.maximum(S[r, a] - S[r, a - 1], 1e-6)
    right = b + (S[r, b] - h) / np.maximum(S[r, b] - S[r, b + 1], 1e-6)
    rr = rows[inside]
    out[rr] = 0.5 * (left + right)
    pk[rr] = head * np.sqrt(best[inside])
    # the albedo under the run and its edge samples: one square, or the profile is dropped
    span = (idx >= (a - 1)[:, None]) & (idx <= (b + 1)[:, None])
    B = bprof[rr]
    db = np.max(np.where(span, B, -np.inf), axis=1) - np.min(np.where(span, B, np.inf), axis=1)
    out[rr[db * h > max(noise, 1e-6)]] = np.nan
    return out, pk


def _run_centres(prof: np.ndarray, s: np.ndarray, cen: np.ndarray) -> np.ndarray:
    """Centres of clipped profiles without a blackness map: the midpoint of the run above half
    the peak through the centroid ``cen``, its two edges interpolated linearly (sub-pixel) on
    the unsaturated flanks.

    A profile is clipped when at least 3 samples lie within 1 DN of its maximum and that
    maximum is ``SATURATED_DN`` or more (a saturated laser core is a flat top). Other
    profiles, and those whose run reaches the window's end or does not hold the centroid,
    keep their centroid ``cen``. (Without the squares' albedo, a run over a square edge
    cannot be told from one on a single square: the run through the centroid, whose
    window is symmetric about it, is the one taken.)
    """
    top = np.ascontiguousarray(prof.T).max(axis=0)
    rows = np.flatnonzero((top >= SATURATED_DN) & np.isfinite(cen))
    rows = rows[np.count_nonzero(prof[rows] >= top[rows, None] - 1, axis=1) >= 3]  # flat tops
    out = cen.copy()
    if rows.size == 0:
        return out
    n = s.shape[1]
    S = s[rows]
    k = np.clip(np.rint(cen[rows]), 0, n - 1).astype(np.intp)
    half = 0.5 * S.max(axis=1)
    r = np.arange(len(rows))
    idx = np.arange(n)[None, :]
    below = S < half[:, None]
    # the run of samples >= half through k: from after the last one below it on the left
    # to before the first one below it on the right
    a = np.max(np.where(below & (idx < k[:, None]), idx, -1), axis=1) + 1
    b = np.min(np.where(below & (idx > k[:, None]), idx, n), axis=1) - 1
    use = ~below[r, k] & (a > 0) & (b < n - 1)  # an edge outside the window: keep the centroid
    r, a, b, h = r[use], a[use], b[use], half[use]
    left = a - (S[r, a] - h) / np.maximum(S[r, a] - S[r, a - 1], 1e-6)
    right = b + (S[r, b] - h) / np.maximum(S[r, b] - S[r, b + 1], 1e-6)
    out[rows[use]] = 0.5 * (left + right)
    return out
