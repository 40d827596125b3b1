"""Rig-class robustness sweep: ``lidarcal calibrate`` on simulated camera and board variants.

Each variant is a :class:`lidarcal.synthetic.config.RigConfig` built from the ``paper`` or
``wide`` preset with ``.with_(...)`` (other cameras: resolution, focal length, distortion,
non-square pixels, principal point; the camera stored in dataset.json or calibrated from
intrinsics photos; other intrinsics boards; other V-boards: pattern, orientation, square
size, margin, opening angle, hinge distance). Per variant and seed the script

1. simulates the dataset (``lidarcal.synthetic.simulate``, ``--positions`` positions over
   the preset's turntable span, no sweeps; a variant whose geometry the simulator cannot place is reported ``sim-fail``),
2. runs ``python -m lidarcal calibrate DATASET --out OUT`` in a subprocess,
3. prints one row: the exit status, the number of warnings (``calibration.json``
   ``warnings``; on exit 2 the error line), the pixels per V-board square, the mean true
   errors of ``poses`` (the default joint fit) against ``truth.json`` (LiDAR centre mm,
   z and x axes deg, axis direction deg), the solvePnP board-plane normal errors (deg, worst
   of the two; the planes the joint fit holds) and the share of positions whose true
   centre, z- and x-axis errors lie within the reported 2-sigma (``sigma``; 100 % is the target, well below means the sigmas lie).

``--csv FILE`` also writes the rows; ``--keep DIR`` keeps the datasets and outputs there
(else a temporary folder); ``--list`` prints the variants. Examples::

    .venv/bin/python scripts/rig_sweep.py                         # every variant, seed 1
    .venv/bin/python scripts/rig_sweep.py --variants cam_vga v_9x6 --seeds 1 2 3
    .venv/bin/python scripts/rig_sweep.py --variants v_tiny_squares --positions 12 --csv s.csv

The numbers are true errors of single simulated rigs (a handful of positions): they show
where the pipeline breaks or is silently wrong, not its accuracy (see ``make study``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from lidarcal.evaluate import axis_direction_error_deg, plane_error, pose_errors, truth_board_planes
from lidarcal.geometry import Plane, Pose
from lidarcal.synthetic import simulate
from lidarcal.synthetic.config import PAPER, WIDE, RigConfig


def _K(fx: float, fy: float, cx: float, cy: float) -> tuple:
    return ((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0))


def _v(base: RigConfig, **changes) -> tuple[RigConfig, dict]:
    return base, changes


# name -> (base, changes). Distances keep the V in the image for the camera's field of view.
VARIANTS: dict[str, tuple[RigConfig, dict]] = {
    "paper": (PAPER, {}),
    "wide": (WIDE, {}),
    # --- cameras ---
    "cam_vga": _v(PAPER, image_size=(640, 480), K=_K(500, 500, 322, 238),
                  dist=(-0.05, 0.02, 0, 0, 0), v_inner_corners=(6, 9), v_square_mm=40.0,
                  hinge_distance_mm=(900.0, 1000.0)),
    "cam_752": _v(PAPER, image_size=(752, 480), K=_K(480, 480, 380, 236),
                  dist=(-0.28, 0.08, 0, 0, 0), v_inner_corners=(6, 9), v_square_mm=40.0,
                  hinge_distance_mm=(850.0, 950.0), camera_in_dataset=False,
                  intrinsics_square_mm=40.0),
    "cam_4k": _v(PAPER, image_size=(3840, 2160), K=_K(3000, 3000, 1920, 1080),
                  dist=(-0.08, 0.1, 0, 0, 0), supersample=2),
    "cam_barrel": _v(WIDE, dist=(-0.4, 0.2, 0.0, 0.0, -0.05)),
    "cam_barrel_ds": _v(WIDE, dist=(-0.4, 0.2, 0.0, 0.0, -0.05), camera_in_dataset=True),
    "cam_tangential": _v(WIDE, dist=(-0.3, 0.12, 0.004, -0.003, -0.02)),
    "cam_nonsquare": _v(PAPER, K=_K(2757.4, 2812.5, 831.6, 638.9), camera_in_dataset=False),
    "cam_pp_off": _v(WIDE, K=_K(1187.0, 1189.5, 1150.0, 470.0)),
    "cam_photos": _v(PAPER, camera_in_dataset=False),
    "cam_intr_7x5": _v(WIDE, intrinsics_inner_corners=(7, 5), intrinsics_square_mm=40.0),
    "cam_intr_11x8": _v(WIDE, intrinsics_inner_corners=(11, 8), intrinsics_square_mm=22.0),
    "cam_intr_6views": _v(WIDE, n_intrinsics_views=6),
    # --- V-boards ---
    "v_9x6": _v(WIDE, v_inner_corners=(9, 6)),
    "v_6x9": _v(WIDE, v_inner_corners=(6, 9)),
    "v_8x11": _v(WIDE, v_inner_corners=(8, 11), v_square_mm=25.0),
    "v_5x7": _v(WIDE, v_inner_corners=(5, 7), v_square_mm=40.0),
    "v_7x5": _v(WIDE, v_inner_corners=(7, 5), v_square_mm=40.0),
    "v_7x9": _v(WIDE, v_inner_corners=(7, 9)),     # both odd: a point-symmetric pattern
    "v_8x6": _v(WIDE, v_inner_corners=(8, 6)),     # both even
    "v_sq15": _v(PAPER, v_inner_corners=(19, 27), v_square_mm=15.0),
    "v_sq60": _v(WIDE, v_inner_corners=(4, 6), v_square_mm=60.0),
    # small boards far away (pixels per square ~ fx * square / distance; a short turntable
    # span keeps both stripes on the small boards)
    "v_small_far": _v(PAPER, v_inner_corners=(7, 10), v_square_mm=20.0, psi_step_deg=0.3,
                      hinge_distance_mm=(2200.0, 2300.0), wall_distance_mm=(3000.0, 3400.0),
                      lidar_range_max_mm=4000.0),
    "v_tiny_8px": _v(WIDE, v_inner_corners=(7, 10), v_square_mm=15.0, psi_step_deg=0.25,
                     hinge_distance_mm=(2200.0, 2250.0), wall_distance_mm=(3000.0, 3600.0)),
    "v_tiny_5px": _v(WIDE, v_inner_corners=(7, 10), v_square_mm=10.0, psi_step_deg=0.2,
                     hinge_distance_mm=(2350.0, 2400.0), wall_distance_mm=(3000.0, 3600.0)),
    "v_tiny_6px": _v(WIDE, v_inner_corners=(10, 14), v_square_mm=10.0, psi_step_deg=0.2,
                     hinge_distance_mm=(1950.0, 2000.0), wall_distance_mm=(2600.0, 3000.0)),
    "v_tiny_3px": _v(WIDE, v_inner_corners=(14, 20), v_square_mm=6.0, psi_step_deg=0.1,
                     hinge_distance_mm=(2000.0, 2050.0), wall_distance_mm=(2600.0, 3000.0)),
    "v_fill": _v(WIDE, hinge_distance_mm=(600.0, 640.0), image_border_px=4.0),
    "v_margin_0.25": _v(WIDE, v_margin_squares=0.25),
    "v_margin_0.5": _v(WIDE, v_margin_squares=0.5),
    "v_margin_2": _v(WIDE, v_margin_squares=2.0),
    "v_angle_90": _v(WIDE, v_angle_deg=(90.0, 92.0)),
    "v_angle_150": _v(WIDE, v_angle_deg=(148.0, 150.0)),
    "v_near": _v(PAPER, v_inner_corners=(10, 14), hinge_distance_mm=(950.0, 1000.0)),
    "v_far": _v(PAPER, psi_step_deg=0.15, hinge_distance_mm=(1800.0, 1900.0),
                wall_distance_mm=(2600.0, 3400.0)),
}


def _square_px(rig: RigConfig, truth: dict) -> float:
    """Mean pixels per V-board square at the hinge (fx * square / hinge depth)."""
    fx = float(np.asarray(truth["camera"]["K"])[0][0])
    return fx * rig.v_square_mm / float(truth["hinge"]["point_mm"][2])


def evaluate(ds: Path, cal: dict) -> dict:
    """True errors of ``cal`` (calibration.json) against ``ds``/truth.json; 2-sigma shares."""
    truth = json.loads((ds / "truth.json").read_text())
    est = {int(p["index"]): Pose.from_dict(p) for p in cal["poses"]}
    e = pose_errors(est, truth)
    ax = axis_direction_error_deg(np.array(cal["model"]["axis"]["direction"]),
                  np.array(truth["axis"]["direction"]))
    # the solvePnP planes: the ones the joint fit holds (``boards[].normal`` is eqs. 2-3's)
    planes = [Plane(np.asarray(b["pnp"]["normal"], float), float(b["pnp"]["d_mm"]))
              for b in cal["boards"]]
    true_planes = truth_board_planes(truth)
    normal = max(min(plane_error(p, t)["normal_deg"] for t in true_planes) for p in planes)
    out = {"centre_mm": e.centre_mm.mean(), "z_deg": e.z_axis_deg.mean(), "x_deg": e.x_axis_deg.mean(),
           "axis_deg": ax, "plane_deg": normal}
    sig = {int(s["index"]): s for s in (cal.get("sigma") or {}).get("poses", [])}
    for q, col in (("centre_mm", "centre_mm"), ("z_axis_deg", "z_axis_deg"), ("x_axis_deg", "x_axis_deg")):
        ok = [r[col] <= 2 * sig[int(r["index"])][q] for _, r in e.iterrows()
              if int(r["index"]) in sig and sig[int(r["index"])].get(q) is not None]
        out[f"in2s_{q.split('_')[0]}"] = 100.0 * float(np.mean(ok)) if ok else float("nan")
    return out


def run_variant(name: str, seed: int, positions: int, work: Path) -> dict:
    """Simulate variant ``name`` with ``seed``, calibrate it, evaluate against truth: one row."""
    base, changes = VARIANTS[name]
    # the preset's turntable span with fewer positions (the axis stays as well determined)
    step = base.psi_step_deg * (base.n_positions - 1) / max(positions - 1, 1)
    rig = base.with_(name=f"{base.name}-{name}", n_positions=positions,
                     **{"psi_step_deg": round(step, 4), **changes})
    ds, out = work / f"{name}_s{seed}", work / f"{name}_s{seed}_out"
    row: dict = {"variant": name, "seed": seed}
    try:
        simulate(ds, seed, rig, with_sweeps=False, overwrite=True)
    except ValueError as e:
        return {**row, "rc": "sim-fail", "note": str(e)}
    truth = json.loads((ds / "truth.json").read_text())
    row["sq_px"] = _square_px(rig, truth)
    p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(ds), "--out", str(out)],
                  capture_output=True, text=True, check=False)
    row["rc"] = p.returncode
    cal_path = out / "calibration.json"
    if p.returncode != 0 or not cal_path.exists():
        lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
        return {**row, "note": lines[-1] if lines else ""}
    cal = json.loads(cal_path.read_text())
    row["warnings"] = len(cal.get("warnings", []))
    row["note"] = "; ".join(w[:90] for w in cal.get("warnings", []))
    row.update(evaluate(ds, cal))
    return row


COLUMNS = ("variant", "seed", "rc", "warnings", "sq_px", "centre_mm", "z_deg", "x_deg", "axis_deg",
           "plane_deg", "in2s_centre", "in2s_z", "in2s_x")


def _fmt(v) -> str:
    if isinstance(v, float):
        return "nan" if not np.isfinite(v) else (f"{v:.4f}" if abs(v) < 10 else f"{v:.1f}")
    return "" if v is None else str(v)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", nargs="+", default=None, help="names (default: all; see --list)")
    ap.add_argument("--seeds", nargs="+", type=int, default=[1])
    ap.add_argument("--positions", type=int, default=14)
    ap.add_argument("--keep", type=Path, default=None, help="keep datasets and outputs in this folder")
    ap.add_argument("--csv", type=Path, default=None, help="also write the rows as CSV")
    ap.add_argument("--list", action="store_true", help="print the variants and exit")
    args = ap.parse_args(argv)
    if args.list:
        for k, (base, ch) in VARIANTS.items():
            print(f"{k:16s} {base.name}: {ch}")
        return 0
    names = args.variants or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        ap.error(f"unknown variants {unknown}; see --list")
    tmp = None
    if args.keep is None:
        tmp = tempfile.TemporaryDirectory(prefix="rig_sweep_")
        work = Path(tmp.name)
    else:
        work = args.keep
        work.mkdir(parents=True, exist_ok=True)
    rows = []
    print(" ".join(f"{c:>11s}" if i > 1 else f"{c:16s}" if i == 0 else f"{c:>4s}"
                   for i, c in enumerate(COLUMNS)), "  note", flush=True)
    for name in names:
        for seed in args.seeds:
            r = run_variant(name, seed, args.positions, work)
            rows.append(r)
            cells = [f"{_fmt(r.get(c)):16s}" if i == 0 else f"{_fmt(r.get(c)):>4s}" if i == 1
                  else f"{_fmt(r.get(c)):>11s}" for i, c in enumerate(COLUMNS)]
            print(" ".join(cells), " ", r.get("note", "")[:300], flush=True)
    if args.csv is not None:
        import pandas as pd

        pd.DataFrame(rows, columns=[*COLUMNS, "note"]).to_csv(args.csv, index=False)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
