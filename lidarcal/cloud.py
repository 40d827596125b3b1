"""Point clouds of turntable sweeps, eq. (28), for the tools used next (CloudCompare, Open3D, PCL).

Every valid return of a sweep (a finite range inside the LiDAR's
``[range_min_mm, range_max_mm]``) becomes one point, eq. (28)::

    X_c = R(psi) [rho cos theta, rho sin theta, 0]^T + T(psi)

with ``psi`` the turntable angle of its own scan line. Each point keeps its
range ``rho`` (``range_mm``), turntable angle (``psi_deg``), beam angle
(``angle_deg``) and, when the sweep file has an ``intensity`` column, its
intensity.

Frames (``frame=``):

``camera``
    The camera frame (OpenCV: x right, y down, z forward), mm: the frame of
    ``calibration.json``.
``home``
    The LiDAR frame at turntable angle psi = 0 deg (the calibrated pose
    function evaluated at 0): ``X_home = R(0)^T (X_c - T(0))``. Origin at the
    LiDAR's optical centre at psi = 0, x along the beam at angle 0, z normal
    to the scan plane. A cloud in this frame does not depend on where the
    camera was, so sweeps taken with the same turntable line up.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from .io.dataset import DatasetError, LidarSpec, read_sweep
from .measure import PoseFunction, sweep_points

FRAMES = ("camera", "home")


@dataclass(frozen=True)
class SweepCloud:
    """The returns of one sweep as 3D points (mm) with their attributes (one per point)."""

    points: np.ndarray  # (N, 3), mm, in ``frame``
    range_mm: np.ndarray  # (N,)
    psi_deg: np.ndarray  # (N,)
    angle_deg: np.ndarray  # (N,)
    intensity: np.ndarray | None
    frame: str

    def __len__(self) -> int:
        return len(self.points)

    def attributes(self) -> dict[str, np.ndarray]:
        """Per-point attributes as written to files: range_mm, psi_deg, angle_deg[, intensity]."""
        out = {"range_mm": self.range_mm, "psi_deg": self.psi_deg, "angle_deg": self.angle_deg}
        if self.intensity is not None:
            out["intensity"] = self.intensity
        return out

    def write(self, path: str | os.PathLike) -> Path:
        """Write to ``path`` (.ply, .pcd, .vtp, .csv; see :mod:`lidarcal.io.clouds`)."""
        from .io.clouds import write_cloud

        return write_cloud(path, self.points, self.attributes())


def read_sweep_with_intensity(path: str | os.PathLike, lidar: LidarSpec | None = None) -> pd.DataFrame:
    """A sweep file (``measure/*.csv.gz``) with its optional ``intensity`` column (NaN if absent)."""
    path = Path(path)
    sweep = read_sweep(path, lidar)
    try:
        head = pd.read_csv(path, nrows=0).columns
    except (ValueError, OSError, EOFError, pd.errors.ParserError):
        return sweep
    if "intensity" in head:
        vals = pd.read_csv(path, usecols=["intensity"])["intensity"]
        sweep["intensity"] = pd.to_numeric(vals, errors="coerce").to_numpy(float)
    return sweep


def sweep_cloud(sweep: pd.DataFrame, model: PoseFunction, frame: str = "camera",
                lidar: LidarSpec | None = None) -> SweepCloud:
    """Every valid return of a sweep as a point, eq. (28), psi per scan line.

    Parameters
    ----------
    sweep : DataFrame with psi_deg, angle_deg, range_mm (NaN or 0 = no return)
        and optionally intensity.
    model : the calibrated pose function, ``model.pose(psi_deg) -> Pose``.
    frame : ``"camera"`` or ``"home"`` (module docstring).
    lidar : range limits; returns outside ``[range_min_mm, range_max_mm]`` are dropped.
    """
    if frame not in FRAMES:
        raise ValueError(f"frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    rng = sweep["range_mm"].to_numpy(float)
    ok = np.isfinite(rng) & (rng > 0)
    if lidar is not None:
        ok &= (rng >= lidar.range_min_mm) & (rng <= lidar.range_max_mm)
    valid = sweep.loc[ok]
    pts = sweep_points(valid, model) if len(valid) else np.zeros((0, 3))
    if frame == "home":
        pts = model.pose(0.0).inverse_apply(pts) if len(pts) else pts
    inten = None
    if "intensity" in valid.columns and np.isfinite(valid["intensity"].to_numpy(float)).any():
        inten = valid["intensity"].to_numpy(float)
    return SweepCloud(np.asarray(pts, float), valid["range_mm"].to_numpy(float),
                      valid["psi_deg"].to_numpy(float), valid["angle_deg"].to_numpy(float), inten, frame)


def dataset_clouds(dataset: str | os.PathLike, calibration: str | os.PathLike, names: list[str] | None,
                   out: str | os.PathLike, frame: str = "camera", fmt: str = ".ply") -> list[Path]:
    """Write the cloud of each named sweep (all when ``names`` is None) of a dataset.

    One named sweep: ``out`` is the file (its suffix picks the format; none:
    ``fmt``). Several, or all (``names=None``): ``out`` is a folder, one
    ``NAME<fmt>`` each.
    """
    from .api import load_calibration
    from .io.clouds import FORMATS
    from .io.dataset import load_dataset

    ds = load_dataset(dataset)
    cal = load_calibration(calibration)
    specs = {m.name: m for m in ds.measurements}
    names_given = names is not None
    if names is None:
        if not specs:
            raise DatasetError(ds.dataset_json, "lists no 'measurements' (sweeps) to export")
        names = list(specs)
    unknown = [n for n in names if n not in specs]
    if unknown:
        raise DatasetError(ds.dataset_json, f"no measurement named {', '.join(unknown)}; "
                                            f"known: {', '.join(specs) or 'none'}")
    fmt = fmt if fmt.startswith(".") else "." + fmt
    out = Path(out)
    single = names_given and len(names) == 1
    if single and not out.suffix:
        out = out.with_suffix(fmt)
    if single and out.suffix.lower() not in FORMATS:
        raise DatasetError(out, f"unknown point-cloud format {out.suffix!r}; use one of {', '.join(FORMATS)}")
    written = []
    for name in names:
        sweep = read_sweep_with_intensity(specs[name].sweep, ds.lidar)
        cloud = cal.cloud(sweep, frame=frame, lidar=ds.lidar)
        if len(cloud) == 0:
            raise DatasetError(specs[name].sweep, "holds no valid return; nothing to export")
        written.append(cloud.write(out if single else out / f"{name}{fmt}"))
    return written
