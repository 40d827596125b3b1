"""What the report is made of: the dataset and its calibration / measurements JSON files
(read, or computed by the pipeline and read back)."""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from ..io.dataset import (
    CALIBRATION_FORMAT,
    MEASUREMENTS_FORMAT,
    Dataset,
    DatasetError,
    load_dataset,
    read_json_object,
)


@dataclass
class ReportInputs:
    """Everything the report is made of. ``cal``/``meas`` are the parsed JSON files."""

    dataset: Dataset
    cal: dict
    meas: dict | None = None
    truth: dict | None = None
    result: object | None = None  # lidarcal.pipeline.CalibrationResult when computed here
    command: str | None = None
    calibration_path: Path | None = None
    measurements_path: Path | None = None
    notes: list[str] = field(default_factory=list)  # problems met while making the report
    created: str = field(default_factory=lambda: datetime.now(UTC)
                         .strftime("%Y-%m-%d %H:%M UTC"))


def _read_json(path: Path, what: str, fmt: str) -> dict:
    """``what`` (calibration.json, measurements.json) of format ``fmt`` exactly; a calibration's
    pose function is read too (:func:`lidarcal.api.load_calibration`), so a broken one is
    refused here rather than drawn."""
    p = Path(path)
    if p.is_dir():
        p = p / what
    fix = f"give the {what} written by lidarcal"
    data = read_json_object(p, f"missing; {fix}", fix, f" (a {fmt} file); {fix}")
    if data.get("format") != fmt:
        raise DatasetError(p, f"format {data.get('format')!r}, expected '{fmt}'; {fix} (another "
                              "version: run that lidarcal's command again with this one)")
    if fmt == CALIBRATION_FORMAT:
        from ..api import load_calibration

        load_calibration(p)
    return data


def gather_inputs(dataset: str | os.PathLike | Dataset, calibration: str | os.PathLike | None = None,
                  measurements: str | os.PathLike | None = None, command: str | None = None,
                  workdir: str | os.PathLike | None = None) -> ReportInputs:
    """Load (or compute) the calibration and measurements the report shows.

    With ``calibration=None`` the pipeline runs on ``dataset``; its
    ``calibration.json`` (and, if the dataset lists measurements,
    ``measurements.json``) are written to ``workdir`` (a temporary folder by
    default) and read back, exactly as the CLI would write them.
    """
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    from .. import pipeline

    result = None
    tmp = None
    if calibration is None:
        tmp = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="lidarcal_rep_"))
        tmp.mkdir(parents=True, exist_ok=True)
        result = pipeline.calibrate(ds)
        calibration = pipeline.write_calibration(result, tmp, command=command)
        if measurements is None and ds.measurements:
            table = pipeline.measure_dataset(ds.root, calibration)
            measurements = pipeline.write_measurements(table, tmp, ds.root)
    cal_path = Path(calibration)
    cal = _read_json(cal_path, "calibration.json", CALIBRATION_FORMAT)
    meas = None
    if measurements is not None:
        meas = _read_json(Path(measurements), "measurements.json", MEASUREMENTS_FORMAT)
    return ReportInputs(ds, cal, meas, ds.truth(), result, command,
                        cal_path if cal_path.is_file() else cal_path / "calibration.json",
                        None if measurements is None else Path(measurements))
