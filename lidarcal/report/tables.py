"""The report's numbers, from ``calibration.json`` / ``measurements.json`` only: the
paper's Tables 1 and 2 reproduced, the comparisons behind them, the axes and the uncertainty
summary."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from .. import paper
from ..evaluate import pose_error
from ..geometry import Pose
from .markup import fnum

# the paper's published figures, under the names the report has always used
PAPER_TABLE1 = paper.TABLE1
PAPER_TABLE2 = paper.TABLE2
PAPER_TABLE2_MEAN = paper.TABLE2_MEAN
PAPER_REFERENCE_MM = paper.REFERENCE_MM

#: Decimals used in the tables (tests format with the same precision).
DECIMALS = {"centre_mm": 3, "z_axis_deg": 4, "x_axis_deg": 4, "diameter_mm": 2, "error_mm": 2}

COMPARISON_COLUMNS = ("centre_mm", "z_axis_deg", "x_axis_deg")


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

    The columns come from :func:`lidarcal.disc.table2_columns` (name, diameter,
    its 1-sigma ``diameter_sigma_mm`` including the edge model, reference
    diameter, error, ``reference``: the trial calibrated the edge model), plus
    the naive diameter, the point count and the true diameter (truth.json).
    Older files without ``diameter_sigma_mm`` / ``reference`` give NaN / False.

    Summary keys, over the test trials only (a reference's error is fitted, not
    measured): ``trials``, ``tests``, ``references``, ``mean_diameter_mm``,
    ``mean_error_mm`` (signed), ``mean_abs_error_mm`` (the paper's "error"
    column is |error|), ``mean_abs_error_truth_mm`` when truth.json gives the
    true diameters, ``naive_mean_abs_error_mm``, ``mean_sigma_mm``, and
    ``within_2sigma`` / ``within_2sigma_of``: how many trials have
    |diameter - true| <= 2 sigma (true: truth.json, else the reference diameter).
    """
    from ..disc import table2_columns

    tdiam = {}
    if truth is not None:
        tdiam = {m.get("name"): m.get("diameter_mm") for m in truth.get("measurements", [])}
    trials = [{**m, "name": m.get("name", f"trial {k + 1}")}
              for k, m in enumerate((meas or {}).get("measurements", []))]
    cols = table2_columns({"measurements": trials})
    num = lambda v: np.nan if v is None else float(v)
    rows = []
    for k, m in enumerate(trials):
        d = float(cols["diameter_mm"][k])
        ref = num(cols["reference_diameter_mm"][k])
        err = num(cols["error_mm"][k])
        if np.isnan(err) and not np.isnan(ref):
            err = d - ref
        rows.append({"name": cols["name"][k], "diameter_mm": d,
                     "diameter_sigma_mm": num(cols["diameter_sigma_mm"][k]),
                     "reference_diameter_mm": ref, "error_mm": err,
                     "reference": bool(cols["reference"][k]),
                     "naive_diameter_mm": num(m.get("naive_diameter_mm")),
                     "points": m.get("points"),
                     "truth_diameter_mm": num(tdiam.get(m["name"]))})
    df = pd.DataFrame(rows, columns=["name", "diameter_mm", "diameter_sigma_mm",
                                     "reference_diameter_mm", "error_mm", "reference",
                                     "naive_diameter_mm", "points", "truth_diameter_mm"])
    df["reference"] = df["reference"].astype(bool)
    test = df[~df["reference"]]
    summ: dict = {"trials": len(df), "tests": len(test), "references": int(df["reference"].sum())}
    if len(test):
        summ["mean_diameter_mm"] = float(test["diameter_mm"].mean())
        e = test["error_mm"].dropna()
        if len(e):
            summ["mean_error_mm"] = float(e.mean())
            summ["mean_abs_error_mm"] = float(e.abs().mean())
        t = test.dropna(subset=["truth_diameter_mm"])
        if len(t):
            summ["mean_abs_error_truth_mm"] = float((t["diameter_mm"] - t["truth_diameter_mm"])
                                                   .abs().mean())
        nv = test.dropna(subset=["naive_diameter_mm"])
        if len(nv) and test["reference_diameter_mm"].notna().all():
            summ["naive_mean_abs_error_mm"] = float(
                (nv["naive_diameter_mm"] - nv["reference_diameter_mm"]).abs().mean())
        sig = test["diameter_sigma_mm"].dropna()
        if len(sig):
            summ["mean_sigma_mm"] = float(sig.mean())
        true = test["truth_diameter_mm"].fillna(test["reference_diameter_mm"])
        ok = true.notna() & test["diameter_sigma_mm"].notna()
        if ok.any():
            dev = (test["diameter_mm"] - true)[ok].abs()
            summ["within_2sigma"] = int((dev <= 2.0 * test["diameter_sigma_mm"][ok]).sum())
            summ["within_2sigma_of"] = int(ok.sum())
    return df, summ


def edge_model_text(meas: dict | None) -> str:
    """The edge model of measurements.json in words, as typst markup (``lidarcal.disc``: the
    detected rim lies ``k`` edge spacings outside the true rim, ``D = D_half - 2 k u s``, the edge
    spacing ``u s`` being the beam spacing times the rim stretch); ""
    for older files without ``edge_model``."""
    from .markup import esc

    em = (meas or {}).get("edge_model")
    if not isinstance(em, dict):
        return ""
    k, ks = em.get("k"), em.get("k_sigma")
    src = em.get("source", "?")
    if src == "reference":
        refs = [str(x) for x in em.get("references") or []]
        s = "s" if len(refs) != 1 else ""
        out = (f"fitted on the reference disc{s} {', '.join(esc(r) for r in refs) or '?'} "
               f"(known diameter{s})")
    elif src == "prior":
        out = f"the prior, no reference disc (rim echo type {esc(em.get('echo', '?'))})"
    else:
        out = f"source {esc(src)}"
    out += (f": the detected rim lies k = {fnum(k, 3)} \u00b1 {fnum(ks, 3)} edge spacings (1 sigma) "
            f"outside the true rim (model {esc(em.get('type', '?'))})")
    rows = (meas or {}).get("measurements", [])
    u = [float(r.get("edge_spacing_mm", r.get("beam_spacing_mm")))
         for r in rows if r.get("edge_spacing_mm", r.get("beam_spacing_mm")) is not None]
    off = [float(r["edge_offset_mm"]) for r in rows if r.get("edge_offset_mm") is not None]
    if u:
        out += (f"; edge spacing (beam spacing x rim stretch) at the discs {fnum(min(u), 2)} to "
                f"{fnum(max(u), 2)} mm")
    if off:
        out += f", rim offset {fnum(min(off), 2)} to {fnum(max(off), 2)} mm"
    mix = [float(r["mixed_share"]) for r in rows if r.get("mixed_share") is not None]
    if mix:
        out += f", median mixed share of the rim crossings {fnum(float(np.median(mix)), 2)}"
    return out


def axes_table(cal: dict, truth: dict | None) -> pd.DataFrame:
    """The turntable axis of each stored pose function, with its true error when known."""
    from ..turntable import Axis, axis_distance_mm, model_from_dict

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
