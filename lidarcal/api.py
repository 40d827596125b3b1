"""The small public API: load a ``calibration.json`` and turn scans into 3D points."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .geometry import Pose
from .io.dataset import CALIBRATION_FORMAT, DatasetError, read_json_object


@dataclass(frozen=True)
class Calibration:
    """A calibrated rig: the LiDAR pose as a function of the turntable angle."""

    path: Path
    data: dict
    model: object  # a lidarcal.turntable pose function

    @property
    def axis(self):
        return self.model.axis

    def pose(self, psi_deg: float) -> Pose:
        """LiDAR pose in the camera frame at turntable angle ``psi_deg`` (eqs. 26-27)."""
        return self.model.pose(float(psi_deg))

    @property
    def ranging(self):
        """The LiDAR's ranging model (:class:`lidarcal.ranging.RangingModel`) fitted with this
        pose function: calibration.json ``ranging`` for the joint fit; zero terms for a pose
        function fitted without one (the paper's chain, the rigid fit) or an older file."""
        from .ranging import RangingModel

        own = getattr(self.model, "ranging", None)
        if isinstance(own, RangingModel):
            return own
        if type(self.model).__name__ == "JointModel":
            return RangingModel.from_dict(self.data.get("ranging"))
        return RangingModel()

    def points(self, psi_deg: float | np.ndarray, angle_deg: np.ndarray,
               range_mm: np.ndarray) -> np.ndarray:
        """Camera-frame points of LiDAR returns, eq. (28):
        ``X_c = R(psi) [rho cos theta, rho sin theta, 0]^T + T(psi)``, with ``rho`` the range
        corrected by the ranging model (``rho - offset_mm``, :mod:`lidarcal.ranging`).

        ``psi_deg`` is one angle or one per return; NaN ranges (no return) give NaN rows.
        """
        from .measure import returns_points  # lazy: measure imports pandas and scipy

        return returns_points(psi_deg, angle_deg, range_mm, self)

    def cloud(self, sweep, frame: str = "camera", lidar=None):
        """Every valid return of a sweep as a 3D point, eq. (28), psi per scan line.

        ``sweep``: a DataFrame (psi_deg, angle_deg, range_mm[, intensity]) or
        the path of a sweep file; ``frame``: ``"camera"`` or ``"home"`` (the
        LiDAR frame at psi = 0). Returns a :class:`lidarcal.cloud.SweepCloud`
        (``.points``, ``.attributes()``, ``.write(path)``).
        """
        from .cloud import read_sweep_with_intensity, sweep_cloud

        if isinstance(sweep, (str, os.PathLike)):
            sweep = read_sweep_with_intensity(sweep, lidar)
        return sweep_cloud(sweep, self.model, frame=frame, lidar=lidar)


def _number_as_text(value, where: str) -> str | None:
    """Where in ``value`` (nested dicts and lists) a number is written as text (``"12.5"``),
    which numpy would read as the number without a word: None when nowhere."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return None
        return f"'{where}' ({value!r})"
    items = value.items() if isinstance(value, dict) else enumerate(value) \
        if isinstance(value, list) else ()
    for k, v in items:
        found = _number_as_text(v, f"{where}.{k}" if isinstance(k, str) else f"{where}[{k}]")
        if found:
            return found
    return None


def load_calibration(path: str | os.PathLike, model: str = "poses") -> Calibration:
    """Read ``calibration.json`` (a file or the folder holding it).

    ``model="poses"`` gives the pose function that filled ``poses``; ``"paper"``,
    ``"rigid"`` or ``"joint"`` that pose function when it was stored.
    """
    from .turntable import model_from_dict

    p = Path(path)
    if p.is_dir():
        p = p / "calibration.json"
    fix = "give the calibration.json of 'lidarcal calibrate' (or run it again)"
    data = read_json_object(p, "missing; run 'lidarcal calibrate DATASET --out DIR' first",
                            "run 'lidarcal calibrate' again", f" ('{CALIBRATION_FORMAT}'); {fix}")
    if data.get("format") != CALIBRATION_FORMAT:
        raise DatasetError(p, f"unknown format {data.get('format')!r}, expected "
                              f"'{CALIBRATION_FORMAT}' (not a calibration of this lidarcal); {fix}")
    key = "model" if model == "poses" else f"model_{model}"
    if key not in data and data.get("method") == model:
        key = "model"
    if key not in data:
        raise DatasetError(p, f"holds no '{key}' pose function; recalibrate with this lidarcal version")
    try:
        if not isinstance(data[key], dict):
            raise TypeError(f"expected an object, got {type(data[key]).__name__}")
        where = _number_as_text(data[key], key)
        if where:
            raise TypeError(f"{where} is a number written as text")
        fn = model_from_dict(data[key])
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as e:
        raise DatasetError(p, f"'{key}' is malformed ({' '.join(str(e).split())}); {fix}") from None
    return Calibration(p, data, fn)
