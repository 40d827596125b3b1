"""The board planes as parameters of the joint fit, under the camera's estimate as a prior.

The held-planes fit (:mod:`lidarcal.joint`) takes both board poses from
``cv2.solvePnP`` on one image (``board.png``, eq. 1) as exact and only
propagates their uncertainty. Where that image is weak (a wide lens: few
pixels per mm, and a camera calibrated from photos, whose intrinsics error
moves every board pose coherently) the scans and stripes of all positions know
more about the planes than the corners do. Here the 12 board-pose parameters
(rotation vector and translation per board, the parametrisation of
:func:`lidarcal.joint.params._boards`) are fitted with the rig under a Gaussian
prior: the camera's estimate ``p0`` with covariance

``P = blockdiag(s_b^2 (J_b^T J_b)^-1) + A Sigma_K A^T``

(the maximum-likelihood pose's covariance from the corners, Gauss-Newton; plus the
intrinsics' uncertainty carried through the PnP solution,
``A_b = -(J_b^T J_b)^-1 J_b^T J_K``, which correlates the two boards). ``s_b`` is the
board's corner reprojection scatter, but at least ``CORNER_FLOOR_PX``: chessboard
detectors' errors are correlated over the board and the pose absorbs their
low-order part, so the residual scatter understates the pose error.
``Sigma_K`` is the marginal covariance of ``(fx, fy, cx, cy, k1, k2, p1, p2[, k3])``
from the intrinsics calibration's own views (``cv2.calibrateCamera``'s
Gauss-Newton information, every view's pose a nuisance; residual scale floored
alike); a camera given in dataset.json carries no uncertainty and only the
corner term enters. The prior enters the fit as 12 whitened pseudo-observations
``L (p - p0)`` with ``L^T L = P^-1`` (maximum a posteriori = the maximum-likelihood
fit of corners through the intrinsics, without re-solving the camera).

The stripe rays still use the calibrated intrinsics as exact; the plane
correction absorbs what of their error shows as a plane error.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import skew
from ..io.dataset import CameraModel
from .params import CORNER_FLOOR_PX, MAD_TO_SIGMA, N_BOARD

N_INTRINSICS = 9  # fx, fy, cx, cy, k1, k2, p1, p2, k3
# the fitted board poses' shift from the camera's estimate, chi-square on 12 dof, beyond which
# the joint fit warns (its 99.9 % point: 32.9)
PLANE_SHIFT_CHI2 = 32.9
_POSE_STEPS = np.array([1e-6] * 3 + [1e-3] * 3)


@dataclass(frozen=True)
class PlanePrior:
    """Gaussian prior of both board poses: mean ``R0`` (2, 3, 3), ``T0`` (2, 3) and the
    covariance ``cov`` (12, 12) of ``[rotvec_0, T_0, rotvec_1, T_1]`` (rad, mm; rotation
    steps left-multiplied, ``R = Rot(rotvec) R0``). ``corner_px``: the per-board corner
    sigma used; ``intrinsics``: whether the intrinsics' uncertainty is in ``cov``."""

    R0: np.ndarray
    T0: np.ndarray
    cov: np.ndarray
    corner_px: tuple[float, float]
    intrinsics: bool

    @cached_property
    def whitener(self) -> np.ndarray:
        """``L`` (12, 12) with ``L^T L = cov^-1``."""
        return np.linalg.cholesky(np.linalg.inv(self.cov)).T

    def steps(self, bR: np.ndarray, bT: np.ndarray) -> np.ndarray:
        """``p - p0`` (12,) of board poses ``bR`` (2, 3, 3), ``bT`` (2, 3)."""
        out = []
        for j in range(2):
            out.append(Rotation.from_matrix(bR[j] @ self.R0[j].T).as_rotvec())
            out.append(np.asarray(bT[j], float) - self.T0[j])
        return np.concatenate(out)

    def residuals(self, bR: np.ndarray, bT: np.ndarray) -> np.ndarray:
        """Whitened prior residuals ``L (p - p0)`` (12,): each ~ N(0, 1) under the prior."""
        return self.whitener @ self.steps(bR, bT)

    def sigmas(self) -> dict[str, np.ndarray]:
        """Per board: 1-sigma of the plane's normal (deg) and offset along it (mm)."""
        out = {"normal_deg": np.zeros(2), "offset_mm": np.zeros(2)}
        for j in range(2):
            c = self.cov[6 * j:6 * j + 6, 6 * j:6 * j + 6]
            n = self.R0[j][:, 2]
            # normal n' = Rot(w) n: dn = w x n; offset d = n . T: dd = (w x n) . T + n . dT
            Jn = -skew(n)  # dn / dw
            Jd = np.concatenate([np.cross(n, self.T0[j]), n])  # d d / d(w, T)
            cn = Jn @ c[:3, :3] @ Jn.T
            out["normal_deg"][j] = np.degrees(np.sqrt(max(np.trace(cn), 0.0)))
            out["offset_mm"][j] = float(np.sqrt(max(Jd @ c @ Jd, 0.0)))
        return out


def _intrinsics_vector(camera: CameraModel) -> np.ndarray:
    K, d = np.asarray(camera.K, float), np.zeros(5)
    d[:len(camera.dist)] = np.asarray(camera.dist, float).ravel()[:5]
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d]


def _camera_of(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return K, v[4:9]


def _project(obj: np.ndarray, R: np.ndarray, T: np.ndarray, kv: np.ndarray) -> np.ndarray:
    K, dist = _camera_of(kv)
    px, _ = cv2.projectPoints(obj.reshape(-1, 1, 3), cv2.Rodrigues(R)[0], np.asarray(T, float),
                              K, dist)
    return px.reshape(-1)


def _pose_jacobians(obj: np.ndarray, R0: np.ndarray, T0: np.ndarray, kv: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobians of the projected corners (2C,) wrt the pose step (2C, 6)
    and wrt the intrinsics vector (2C, 9)."""
    def at(p: np.ndarray, k: np.ndarray) -> np.ndarray:
        return _project(obj, Rotation.from_rotvec(p[:3]).as_matrix() @ R0, T0 + p[3:], k)

    Jp = np.zeros((2 * len(obj), 6))
    for i in range(6):
        e = np.zeros(6)
        e[i] = _POSE_STEPS[i]
        Jp[:, i] = (at(e, kv) - at(-e, kv)) / (2 * _POSE_STEPS[i])
    Jk = np.zeros((2 * len(obj), N_INTRINSICS))
    h = np.r_[np.full(4, 1e-3), np.full(5, 1e-7)]
    for i in range(N_INTRINSICS):
        e = np.zeros(N_INTRINSICS)
        e[i] = h[i]
        Jk[:, i] = (at(np.zeros(6), kv + e) - at(np.zeros(6), kv - e)) / (2 * h[i])
    return Jp, Jk


def intrinsics_covariance(intrinsics, floor_px: float = CORNER_FLOOR_PX) -> np.ndarray:
    """Marginal covariance (9, 9) of ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` of a
    :class:`lidarcal.camera.IntrinsicsResult` (``cv2.calibrateCamera``, Zhang's method):
    ``s^2 [(J^T J)^-1]_KK`` with every view's pose a nuisance parameter (Gauss-Newton
    information of the reprojection residuals at the solution; ``s`` the residual RMS per
    coordinate, at least ``floor_px``). A fixed k3 (``CALIB_FIX_K3``) has zero variance."""
    cam = intrinsics.camera
    kv = _intrinsics_vector(cam)
    free = np.ones(N_INTRINSICS, bool)
    if intrinsics.flags & cv2.CALIB_FIX_K3:
        free[8] = False
    n_v = len(intrinsics.image_points)
    nk = int(free.sum())
    H = np.zeros((nk + 6 * n_v, nk + 6 * n_v))
    ssq, m = 0.0, 0
    K, dist = _camera_of(kv)
    for v in range(n_v):
        obj = np.asarray(intrinsics.object_points[v], float).reshape(-1, 3)
        img = np.asarray(intrinsics.image_points[v], float).reshape(-1, 2)
        rvec = np.asarray(intrinsics.rvecs[v], float).reshape(3)
        tvec = np.asarray(intrinsics.tvecs[v], float).reshape(3)
        px, J = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, dist)
        ssq += float(np.sum((px.reshape(-1, 2) - img) ** 2))
        m += img.size
        # cv2's columns: rvec 3, tvec 3, fx fy, cx cy, dist 5
        Jk = J[:, 6:6 + N_INTRINSICS][:, free]
        Jv = J[:, :6]
        cols = np.r_[np.arange(nk), nk + 6 * v + np.arange(6)]
        Jf = np.hstack([Jk, Jv])
        H[np.ix_(cols, cols)] += Jf.T @ Jf
    dof = max(m - H.shape[0], 1)
    s2 = max(ssq / dof, floor_px**2)
    C = np.linalg.pinv(H)[:nk, :nk] * s2
    out = np.zeros((N_INTRINSICS, N_INTRINSICS))
    out[np.ix_(free, free)] = C
    return out


def board_plane_prior(camera: CameraModel, corners_px, object_points: np.ndarray,
                      board_R: np.ndarray, board_T: np.ndarray, intrinsics=None,
                      floor_px: float = CORNER_FLOOR_PX) -> PlanePrior:
    """The camera's estimate of both board poses and its covariance (module docstring).

    ``corners_px``: each board's detected corners (C, 2); ``object_points`` (C, 3) mm;
    ``board_R``, ``board_T``: the poses (the corners' maximum-likelihood ones, solvePnP);
    ``intrinsics``: the :class:`lidarcal.camera.IntrinsicsResult` the camera came from
    (None: the camera is taken as exact).
    """
    kv = _intrinsics_vector(camera)
    obj = np.asarray(object_points, float).reshape(-1, 3)
    cov = np.zeros((2 * N_BOARD, 2 * N_BOARD))
    A = np.zeros((2 * N_BOARD, N_INTRINSICS))
    sig = []
    for j in range(2):
        c = np.asarray(corners_px[j], float).reshape(-1)
        r = _project(obj, board_R[j], board_T[j], kv) - c
        s = max(MAD_TO_SIGMA * float(np.median(np.abs(r))), float(floor_px))
        sig.append(s)
        Jp, Jk = _pose_jacobians(obj, board_R[j], board_T[j], kv)
        Hinv = np.linalg.inv(Jp.T @ Jp)
        b = slice(N_BOARD * j, N_BOARD * (j + 1))
        cov[b, b] = s**2 * Hinv
        A[b] = -Hinv @ (Jp.T @ Jk)
    use_k = intrinsics is not None and len(getattr(intrinsics, "image_points", ())) > 0
    if use_k:
        cov = cov + A @ intrinsics_covariance(intrinsics, floor_px) @ A.T
    cov = 0.5 * (cov + cov.T)
    return PlanePrior(np.asarray(board_R, float).copy(), np.asarray(board_T, float).copy(), cov,
                      (sig[0], sig[1]), bool(use_k))


def plane_prior_of(data, intrinsics=None, floor_px: float = CORNER_FLOOR_PX) -> PlanePrior:
    """:func:`board_plane_prior` for a :class:`lidarcal.joint.JointData` (its held board poses,
    corners and object points)."""
    if data.corners_px is None or data.object_points is None:
        raise ValueError("the board-plane prior needs the board corners and object points (v_board)")
    return board_plane_prior(data.camera, data.corners_px, data.object_points, data.board_R,
                             data.board_T, intrinsics, floor_px)
