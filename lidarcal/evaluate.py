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
