"""RIG.json: what a bag cannot hold (camera or intrinsics photos, boards, z-axis hint, sweeps).

Read by ``lidarcal import`` (:mod:`lidarcal.io.bag`); the format is in ``docs/ros-bags.md``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import DEFAULT_Z_AXIS_HINT, DatasetError, parse_camera, read_json_object


@dataclass(frozen=True)
class SweepWindow:
    """A measurement sweep: the bag's time window ``[start_s, end_s]`` (s from its first message)."""

    name: str
    start_s: float
    end_s: float
    object: str = "disc"
    reference_diameter_mm: float | None = None


@dataclass
class RigFile:
    """RIG.json: what a bag cannot hold (camera or intrinsics photos, boards, z-axis hint)."""

    path: Path
    base: dict  # dataset.json keys: camera, intrinsics_board, v_board
    z_axis_hint: list[float]
    lidar_limits: dict[str, float]  # optional angle/range limits to check the messages against
    intrinsics_dir: Path | None
    sweeps: list[SweepWindow]


_LIMIT_KEYS = ("angle_min_deg", "angle_max_deg", "angle_step_deg", "range_min_mm", "range_max_mm")


def _finite(v, path: Path, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise DatasetError(path, f"'{key}' must be a finite number, got {v!r}; fix RIG.json")
    return float(v)


def read_rig(path: str | os.PathLike) -> RigFile:
    """Read and check RIG.json (format in ``docs/ros-bags.md``); every problem is a
    :class:`DatasetError` naming it and saying what to do."""
    try:
        return _read_rig(Path(path))
    except DatasetError as e:
        if ";" in e.problem:
            raise
        raise DatasetError(e.path, f"{e.problem}; fix RIG.json (see docs/ros-bags.md)") from None


def _read_rig(path: Path) -> RigFile:
    raw = read_json_object(path, "missing rig file; write RIG.json (see docs/ros-bags.md)",
                           "fix it", " (see docs/ros-bags.md)")
    base: dict = {}
    if raw.get("camera") is not None:
        parse_camera(raw["camera"], path)  # validates
        base["camera"] = raw["camera"]
    intr_dir = None
    if raw.get("intrinsics") is not None:
        if not isinstance(raw["intrinsics"], str):
            raise DatasetError(path, "'intrinsics' must be a folder of chessboard photos (a path)")
        intr_dir = (path.parent / raw["intrinsics"]).resolve()
        if not intr_dir.is_dir():
            raise DatasetError(path, f"'intrinsics' folder {intr_dir} does not exist")
        if raw.get("intrinsics_board") is None:
            raise DatasetError(path, "'intrinsics' photos need 'intrinsics_board' "
                                     "(inner_corners, square_mm)")
    if "camera" not in base and intr_dir is None:
        raise DatasetError(path, "needs 'camera' (image_size, K, dist) or 'intrinsics' (a folder "
                                 "of chessboard photos) with 'intrinsics_board'")
    for key in ("intrinsics_board", "v_board"):
        if raw.get(key) is not None:
            base[key] = raw[key]
    if "v_board" not in base:
        raise DatasetError(path, "missing 'v_board' (inner_corners, square_mm of each board of the V)")
    lidar = raw.get("lidar", {})
    if not isinstance(lidar, dict):
        raise DatasetError(path, "'lidar' must be an object")
    hint = lidar.get("z_axis_hint", list(DEFAULT_Z_AXIS_HINT))
    if (not isinstance(hint, list) or len(hint) != 3
            or not np.linalg.norm([_finite(v, path, "lidar.z_axis_hint") for v in hint]) > 0):
        raise DatasetError(path, f"'lidar.z_axis_hint' must be a non-zero [x, y, z], got {hint!r}")
    limits = {k: _finite(lidar[k], path, f"lidar.{k}") for k in _LIMIT_KEYS if k in lidar}
    sweeps = []
    items = raw.get("measurements", [])
    if not isinstance(items, list):
        raise DatasetError(path, "'measurements' must be a list of {name, start_s, end_s}")
    for i, m in enumerate(items):
        if not isinstance(m, dict) or not {"name", "start_s", "end_s"} <= m.keys():
            raise DatasetError(path, f"measurements[{i}] needs name, start_s and end_s "
                                     "(seconds from the bag's first message)")
        name = str(m["name"])
        if not name or any(c in name for c in "/\\") or name.startswith("."):
            raise DatasetError(path, f"measurements[{i}].name {name!r} must be a plain file name")
        s0 = _finite(m["start_s"], path, f"measurements[{i}].start_s")
        s1 = _finite(m["end_s"], path, f"measurements[{i}].end_s")
        if s1 <= s0:
            raise DatasetError(path, f"measurements[{i}]: end_s must be after start_s")
        ref = m.get("reference_diameter_mm")
        ref = None if ref is None else _finite(ref, path, f"measurements[{i}].reference_diameter_mm")
        sweeps.append(SweepWindow(name, s0, s1, str(m.get("object", "disc")), ref))
    if len({s.name for s in sweeps}) != len(sweeps):
        raise DatasetError(path, "measurement names must be distinct")
    return RigFile(path, base, [float(v) for v in hint], limits, intr_dir, sweeps)
