"""d pixel / d point through OpenCV's lens model (:func:`pixel_jacobian`), and the
Binet-Cauchy forms of it that the joint fit's stripe scale needs
(:meth:`lidarcal.joint.problem._Problem.set_stripe_scale`): image cross products and lengths
of directions at a point from nine numbers per point.
"""

from __future__ import annotations

import cv2
import numpy as np

from .lens import distortion_jacobian


def pixel_jacobian(camera, P: np.ndarray) -> np.ndarray:
    """d pixel / d point (S, 2, 3) of camera-frame points ``P`` through the lens model.

    OpenCV's five-coefficient model as ``cv2.projectPoints`` has it (no skew):
    ``diag(fx, fy) J_d(x, y) [[1, 0, -x], [0, 1, -y]] / Z`` with ``(x, y) = (X / Z, Y / Z)``
    and ``J_d`` the distortion's 2 x 2 Jacobian (:func:`lidarcal.lens.distortion_jacobian`);
    other models: ``cv2.projectPoints``' Jacobian wrt the translation (columns 3-5, exactly
    that with a zero rotation)."""
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float).ravel()
    if len(dist) != 5:
        _, Jt = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
        return Jt[:, 3:6].reshape(-1, 2, 3)
    iz = 1 / P[:, 2]
    xy = P[:, :2] * iz[:, None]
    dxx, dxy, dyx, dyy = distortion_jacobian(dist, xy)  # J_d's entries, each (N,)
    out = np.empty((len(P), 2, 3))
    A = out[:, :, :2]  # d pixel / d (X, Y) at fixed Z: diag(fx, fy) J_d / Z
    A[:, 0, 0], A[:, 0, 1] = K[0, 0] * dxx * iz, K[0, 0] * dxy * iz
    A[:, 1, 0], A[:, 1, 1] = K[1, 1] * dyx * iz, K[1, 1] * dyy * iz
    out[:, :, 2] = -(A[:, :, 0] * xy[:, :1] + A[:, :, 1] * xy[:, 1:])
    return out


def jacobian_forms(J: np.ndarray) -> np.ndarray:
    """Per row of the pixel Jacobians ``J`` (S, 2, 3), rows ``j0``, ``j1``: ``j0 x j1`` and the
    six entries of ``A = j0 j0^T + j1 j1^T`` (``A00, A11, A22, A01, A02, A12``), (S, 9).

    By the Binet-Cauchy identity ``(J u) x (J l) = (j0 x j1) . (u x l)`` (2D cross product)
    and ``|J l|^2 = l^T A l`` (:func:`quadratic_form_coefficients`): image cross products and
    lengths of board directions from nine numbers per centre, without the (S, 2) images."""
    j0, j1 = J[:, 0], J[:, 1]
    out = np.empty((len(J), 9))
    out[:, :3] = np.cross(j0, j1)
    for c, (i, k) in enumerate(((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))):
        out[:, 3 + c] = j0[:, i] * j0[:, k] + j1[:, i] * j1[:, k]
    return out


FORMS_BLOCK = 16384  # centres per block of :func:`pixel_jacobian_forms` (~0.13 MB temporaries)


def pixel_jacobian_forms(camera, P: np.ndarray) -> np.ndarray:
    """:func:`jacobian_forms` of :func:`pixel_jacobian` (S, 9), for OpenCV's five-coefficient
    model without the (S, 2, 3) Jacobians: with ``J = diag(fx, fy) J_d B / Z``,
    ``B = [[1, 0, -x], [0, 1, -y]]``, the cross product of its rows is
    ``fx fy det(J_d) / Z^2 (x, y, 1)`` and ``J^T J = B^T S B``, ``S = J_d^T diag(fx, fy)^2 J_d
    / Z^2`` (2 x 2): every entry an elementwise product of the centres' columns.

    Computed in blocks of :data:`FORMS_BLOCK` centres (each row on its own: the same
    numbers): the ~20 temporaries per centre then reuse a few small buffers instead of
    touching ~20 MB of fresh memory on ~1e5 centres."""
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float).ravel()
    if len(dist) != 5:
        return jacobian_forms(pixel_jacobian(camera, P))
    out = np.empty((len(P), 9))
    for i in range(0, len(P), FORMS_BLOCK):
        _forms_block(K, dist, P[i:i + FORMS_BLOCK], out[i:i + FORMS_BLOCK])
    return out


def _forms_block(K: np.ndarray, dist: np.ndarray, P: np.ndarray, out: np.ndarray) -> None:
    """:func:`pixel_jacobian_forms` of the centres ``P`` (n, 3) into ``out`` (n, 9)."""
    iz = 1 / P[:, 2]
    x, y = P[:, 0] * iz, P[:, 1] * iz
    dxx, dxy, dyx, dyy = distortion_jacobian(dist, np.column_stack([x, y]))
    fx2, fy2, iz2 = K[0, 0] ** 2, K[1, 1] ** 2, iz * iz
    s00 = (fx2 * dxx * dxx + fy2 * dyx * dyx) * iz2
    s01 = (fx2 * dxx * dxy + fy2 * dyx * dyy) * iz2
    s11 = (fx2 * dxy * dxy + fy2 * dyy * dyy) * iz2
    det = K[0, 0] * K[1, 1] * (dxx * dyy - dxy * dyx) * iz2
    a02, a12 = -(s00 * x + s01 * y), -(s01 * x + s11 * y)
    for j, col in enumerate((det * x, det * y, det, s00, s11, -(a02 * x + a12 * y), s01, a02, a12)):
        out[:, j] = col


def quadratic_form_coefficients(v: np.ndarray) -> np.ndarray:
    """Coefficients (G, 6) of ``v^T A v`` against :func:`jacobian_forms`' six entries of ``A``:
    ``v0^2, v1^2, v2^2, 2 v0 v1, 2 v0 v2, 2 v1 v2``."""
    return np.column_stack([v * v, 2 * v[:, 0] * v[:, 1], 2 * v[:, 0] * v[:, 2],
                            2 * v[:, 1] * v[:, 2]])
