"""Compare estimates with a simulator's ``truth.json`` (evaluation only, never calibration)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from .geometry import Plane, Pose, angle_between_deg, intersect_planes


def pose_error(est: Pose, truth: Pose) -> dict[str, float]:
    """True error of one pose: LiDAR centre (mm), z axis and x axis (deg)."""
    return {
        "centre_mm": float(np.linalg.norm(np.asarray(est.T) - np.asarray(truth.T))),
        "z_axis_deg": angle_between_deg(est.z_axis, truth.z_axis),
        "x_axis_deg": angle_between_deg(est.x_axis, truth.x_axis),
    }


def truth_poses(truth: dict) -> dict[int, Pose]:
    """``truth.json`` poses by position index."""
    return {int(p["index"]): Pose.from_dict(p) for p in truth["poses"]}


def pose_errors(estimates: dict[int, Pose], truth: dict) -> pd.DataFrame:
    """One row per position present in both: index, centre_mm, z_axis_deg, x_axis_deg."""
    import pandas as pd

    tp = truth_poses(truth)
    rows = [{"index": i, **pose_error(p, tp[i])} for i, p in sorted(estimates.items()) if i in tp]
    return pd.DataFrame(rows, columns=["index", "centre_mm", "z_axis_deg", "x_axis_deg"])


def axis_direction_error_deg(direction: np.ndarray, truth_direction: np.ndarray) -> float:
    """Angle between two axis directions, as lines (sign ignored), deg."""
    a = angle_between_deg(direction, truth_direction)
    return min(a, 180.0 - a)


def truth_board_planes(truth: dict) -> list[Plane]:
    """The V-board planes of ``truth.json`` (``normal . X = d_mm``)."""
    return [Plane.from_normal_point(np.asarray(b["normal"], float),
                                    np.asarray(b["normal"], float) * float(b["d_mm"]))
            for b in truth["boards"]]


def plane_error(est: Plane, truth: Plane) -> dict[str, float]:
    """Normal angle (deg, sign ignored) and distance error (mm) along the truth normal at the
    point of the truth plane nearest the camera."""
    ang = angle_between_deg(est.normal, truth.normal)
    ang = min(ang, 180.0 - ang)
    foot = truth.normal * truth.d
    return {"normal_deg": ang, "offset_mm": float(abs(est.distance(foot)[0]))}


def match_planes(est: list[Plane], truth: list[Plane]) -> list[int]:
    """For each estimated plane, the index of the truth plane with the nearest normal."""
    return [int(np.argmin([plane_error(e, t)["normal_deg"] for t in truth])) for e in est]


def truth_laser_plane(pose: Pose) -> Plane:
    """The LiDAR scan plane (its z = 0 plane) of a truth pose, in the camera frame."""
    return Plane.from_normal_point(pose.z_axis, pose.T)


def truth_E(truth: dict, index: int) -> np.ndarray:
    """E of section 1.3 from the truth: both board planes and the truth laser plane."""
    b1, b2 = truth_board_planes(truth)[:2]
    return intersect_planes(b1, b2, truth_laser_plane(truth_poses(truth)[index]))


def truth_lines(truth: dict, index: int, order: list[int] | None = None
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Section 1.3 from the truth at one position: E (3,), the stripe rays l (2, 3) and alpha
    (rad). ``l_k = n_k x n_L`` (board ``k``'s plane with the truth laser plane) is oriented
    from E towards board ``k``'s outline centre, as the stripe runs; ``alpha = arccos(l_0 .
    l_1)``. ``order``: truth.json's board indices in the estimate's order
    (:func:`match_planes`); default truth.json's order."""
    order = [0, 1] if order is None else list(order)
    planes = truth_board_planes(truth)
    laser = truth_laser_plane(truth_poses(truth)[index])
    E = intersect_planes(planes[order[0]], planes[order[1]], laser)
    l = []
    for k in order:
        v = np.cross(planes[k].normal, laser.normal)
        v /= np.linalg.norm(v)
        centre = np.mean(np.asarray(truth["boards"][k]["outline_mm"], float), axis=0)
        l.append(v if (centre - E) @ v >= 0 else -v)
    l = np.vstack(l)
    return E, l, float(np.arccos(np.clip(l[0] @ l[1], -1.0, 1.0)))


def v_fit_crlb(points1: np.ndarray, points2: np.ndarray, normal1: np.ndarray, offsets: tuple[
        float, float], alpha: float, sign: int, range_noise_mm: float) -> dict[str, object]:
    """Cramer-Rao bound of the constrained V fit of eqs. (7)-(12) for range noise along the
    beams (the LiDAR's noise model: ``r_i = c_k / (n_k . b_i) + e_i``, ``e_i ~ N(0, s^2)``,
    ``b_i`` the unit beam direction of point ``i``).

    The V has three parameters: the normal angle ``phi`` of line 1 (``n1 = (cos phi, sin phi)``,
    ``n2 = Rot(sign alpha) n1``) and the offsets ``c1``, ``c2`` (``n_k . p = c_k``). Their
    Fisher information is ``J^T J / s^2`` with ``dr/dc_k = 1 / (n_k . b)`` and
    ``dr/dphi = -c_k (n_k^perp . b) / (n_k . b)^2``. The LiDAR centre seen from the V
    (``o = Rot(-phi) (-E)``, E the vertex) carries the bound that limits a single-shot pose's
    centre (eq. 14): ``cov_o = G cov G^T`` with G its Jacobian (central differences).

    Returns ``cov`` (3 x 3, of phi [rad], c1, c2 [mm]), ``phi_std_deg`` and ``centre_rms_mm``
    (``sqrt(trace(cov_o))``, the in-plane rms of the centre's error at the bound).
    """
    from .scan import Line2D, intersect_lines_2d

    p = [np.asarray(points1, float), np.asarray(points2, float)]
    b = [q / np.linalg.norm(q, axis=1)[:, None] for q in p]
    ca, sa = np.cos(sign * alpha), np.sin(sign * alpha)
    Q = np.array([[ca, -sa], [sa, ca]])
    phi0 = float(np.arctan2(normal1[1], normal1[0]))

    def normals(phi: float) -> tuple[np.ndarray, np.ndarray]:
        n1 = np.array([np.cos(phi), np.sin(phi)])
        return n1, Q @ n1

    n = normals(phi0)
    rows = []
    for k in range(2):
        nb = b[k] @ n[k]
        perp = b[k] @ np.array([-n[k][1], n[k][0]])
        J = np.zeros((len(b[k]), 3))
        J[:, 0] = -offsets[k] * perp / nb ** 2
        J[:, 1 + k] = 1.0 / nb
        rows.append(J)
    J = np.vstack(rows)
    cov = range_noise_mm ** 2 * np.linalg.inv(J.T @ J)

    def origin(x: np.ndarray) -> np.ndarray:
        n1, n2 = normals(x[0])
        E = intersect_lines_2d(Line2D(n1, x[1]), Line2D(n2, x[2]))
        c, s = np.cos(x[0]), np.sin(x[0])
        return np.array([[c, s], [-s, c]]) @ (-E)

    x0 = np.array([phi0, offsets[0], offsets[1]])
    h = np.array([1e-7, 1e-4, 1e-4])
    G = np.column_stack([(origin(x0 + h[i] * np.eye(3)[i]) - origin(x0 - h[i] * np.eye(3)[i]))
                         / (2 * h[i]) for i in range(3)])
    cov_o = G @ cov @ G.T
    return {"cov": cov, "phi_std_deg": float(np.degrees(np.sqrt(cov[0, 0]))),
            "centre_cov": cov_o, "centre_rms_mm": float(np.sqrt(np.trace(cov_o)))}
