"""Compare estimates with a simulator's ``truth.json`` (evaluation only, never calibration)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .geometry import Pose, angle_between_deg


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
    tp = truth_poses(truth)
    rows = [{"index": i, **pose_error(p, tp[i])} for i, p in sorted(estimates.items()) if i in tp]
    return pd.DataFrame(rows, columns=["index", "centre_mm", "z_axis_deg", "x_axis_deg"])


def axis_direction_error_deg(direction: np.ndarray, truth_direction: np.ndarray) -> float:
    """Angle between two axis directions, as lines (sign ignored), deg."""
    a = angle_between_deg(direction, truth_direction)
    return min(a, 180.0 - a)
