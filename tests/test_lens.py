"""OpenCV's projection through its lens model in numpy (lidarcal.lens) against cv2.projectPoints."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from lidarcal.lens import project_camera_points


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.076, 0.371, 0.0, 0.0, 0.0),
                                  (-0.30, 0.12, 0.0008, -0.0006, -0.02),
                                  (0.2, -0.5, -0.002, 0.003, 0.8)])
def test_projection_matches_opencv(dist) -> None:
    """Points spread over a wide field of view project to OpenCV's pixels to 1e-9 px (a skew
    in K ignored, as OpenCV does)."""
    rng = np.random.default_rng(7)
    X = np.column_stack([rng.uniform(-600, 600, (500, 2)), rng.uniform(300, 2000, 500)])
    for skew in (0.0, 0.4):
        K = np.array([[1187.0, skew, 968.5], [0, 1189.5, 597.0], [0, 0, 1]])
        ref, _ = cv2.projectPoints(X.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                                   np.array(dist, float))
        got = project_camera_points(K, np.array(dist), X)
        assert np.max(np.abs(got - ref.reshape(-1, 2))) < 1e-9
