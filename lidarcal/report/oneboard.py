"""The PDF report of a one-board calibration (``lidarcal report VIEWS/``, the classic method of
``lidarcal planes``: Zhang and Pless 2004, one flat chessboard per view).

A folder of photo + scan pairs is calibrated (:func:`lidarcal.planes.run_planes`) and every
number of the report comes from that result's ``extrinsics.json`` document
(:meth:`lidarcal.planes.PlanesResult.to_dict`), so the report agrees with what ``lidarcal
planes`` writes. Added: the leave-one-out check (:func:`lidarcal.planes.leave_one_out`: each
view predicted by the others, the held-out residual against the in-sample one), and with a
stored ``extrinsics.json`` (``--calibration``) that calibration scored on these views: the
held-out check of a calibration on views it did not see.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from .. import __version__
from ..degeneracy import pose_difference
from ..geometry import check_rotation
from ..io.dataset import BoardSpec, DatasetError, read_json_object
from .figures import _Figures
from .markup import _template, compile_typst, esc, fnum, typst_table, vec

#: the held-out residual of a view may exceed its in-sample residual by this factor before the
#: report flags it (the acceptance bound of a one-board calibration checked on other views)
HELD_OUT_RATIO = 1.25


def read_extrinsics(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """``R``, ``T_mm`` of a stored ``extrinsics.json`` (``lidarcal-extrinsics/1``), checked:
    ``R`` a rotation (orthonormal, det +1, to 1e-6), ``T_mm`` three finite numbers."""
    from ..planes import EXTRINSICS_FORMAT

    p = Path(path)
    doc = read_json_object(p, "missing extrinsics file; give the extrinsics.json that "
                              "`lidarcal planes` wrote", "write it again with `lidarcal planes`")
    if doc.get("format") != EXTRINSICS_FORMAT:
        raise DatasetError(p, f"format is {doc.get('format')!r}, expected {EXTRINSICS_FORMAT!r}; "
                              "give the extrinsics.json that `lidarcal planes` wrote")
    try:
        R = np.array(doc["R"], dtype=float)
        T = np.array(doc["T_mm"], dtype=float)
    except (KeyError, TypeError, ValueError) as e:
        raise DatasetError(p, f"R or T_mm missing or not numbers ({e}); write it again with "
                              "`lidarcal planes`") from None
    if R.shape != (3, 3) or T.shape != (3,) or not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))):
        raise DatasetError(p, "R must be 3x3 and T_mm 3 finite numbers; write it again with "
                              "`lidarcal planes`")
    try:
        check_rotation(R)
    except ValueError as e:
        raise DatasetError(p, f"R is not a rotation ({e}); write it again with `lidarcal planes`"
                           ) from None
    return R, T


def stored_residuals(res, R: np.ndarray, T: np.ndarray) -> list[dict]:
    """Per used view, the point-to-plane RMS (mm) of its board returns under a stored ``(R, T)``
    against the same under this folder's own fit (``res``)."""
    from ..planes import plane_residuals_mm

    rows = []
    for v, u, r in zip(res.views, res.used, res.rms_mm):
        if u:
            e = plane_residuals_mm(v, R, T)
            rows.append({"name": v.name, "rms_mm": float(np.sqrt(np.mean(e ** 2))),
                         "own_fit_rms_mm": float(r)})
    return rows


def _held_out(res, leave_one_out) -> list[dict]:
    """:func:`lidarcal.planes.leave_one_out` view by view; a view whose others cannot be
    calibrated without it (too few left to agree on the board segments) gets ``rms_mm`` None
    and the reason in ``note``."""
    rows = []
    for v, u, r in zip(res.views, res.used, res.rms_mm):
        if not u:
            continue
        try:
            rows += leave_one_out(res.views, res, names=[v.name])
        except DatasetError as e:
            rows.append({"name": v.name, "rms_mm": None, "in_sample_rms_mm": r, "determined": False,
                         "note": f"the other views alone: {e.problem}"})
    return rows


def _rotation_deg(R_a: np.ndarray, R_b: np.ndarray) -> float:
    """The angle (deg) of the rotation between two poses' ``R``."""
    return float(np.degrees(np.linalg.norm(pose_difference(R_a, np.zeros(3), R_b, np.zeros(3))[:3])))


def _sigma_text(values) -> str:
    return "(" + ", ".join("undetermined" if v is None else fnum(v, 3) for v in values) + ")"


def _margin_text(bm: dict | None) -> str:
    """The ``board_margins`` of extrinsics.json in words: measured margins with their sigma, or
    the margin assumed (where not measured, or ``--assumed-margin``)."""
    if bm is None:
        return "assumed (--assumed-margin): half the pattern's shorter side"
    ax = [f"{bm[f'{a}_mm']:.1f} +- {bm[f'sigma_{a}_mm']:.1f} (measured, {bm[f'views_{a}']} edges)"
          if bm[f"{a}_mm"] is not None else f"{bm['assumed_mm']:g} (assumed: not measured)"
          for a in "uv"]
    return ", ".join(ax)


def _summary(doc: dict, board: BoardSpec) -> str:
    used = sum(1 for v in doc["views"] if v["used"])
    sig = doc["sigma"]
    rows = [
        ["views used", f"{used} of {len(doc['views'])}"],
        ["board", esc(f"{board.inner_corners[0]}x{board.inner_corners[1]} inner corners, "
                      f"{board.square_mm:g} mm squares")],
        ["R (LiDAR to camera)", " \\ ".join(vec(r, 5) for r in doc["R"])],
        ["T (mm)", vec(doc["T_mm"], 1)],
        ["1-sigma rotation (deg, about x, y, z)", esc(_sigma_text(sig["rotation_deg"]))],
        ["1-sigma translation (mm, x, y, z)", esc(_sigma_text(sig["translation_mm"]))],
        ["point-to-plane RMS (mm)", fnum(doc["rms_mm"], 2)],
        ["noise scale (residuals / noise model)", fnum(doc["noise_scale"], 2)],
        ["view-level chi2 / dof", f"{fnum(doc['view_chi2']['chi2'], 1)} / {doc['view_chi2']['dof']}"],
        ["board margin beyond the pattern (mm, u, v)", esc(_margin_text(doc.get("board_margins")))],
        ["linear start: rotation, translation off the refined",
         (f"{fnum(_rotation_deg(np.array(doc['R']), np.array(doc['linear']['R'])), 3)} deg, "
         f"{fnum(np.linalg.norm(np.subtract(doc['T_mm'], doc['linear']['T_mm'])), 1)} mm")],
    ]
    out = ["= Summary <no-break>\n",
           ("The pose maps LiDAR points into the camera frame (OpenCV's): "
           "$X_\"cam\" = R X_\"lidar\" + T$. Each view's board plane comes from its "
           "chessboard (cv2.solvePnP, eqs. 1-3 of the paper's section 1.2); the scan's board "
           "segment must lie on it (Zhang and Pless 2004), fitted by robust maximum likelihood "
           "with the board planes' uncertainty.\n"),
           typst_table(["quantity", "value"], rows, align="left", columns="(auto, 1fr)")]
    if doc["undetermined"]:
        kinds = ", ".join(sorted({d["kind"] for d in doc["undetermined"]}))
        msg = (f"These views do not determine the whole pose ({kinds}): the sigma of the "
               "undetermined directions is given as undetermined. Add views with the board tilted "
               "differently.")
        out.append(f"#notebox[{esc(msg)}]\n")
    if doc["warnings"]:
        out.append("== Warnings\n")
        out += [f"- {esc(w)}\n" for w in doc["warnings"]]
    else:
        out.append("No warnings: every view agrees with the others within the noise.\n")
    return "\n".join(out)


def _views_table(doc: dict, loo: list[dict]) -> str:
    held = {r["name"]: r for r in loo}
    rows = []
    for v in doc["views"]:
        h = held.get(v["name"])
        ratio = h["rms_mm"] / h["in_sample_rms_mm"] if h and h["rms_mm"] is not None else None
        flag = "" if ratio is None or ratio <= HELD_OUT_RATIO else " (!)"
        note = "; ".join(t for t in (v.get("note", ""), (h or {}).get("note", "")) if t)
        rows.append([esc(v["name"]), "yes" if v["used"] else "no", str(v["points"]),
                     fnum(v["rms_mm"], 2), fnum(h["rms_mm"], 2) + flag if h else "--",
                     fnum(v["range_noise_mm"], 1), fnum(v["corner_noise_px"], 3), esc(note)])
    text = ["= Views\n",
            ("Per view: its board returns, their RMS distance to the board plane under the fit "
            "(in sample) and under a fit to the other views (held out: the view predicted by a "
            f"calibration that did not see it; (!) where it exceeds {HELD_OUT_RATIO:g}x the in-sample "
            "RMS), the range noise estimated from the scan and the corners' fit to their board.\n"),
            typst_table(["view", "used", "returns", "RMS mm", "held-out RMS mm", "range noise mm",
                         "corner RMS px", "note"], rows, columns="(auto, auto, auto, auto, auto, auto, "
                                                                   "auto, 1fr)")]
    scored = [h for h in loo if h["rms_mm"] is not None]
    if scored:
        r = np.array([h["rms_mm"] for h in scored])
        i = np.array([h["in_sample_rms_mm"] for h in scored])
        text.append(f"Held out over {len(scored)} views: RMS {fnum(np.sqrt(np.mean(r ** 2)), 2)} mm "
                    f"against {fnum(np.sqrt(np.mean(i ** 2)), 2)} mm in sample (ratio "
                    f"{fnum(np.sqrt(np.mean(r ** 2)) / np.sqrt(np.mean(i ** 2)), 2)}).\n")
        if not all(h["determined"] for h in loo):
            text.append("#notebox[" + esc("Some views leave a pose direction undetermined when left "
                                          "out: their held-out residual tests only the determined part.")
                        + "]\n")
    return "\n".join(text)


def _stored_section(path: Path, R: np.ndarray, T: np.ndarray, res, rows: list[dict]) -> str:
    r = np.array([x["rms_mm"] for x in rows])
    own = np.array([x["own_fit_rms_mm"] for x in rows])
    table = typst_table(["view", "RMS mm, stored calibration", "RMS mm, these views' own fit"],
                        [[esc(x["name"]), fnum(x["rms_mm"], 2), fnum(x["own_fit_rms_mm"], 2)]
                         for x in rows])
    return "\n".join([
        "= The stored calibration on these views\n",
        (f"{esc(str(path))} scored on these views' board returns: RMS {fnum(np.sqrt(np.mean(r ** 2)), 2)} "
        f"mm against {fnum(np.sqrt(np.mean(own ** 2)), 2)} mm for the fit to these views (ratio "
        f"{fnum(np.sqrt(np.mean(r ** 2)) / np.sqrt(np.mean(own ** 2)), 2)}). The stored pose is "
        f"{fnum(_rotation_deg(R, res.R), 3)} deg and {fnum(np.linalg.norm(T - res.T), 1)} mm from "
        "this folder's own fit.\n"), table])


def build_oneboard_source(res, board: BoardSpec, folder: Path, name: str, figures: bool = True,
                          stored: tuple[Path, np.ndarray, np.ndarray] | None = None,
                          command: str | None = None) -> str:
    """The one-board report's typst source; figures are written as PNG files into ``folder``."""
    from ..planes import leave_one_out
    from ..planes_plots import plot_board_segments, plot_view_residuals, projection_figure

    doc = res.to_dict()
    notes: list[str] = []
    fig = _Figures(folder, notes, enabled=figures)
    loo = _held_out(res, leave_one_out) if sum(res.used) > 3 else []
    created = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    title = "lidarcal one-board calibration report"
    parts = [_template(),
             (f'#show: lidarcal-doc.with(title: [{title}], subtitle: [{esc(name)}], '
              f'footer-left: [lidarcal {esc(__version__)} -- {esc(created)}])\n'),
             (f"#align(center)[#text(18pt, weight: \"bold\")[{title}] \\ #v(0.3em) "
              f"#text(12pt)[{esc(name)}: {len(res.views)} photo + scan pairs]]\n"),
             _summary(doc, board), _views_table(doc, loo)]
    if stored is not None:
        parts.append(_stored_section(stored[0], stored[1], stored[2], res,
                                     stored_residuals(res, stored[1], stored[2])))
    parts.append("= Figures\n")
    parts.append(fig("segments", lambda: plot_board_segments(res),
                     "Every scan in the LiDAR frame: the board's returns (red) and the board "
                     "plane's trace predicted by the calibration (dashed)."))
    parts.append(fig("residuals", lambda: plot_view_residuals(res),
                     "Point-to-plane residuals of every used view's board returns."))
    for k, v in enumerate(res.views):
        parts.append(fig(f"projection_{k:02d}", lambda k=k: projection_figure(res, k),
                         f"{v.name}: the LiDAR returns drawn on the photo with the calibration "
                         "(board returns ringed, the board's outline in yellow).", width="80%",
                         photo=True))
    parts.append("= Provenance\n")
    parts.append(typst_table(["", ""], [["lidarcal", esc(__version__)], ["command", esc(command or "")],
                                        ["created", esc(created)]], align="left",
                             columns="(auto, 1fr)"))
    if notes:
        parts += [f"- {esc(n)}\n" for n in notes]
    return "\n".join(parts)


def write_oneboard_report(folder: str | os.PathLike, out_pdf: str | os.PathLike,
                          camera_json: str | os.PathLike, board: BoardSpec,
                          calibration: str | os.PathLike | None = None,
                          command: str | None = None, assumed_margin: bool = False) -> Path:
    """Calibrate the view pairs in ``folder`` (``lidarcal planes``, ``assumed_margin`` as there)
    and write the report to ``out_pdf``; ``calibration``: a stored ``extrinsics.json`` to score on
    these views too."""
    from ..planes import run_planes

    stored = None
    if calibration is not None:
        stored = (Path(calibration), *read_extrinsics(calibration))
    res = run_planes(folder, camera_json, board, assumed_margin=assumed_margin)
    work = Path(tempfile.mkdtemp(prefix="lidarcal_report_"))
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        src = build_oneboard_source(res, board, work, Path(folder).resolve().name, stored=stored,
                                    command=command)
        typ = work / "report.typ"
        typ.write_text(src)
        return compile_typst(typ, Path(out_pdf), root=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
