"""Rig-class robustness sweep: other LiDARs, turntables and geometry than the presets.

Builds :class:`lidarcal.synthetic.config.RigConfig` variants of the paper and wide
presets (``PAPER.with_(...)``), simulates each (``lidarcal.synthetic.simulate``, a
few positions, disc sweeps only where ``measure`` is tested), post-processes the
dataset where the variant is about the files (unsorted ``positions.csv`` rows,
angles wrapped at 360 deg), then runs ``lidarcal check``, ``lidarcal calibrate`` and
(with sweeps) ``lidarcal measure`` as subprocesses, and compares the outputs with
``truth.json`` (``lidarcal.evaluate``). One line per variant:

``variant  check  cal  warn  centre_mm  (max)  z_deg  x_deg  axis_deg  in2s_c  in2s_z  in2s_ax  [meas]``

- ``check``/``cal``: exit codes of ``lidarcal check`` / ``lidarcal calibrate`` (0 ok, 1 check
  found problems, 2 DatasetError);
- ``warn``: number of warnings in calibration.json (their first words are listed below the table
  with ``--verbose``);
- ``centre_mm``/``z_deg``/``x_deg``: mean true errors of ``poses`` (the default pose function)
  over the positions, ``(max)`` the worst centre; ``axis_deg``: the axis direction's true error;
- ``in2s_c``/``in2s_z``: share of positions whose true centre / z-axis error lies within the
  reported 2-sigma (``sigma.poses``); ``in2s_ax``: the axis direction within its 2-sigma (1/0);
- ``meas`` (variants with sweeps): measure's exit code, mean |diameter error| mm, share of discs
  within 2 ``diameter_sigma_mm`` (no reference: the prior edge model).

A variant that exits 2 reports the error line instead. ``--csv FILE`` also writes the rows.

usage::

    python scripts/lidar_sweep.py --work /tmp/sweep [--only fov270 noise10 ...] [--seed 5]
    python scripts/lidar_sweep.py --list          # the variants and what each changes
    python scripts/lidar_sweep.py --only base --positions 4 --work /tmp/quick   # a quick run

Each variant takes ~10-60 s (rendering dominates); ``--only`` picks some.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidarcal.evaluate import axis_direction_error_deg, pose_errors
from lidarcal.geometry import Pose
from lidarcal.synthetic import simulate
from lidarcal.synthetic.config import PAPER, WIDE, RigConfig

# the sweep's base: the paper rig with 16 positions 0.75 deg apart (an 11.25 deg sweep)
BASE = PAPER.with_(n_positions=16, psi_step_deg=0.75)
WBASE = WIDE.with_(n_positions=16, psi_step_deg=0.75)
SMALL_V = {"v_inner_corners": (7, 10), "v_square_mm": 30.0}     # a smaller V-board (the wide rig's)


@dataclass(frozen=True)
class Variant:
    """One rig variant: the config, whether to simulate sweeps, and a dataset post-processing."""

    name: str
    rig: RigConfig
    sweeps: bool = False
    post: str = ""            # "shuffle" (positions.csv rows), "wrap" (psi mod 360)
    note: str = ""
    changes: dict = field(default_factory=dict)


def _v(name: str, base: RigConfig = BASE, sweeps: bool = False, post: str = "", note: str = "",
       **changes) -> Variant:
    return Variant(name, base.with_(name=f"{base.name}-{name}", **changes), sweeps, post, note, changes)


def variants() -> list[Variant]:
    """Every variant of the sweep (LiDARs, turntables, geometry, measure)."""
    disc = {"n_discs": 4, "disc_diameters_mm": (100.0, 300.0)}
    return [
        _v("base"),
        _v("wide", WBASE),
        # --- LiDARs ---
        _v("fov270", lidar_angle_min_deg=-135.0, lidar_angle_max_deg=135.0, lidar_angle_step_deg=0.25),
        _v("fov360", lidar_angle_min_deg=-180.0, lidar_angle_max_deg=179.5, lidar_angle_step_deg=0.5),
        _v("step0.5", lidar_angle_step_deg=0.5),
        _v("step1", lidar_angle_step_deg=1.0),
        _v("step_fine", lidar_angle_step_deg=0.0625),
        _v("noise5", range_noise_mm=5.0),
        _v("noise10", range_noise_mm=10.0),
        _v("noise20", range_noise_mm=20.0),
        _v("quantum10", range_quantum_mm=10.0),
        _v("noise1pct", range_noise_mm=0.0, range_noise_rel=0.01),
        _v("offset+25", range_offset_mm=25.0),
        _v("offset-30", range_offset_mm=-30.0),
        _v("spurious5", spurious_rate=0.05),
        _v("incidence10", incidence_extra_mm=10.0),
        _v("incidence30", incidence_extra_mm=30.0),
        _v("scale0.2pct", range_scale_error=0.002),
        _v("scale1pct", range_scale_error=0.01),
        _v("drop20", drop_rate=0.2),
        _v("maxrange4m", lidar_range_max_mm=4000.0, wall_distance_mm=(4500.0, 5500.0)),
        _v("maxrange2m_far", lidar_range_max_mm=2000.0, wall_distance_mm=(2300.0, 3400.0)),
        _v("firstecho", footprint_model="first-echo"),
        _v("divergence", beam_exit_mm=10.0, beam_divergence_mrad=10.0),
        _v("upside_down", lidar_roll_deg=180.0),
        _v("rolled20", lidar_roll_deg=20.0),
        _v("fov360_yaw180", lidar_angle_min_deg=-180.0, lidar_angle_max_deg=179.5, lidar_angle_step_deg=0.5,
           lidar_yaw_deg=180.0),
        _v("fov270_yaw90", lidar_angle_min_deg=-135.0, lidar_angle_max_deg=135.0, lidar_angle_step_deg=0.25,
           lidar_yaw_deg=90.0),
        _v("lever_big", lever_arm_mm=(150.0, 250.0),
           lidar_offset_mm=((-250.0, 250.0), (200.0, 350.0), (150.0, 300.0))),
        # --- turntables ---
        _v("pos3", n_positions=3, psi_step_deg=0.25),
        _v("pos5", n_positions=5, psi_step_deg=0.25),
        _v("pos150", n_positions=150, psi_step_deg=0.1),
        _v("step2", n_positions=12, psi_step_deg=2.0),
        _v("step3_wide", WBASE, n_positions=10, psi_step_deg=3.0),     # a 27 deg sweep
        _v("pos3_step5", n_positions=3, psi_step_deg=5.0),
        _v("negstep", psi_step_deg=-0.75),
        _v("unsorted", post="shuffle"),
        _v("psi300", psi0_deg=(300.0, 310.0)),
        _v("psiwrap", psi0_deg=(352.0, 355.0), post="wrap"),
        _v("encoder0.02", encoder_noise_deg=0.02),
        _v("psiscale1pct", post="scale0.01"),
        _v("psiscale3pct", post="scale0.03"),
        _v("axis_tilt10", axis_tilt_deg=10.0),
        # --- geometry ---
        _v("v_near", WBASE, hinge_distance_mm=(600.0, 680.0)),
        _v("v_far", hinge_distance_mm=(2000.0, 2200.0), lidar_range_max_mm=5000.0,
           wall_distance_mm=(3000.0, 3500.0)),
        _v("wall_close", wall_distance_mm=(1300.0, 1400.0), wall_min_gap_mm=60.0),
        _v("posts_fat", post_radius_mm=(50.0, 80.0)),
        _v("small_board", **SMALL_V),
        # --- measure ---
        _v("disc_near", sweeps=True, disc_distance_mm=(900.0, 1000.0), **disc),
        _v("disc_far", sweeps=True, disc_distance_mm=(2200.0, 2400.0), **disc),
        _v("disc_wide", WBASE, sweeps=True, **disc),
    ]


def spot_variants() -> list[Variant]:
    """Measure with a wide beam spot (~14 beam spacings at 1 m; lidarcal.spot). Kept out of
    :func:`variants` so that ``combo_sweep.py --random``'s seeded draws stay as documented."""
    disc = {"n_discs": 4, "disc_diameters_mm": (100.0, 300.0)}
    beam = {"beam_exit_mm": 10.0, "beam_divergence_mrad": 10.0}
    return [
        _v("div_disc_near", sweeps=True, disc_distance_mm=(900.0, 1000.0), **beam, **disc),
        _v("div_disc", sweeps=True, **beam, **disc),
        _v("div_firstecho_disc", sweeps=True, footprint_model="first-echo", **beam, **disc),
    ]


def _map_psi(rows: list[str], fn) -> list[str]:
    """positions.csv rows with ``psi_deg`` (the second column) replaced by ``fn(psi_deg)``."""
    out = []
    for r in rows:
        f = r.split(",")
        f[1] = f"{fn(float(f[1])):.4f}"
        out.append(",".join(f))
    return out


def _post(ds: Path, how: str, rng: np.random.Generator) -> None:
    """Rewrite positions.csv: rows shuffled ("shuffle"), angles wrapped into [0, 360) ("wrap")
    or their turns from the first row scaled by ``1 + e`` ("scale<e>": an encoder scale error)."""
    if not how:
        return
    lines = (ds / "positions.csv").read_text().splitlines()
    head, rows = lines[0], lines[1:]
    if how == "shuffle":
        rows = [rows[i] for i in rng.permutation(len(rows))]
    elif how.startswith("scale"):  # an encoder/gear scale error: psi - psi_0 read (1 + e) x
        e, f0 = float(how[5:]), float(rows[0].split(",")[1])
        rows = _map_psi(rows, lambda a: f0 + (a - f0) * (1.0 + e))
    elif how == "wrap":
        rows = _map_psi(rows, lambda a: a % 360.0)
    else:
        raise ValueError(how)
    (ds / "positions.csv").write_text("\n".join([head, *rows]) + "\n")


def _lidarcal(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *args], capture_output=True, text=True,
                          check=False, timeout=1800)


def truth_errors(ds: Path, cal: dict) -> dict:
    """Mean true errors of ``poses`` and the share within the reported 2-sigma."""
    truth = json.loads((ds / "truth.json").read_text())
    est = {int(p["index"]): Pose.from_dict(p) for p in cal["poses"]}
    e = pose_errors(est, truth)
    out = {"centre_mm": e.centre_mm.mean(), "centre_max_mm": e.centre_mm.max(),
           "z_deg": e.z_axis_deg.mean(), "x_deg": e.x_axis_deg.mean(), "axis_deg": np.nan,
           "in2s_c": np.nan, "in2s_z": np.nan, "in2s_ax": np.nan}
    model = cal.get("model", {})
    if "axis" in model:
        out["axis_deg"] = axis_direction_error_deg(np.array(model["axis"]["direction"]),
                                                   np.array(truth["axis"]["direction"]))
    sig = cal.get("sigma") or {}
    sp = {int(s["index"]): s for s in sig.get("poses", [])}
    if sp:
        rows = [(r, sp[int(r["index"])]) for _, r in e.iterrows() if int(r["index"]) in sp]
        c = [r.centre_mm <= 2 * s["centre_mm"] for r, s in rows if s.get("centre_mm") is not None]
        z = [r.z_axis_deg <= 2 * s["z_axis_deg"] for r, s in rows if s.get("z_axis_deg") is not None]
        out["in2s_c"] = float(np.mean(c)) if c else np.nan
        out["in2s_z"] = float(np.mean(z)) if z else np.nan
    if sig.get("axis_direction_deg") is not None and np.isfinite(out["axis_deg"]):
        out["in2s_ax"] = float(out["axis_deg"] <= 2 * sig["axis_direction_deg"])
    return out


def measure_errors(out: Path) -> dict:
    """Mean |diameter error| and the share of discs within 2 diameter_sigma_mm."""
    m = json.loads((out / "measurements.json").read_text())["measurements"]
    err = np.array([d["error_mm"] for d in m if d.get("error_mm") is not None], float)
    sig = np.array([d["diameter_sigma_mm"] for d in m if d.get("error_mm") is not None], float)
    return {"meas_abs_mm": float(np.mean(np.abs(err))) if len(err) else np.nan,
            "meas_in2s": float(np.mean(np.abs(err) <= 2 * sig)) if len(err) else np.nan,
            "meas_n": len(err)}


def run_variant(v: Variant, work: Path, seed: int, reuse: bool = False) -> dict:
    """Simulate, check, calibrate (and measure) one variant; its row of the table. ``reuse``:
    a dataset already simulated in ``work`` (same seed and variant) is used again."""
    ds, out = work / v.name, work / v.name / "out"
    row: dict = {"variant": v.name}
    if not (reuse and (ds / "truth.json").is_file()):
        if ds.exists():
            shutil.rmtree(ds)
        try:
            simulate(ds, seed=seed, rig=v.rig, with_sweeps=v.sweeps)
        except ValueError as exc:          # the simulator cannot place such a rig
            row["error"] = f"simulate: {exc}"
            return row
        _post(ds, v.post, np.random.default_rng(seed))
    chk = _lidarcal("check", str(ds), "--sheet", str(work / f"{v.name}-check.png"))
    row["check"] = chk.returncode
    cal = _lidarcal("calibrate", str(ds), "--out", str(out))
    row["cal"] = cal.returncode
    if cal.returncode != 0:
        row["error"] = (cal.stderr.strip().splitlines() or ["?"])[-1][:160]
        return row
    c = json.loads((out / "calibration.json").read_text())
    row["warn"] = len(c.get("warnings", []))
    row["warnings"] = [w[:110] for w in c.get("warnings", [])]
    row["skipped"] = len(c.get("skipped", []))
    row.update(truth_errors(ds, c))
    if v.sweeps:
        m = _lidarcal("measure", str(ds), "--calibration", str(out / "calibration.json"), "--out", str(out))
        row["meas"] = m.returncode
        if m.returncode == 0:
            row.update(measure_errors(out))
        else:
            row["meas_error"] = (m.stderr.strip().splitlines() or ["?"])[-1][:160]
    return row


def _fmt(x, f: str) -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "-"
    return format(x, f)


def format_row(r: dict) -> str:
    """One table line (see the module docstring)."""
    head = f"{r['variant']:15s}"
    if "cal" not in r or r.get("cal") != 0:
        return f"{head} check {r.get('check', '-')} cal {r.get('cal', '-')}  {r.get('error', '')}"
    s = (f"{head} check {r['check']} cal 0 warn {r['warn']:2d} skip {r['skipped']:2d}  "
         f"centre {_fmt(r['centre_mm'], '8.3f')} ({_fmt(r['centre_max_mm'], '.3f')}) mm  "
         f"z {_fmt(r['z_deg'], '.4f')}  x {_fmt(r['x_deg'], '.4f')}  axis {_fmt(r['axis_deg'], '.4f')} deg  "
         f"in2s c {_fmt(r['in2s_c'], '.2f')} z {_fmt(r['in2s_z'], '.2f')} ax {_fmt(r['in2s_ax'], '.0f')}")
    if "meas" in r:
        s += f"  measure {r['meas']}"
        if r["meas"] == 0:
            s += f" |err| {_fmt(r['meas_abs_mm'], '.2f')} mm in2s {_fmt(r['meas_in2s'], '.2f')}"
        else:
            s += f" {r.get('meas_error', '')}"
    return s


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("sweep-work"), help="folder for the datasets")
    ap.add_argument("--only", nargs="*", default=None, help="variant names (default: all)")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--positions", type=int, default=None,
                    help="override every variant's number of positions (a quick run)")
    ap.add_argument("--csv", type=Path, default=None, help="also write the rows to this CSV")
    ap.add_argument("--list", action="store_true", help="list the variants and exit")
    ap.add_argument("--reuse", action="store_true",
                    help="use the datasets already simulated in --work again (compare code versions)")
    ap.add_argument("--verbose", action="store_true", help="print each variant's warnings")
    a = ap.parse_args(argv)
    vs = variants() + spot_variants()
    if a.list:
        for v in vs:
            print(f"{v.name:15s} {v.rig.name.split('-')[0]:6s} sweeps={int(v.sweeps)} post={v.post or '-'} "
                  f"{v.changes}")
        return 0
    if a.only:
        unknown = set(a.only) - {v.name for v in vs}
        if unknown:
            ap.error(f"unknown variants {sorted(unknown)}; see --list")
        vs = [v for v in vs if v.name in a.only]
    if a.positions:
        vs = [Variant(v.name, v.rig.with_(n_positions=a.positions), v.sweeps, v.post, v.note, v.changes)
              for v in vs]
    a.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for v in vs:
        r = run_variant(v, a.work, a.seed, a.reuse)
        rows.append(r)
        print(format_row(r), flush=True)
        if a.verbose:
            for w in r.get("warnings", []):
                print(f"    warning: {w}", flush=True)
    if a.csv:
        keys = sorted({k for r in rows for k in r if k != "warnings"})
        with a.csv.open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=keys)
            w.writeheader()
            w.writerows([{k: r.get(k) for k in keys} for r in rows])
    return 0


if __name__ == "__main__":
    sys.exit(main())
