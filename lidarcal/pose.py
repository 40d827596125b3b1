"""LiDAR pose in the camera frame from the two stripe lines, eqs. (13)-(14) (section 1.5).

Convention: ``X_camera = R @ X_lidar + T`` (:class:`lidarcal.geometry.Pose`);
R's columns are the LiDAR's x, y, z axes in the camera frame, T its optical
centre, mm.

The mirror ambiguity: the camera sees which stripe lies on which board, the
scan only which segment comes first in beam order. Pairing camera line 1 with
LiDAR segment 1 or with LiDAR segment 2 gives two proper rotations that fit
the data equally well (mirror images across the V's bisector; the LiDAR z axis
flips). :func:`single_shot_pose` solves both and lets the rig's
``z_axis_hint`` pick one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .geometry import Line3D, Pose, angle_between, cross3, nearest_rotation, unit
from .scan import LidarLines


def pose_from_line_pairs(l_cam: np.ndarray, l_lidar: np.ndarray, E_cam: np.ndarray,
                         E_lidar: np.ndarray) -> Pose:
    """LiDAR pose from two line correspondences, eqs. (13)-(14).

    ``R = [l1c l2c l1c x l2c] [l1l l2l l1l x l2l]^-1`` (eq. 13) is a rotation
    only when both pairs meet at the same angle; it is projected onto SO(3)
    (SVD, :func:`nearest_rotation`) and the Frobenius distance of the raw
    product from the rotation is kept in ``Pose.residual``.
    ``T = E_c - R E_l`` (eq. 14).

    Parameters
    ----------
    l_cam : array, shape (2, 3)
        Unit directions l1, l2 in the camera frame (rows).
    l_lidar : array, shape (2, 3)
        The same lines in the LiDAR frame (rows, z = 0 for scan lines).
    E_cam, E_lidar : arrays, shape (3,)
        The lines' common point in each frame, mm.
    """
    lc, ll, Ec, El = _checked_pairs(l_cam, l_lidar, E_cam, E_lidar)
    return _pose_from_frames(_frame(lc), _frame(ll), Ec, El,
                             {"angle_cam": angle_between(lc[0], lc[1]),
                              "angle_lidar": angle_between(ll[0], ll[1])})


def _checked_pairs(l_cam: np.ndarray, l_lidar: np.ndarray, E_cam: np.ndarray,
                   E_lidar: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inputs of :func:`pose_from_line_pairs` checked, as float arrays, directions unit."""
    lc = np.asarray(l_cam, dtype=float)
    ll = np.asarray(l_lidar, dtype=float)
    if lc.shape != (2, 3) or ll.shape != (2, 3):
        raise ValueError(f"Expected l_cam and l_lidar with shape (2, 3), got {lc.shape} and "
                         f"{ll.shape}")
    Ec = np.asarray(E_cam, dtype=float).reshape(3)
    El = np.asarray(E_lidar, dtype=float).reshape(3)
    return unit(lc), unit(ll), Ec, El


def _frame(l: np.ndarray) -> np.ndarray:
    """``[l1 l2 l1 x l2]`` (columns) of two unit directions (rows of ``l``), for eq. (13)."""
    return np.column_stack([l[0], l[1], cross3(l[0], l[1])])


def _pose_from_frames(C: np.ndarray, L: np.ndarray, Ec: np.ndarray, El: np.ndarray,
                      angles: dict[str, float]) -> Pose:
    """Eqs. (13)-(14) from the frames of :func:`_frame` in the camera (``C``) and the LiDAR
    (``L``); ``angles`` (each pair's angle) go to ``info``."""
    if abs(np.linalg.det(L)) < 1e-9 or abs(np.linalg.det(C)) < 1e-9:
        raise ValueError("the two lines are parallel: eq. (13) has no solution")
    M = C @ np.linalg.inv(L)  # eq. (13)
    R, resid = nearest_rotation(M)
    T = Ec - R @ El  # eq. (14)
    return Pose(R, T, resid, info={"raw_R": M, **angles})


def single_shot_pose(l_cam: np.ndarray, E_cam: np.ndarray, alpha_cam: float,
                     lidar_lines: LidarLines,
                     z_axis_hint: Sequence[float] = (0.0, -1.0, 0.0)) -> Pose:
    """The single-shot pose of section 1 with the mirror ambiguity resolved.

    Both pairings are solved with eqs. (13)-(14): "direct" (camera board 1 <->
    scan segment 1, the lower beam angles) and "swapped" (camera board 1 <->
    scan segment 2). Both are proper rotations; the one whose LiDAR z axis
    ``R[:, 2]`` points along ``z_axis_hint`` is returned.

    Parameters
    ----------
    l_cam : array, shape (2, 3)
        Stripe directions from E on camera board 1 and board 2.
    E_cam : array, shape (3,)
        Intersection of both board planes and the laser plane, mm.
    alpha_cam : float
        ``arccos(l1 . l2)`` in the camera frame (rad); ``lidar_lines`` must
        have been fitted with it (:func:`lidarcal.scan.fit_v_lines`).
    lidar_lines : LidarLines
        The constrained scan lines (segments in beam order).
    z_axis_hint : (3,)
        Rough direction of the LiDAR z axis in the camera frame.

    Returns
    -------
    Pose
        ``info`` holds ``assignment`` ("direct" or "swapped"), ``pairs``
        (camera line k <-> scan segment ``pairs[k]``), ``hint_dot`` for the
        chosen pose and ``candidates`` (both poses by name).
    """
    if abs(lidar_lines.alpha - alpha_cam) > 1e-6:
        raise ValueError(f"the LiDAR lines meet at {np.degrees(lidar_lines.alpha):.4f} deg but the "
                         f"camera's alpha is {np.degrees(alpha_cam):.4f} deg; fit them with "
                         "fit_v_lines(points1, points2, alpha_cam)")
    hint = unit(np.asarray(z_axis_hint, dtype=float))
    # both pairings share the camera frame and the angles (swapping the scan lines only
    # reverses their order): eqs. (13)-(14) as pose_from_line_pairs, the common part once
    lc, ll, Ec, El = _checked_pairs(l_cam, lidar_lines.l_lidar, E_cam, lidar_lines.E_lidar)
    C = _frame(lc)
    angles = {"angle_cam": angle_between(lc[0], lc[1]),
              "angle_lidar": angle_between(ll[0], ll[1])}
    cands = {"direct": _pose_from_frames(C, _frame(ll), Ec, El, angles),
             "swapped": _pose_from_frames(C, _frame(ll[::-1]), Ec, El, angles)}
    dots = {k: float(p.z_axis @ hint) for k, p in cands.items()}
    best = max(dots, key=dots.get)
    p = cands[best]
    info = dict(p.info)
    info.update(assignment=best, pairs=(0, 1) if best == "direct" else (1, 0),
                hint_dot=dots[best], hint_dots=dots, candidates=cands)
    if abs(dots[best]) < 0.1:
        info["warning"] = ("z_axis_hint is almost perpendicular to both candidate z axes; "
                           "the mirror choice is unreliable")
    return Pose(p.R, p.T, p.residual, info)


def refine_pose(pose: Pose, cam_lines: Sequence[Line3D], seg_points: Sequence[np.ndarray],
                *, loss: str = "linear") -> Pose:
    """Least-squares refinement of R, T on all scan points (beyond the paper).

    Minimises the distances of the scan points, mapped into the camera frame,
    to the camera's 3D stripe lines ``E_c + t l_k``: ``seg_points[k]`` (LiDAR
    plane points, (N_k, 2) or (N_k, 3)) must lie on ``cam_lines[k]`` (for a
    pose from :func:`single_shot_pose`, segment ``pose.info["pairs"][k]`` goes
    with camera line k). Rotation as a rotation vector about ``pose.R``.

    Note: with the camera lines held fixed this optimum coincides with the
    constrained orthogonal line fit (``fit_v_lines(..., weighting="orthogonal")``) + eqs. (13)-(14) (the best plane for the points is the
    lines' plane, and within it the problem is exactly the constrained fit), so
    it mostly serves as a check, or with a robust ``loss``.
    """
    if len(cam_lines) != 2 or len(seg_points) != 2:
        raise ValueError("refine_pose needs two camera lines and two point sets")
    P = []
    for pts in seg_points:
        q = np.asarray(pts, dtype=float)
        if q.ndim != 2 or q.shape[1] not in (2, 3):
            raise ValueError(f"segment points must have shape (N, 2) or (N, 3), got {q.shape}")
        P.append(np.column_stack([q[:, :2], np.zeros(len(q))]) if q.shape[1] == 2 else q)
    bases = []
    for ln in cam_lines:
        d = unit(ln.direction)
        a = np.array([1.0, 0, 0]) if abs(d[0]) < 0.9 else np.array([0, 1.0, 0])
        u = unit(np.cross(d, a))
        bases.append((np.asarray(ln.point, float), np.vstack([u, np.cross(d, u)])))
    R0 = pose.R

    def residuals(x: np.ndarray) -> np.ndarray:
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        out = []
        for (c, B), q in zip(bases, P):
            out.append(((q @ R.T + x[3:] - c) @ B.T).ravel())
        return np.concatenate(out)

    x0 = np.concatenate([np.zeros(3), pose.T])
    sol = least_squares(residuals, x0, loss=loss, x_scale="jac")
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
    r = residuals(sol.x).reshape(-1, 2)
    info = dict(pose.info)
    info.update(refined=True, refine_rms_mm=float(np.sqrt(np.mean(np.sum(r ** 2, 1)))),
                refine_status=sol.status)
    return Pose(R, sol.x[3:], pose.residual, info)
