"""The stripe's coverage gate (lidarcal.stripe_quality): the band of mask pixels near the
centres' line, gathered along the line, is the one a scan of the whole mask finds."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lidarcal.stripe_quality import stripe_quality


def _coverage_brute_force(pts: np.ndarray, mask: np.ndarray, origin: tuple[int, int]) -> float:
    """The coverage of :func:`stripe_quality` from every mask pixel (its definition)."""
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    t_dir, n_dir = vt[0], vt[1]
    ys, xs = np.nonzero(mask)
    P = np.column_stack([xs + origin[0], ys + origin[1]]).astype(float) - c
    band = np.abs(P @ n_dir) <= 2.0
    if not band.any():
        return 0.0
    tm = P[band] @ t_dir
    lo = tm.min()
    nb = int((tm.max() - lo) // 4) + 1
    board_bins = np.zeros(nb, bool)
    board_bins[((tm - lo) // 4).astype(int)] = True
    tc = ((pts - c) @ t_dir - lo) // 4
    hit = np.zeros(nb, bool)
    hit[tc[(tc >= 0) & (tc < nb)].astype(int)] = True
    return float((hit & board_bins).sum() / max(board_bins.sum(), 1))


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
    assert q["coverage"] == _coverage_brute_force(pts, mask, origin)
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
