"""The PDF calibration report (in the spirit of Kalibr's report).

Numbers come from ``calibration.json`` / ``measurements.json`` only, so the
report always agrees with the files: when no calibration is given the
pipeline is run and its output written to a temporary folder first, then read
back like any other. Figures that need images (corners, stripes, scan lines,
disc cloud) re-run only those steps, on one representative position.

The document is typst source (tables + PNG figures) compiled with the
``typst`` Python binding; :func:`build_report_source` gives the source
without compiling it (tests compare its numbers with the JSON files).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from . import __version__
from .dataset import CameraModel, Dataset, DatasetError, load_dataset
from .evaluate import pose_error
from .geometry import Pose

#: The paper's Table 1 (fitted function vs the 87 samples): (mean, max).
PAPER_TABLE1 = {"centre_mm": (1.12, 2.72), "z_axis_deg": (0.203, 0.455),
                "x_axis_deg": (0.662, 1.580)}
#: The paper's Table 2: trial, diameter (mm), |error| (mm); reference 140 mm.
PAPER_TABLE2 = [(1, 137.12, 2.88), (2, 135.80, 4.20), (3, 134.89, 5.11), (4, 142.63, 2.63),
                (5, 138.48, 1.52), (6, 135.64, 4.36), (7, 141.57, 1.57), (8, 136.87, 3.13),
                (9, 139.81, 0.19), (10, 142.08, 2.08)]
PAPER_TABLE2_MEAN = (138.49, 2.77)  # mean diameter, mean |error|
PAPER_REFERENCE_MM = 140.0
FIG_DPI = 150
#: Decimals used in the tables (tests format with the same precision).
DECIMALS = {"centre_mm": 3, "z_axis_deg": 4, "x_axis_deg": 4, "diameter_mm": 2, "error_mm": 2}

COMPARISON_COLUMNS = ("centre_mm", "z_axis_deg", "x_axis_deg")


# ---------------------------------------------------------------- inputs


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


def _read_json(path: Path, what: str, fmt_prefix: str) -> dict:
    p = Path(path)
    if p.is_dir():
        p = p / what
    if not p.is_file():
        raise DatasetError(p, f"missing; give the {what} written by lidarcal")
    try:
        data = json.loads(p.read_text(encoding="utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(p, f"not valid JSON ({e})") from None
    if not isinstance(data, dict) or not str(data.get("format", "")).startswith(fmt_prefix):
        raise DatasetError(p, f"is not a {fmt_prefix} file (format "
                              f"{data.get('format') if isinstance(data, dict) else None!r})")
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
    from . import pipeline

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
    cal = _read_json(cal_path, "calibration.json", "lidarcal-calibration/")
    meas = None
    if measurements is not None:
        meas = _read_json(Path(measurements), "measurements.json", "lidarcal-measurements/")
    return ReportInputs(ds, cal, meas, ds.truth(), result, command,
                        cal_path if cal_path.is_file() else cal_path / "calibration.json",
                        None if measurements is None else Path(measurements))


# ---------------------------------------------------------------- numbers (from the JSON only)


def _poses(rows: list[dict] | None) -> dict[int, Pose]:
    return {int(r["index"]): Pose.from_dict(r) for r in rows or []}


def model_poses(cal: dict, kind: str) -> dict[int, Pose]:
    """Poses of pose function ``kind`` ("paper", "rigid" or "joint") at the positions, from
    calibration.json."""
    if cal.get("method") == kind:
        return _poses(cal.get("poses"))
    return _poses(cal.get(f"poses_{kind}"))


def comparison(est: dict[int, Pose], ref: dict[int, Pose], psi: dict[int, float]) -> pd.DataFrame:
    """Per position: ``pose_error(est, ref)`` (centre mm, z axis deg, x axis deg)."""
    rows = [{"index": i, "psi_deg": psi.get(i, np.nan), **pose_error(est[i], ref[i])}
            for i in sorted(est) if i in ref]
    return pd.DataFrame(rows, columns=["index", "psi_deg", *COMPARISON_COLUMNS])


def uncertainty_summary(cal: dict, truth: dict | None) -> str:
    """The joint fit's reported 1-sigma (mean over positions) and, with ``truth.json``, how
    often the true error of ``poses`` lies within 2 sigma; "" without a ``sigma`` block."""
    sig = cal.get("sigma")
    if not isinstance(sig, dict) or not sig.get("poses"):
        return ""
    qs = ("centre_mm", "z_axis_deg", "x_axis_deg")
    rows = {int(r["index"]): r for r in sig["poses"]}
    val = lambda r, q: np.inf if r.get(q) is None else float(r[q])
    mean = {q: float(np.mean([val(r, q) for r in rows.values()])) for q in qs}
    out = (f"centre {fnum(mean['centre_mm'], 3)} mm, z axis {fnum(mean['z_axis_deg'], 4)} deg, "
           f"x axis {fnum(mean['x_axis_deg'], 4)} deg, axis direction "
           f"{fnum(sig.get('axis_direction_deg') or np.inf, 4)} deg")
    if sig.get("angle_jitter_deg"):
        out += (f"; turntable encoder jitter {fnum(float(sig['angle_jitter_deg']), 4)} deg "
                "(each position's angle corrected)")
    if truth is not None and truth.get("poses"):
        tp, est = _poses(truth["poses"]), _poses(cal.get("poses"))
        inside = [pose_error(est[i], tp[i])[q] <= 2 * val(r, q)
                  for i, r in rows.items() if i in tp and i in est for q in qs]
        if inside:
            out += (f"; the true error lies within 2 sigma for {100 * np.mean(inside):.0f} % of "
                    "positions x quantities")
    return out


def comparisons(cal: dict, truth: dict | None) -> dict[str, pd.DataFrame]:
    """Every Table 1 comparison available: each pose function vs the samples (the
    paper's metric), and, with ``truth.json``, vs the true poses (and the samples vs truth)."""
    psi = {int(r["index"]): float(r["psi_deg"]) for r in cal.get("samples", [])}
    samples = _poses(cal.get("samples"))
    out: dict[str, pd.DataFrame] = {}
    models = [k for k in ("paper", "rigid", "joint") if model_poses(cal, k)]
    for k in models:
        out[f"{k} function vs samples"] = comparison(model_poses(cal, k), samples, psi)
    if truth is not None and truth.get("poses"):
        tp = _poses(truth["poses"])
        for k in models:
            out[f"{k} function vs truth"] = comparison(model_poses(cal, k), tp, psi)
        out["samples vs truth"] = comparison(samples, tp, psi)
    return out


def table1(cal: dict, truth: dict | None = None) -> pd.DataFrame:
    """Table 1 reproduced: one row per comparison, mean and max of each column.

    Columns ``centre_mm_mean, centre_mm_max, z_axis_deg_mean, ...``; index is
    the comparison label. The paper's published row is ``"paper (published)"``.
    """
    rows = {"paper (published)": {f"{c}_{s}": PAPER_TABLE1[c][j] for c in COMPARISON_COLUMNS
                                  for j, s in enumerate(("mean", "max"))}}
    for label, df in comparisons(cal, truth).items():
        rows[label] = {f"{c}_{s}": float(getattr(df[c], s)()) if len(df) else np.nan
                       for c in COMPARISON_COLUMNS for s in ("mean", "max")}
    return pd.DataFrame.from_dict(rows, orient="index")


def table2(meas: dict | None, truth: dict | None = None) -> tuple[pd.DataFrame, dict]:
    """Table 2 reproduced from measurements.json: per trial and the summary.

    Summary keys: ``trials``, ``mean_diameter_mm``, ``mean_error_mm`` (signed),
    ``mean_abs_error_mm`` (the paper's "error" column is |error|), and
    ``mean_abs_error_truth_mm`` when truth.json gives the true diameters.
    """
    rows = []
    tdiam = {}
    if truth is not None:
        tdiam = {m.get("name"): m.get("diameter_mm") for m in truth.get("measurements", [])}
    for m in (meas or {}).get("measurements", []):
        d = float(m["diameter_mm"])
        ref = m.get("reference_diameter_mm")
        err = m.get("error_mm")
        if err is None and ref is not None:
            err = d - float(ref)
        rows.append({"name": m.get("name", f"trial {len(rows) + 1}"), "diameter_mm": d,
                     "reference_diameter_mm": np.nan if ref is None else float(ref),
                     "error_mm": np.nan if err is None else float(err),
                     "naive_diameter_mm": float(m["naive_diameter_mm"])
                     if m.get("naive_diameter_mm") is not None else np.nan,
                     "points": m.get("points"),
                     "truth_diameter_mm": float(tdiam[m.get("name")])
                     if tdiam.get(m.get("name")) is not None else np.nan})
    df = pd.DataFrame(rows, columns=["name", "diameter_mm", "reference_diameter_mm", "error_mm",
                                     "naive_diameter_mm", "points", "truth_diameter_mm"])
    summ: dict = {"trials": len(df)}
    if len(df):
        summ["mean_diameter_mm"] = float(df["diameter_mm"].mean())
        e = df["error_mm"].dropna()
        if len(e):
            summ["mean_error_mm"] = float(e.mean())
            summ["mean_abs_error_mm"] = float(e.abs().mean())
        t = df.dropna(subset=["truth_diameter_mm"])
        if len(t):
            summ["mean_abs_error_truth_mm"] = float((t["diameter_mm"] - t["truth_diameter_mm"])
                                                   .abs().mean())
        nv = df["naive_diameter_mm"].dropna()
        if len(nv) and df["reference_diameter_mm"].notna().all():
            summ["naive_mean_abs_error_mm"] = float(
                (df.loc[nv.index, "naive_diameter_mm"] - df.loc[nv.index, "reference_diameter_mm"])
                .abs().mean())
    return df, summ


def axes_table(cal: dict, truth: dict | None) -> pd.DataFrame:
    """The turntable axis of each stored pose function, with its true error when known."""
    from .turntable import Axis, axis_distance_mm, model_from_dict

    rows = []
    T = np.array([r["T_mm"] for r in cal.get("samples", [])], dtype=float).reshape(-1, 3)
    near = T.mean(0) if len(T) else np.zeros(3)
    taxis = None
    if truth is not None and truth.get("axis"):
        taxis = Axis.from_point_direction(truth["axis"]["point_mm"], truth["axis"]["direction"])
    for key in ("model", "model_paper", "model_rigid", "model_joint"):
        d = cal.get(key)
        if not isinstance(d, dict):
            continue
        try:
            m = model_from_dict(d)
        except (KeyError, TypeError, ValueError):
            continue
        kind = d.get("type", cal.get("method") if key == "model" else key.split("_", 1)[1])
        if any(r["model"] == kind for r in rows):
            continue
        ax = Axis.from_point_direction(m.axis.point, m.axis.direction)
        row = {"model": kind, "point_mm": ax.point, "direction": ax.direction,
               "direction_err_deg": np.nan, "distance_err_mm": np.nan}
        if taxis is not None:
            a = math.degrees(math.acos(min(1.0, abs(float(ax.direction @ taxis.direction)))))
            row["direction_err_deg"] = a
            row["distance_err_mm"] = axis_distance_mm(ax, taxis, near)
        rows.append(row)
    if taxis is not None:
        rows.append({"model": "truth", "point_mm": taxis.point, "direction": taxis.direction,
                     "direction_err_deg": np.nan, "distance_err_mm": np.nan})
    return pd.DataFrame(rows)


# ---------------------------------------------------------------- typst helpers


def esc(s: object) -> str:
    """Plain text as a typst string expression (no markup), breakable after / _ - ."""
    t = str(s).replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ")
    for ch in "/_-.,":
        t = t.replace(ch, ch + "\u200b")
    return '#"' + t + '"'


def fnum(x: object, nd: int = 3, sign: bool = False) -> str:
    """A number for a table cell ("--" for missing)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "--"
    if not math.isfinite(v):
        return "--"
    s = f"{v:+.{nd}f}" if sign else f"{v:.{nd}f}"
    return s.replace("-", "\u2212")


def vec(v, nd: int = 3) -> str:
    return "(" + ", ".join(fnum(x, nd) for x in np.asarray(v, dtype=float).ravel()) + ")"


def typst_table(header: list[str], rows: list[list[str]], align: str | list[str] | None = None,
                size: str = "8pt", columns: str | None = None, header_rows: list[str] | None = None,
                hlines: tuple[int, ...] = ()) -> str:
    """A typst table; cells are typst markup. Long tables break across pages with the header
    repeated. ``hlines``: body row numbers before which a thicker rule is drawn."""
    n = len(header)
    if align is None:
        align = ["left"] + ["right"] * (n - 1)
    elif isinstance(align, str):
        align = [align] * n
    cols = columns or f"({', '.join(['auto'] * n)})"
    parts = [f"#small(size: {size})[#table(columns: {cols}, align: ({', '.join(align)},),"]
    hdr = ""
    if header_rows:
        hdr += ", ".join(header_rows) + ", "
    hdr += ", ".join(f"[{h}]" for h in header)
    parts.append(f"  table.header({hdr}),")
    for k, r in enumerate(rows):
        if k in hlines:
            parts.append("  table.hline(stroke: 0.9pt),")
        if len(r) != n:
            r = list(r) + [""] * (n - len(r))
        parts.append("  " + ", ".join(f"[{c}]" for c in r) + ",")
    parts.append(")]")
    return "\n".join(parts) + "\n"


def _template() -> str:
    return resources.files("lidarcal").joinpath("report_template.typ").read_text()


# ---------------------------------------------------------------- figures


class _Figures:
    """Saves figures as PNG in ``folder``; a failing figure becomes a note, not a crash."""

    def __init__(self, folder: Path, notes: list[str], enabled: bool = True):
        self.folder = folder
        self.notes = notes
        self.count = 0
        self.enabled = enabled

    def __call__(self, name: str, make: Callable[[], object], caption: str,
                 width: str = "100%") -> str:
        if not self.enabled:
            return ""
        try:
            fig = make()
        except Exception as e:  # noqa: BLE001  (a figure must never stop the report)
            msg = f"figure '{name}' not drawn: {type(e).__name__}: {e}"
            self.notes.append(msg)
            if os.environ.get("LIDARCAL_DEBUG"):
                traceback.print_exc()
            return f"#notebox[{esc(msg)}]\n"
        if fig is None:
            return ""
        self.count += 1
        fname = f"fig_{self.count:02d}_{name}.png"
        fig.savefig(self.folder / fname, dpi=FIG_DPI)
        return (f'#figure(image("{fname}", width: {width}), caption: [{esc(caption)}])\n')


def _camera_from_cal(cal: dict, ds: Dataset) -> CameraModel:
    c = cal["camera"]
    size = tuple(c.get("image_size") or ds.image_size)
    return CameraModel(np.asarray(c["K"], float), np.asarray(c["dist"], float), size,
                       c.get("source", "dataset.json"), c.get("rms_px"))


def _representative(ds: Dataset, cal: dict):
    """The position shown in the section-1 figures: the middle used position."""
    used = sorted(int(r["index"]) for r in cal.get("samples", []))
    if not used:
        return None
    want = used[len(used) // 2]
    return next((p for p in ds.positions if p.index == want), None)


@dataclass
class _Detail:
    """Section-1 objects re-computed for the figures (None when unavailable)."""

    boards: tuple | None = None
    board_image: np.ndarray | None = None
    position: object | None = None  # dataset Position
    stripe_image: np.ndarray | None = None
    solved: object | None = None  # pipeline.PositionResult
    scan: tuple | None = None  # (angle_deg, range_mm)
    intrinsics: object | None = None


def _detail(inp: ReportInputs) -> _Detail:
    from . import pipeline
    from .dataset import read_image, read_scan, read_stripe_image

    ds, cal, res = inp.dataset, inp.cal, inp.result
    det = _Detail()
    camera = res.camera if res is not None else _camera_from_cal(cal, ds)
    try:
        det.board_image = read_image(ds.board_image, camera.image_size)
        det.boards = res.boards if res is not None else pipeline.find_boards(ds, camera)
    except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
        inp.notes.append(f"board detection for the figures failed: {e}")
        return det
    pos = _representative(ds, cal)
    det.position = pos
    if pos is None:
        return det
    try:
        det.stripe_image = read_stripe_image(pos.stripe_image, camera.image_size)
        det.scan = read_scan(pos.scan, ds.lidar)
        found = [p for p in (res.positions if res is not None else []) if p.index == pos.index]
        det.solved = found[0] if found else _resolve_position(pos, camera, det.boards, ds, cal)
    except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
        inp.notes.append(f"position {pos.index} could not be re-solved for the figures: {e}")
    if cal["camera"].get("source") == "intrinsics":
        if res is not None and res.intrinsics is not None:
            det.intrinsics = res.intrinsics
        else:
            try:
                from .camera import calibrate_intrinsics

                det.intrinsics = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board,
                                                      ds.image_size)
            except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
                inp.notes.append(f"intrinsics could not be re-run for the figure: {e}")
    return det


def _resolve_position(pos, camera: CameraModel, boards, ds: Dataset, cal: dict):
    """Section 1 again at one position, with the pipeline's own per-position step.

    Follows the pipeline's signature: newer versions take the dataset's stripe
    reflectance ratio ``rho`` (read from calibration.json when stored there,
    else re-estimated from the dataset as the pipeline does).
    """
    import inspect

    from . import pipeline

    params = list(inspect.signature(pipeline._solve_position).parameters)
    if len(params) >= 5 and params[4] == "rho":
        rho = cal.get("reflectance_ratio", (cal.get("stripe") or {}).get("reflectance_ratio"))
        if rho is None and hasattr(pipeline, "dataset_reflectance_ratio"):
            used = {int(r["index"]) for r in cal.get("samples", [])}
            rho = pipeline.dataset_reflectance_ratio(
                camera, boards, [p for p in ds.positions if p.index in used])
        return pipeline._solve_position(pos, camera, boards, ds.lidar, rho)
    return pipeline._solve_position(pos, camera, boards, ds.lidar, camera.image_size)


def _reprojection_errors(intr) -> tuple[list[np.ndarray], list[str]]:
    import cv2

    cam = intr.camera
    errs, labels = [], []
    for k, (ip, op) in enumerate(zip(intr.image_points, intr.object_points)):
        if k >= len(intr.rvecs):
            break
        proj, _ = cv2.projectPoints(np.asarray(op, float), np.asarray(intr.rvecs[k], float),
                                    np.asarray(intr.tvecs[k], float), cam.K, cam.dist)
        errs.append(proj.reshape(-1, 2) - np.asarray(ip, float).reshape(-1, 2))
        labels.append(Path(intr.files_used[k]).name if k < len(intr.files_used) else f"view {k}")
    return errs, labels


# ---------------------------------------------------------------- the document


def _summary_section(inp: ReportInputs, t1: pd.DataFrame, t2sum: dict, cmp: dict) -> str:
    ds, cal = inp.dataset, inp.cal
    cam = cal["camera"]
    K = np.asarray(cam["K"], float)
    lid = ds.lidar
    psi = np.array([p.psi_deg for p in ds.positions])
    used = len(cal.get("samples", []))
    steps = np.diff(np.sort(psi))
    out = ["= Summary <no-break>\n"]
    rig = [
        ("Camera", (f"{cam.get('image_size', list(ds.image_size))[0]} x "
                   f"{cam.get('image_size', list(ds.image_size))[1]} px; fx {fnum(K[0, 0], 1)}, "
                   f"fy {fnum(K[1, 1], 1)}, cx {fnum(K[0, 2], 1)}, cy {fnum(K[1, 2], 1)} px; "
                   f"dist {vec(cam['dist'], 4)}; from {esc(cam.get('source', '?'))}")),
        ("V-board", (f"two chessboards of {ds.v_board.inner_corners[0]} x "
                    f"{ds.v_board.inner_corners[1]} inner corners, {fnum(ds.v_board.square_mm, 1)} mm "
                    "squares")),
        ("LiDAR", (f"beams {fnum(lid.angle_min_deg, 2)} to {fnum(lid.angle_max_deg, 2)} deg, step "
                  f"{fnum(lid.angle_step_deg, 4)} deg ({lid.n_beams} beams); range "
                  f"{fnum(lid.range_min_mm, 0)} to {fnum(lid.range_max_mm, 0)} mm; z-axis hint "
                  f"{vec(lid.z_axis_hint, 2)}")),
        ("Turntable", f"{len(ds.positions)} positions, psi {fnum(psi.min(), 3)} to "
                      f"{fnum(psi.max(), 3)} deg"
                      + (f", step {fnum(np.median(steps), 3)} deg" if len(steps) else "")
                      + f"; {used} used, {len(cal.get('skipped', []))} skipped"),
        ("Measurements", f"{len(ds.measurements)} sweep(s) listed in dataset.json"),
        ("Ground truth", "truth.json present (synthetic dataset)" if inp.truth is not None
         else "none (real data: only self-consistency can be shown)"),
    ]
    out.append("== Rig\n#kv(" + ", ".join(f"([{k}], [{v}])" for k, v in rig) + ")\n")
    method = cal.get("method", "?")
    ax = cal.get("axis", {})
    key = [("Pose function", f"{esc(method)} (fills 'poses' in calibration.json)"),
           ("Turntable axis", (f"direction {vec(ax.get('direction', [np.nan] * 3), 5)} through "
                              f"{vec(ax.get('point_mm', [np.nan] * 3), 2)} mm"))]
    lab = f"{method} function vs samples"
    if lab in t1.index:
        r = t1.loc[lab]
        key.append(("Function vs samples (paper's metric)",
                    (f"centre {fnum(r['centre_mm_mean'], 3)} / {fnum(r['centre_mm_max'], 3)} mm, "
                    f"z axis {fnum(r['z_axis_deg_mean'], 4)} / {fnum(r['z_axis_deg_max'], 4)} deg, "
                    f"x axis {fnum(r['x_axis_deg_mean'], 4)} / {fnum(r['x_axis_deg_max'], 4)} deg "
                    "(mean / max; paper: 1.12 / 2.72 mm, 0.203 / 0.455 deg, 0.662 / 1.580 deg)")))
    lab = f"{method} function vs truth"
    if lab in t1.index:
        r = t1.loc[lab]
        key.append(("Function vs truth",
                    (f"centre {fnum(r['centre_mm_mean'], 3)} / {fnum(r['centre_mm_max'], 3)} mm, "
                    f"z axis {fnum(r['z_axis_deg_mean'], 4)} / {fnum(r['z_axis_deg_max'], 4)} deg, "
                    f"x axis {fnum(r['x_axis_deg_mean'], 4)} / {fnum(r['x_axis_deg_max'], 4)} deg")))
    unc = uncertainty_summary(cal, inp.truth)
    if unc:
        key.append(("Uncertainty (joint fit, 1-sigma)", unc))
    if t2sum.get("trials"):
        s = (f"{t2sum['trials']} trials, mean diameter {fnum(t2sum.get('mean_diameter_mm'), 2)} mm")
        if "mean_abs_error_mm" in t2sum:
            s += (f", mean error {fnum(t2sum['mean_error_mm'], 2, sign=True)} mm, mean |error| "
                  f"{fnum(t2sum['mean_abs_error_mm'], 2)} mm")
        s += " (paper: 138.49 mm, mean |error| 2.77 mm)"
        key.append(("Disc diameters (Table 2)", s))
    out.append("== Key results\n#notebox[#kv(" + ", ".join(f"([{k}], [{v}])" for k, v in key)
               + ")]\n")
    warns = list(cal.get("warnings", [])) + list(inp.notes)
    if cal.get("skipped"):
        warns.append(f"{len(cal['skipped'])} position(s) skipped (see 'Skipped positions')")
    out.append("== Warnings\n")
    if warns:
        out.append("#warnbox[" + "\n".join(f"- {esc(w)}" for w in warns) + "]\n")
    else:
        out.append("None.\n")
    return "\n".join(out)


def _provenance_section(inp: ReportInputs) -> str:
    from .pipeline import dataset_hash

    cal = inp.cal
    prov = cal.get("provenance", {}) or {}
    try:
        now_hash = dataset_hash(inp.dataset)
    except Exception as e:  # noqa: BLE001  (unreadable file: say so, keep going)
        now_hash = f"not computed ({e})"
    stored = prov.get("dataset_sha256")
    rows = [("Dataset", esc(inp.dataset.root)),
            ("Calibrated from", esc(cal.get("dataset", "?"))),
            ("Dataset SHA-256 (calibration.json)", f"`{stored}`" if stored else "not recorded"),
            ("Dataset SHA-256 (now)", f"`{now_hash}`"),
            ("Calibration made by", f"lidarcal {esc(prov.get('lidarcal_version', '?'))}; command "
                                    + (f"`{prov['command']}`" if prov.get("command") else "not recorded")),
            ("calibration.json", esc(inp.calibration_path) if inp.result is None
             else "computed for this report"),
            ("measurements.json", esc(inp.measurements_path) if inp.measurements_path
             and inp.result is None else ("computed for this report" if inp.meas else "none")),
            ("Report made by", f"lidarcal {esc(__version__)}, {esc(inp.created)}"),
            ("Report command", f"`{inp.command}`" if inp.command else "Python API")]
    out = ["== Provenance\n#kv(" + ", ".join(f"([{k}], [{v}])" for k, v in rows) + ")\n"]
    if stored and stored != now_hash:
        msg = "the dataset has changed since it was calibrated (SHA-256 differs)"
        inp.notes.append(msg)
        out.append(f"#warnbox[{esc(msg)}]\n")
    return "\n".join(out)


def _intrinsics_section(inp: ReportInputs, det: _Detail, fig: _Figures) -> str:
    cam = inp.cal["camera"]
    K = np.asarray(cam["K"], float)
    out = ["= Camera intrinsics\n"]
    src = cam.get("source", "?")
    out.append(f"Source: *{esc(src)}*"
               + (" (calibrated from the chessboard views in intrinsics/)" if src == "intrinsics"
                  else " (the rig's stored calibration; the pipeline did not re-estimate it)")
               + (f"; RMS reprojection error {fnum(cam['rms_px'], 4)} px." if cam.get("rms_px")
                  is not None else ".") + "\n")
    rows = [["K"] + [vec(K[i], 2) for i in range(3)]]
    out.append(typst_table(["", "row 1", "row 2", "row 3"], rows, size="8.5pt"))
    d = np.asarray(cam["dist"], float)
    names = ["k1", "k2", "p1", "p2", "k3"][: len(d)]
    out.append(typst_table(names, [[fnum(v, 5) for v in d]], align="right", size="8.5pt"))
    if inp.truth is not None and inp.truth.get("camera"):
        tc = inp.truth["camera"]
        tK = np.asarray(tc["K"], float)
        out.append(f"Truth: fx {fnum(tK[0, 0], 2)}, fy {fnum(tK[1, 1], 2)}, cx {fnum(tK[0, 2], 2)}, "
                   f"cy {fnum(tK[1, 2], 2)} px; dist {vec(tc.get('dist', []), 5)}.\n")
    if det.intrinsics is not None:
        intr = det.intrinsics
        out.append(f"Views used: {len(intr.files_used)}; rejected: {len(intr.files_rejected)}"
                   + (" (" + ", ".join(esc(Path(p).name) for p in intr.files_rejected) + ")"
                      if intr.files_rejected else "") + ".\n")
        out.append(fig("reprojection", lambda: _plot_reprojection(intr),
                       "Per-corner reprojection errors of the intrinsic calibration, one colour per "
                       "view.", width="60%"))
    return "\n".join(out)


def _plot_reprojection(intr):
    from .plots import plot_reprojection_errors

    errs, labels = _reprojection_errors(intr)
    if not errs:
        raise ValueError("no per-view poses stored with the intrinsics result")
    return plot_reprojection_errors(errs, labels)


def _section1(inp: ReportInputs, det: _Detail, fig: _Figures) -> str:
    from . import plots

    cal = inp.cal
    out = ["= Section 1: the LiDAR pose at one position\n"]
    # board planes
    out.append("== 1.2 Board planes, eqs. (1)-(3)\n")
    rows = []
    tb = (inp.truth or {}).get("boards", [])
    has_pnp = any(isinstance(b.get("pnp"), dict) for b in cal.get("boards", []))
    for i, b in enumerate(cal.get("boards", [])):
        n = b.get("normal")
        dmm = b.get("d_mm", b.get("d"))
        rms = b.get("reprojection_rms_px")
        rms_s = (" / ".join(fnum(v, 3) for v in rms) if isinstance(rms, (list, tuple))
                 else fnum(rms, 3))
        row = [f"{i + 1}", vec(n, 5), fnum(dmm, 2), rms_s]
        if has_pnp:
            pnp = b.get("pnp") or {}
            if pnp.get("normal") is not None:
                pn = pnp["normal"]
                row += [fnum(pnp.get("reprojection_rms_px"), 3),
                        fnum(_angle_deg(n, pn), 4),
                        fnum(abs(float(dmm) - float(pnp.get("d_mm", pnp.get("d")))), 3)]
            else:
                row += ["--"] * 3
        if tb:
            # boards are unordered: compare with the closest true plane
            errs = []
            for t in tb:
                sgn = 1.0 if np.dot(n, t["normal"]) >= 0 else -1.0
                errs.append((_angle_deg(n, t["normal"]), abs(float(dmm) - sgn * float(t["d_mm"]))))
            a, dd = min(errs)
            row += [fnum(a, 4), fnum(dd, 3)]
        rows.append(row)
    hdr = ["board", "normal", "d (mm)", "reproj. RMS (px)"]
    hrow = ["table.cell(align: center, colspan: 4)[homography pose, eq. (2)]"]
    if has_pnp:
        hdr += ["reproj. RMS (px)", "normal diff. (deg)", "d diff. (mm)"]
        hrow.append("table.cell(align: center, colspan: 3)[solvePnP (refined)]")
    if tb:
        hdr += ["normal (deg)", "d (mm)"]
        hrow.append("table.cell(align: center, colspan: 2)[error vs truth]")
    if rows:
        out.append(typst_table(hdr, rows, size="8pt", header_rows=hrow))
        out.append("Plane: normal . X = d in the camera frame (eq. 3). The homography plane is the "
                   "one the pipeline uses; the solvePnP columns compare the refined pose's plane "
                   "with it.\n")
    if det.boards is not None and det.board_image is not None:
        out.append(fig("corners", lambda: plots.plot_corners(
            det.board_image, [b.corners_px for b in det.boards],
            [getattr(b, "outline_px", None) for b in det.boards]),
            "board.png with the detected inner corners of both chessboards (first corner ringed) "
            "and the mask outlines used for the stripes.", width="85%"))
    # per-position fit quality, from the samples table
    out.append("== 1.3-1.5 Stripes, scan lines and single-shot poses\n")
    sol = det.solved
    if sol is not None:
        pos = det.position
        cl, seg, ll = sol.camera_lines, sol.segments, sol.lidar_lines
        srow = next((r for r in cal.get("samples", []) if int(r["index"]) == pos.index), {})
        facts = [("Position shown", f"index {pos.index}, psi {fnum(pos.psi_deg, 3)} deg"),
                 ("Laser plane fit (TLS, eq. 4)",
                  (f"RMS {fnum(getattr(cl, 'residual_rms_mm', np.nan), 4)} mm over "
                  f"{sum(len(c) for c in getattr(cl, 'centres_px', ()))} stripe centres; alpha "
                  f"{fnum(math.degrees(cl.alpha), 4)} deg")),
                 ("Scan lines (eqs. 7-12)",
                  (f"{getattr(ll, 'n1', '?')} + {getattr(ll, 'n2', '?')} points, RMS "
                  f"{fnum(getattr(ll, 'residual_rms_mm', np.nan), 4)} mm, fit "
                  f"{esc(getattr(ll, 'method', '?'))}; range noise "
                  f"{fnum(getattr(seg, 'noise_mm', np.nan), 3)} mm")),
                 ("Pose (eqs. 13-14)", (f"T {vec(srow.get('T_mm', sol.pose.T), 2)} mm; distance of "
                                        "the raw eq. (13) product from SO(3) "
                                        f"{fnum(srow.get('rotation_residual', sol.pose.residual), 6)}"
                                        " (from calibration.json)"))]
        out.append("#kv(" + ", ".join(f"([{k}], [{v}])" for k, v in facts) + ")\n")
        if det.stripe_image is not None:
            out.append(fig("stripes", lambda: plots.plot_stripe_centres(
                det.stripe_image, list(cl.centres_px),
                [getattr(b, "outline_px", None) for b in det.boards]),
                f"Stripe image of position {pos.index} (contrast stretched) with the sub-pixel "
                "stripe centres of each board.", width="85%"))
        out.append(fig("scan", lambda: _plot_scan(det),
                       f"Scan of position {pos.index} in the LiDAR frame: the two board segments, "
                       "the returns rejected from them, the constrained lines L1, L2 and their "
                       "vertex E.", width="100%"))
        out.append(fig("frames", lambda: _plot_frames(inp, det),
                       "Camera frame, LiDAR frames (five positions), the two boards and the scan of "
                       "the position shown mapped by its single-shot pose.", width="70%"))
    out.append(_samples_table(cal))
    return "\n".join(out)


def _angle_deg(a, b) -> float:
    """Angle between two plane normals as lines (sign ignored), deg."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, c)))


def _plot_scan(det: _Detail):
    from .plots import plot_scan_split
    from .scan import scan_points

    ang, rng = det.scan
    pts = np.asarray(scan_points(ang, rng))
    seg, ll = det.solved.segments, det.solved.lidar_lines
    n = len(pts)

    def mask(idx):
        m = np.zeros(n, bool)
        if idx is not None and len(idx):
            idx = np.asarray(idx)
            if idx.dtype == bool:
                return idx[:n]
            m[idx.astype(int)] = True
        return m

    i1 = getattr(seg, "index1", getattr(seg, "first", None))
    i2 = getattr(seg, "index2", getattr(seg, "second", None))
    rej = mask(getattr(seg, "rejected1", None)) | mask(getattr(seg, "rejected2", None))
    lines = []
    E = np.asarray(ll.E, float)
    for l in (ll.l1, ll.l2):
        lines.append((E, np.asarray(l, float)))
    return plot_scan_split(pts, mask(i1), mask(i2), lines, E, rej)


def _plot_frames(inp: ReportInputs, det: _Detail):
    from .plots import plot_frames_3d
    from .scan import scan_points

    samples = [Pose.from_dict(r) for r in inp.cal.get("samples", [])]
    pick = samples[:: max(1, len(samples) // 4)][:5]
    corners = []
    obj = inp.dataset.v_board.object_points()
    for b in det.boards:
        corners.append(obj @ np.asarray(b.R, float).T + np.asarray(b.T, float))
    scan = None
    if det.scan is not None and det.solved is not None:
        pts = np.asarray(scan_points(*det.scan), float)
        if pts.shape[1] == 2:
            pts = np.column_stack([pts, np.zeros(len(pts))])
        seg = det.solved.segments
        keep = [np.asarray(getattr(seg, k), int) for k in ("index1", "index2")
                if getattr(seg, k, None) is not None]
        if keep:  # the board segments only: background returns would dwarf the rig
            pts = pts[np.concatenate(keep)]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        scan = det.solved.pose.apply(pts)
    ax = inp.cal.get("axis")
    axis = (ax["point_mm"], ax["direction"]) if ax else None
    return plot_frames_3d(pick, corners, scan, axis)


def _samples_table(cal: dict) -> str:
    """Per-position single-shot poses (compact) and any extra per-sample numbers."""
    rows = []
    samples = cal.get("samples", [])
    base = {"index", "psi_deg", "R", "T_mm"}
    extra = [k for k in (samples[0].keys() if samples else [])
             if k not in base and isinstance(samples[0][k], (int, float))]
    for r in samples:
        R = np.asarray(r["R"], float)
        row = [str(r["index"]), fnum(r["psi_deg"], 3), *[fnum(v, 2) for v in r["T_mm"]],
               *[fnum(v, 4) for v in R[:, 2]], *[fnum(v, 4) for v in R[:, 0]]]
        for k in extra:
            v = r.get(k)
            row.append(fnum(v, 4 if abs(float(v or 0)) >= 1e-3 or not v else 7)
                       if not isinstance(v, float) or abs(v) >= 1e-4 else f"{v:.1e}")
        rows.append(row)
    hdr = ["idx", "psi (deg)", "Tx", "Ty", "Tz", "z_x", "z_y", "z_z", "x_x", "x_y", "x_z"]
    hdr += [esc(k) for k in extra]
    hrow = ["table.cell(align: center, colspan: 2)[position]", "table.cell(align: center, colspan: 3)[centre T (mm)]",
            "table.cell(align: center, colspan: 3)[z axis (camera frame)]",
            "table.cell(align: center, colspan: 3)[x axis (camera frame)]"]
    if extra:
        hrow.append(f"table.cell(align: center, colspan: {len(extra)})[fit quality]")
    size = "7pt" if len(hdr) <= 13 else "6pt"
    out = ["=== Single-shot samples (section 1, one row per used position)\n",
           typst_table(hdr, rows, size=size, header_rows=hrow)]
    return "\n".join(out)


def _section2(inp: ReportInputs, fig: _Figures, t1: pd.DataFrame, cmp: dict) -> str:
    from . import plots

    cal = inp.cal
    out = ["= Section 2: the pose as a function of the turntable angle\n",
           "== 2.2 Turntable axis, eqs. (15)-(18)\n"]
    try:
        ax = axes_table(cal, inp.truth)
    except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
        inp.notes.append(f"axis table: {e}")
        ax = pd.DataFrame()
    if len(ax):
        rows = []
        for _, r in ax.iterrows():
            rows.append([esc(r["model"]), vec(r["direction"], 6), vec(r["point_mm"], 2),
                         fnum(r["direction_err_deg"], 4), fnum(r["distance_err_mm"], 3)])
        out.append(typst_table(["pose function", "direction", "point (mm, foot from camera origin)",
                                "dir. err. (deg)", "dist. err. (mm)"], rows, size="8pt"))
        out.append("'paper': the paper's chain (circle fits, eqs. 15-27); 'rigid': one rigid "
                   "motion about the axis fitted to all samples with the known turntable angles; "
                   "'joint': the same rigid motion fitted to every scan point and stripe centre "
                   "at once (beyond the paper). Errors against truth.json (distance between the lines near the LiDAR) when "
                   "present.\n")
    out.append("== 2.3-2.5 Pose function and Table 1\n")
    out.append(fig("trajectories", lambda: _plot_traj(inp),
                   "Fig. 4 of the paper reproduced: trajectories of the LiDAR centre and of the z- "
                   "and x-axis tips (100 mm) as the turntable turns; dots are the single-shot "
                   "samples, lines the pose function.", width="100%"))
    # Table 1
    hdr = ["comparison", "mean", "max", "mean", "max", "mean", "max"]
    hrow = ["[]", "table.cell(align: center, colspan: 2)[LiDAR centre (mm)]", "table.cell(align: center, colspan: 2)[z axis (deg)]",
            "table.cell(align: center, colspan: 2)[x axis (deg)]"]
    rows = []
    for label, r in t1.iterrows():
        row = [esc(label)]
        for c in COMPARISON_COLUMNS:
            nd = DECIMALS[c] if label != "paper (published)" else (2 if c == "centre_mm" else 3)
            row += [fnum(r[f"{c}_mean"], nd), fnum(r[f"{c}_max"], nd)]
        rows.append(row)
    hl = tuple(i for i, lab in enumerate(t1.index) if "truth" in lab)[:1]
    out.append("=== Table 1: fitted pose function against the samples and the truth\n")
    out.append(typst_table(hdr, rows, size="8.5pt", header_rows=hrow, hlines=(1,) + hl))
    out.append("'vs samples' is the paper's metric (the function against the very samples it was "
               f"fitted to, {len(cal.get('samples', []))} positions here, 87 in the paper); "
               "'vs truth' is the true error, only a simulator can give it.\n")
    if cmp:
        series = {k: v for k, v in cmp.items()}
        psi = next(iter(cmp.values()))["psi_deg"].to_numpy()
        out.append(fig("residuals", lambda: plots.plot_pose_residuals(psi, series),
                       "Per-position differences of Table 1.", width="95%"))
        out.append(fig("histograms", lambda: plots.plot_residual_histograms(series),
                       "Histograms of the per-position differences.", width="100%"))
    return "\n".join(out)


def _plot_traj(inp: ReportInputs):
    from .plots import plot_trajectories
    from .turntable import model_from_dict

    cal = inp.cal
    rows = cal.get("samples", [])
    psi = np.array([r["psi_deg"] for r in rows], float)
    samples = [Pose.from_dict(r) for r in rows]
    model = model_from_dict(cal["model"])
    grid = np.linspace(psi.min(), psi.max(), 200)
    curve = model.pose(grid)
    truth = None
    if inp.truth is not None and inp.truth.get("poses"):
        tp = _poses(inp.truth["poses"])
        truth = [tp[int(r["index"])] for r in rows if int(r["index"]) in tp]
    ax = cal["axis"]
    return plot_trajectories(psi, samples, curve=curve, axis=(ax["point_mm"], ax["direction"]),
                             truth=truth)


def _section3(inp: ReportInputs, fig: _Figures, t2: pd.DataFrame, t2sum: dict) -> str:
    from . import plots

    out = ["= Section 3.2: measuring the disc (Table 2)\n"]
    if inp.meas is None:
        out.append("No measurements.json: the dataset lists no measurement sweeps, or none was "
                   "given (`lidarcal measure`).\n")
        return "\n".join(out)
    has_truth = t2["truth_diameter_mm"].notna().any()
    hdr = ["trial", "diameter", "|error|", "name", "reference", "diameter", "error"]
    hrow = ["table.cell(align: center, colspan: 3)[paper (mm)]", "table.cell(align: center, colspan: 4)[this dataset (mm)]"]
    if has_truth:
        hdr.append("true diam.")
        hrow[-1] = "table.cell(align: center, colspan: 5)[this dataset (mm)]"
    if t2["naive_diameter_mm"].notna().any():
        hdr.append("naive diam.")
        hrow[-1] = f"table.cell(align: center, colspan: {len(hdr) - 3})[this dataset (mm)]"
    n = max(len(PAPER_TABLE2), len(t2))
    rows = []
    for i in range(n):
        row = ([str(PAPER_TABLE2[i][0]), fnum(PAPER_TABLE2[i][1], 2), fnum(PAPER_TABLE2[i][2], 2)]
               if i < len(PAPER_TABLE2) else ["", "", ""])
        if i < len(t2):
            r = t2.iloc[i]
            row += [esc(r["name"]), fnum(r["reference_diameter_mm"], 2),
                    fnum(r["diameter_mm"], DECIMALS["diameter_mm"]),
                    fnum(r["error_mm"], DECIMALS["error_mm"], sign=True)]
            if has_truth:
                row.append(fnum(r["truth_diameter_mm"], 2))
            if "naive diam." in hdr:
                row.append(fnum(r["naive_diameter_mm"], 2))
        rows.append(row + [""] * (len(hdr) - len(row)))
    mrow = ["mean", fnum(PAPER_TABLE2_MEAN[0], 2), fnum(PAPER_TABLE2_MEAN[1], 2), "",
            "", fnum(t2sum.get("mean_diameter_mm"), 2), fnum(t2sum.get("mean_error_mm"), 2, True)]
    arow = ["", "", "", "mean |error|", "", "", fnum(t2sum.get("mean_abs_error_mm"), 2)]
    rows += [mrow + [""] * (len(hdr) - len(mrow)), arow + [""] * (len(hdr) - len(arow))]
    out.append(typst_table(hdr, rows, size="8.5pt", header_rows=hrow, hlines=(n,)))
    notes = [(f"Reference diameter {fnum(PAPER_REFERENCE_MM, 1)} mm in the paper; error = measured "
             "- reference (the paper lists |error|).")]
    if "mean_abs_error_truth_mm" in t2sum:
        notes.append(f"Mean |measured - true diameter|: {fnum(t2sum['mean_abs_error_truth_mm'], 2)} mm.")
    if "naive_mean_abs_error_mm" in t2sum:
        notes.append("'naive diam.' is the circle through the outermost hits only (the biased-small "
                     f"estimate): mean |error| {fnum(t2sum['naive_mean_abs_error_mm'], 2)} mm.")
    out.append(" ".join(notes) + "\n")
    if len(t2):
        out.append(fig("table2", lambda: plots.plot_table2(
            t2["diameter_mm"].to_numpy(), t2["reference_diameter_mm"].to_numpy(),
            list(t2["name"]), np.array([r[1] for r in PAPER_TABLE2])),
            "Measured minus reference diameter per trial, beside the paper's.", width="75%"))
        out.append(fig("disc", lambda: _plot_disc(inp),
                       "The first trial's point cloud (eq. 28): disc points, rejected rim returns "
                       "and the fitted circle; right: the disc plane face on.", width="100%"))
    return "\n".join(out)


def _plot_disc(inp: ReportInputs):
    from .api import load_calibration
    from .dataset import read_sweep
    from .measure import measure_disc
    from .plots import plot_disc_cloud

    ds = inp.dataset
    m = ds.measurements[0]
    cal = load_calibration(inp.calibration_path)
    sweep = read_sweep(m.sweep, ds.lidar)
    r = measure_disc(sweep, cal, ds.lidar)
    pts = getattr(r, "cloud", None)
    if pts is None or np.ndim(pts) != 2:
        ok = np.isfinite(sweep["range_mm"].to_numpy())
        pts = cal.points(sweep["psi_deg"].to_numpy()[ok], sweep["angle_deg"].to_numpy()[ok],
                         sweep["range_mm"].to_numpy()[ok])
    disc = getattr(r, "disc_mask", None)
    rim = getattr(r, "rim_mask", None)
    cross = getattr(r, "crossings", None)
    inl = getattr(r, "crossing_inlier", None)
    if cross is not None and inl is not None and len(inl) == len(cross):
        cross = np.asarray(cross)[np.asarray(inl, bool)]

    class _C:
        centre = np.asarray(r.center_mm, float)
        normal = np.asarray(r.normal, float)
        radius = float(r.diameter_mm) / 2

    bounds = None
    if getattr(r, "boundary_inside", None) is not None and getattr(r, "boundary_outside", None) is not None:
        bounds = (r.boundary_inside, r.boundary_outside)
    return plot_disc_cloud(pts, disc, rim, _C, m.reference_diameter_mm, rim_estimates=cross,
                           rim_bounds=bounds,
                           title=f"Disc point cloud, {m.name} (section 3.2)")


def _skipped_section(inp: ReportInputs) -> str:
    cal = inp.cal
    out = ["= Skipped positions and warnings\n", "== Skipped positions\n"]
    sk = cal.get("skipped", [])
    if sk:
        out.append(typst_table(["index", "reason"], [[str(s["index"]), esc(s["reason"])] for s in sk],
                               align=["right", "left"], columns="(auto, 1fr)"))
    else:
        out.append("None: every position of the dataset was used.\n")
    out.append("== Warnings from the calibration\n")
    w = cal.get("warnings", [])
    out.append("\n".join(f"- {esc(x)}" for x in w) + "\n" if w else "None.\n")
    out.append("== Notes from making this report\n")
    out.append("\n".join(f"- {esc(x)}" for x in inp.notes) + "\n" if inp.notes else "None.\n")
    return "\n".join(out)


def build_report_source(inp: ReportInputs, folder: str | os.PathLike, figures: bool = True) -> str:
    """The report's typst source; figures are written as PNG files into ``folder``.

    ``figures=False`` leaves the figures (and the re-run of section 1 they need)
    out: the tables only, fast.

    Every number in the tables is computed from ``inp.cal`` / ``inp.meas``
    (the JSON files) by :func:`table1` and :func:`table2`.
    """
    folder = Path(folder)
    fig = _Figures(folder, inp.notes, enabled=figures)
    cal = inp.cal
    cmp = comparisons(cal, inp.truth)
    t1 = table1(cal, inp.truth)
    t2, t2sum = table2(inp.meas, inp.truth)
    det = _detail(inp) if figures else _Detail()
    import matplotlib

    matplotlib.use("Agg", force=False)
    body = [
        _intrinsics_section(inp, det, fig),
        _section1(inp, det, fig),
        _section2(inp, fig, t1, cmp),
        _section3(inp, fig, t2, t2sum),
    ]
    prov = _provenance_section(inp)
    tail = _skipped_section(inp)
    summary = _summary_section(inp, t1, t2sum, cmp)  # last: collects the notes
    name = inp.dataset.root.name
    title = "lidarcal calibration report"
    head = [_template(),
            (f'#show: lidarcal-doc.with(title: [{title}], subtitle: [{esc(name)}], '
            f'footer-left: [lidarcal {esc(__version__)} -- {esc(inp.created)}])\n'),
            (f"#align(center)[#text(20pt, weight: \"bold\")[{title}] \\ "
            f"#v(0.3em) #text(12pt)[dataset {esc(name)}] \\ #text(9pt)[Liu, Jiang, Jia, Qu: "
            "Pose determination of 2D LiDAR on uniaxial turntable (JEMI)]]\n"),
            summary, prov,
            "#pagebreak()\n#outline(depth: 2, indent: auto)\n"]
    return "\n".join(head + body + [tail])


def compile_typst(source_path: Path, out_pdf: Path, root: Path | None = None) -> Path:
    """Compile a .typ file to ``out_pdf`` atomically (temporary file in the same folder, rename)."""
    import typst

    out_pdf = Path(out_pdf)
    out_pdf.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{out_pdf.name}.", suffix=".tmp", dir=out_pdf.parent)
    os.close(fd)
    try:
        typst.compile(str(source_path), output=tmp, root=str(root or source_path.parent))
        os.replace(tmp, out_pdf)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return out_pdf


def write_report(dataset: str | os.PathLike | Dataset, out_pdf: str | os.PathLike,
                 calibration: str | os.PathLike | None = None,
                 measurements: str | os.PathLike | None = None,
                 command: str | None = None, keep_source: str | os.PathLike | None = None) -> Path:
    """Write the PDF calibration report of ``dataset`` to ``out_pdf``.

    With ``calibration=None`` the pipeline is run first (and the dataset's
    measurement sweeps measured); otherwise the given ``calibration.json`` (and
    ``measurements.json``, if given) are shown as they are. ``keep_source``:
    a folder to copy the typst source and figures into (for debugging).
    """
    work = Path(tempfile.mkdtemp(prefix="lidarcal_report_"))
    try:
        inp = gather_inputs(dataset, calibration, measurements, command, workdir=work / "json")
        src = build_report_source(inp, work)
        typ = work / "report.typ"
        typ.write_text(src)
        if keep_source is not None:
            shutil.copytree(work, keep_source, dirs_exist_ok=True)
        return compile_typst(typ, Path(out_pdf), root=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
