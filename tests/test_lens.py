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


@pytest.mark.parametrize("dist", [(-0.076, 0.371, 0.0, 0.0, 0.0),
                                  (-0.30, 0.12, 0.0008, -0.0006, -0.02),
                                  (0.2, -0.5, -0.002, 0.003, 0.8)])
def test_distortion_jacobian_matches_central_differences(dist) -> None:
    """The analytic 2 x 2 Jacobian of the distortion against central differences of
    distort_normalised (step 1e-6, agreement 1e-8) over a wide field of view."""
    from lidarcal.lens import distort_normalised, distortion_jacobian
    xy = np.random.default_rng(3).uniform(-0.8, 0.8, (400, 2))
    J = np.stack(distortion_jacobian(np.array(dist), xy), axis=1).reshape(-1, 2, 2)
    h = 1e-6
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        num = (distort_normalised(np.array(dist), xy + e)
               - distort_normalised(np.array(dist), xy - e)) / (2 * h)
        assert np.max(np.abs(J[:, :, k] - num)) < 1e-8
