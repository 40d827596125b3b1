"""``lidarcal planes``' sigmas against the truth when the scans are precise (the camera-side
board planes dominate): rendered one-board photos, 0.4 mm range noise (a per-beam median of a
few dozen 3 mm scans, as ``lidarcal import BAG --views`` writes), integer-mm ranges.

With OpenCV's accuracy-mode corners chosen for their lower residual, their pattern-scale error
(0.2-0.9 per mille, the same sign in most views, invisible in the residuals) put the camera-z
translation 2.3-3.2 sigma off on these seeds; the package's cornerSubPix corners cover it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal.planes import ACCURACY_MODE_GAIN_PX, BoardPlane, choose_corner_set, run_planes
from lidarcal.synthetic.oneboard import simulate_oneboard, write_oneboard

SEEDS = (0, 1, 3)


@pytest.fixture(scope="module")
def z_scores(tmp_path_factory) -> np.ndarray:
    """|error| / sigma per seed (rows) and component (rx, ry, rz, tx, ty, tz)."""
    rows = []
    for seed in SEEDS:
        rig = simulate_oneboard(seed, 7, range_noise_mm=0.4)
        folder = write_oneboard(rig, tmp_path_factory.mktemp(f"precise{seed}"), seed=seed)
        res = run_planes(folder, folder / "camera.json", rig.board)
        d_rot = np.degrees(Rotation.from_matrix(res.R @ rig.R.T).as_rotvec())
        sig = np.array(res.uncertainty.rotation_deg + res.uncertainty.translation_mm, float)
        rows.append(np.abs(np.concatenate([d_rot, res.T - rig.T])) / sig)
    return np.array(rows)


def test_precise_scans_sigmas_cover_the_truth(z_scores):
    # under the noise model |z| is half-normal: P(|z| > 3) = 0.27 %, median 0.67; a component
    # whose median over the seeds exceeds 1.5 is optimistic (Tz was 2.3-3.2 on these seeds)
    assert np.all(np.isfinite(z_scores)), z_scores
    assert z_scores.max() <= 3.0, z_scores
    assert np.mean(z_scores <= 2.0) >= 0.85, z_scores
    assert np.all(np.median(z_scores, axis=0) <= 1.5), z_scores
    # ... and not inflated: the errors use the sigmas (half-normal median 0.67)
    assert np.median(z_scores) >= 0.25, z_scores


def _fit(sigma_px: float) -> BoardPlane:
    return BoardPlane(None, np.eye(3), np.eye(3)[:, :2], np.eye(3), np.zeros(3), np.zeros((40, 2)),
                      sigma_px, None)


def test_choose_corner_set_prefers_the_refined_corners_unless_clearly_worse():
    pkg, sb = _fit(0.06), _fit(0.02)
    assert choose_corner_set([pkg, sb]) is pkg  # a lower residual alone is no reason
    bad = _fit(0.02 + ACCURACY_MODE_GAIN_PX + 0.5)  # corners pulled by markers beside the board
    assert choose_corner_set([bad, sb]) is sb
    assert choose_corner_set([sb]) is sb
