"""The stripe's coverage gate (lidarcal.stripe_quality): the band of mask pixels near the
centres' line, gathered along the line, is the one a scan of the whole mask finds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lidarcal.stripe_quality import _band_candidates, _coverage, stripe_quality


def _band(P: np.ndarray, n_dir: np.ndarray) -> set[tuple[float, float]]:
    """The pixels of ``P`` within 2 px of the centres' line (the coverage gate's band)."""
    return set(map(tuple, P[np.abs(P @ n_dir) <= 2.0].tolist()))


@pytest.mark.parametrize("seed", range(12))
def test_coverage_equals_whole_mask_scan(seed: int) -> None:
    rng = np.random.default_rng(seed)
    H, W = rng.integers(120, 400, 2)
    mask = np.zeros((H, W), np.uint8)
    quad = np.column_stack([rng.uniform(0, W, 4), rng.uniform(0, H, 4)]).astype(np.int32)
    cv2.fillConvexPoly(mask, cv2.convexHull(quad), 1)
    mask = mask.astype(bool)
    if mask.sum() < 50:
        mask[H // 4:3 * H // 4, W // 4:3 * W // 4] = True
    origin = (int(rng.integers(0, 500)), int(rng.integers(0, 500)))
    # a stripe through the mask at any angle (shallow and steep), partly covered, with noise
    ys, xs = np.nonzero(mask)
    k = rng.integers(len(xs))
    centre = np.array([xs[k] + origin[0], ys[k] + origin[1]], float)
    ang = rng.uniform(0, np.pi)
    s = np.sort(rng.uniform(-0.6, 0.6, 80) * max(H, W))
    s = s[(s < -0.1 * max(H, W)) | (s > 0.05 * max(H, W))]  # a gap: coverage below 1
    pts = centre + np.outer(s, [np.cos(ang), np.sin(ang)]) + rng.normal(0, 0.3, (len(s), 2))
    q = stripe_quality(pts, 0, 0.3, 3.0, np.full(len(pts), 20.0), mask, origin)
    # the band gathered along the line is the band of a scan of every mask pixel
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    ys, xs = np.nonzero(mask)
    P_all = np.column_stack([xs + origin[0], ys + origin[1]]).astype(float) - c
    band_all = _band(P_all, vt[1])
    assert _band(_band_candidates(mask, origin, c, vt[1]), vt[1]) == band_all
    assert q["coverage"] == _coverage(pts - c, P_all, vt[0], vt[1])
    assert 0.0 <= q["coverage"] <= 1.0


def test_coverage_of_a_full_stripe_is_one_and_of_a_half_stripe_about_half() -> None:
    mask = np.zeros((200, 300), bool)
    mask[20:180, 30:270] = True
    x = np.arange(30, 270, 1.0)
    full = np.column_stack([x, 100 + 0.2 * (x - 150)])
    q = stripe_quality(full, 0, 0.2, 3.0, np.full(len(x), 20.0), mask)
    assert q["coverage"] == 1.0
    half = full[x < 150]
    q = stripe_quality(half, 0, 0.2, 3.0, np.full(len(half), 20.0), mask)
    assert 0.45 <= q["coverage"] <= 0.55
