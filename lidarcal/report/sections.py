"""The report's sections as typst markup: summary, provenance, intrinsics, the paper's
sections 1, 2 and 3.2, skipped positions and warnings."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from .. import __version__
from .figures import (
    _Detail,
    _disc_trial,
    _Figures,
    _plot_disc,
    _plot_frames,
    _plot_reprojection,
    _plot_scan,
    _plot_traj,
)
from .inputs import ReportInputs
from .markup import esc, fnum, typst_table, vec
from .tables import (
    COMPARISON_COLUMNS,
    DECIMALS,
    PAPER_REFERENCE_MM,
    PAPER_TABLE2,
    PAPER_TABLE2_MEAN,
    axes_table,
    edge_model_text,
    uncertainty_summary,
)


def _summary_section(inp: ReportInputs, t1: pd.DataFrame, t2sum: dict) -> str:
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
    for against, name, tail in (
            ("samples", "Function vs samples (paper's metric)",
             " (mean / max; paper: 1.12 / 2.72 mm, 0.203 / 0.455 deg, 0.662 / 1.580 deg)"),
            ("truth", "Function vs truth", "")):
        lab = f"{method} function vs {against}"
        if lab in t1.index:
            r = t1.loc[lab]
            key.append((name, (
                f"centre {fnum(r['centre_mm_mean'], 3)} / {fnum(r['centre_mm_max'], 3)} mm, "
                f"z axis {fnum(r['z_axis_deg_mean'], 4)} / {fnum(r['z_axis_deg_max'], 4)} deg, "
                f"x axis {fnum(r['x_axis_deg_mean'], 4)} / {fnum(r['x_axis_deg_max'], 4)} deg"
                + tail)))
    unc = uncertainty_summary(cal, inp.truth)
    if unc:
        key.append(("Uncertainty (joint fit, 1-sigma)", unc))
    if t2sum.get("trials"):
        s = f"{t2sum['trials']} trials"
        if t2sum.get("references"):
            s += f" ({t2sum['references']} reference, left out of the means)"
        s += f", mean diameter {fnum(t2sum.get('mean_diameter_mm'), 2)} mm"
        if "mean_sigma_mm" in t2sum:
            s += f" (σ {fnum(t2sum['mean_sigma_mm'], 2)} mm)"
        if "mean_abs_error_mm" in t2sum:
            s += (f", mean error {fnum(t2sum['mean_error_mm'], 2, sign=True)} mm, mean |error| "
                  f"{fnum(t2sum['mean_abs_error_mm'], 2)} mm")
        if "within_2sigma" in t2sum:
            s += f", within 2 σ: {t2sum['within_2sigma']} of {t2sum['within_2sigma_of']}"
        em = (inp.meas or {}).get("edge_model")
        if isinstance(em, dict):
            s += (f"; edge model from {esc(em.get('source', '?'))}, k {fnum(em.get('k'), 3)} "
                  f"± {fnum(em.get('k_sigma'), 3)}")
        s += " (paper: 138.49 mm, mean |error| 2.77 mm)"
        key.append(("Disc diameters (Table 2)", s))
    out.append("== Key results\n#notebox[#kv(" + ", ".join(f"([{k}], [{v}])" for k, v in key)
               + ")]\n")
    warns = list(cal.get("warnings", [])) + _measurement_warnings(inp.meas) + list(inp.notes)
    if cal.get("skipped"):
        warns.append(f"{len(cal['skipped'])} position(s) skipped (see 'Skipped positions')")
    out.append("== Warnings\n")
    if warns:
        out.append("#warnbox[" + "\n".join(f"- {esc(w)}" for w in warns) + "]\n")
    else:
        out.append("None.\n")
    return "\n".join(out)


def _provenance_section(inp: ReportInputs) -> str:
    from ..pipeline import dataset_hash

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
        if intr.sigma_px is not None:
            out.append("1-sigma of the camera (the spread of the fits leaving each group of views "
                       "out): fx {}, fy {}, cx {}, cy {} px.\n".format(
                           *(fnum(v, 2) for v in intr.sigma_px)))
        out.append(fig("reprojection", lambda: _plot_reprojection(intr),
                       "Per-corner reprojection errors of the intrinsic calibration, one colour per "
                       "view.", width="60%"))
    return "\n".join(out)


def _section1(inp: ReportInputs, det: _Detail, fig: _Figures) -> str:
    from .. import plots

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
            "and the mask outlines used for the stripes.", width="75%"))
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
                "stripe centres of each board.", width="75%"))
        out.append(fig("scan", lambda: _plot_scan(det),
                       f"Scan of position {pos.index} in the LiDAR frame: the two board segments, "
                       "the returns rejected from them, the constrained lines L1, L2 and their "
                       "vertex E.", width="100%"))
        out.append(fig("frames", lambda: _plot_frames(inp, det),
                       "The rig in 3D (pyvista, camera frame): the camera's frustum, the LiDAR frame "
                       "at five positions (x red, y green, z blue), the turntable axis (purple), the "
                       "two boards, the laser fans at the first and last of them (orange) and the "
                       "scan of the position shown mapped by its single-shot pose (grey).",
                       width="75%"))
    out.append(_samples_table(cal))
    return "\n".join(out)


def _angle_deg(a, b) -> float:
    """Angle between two plane normals as lines (sign ignored), deg."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(min(1.0, c)))


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
    from .. import plots

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
    out.append(_ranging_block(cal))
    if cmp:
        series = {k: v for k, v in cmp.items()}
        psi = next(iter(cmp.values()))["psi_deg"].to_numpy()
        out.append(fig("residuals", lambda: plots.plot_pose_residuals(psi, series),
                       "Per-position differences of Table 1.", width="95%"))
        out.append(fig("histograms", lambda: plots.plot_residual_histograms(series),
                       "Histograms of the per-position differences.", width="100%"))
    return "\n".join(out)


def _ranging_block(cal: dict) -> str:
    """The LiDAR's ranging terms (zero offset, dark-square extra) with their 1-sigma, next to
    the pose function (:func:`lidarcal.ranging.ranging_text`); without a calibration.json
    ``ranging`` block (the rigid or paper method, older files) the ranges were taken as exact."""
    from ..ranging import ranging_text

    rng = cal.get("ranging")
    note = ("\nThe pose function was fitted with these terms; its 1-sigma include their "
            "uncertainty.\n" if rng else "")
    return "=== Ranging model of the LiDAR\n" + ranging_text(rng, fmt="typst") + note


def _measurement_warnings(meas: dict | None) -> list[str]:
    """measurements.json's warnings: the file's list and any per-trial lists."""
    out = [f"measurements.json: {w}" for w in (meas or {}).get("warnings", []) or []]
    for r in (meas or {}).get("measurements", []):
        out += [f"measurements.json, {r.get('name', '?')}: {w}" for w in r.get("warnings", []) or []]
    return out


def _section3(inp: ReportInputs, fig: _Figures, t2: pd.DataFrame, t2sum: dict) -> str:
    from .. import plots

    out = ["= Section 3.2: measuring the disc (Table 2)\n"]
    if inp.meas is None:
        out.append("No measurements.json: the dataset lists no measurement sweeps, or none was "
                   "given (`lidarcal measure`).\n")
        return "\n".join(out)
    has_truth = t2["truth_diameter_mm"].notna().any()
    has_sigma = t2["diameter_sigma_mm"].notna().any()
    here = ["name", "reference", "diameter"] + (["σ"] if has_sigma else []) + ["error"]
    if has_truth:
        here.append("true diam.")
    if t2["naive_diameter_mm"].notna().any():
        here.append("naive diam.")
    hdr = ["trial", "diameter", "|error|"] + here
    hrow = ["table.cell(align: center, colspan: 3)[paper (mm)]",
            f"table.cell(align: center, colspan: {len(here)})[this dataset (mm)]"]
    n = max(len(PAPER_TABLE2), len(t2))
    rows = []
    for i in range(n):
        row = ([str(PAPER_TABLE2[i][0]), fnum(PAPER_TABLE2[i][1], 2), fnum(PAPER_TABLE2[i][2], 2)]
               if i < len(PAPER_TABLE2) else ["", "", ""])
        if i < len(t2):
            r = t2.iloc[i]
            err = fnum(r["error_mm"], DECIMALS["error_mm"], sign=True)
            row += [esc(r["name"]) + (" _(ref.)_" if r["reference"] else ""),
                    fnum(r["reference_diameter_mm"], 2),
                    fnum(r["diameter_mm"], DECIMALS["diameter_mm"])]
            if has_sigma:
                row.append(fnum(r["diameter_sigma_mm"], 2))
            row.append(f"({err})" if r["reference"] and err != "--" else err)
            if has_truth:
                row.append(fnum(r["truth_diameter_mm"], 2))
            if "naive diam." in hdr:
                row.append(fnum(r["naive_diameter_mm"], 2))
        rows.append(row + [""] * (len(hdr) - len(row)))
    mean_here = ["", "", fnum(t2sum.get("mean_diameter_mm"), 2)]
    abs_here = ["mean |error|", "", ""]
    if has_sigma:
        mean_here.append(fnum(t2sum.get("mean_sigma_mm"), 2))
        abs_here.append("")
    mean_here.append(fnum(t2sum.get("mean_error_mm"), 2, True))
    abs_here.append(fnum(t2sum.get("mean_abs_error_mm"), 2))
    mrow = ["mean", fnum(PAPER_TABLE2_MEAN[0], 2), fnum(PAPER_TABLE2_MEAN[1], 2), *mean_here]
    arow = ["", "", "", *abs_here]
    rows += [mrow + [""] * (len(hdr) - len(mrow)), arow + [""] * (len(hdr) - len(arow))]
    out.append(typst_table(hdr, rows, size="8.5pt", header_rows=hrow, hlines=(n,)))
    notes = [(f"Reference diameter {fnum(PAPER_REFERENCE_MM, 1)} mm in the paper; error = measured "
             "- reference (the paper lists |error|).")]
    if has_sigma:
        notes.append("σ: the 1-sigma of the diameter, the rim fit's and the edge model's "
                     "uncertainty together.")
    if t2sum.get("references"):
        names = ", ".join(esc(x) for x in t2.loc[t2["reference"], "name"])
        notes.append(f"_(ref.)_: {names} calibrated the edge model, so its error (in parentheses) "
                     "is fitted, not measured; the means leave it out.")
    out.append(" ".join(notes) + "\n")
    em = edge_model_text(inp.meas)
    if em:
        out.append(f"*Edge model:* {em}. Diameter = half-share diameter - 2 k x beam "
                   "spacing (lidarcal.disc).\n")
    else:
        out.append("*Edge model:* measurements.json records none (written by an older lidarcal): "
                   "the diameters carry no edge correction and no sigma.\n")
    stats = []
    if "within_2sigma" in t2sum:
        k, m = t2sum["within_2sigma"], t2sum["within_2sigma_of"]
        against = "the true diameters (truth.json)" if has_truth else "the reference diameters"
        stats.append(f"The error against {against} lies within 2 σ for {k} of {m} test trials "
                     f"({fnum(100.0 * k / m, 0)} %).")
    if "mean_abs_error_truth_mm" in t2sum:
        stats.append(f"Mean |measured - true diameter|: {fnum(t2sum['mean_abs_error_truth_mm'], 2)} mm.")
    if "naive_mean_abs_error_mm" in t2sum:
        stats.append("'naive diam.' is the circle through the outermost hits only (the biased-small "
                     f"estimate): mean |error| {fnum(t2sum['naive_mean_abs_error_mm'], 2)} mm.")
    if stats:
        out.append(" ".join(stats) + "\n")
    warns = _measurement_warnings(inp.meas)
    if warns:
        out.append("#warnbox[" + "\n".join(f"- {esc(w)}" for w in warns) + "]\n")
    if len(t2):
        out.append(fig("table2", lambda: plots.plot_table2(
            t2["diameter_mm"].to_numpy(), t2["reference_diameter_mm"].to_numpy(),
            list(t2["name"]), np.array([r[1] for r in PAPER_TABLE2])),
            "Measured minus reference diameter per trial, beside the paper's."
            + (f" {', '.join(t2.loc[t2['reference'], 'name'])}: reference (its error is fitted)."
               if t2sum.get("references") else ""), width="75%"))
        out.append(fig("disc", lambda: _plot_disc(inp, _disc_trial(inp)),
                       "A test trial's point cloud (eq. 28): disc points, rejected rim returns "
                       "and the circle of the measured (edge-corrected) diameter; right: the disc "
                       "plane face on.", width="100%"))
    return "\n".join(out)


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
