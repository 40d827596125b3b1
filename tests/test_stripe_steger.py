"""Steger's line detector (lidarcal.stripe_steger) on stripes of known centre line.

A stripe through a known line at a known angle: a Gaussian (the laser's sheet) or a
clipped bar (a saturated core), with speckle (multiplicative, grain ~1 px) and sensor
noise; the detector's centres against the true line, perpendicular distance (px).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lidarcal.stripe_steger import (
    MIN_RIDGE_SNR,
    half_max_midpoints,
    hessian_line_points,
    ridge_noise,
    steger_centres,
    steger_sigma,
)


def _stripe(angle_deg: float, offset: float, rng, bar_half: float | None = None,
            speckle: float = 0.3) -> tuple[np.ndarray, callable]:
    """(image float32 240 x 320, signed distance of points to the true line)."""
    H, W = 240, 320
    y, x = np.mgrid[0:H, 0:W].astype(float)
    a = np.radians(angle_deg)
    c = np.array([160.0, 120.0 + offset])

    def dist(p: np.ndarray) -> np.ndarray:
        return -(p[..., 0] - c[0]) * np.sin(a) + (p[..., 1] - c[1]) * np.cos(a)

    d = dist(np.stack([x, y], -1))
    if bar_half is None:
        img = 120 * np.exp(-0.5 * (d / 1.5) ** 2)
    else:  # a clipped core: flat top, soft flanks
        img = np.clip(200 * np.exp(-0.5 * (np.maximum(np.abs(d) - bar_half, 0) / 1.2) ** 2),
                      0, 150)
    z = cv2.GaussianBlur(rng.standard_normal((H, W)).astype(np.float32), (0, 0), 1.0)
    img = img * np.maximum(1 + speckle * z / z.std(), 0) + rng.normal(0, 1.5, (H, W))
    return img.astype(np.float32), dist


def _guide(dist_fn, angle_deg: float) -> np.ndarray:
    """Points on the true line 1.5 px off (a guide as the centroid gives), every 2 px."""
    a = np.radians(angle_deg)
    t = np.arange(-100, 101, 2.0)
    p = np.column_stack([160 + t * np.cos(a), 120 + t * np.sin(a)])
    return p + 1.5 * np.array([-np.sin(a), np.cos(a)])


@pytest.mark.parametrize("angle", [8.0, 37.0, 71.0, 124.0])
@pytest.mark.parametrize("speckle,bound", [(0.0, 0.03), (0.1, 0.15)])
def test_steger_centres_lie_on_a_gaussian_stripe(angle, speckle, bound) -> None:
    """Sensor noise 1.5 DN on a peak of 120 (sigma 1.5 px): measured rms 0.013-0.017 px
    (max 0.056); with speckle of contrast 0.1 (grain 1 px) 0.085-0.099 px (max 0.30).
    (Speckle 0.3 gives 0.3-0.38 px: the scale sigma = w / sqrt(3) ~ 1 px averages it over
    about a pixel only; :mod:`lidarcal.laserplane` averages the response along the stripe
    first.)"""
    rng = np.random.default_rng(int(angle))
    img, dist = _stripe(angle, 0.37, rng, speckle=speckle)
    mask = np.zeros(img.shape, bool)
    mask[30:210, 40:280] = True
    pts, strength, sigma = steger_centres(img, mask, _guide(dist, angle) + [0, 0.37], 3.5,
                                          noise_dn=1.5)
    assert sigma == pytest.approx(steger_sigma(3.5))
    assert len(pts) > 150 and (strength > 0).all()
    e = dist(pts)
    assert abs(e.mean()) < bound / 2 and np.sqrt(np.mean(e ** 2)) < bound
    assert np.abs(e).max() < 4 * bound
    # one centre per column (per row for a steep stripe)
    key = np.round(pts[:, 0] if abs(np.cos(np.radians(angle))) >= 0.7 else pts[:, 1])
    assert len(np.unique(key)) >= 0.9 * len(key)


def test_weak_ridges_of_the_noise_are_not_line_points() -> None:
    """Noise alone (no stripe): no point passes MIN_RIDGE_SNR; without the noise level
    (``noise_dn`` 0) the noise's own ridges would be taken."""
    rng = np.random.default_rng(2)
    img = rng.normal(50, 1.5, (120, 160)).astype(np.float32)
    mask = np.ones(img.shape, bool)
    guide = np.column_stack([np.arange(20, 140, 2.0), np.full(60, 60.0)])
    assert len(steger_centres(img, mask, guide, 3.5, noise_dn=1.5)[0]) == 0
    assert len(steger_centres(img, mask, guide, 3.5)[0]) > 20


def test_a_clipped_bar_needs_sigma_from_its_width() -> None:
    """A flat-topped bar of half-width w = 4 px (FWHM ~10 px): at sigma >= w / sqrt(3)
    (eq. 9) one centre on the line; below it the two edges of the top are ridges of their
    own. Measured: sigma 2.89 (from the FWHM) rms 0.010 px, 2.31 (= w / sqrt 3) 0.026 px,
    1.5 0.93 px, 1.0 2.7 px."""
    rng = np.random.default_rng(5)
    img, dist = _stripe(30.0, 0.0, rng, bar_half=4.0, speckle=0.0)
    ys, xs = np.mgrid[60:180, 100:220]
    cand = np.column_stack([xs.ravel(), ys.ravel()])

    def err(sigma: float) -> np.ndarray:
        p, st, _, _ = hessian_line_points(img, sigma, cand)
        return dist(p[st >= MIN_RIDGE_SNR * ridge_noise(1.5, sigma)])

    for sigma in (steger_sigma(10.0), 4.0 / np.sqrt(3.0)):
        e = err(sigma)
        assert len(e) > 100 and np.sqrt(np.mean(e ** 2)) < 0.05 and np.abs(e).max() < 0.15
    for sigma in (1.5, 1.0):
        assert np.sqrt(np.mean(err(sigma) ** 2)) > 0.5


def test_half_max_midpoint_of_a_lopsided_flat_top() -> None:
    """A filled core whose top rises slowly on one side (the profile at a square edge, as
    on the 12 MP semi-real photos): the centre of the run above half the peak, not the
    top's curvature, is the stripe's centre."""
    s = np.arange(80, dtype=float)
    prof = np.where((s >= 20) & (s <= 60), 40 + 0.8 * np.clip(s - 20, 0, 25), 5.0)
    img = np.tile(prof[:, None], (1, 40)).astype(np.float32)  # a horizontal stripe
    pts = np.array([[20.0, 48.0], [25.0, 45.0]])             # Steger's biased points
    out = half_max_midpoints(img, pts, np.array([[0.0, 1.0], [0.0, 1.0]]), 30.0)
    # half max = 5 + (60 - 5) / 2 = 32.5: between rows 19 (5) and 20 (40): 19.79; and
    # between 60 (60) and 61 (5): 60.5
    assert out[:, 1] == pytest.approx(0.5 * (19 + 27.5 / 35 + 60 + 27.5 / 55), abs=0.02)
    assert np.array_equal(out[:, 0], pts[:, 0])
