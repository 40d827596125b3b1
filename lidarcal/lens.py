"""OpenCV's projection of camera-frame points through its lens model, in numpy (section 1.2).

OpenCV's distortion ``(k1, k2, p1, p2, k3)`` (``cv2.projectPoints``; "Camera Calibration and
3D Reconstruction" in its documentation): with ``(x, y) = (X / Z, Y / Z)`` and
``r^2 = x^2 + y^2``,

    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

and the pixel ``u = fx x_d + cx``, ``v = fy y_d + cy`` (``cv2.projectPoints`` reads no skew
from ``K``). Called from Python, ``cv2.projectPoints`` always computes its (2N x 15) Jacobian
as well, five times the cost of the projection itself (5 ms for the 37,000 points
:mod:`lidarcal.corner_symmetry` projects per board); :func:`project_camera_points` computes
the projection alone. :func:`distort_normalised` and its 2 x 2 Jacobian
(:func:`distortion_jacobian`) serve the undistortion's Newton steps
(:func:`lidarcal.camera.undistort_pixels`) and the pixel Jacobian of a camera-frame point
(:mod:`lidarcal.pixel_jacobian`). Imports only numpy.
"""

from __future__ import annotations

import numpy as np


def _coefficients(dist: np.ndarray) -> tuple[float, float, float, float, float]:
    k1, k2, p1, p2, k3 = (float(v) for v in np.asarray(dist, float).ravel()[:5])
    return k1, k2, p1, p2, k3


def distort_normalised(dist: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Normalised points (N, 2) -> distorted normalised points (N, 2): the model of the
    module docstring, ``dist`` = (k1, k2, p1, p2, k3)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return np.column_stack([x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
                            y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y])


def distortion_jacobian(dist: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, ...]:
    """The 2 x 2 Jacobian of :func:`distort_normalised` per point, as its entries
    ``(dxd/dx, dxd/dy, dyd/dx, dyd/dy)``, each (N,)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d rad / d r2
    cross = 2 * drad * x * y + 2 * p1 * x + 2 * p2 * y  # dxd/dy = dyd/dx
    return (rad + 2 * drad * x * x + 2 * p1 * y + 6 * p2 * x, cross, cross,
            rad + 2 * drad * y * y + 6 * p1 * y + 2 * p2 * x)


def project_camera_points(K: np.ndarray, dist: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3), in front of the camera -> distorted pixels (N, 2): the
    pinhole ``(X / Z, Y / Z)``, :func:`distort_normalised`, then ``u = fx x_d + cx``,
    ``v = fy y_d + cy``. OpenCV's pixels to ~1e-12 px (``tests/test_lens.py`` checks 1e-9)."""
    K = np.asarray(K, float)
    P = np.asarray(X, float).reshape(-1, 3)
    d = distort_normalised(dist, P[:, :2] / P[:, 2:3])
    return np.column_stack([d[:, 0] * K[0, 0] + K[0, 2], d[:, 1] * K[1, 1] + K[1, 2]])
