"""The clean-room simulator's evaluation: ``lidarcal check``, ``calibrate`` and ``measure``
run from the command line on its datasets and compared with its own truth.json.

Used by ``scripts/cleanroom_rig.py --evaluate`` (and tests/test_cleanroom_rig.py): LiDAR
centre error mm, z / x axis error deg, axis direction deg and the axis line's distance near
the LiDAR, the share of positions within 2 reported sigma and the largest error / sigma,
disc diameter errors. Its own comparison: it reads calibration.json and truth.json as the
docs describe them, nothing of lidarcal.
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np
from cleanroom_rig import generate, unit


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = np.clip(np.dot(unit(a), unit(b)), -1, 1)
    return float(np.degrees(np.arccos(c)))


def line_distance_near(p_true, d_true, p_est, d_est, near) -> float:
    """Distance from the true axis' point nearest `near` to the estimated line."""
    q = p_true + ((near - p_true) @ d_true) * d_true
    r = q - p_est
    return float(np.linalg.norm(r - (r @ d_est) * d_est))


def compare(cal: dict, truth: dict) -> dict:
    """Our own comparison of calibration.json against truth.json."""
    tp = {p["index"]: p for p in truth["poses"]}
    sig = {p["index"]: p for p in (cal.get("sigma") or {}).get("poses", [])}
    ce, ze, xe, within, ratio = [], [], [], [], []
    for p in cal["poses"]:
        t = tp[p["index"]]
        R, T = np.array(p["R"]), np.array(p["T_mm"])
        Rt, Tt = np.array(t["R"]), np.array(t["T_mm"])
        c = float(np.linalg.norm(T - Tt))
        z = angle_deg(R[:, 2], Rt[:, 2])
        x = angle_deg(R[:, 0], Rt[:, 0])
        ce.append(c)
        ze.append(z)
        xe.append(x)
        s = sig.get(p["index"])
        if s and s.get("centre_mm") is not None:
            within.append(c <= 2 * s["centre_mm"] and z <= 2 * s["z_axis_deg"]
                          and x <= 2 * s["x_axis_deg"])
            ratio.append(max(c / s["centre_mm"], z / s["z_axis_deg"], x / s["x_axis_deg"]))
    ax_t, ax_e = truth["axis"], cal["axis"]
    near = np.array(truth["pose_ref"]["T_mm"])
    sigma = cal.get("sigma") or {}
    return {
        "positions": len(cal["poses"]),
        "centre_mm": float(np.mean(ce)), "centre_max_mm": float(np.max(ce)),
        "z_deg": float(np.mean(ze)), "x_deg": float(np.mean(xe)),
        "axis_dir_deg": angle_deg(ax_t["direction"], ax_e["direction"]),
        "axis_point_mm": line_distance_near(np.array(ax_t["point_mm"]), unit(ax_t["direction"]),
                                            np.array(ax_e["point_mm"]), unit(ax_e["direction"]),
                                            near),
        "sigma_centre_mm": float(np.mean([s["centre_mm"] for s in sig.values()
                                          if s.get("centre_mm") is not None] or [np.nan])),
        "sigma_axis_dir_deg": sigma.get("axis_direction_deg"),
        "within_2sigma": float(np.mean(within)) if within else None,
        "worst_sigma_ratio": float(np.max(ratio)) if ratio else None,
        "method": cal.get("method"),
        "warnings": len(cal.get("warnings", [])),
        "skipped": len(cal.get("skipped", [])),
    }


def run(cmd: list[str]) -> tuple[int, str, float]:
    t0 = time.time()
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    return p.returncode, (p.stdout + p.stderr), time.time() - t0


def measure_row(lidarcal: str, ds: Path, out: Path, truth: dict) -> dict:
    """`lidarcal measure` on the dataset's sweeps: each disc's error against the truth."""
    rc, text, secs = run([lidarcal, "measure", str(ds), "--calibration",
                          str(out / "calibration.json"), "--out", str(out)])
    row = {"measure_rc": rc, "measure_s": round(secs, 1)}
    if rc != 0:
        row["measure_out"] = text.strip().splitlines()[-1:]
        return row
    mj = json.loads((out / "measurements.json").read_text())
    got = {m["name"]: m for m in mj["measurements"]}
    errs = [(got[t["name"]]["diameter_mm"] - t["diameter_mm"], got[t["name"]]["diameter_sigma_mm"])
            for t in truth["measurements"]]
    row["disc_err_mm"] = [round(e, 2) for e, _ in errs]
    row["disc_sigma_mm"] = [round(sg, 2) for _, sg in errs]
    row["disc_within_2sigma"] = float(np.mean([abs(e) <= 2 * sg for e, sg in errs]))
    return row


def evaluate(work: Path, variants: list[str], seeds: list[int], lidarcal: str,
             n_positions: int | None, overrides: dict | None = None,
             sweeps: bool = True) -> list[dict]:
    rows = []
    for var in variants:
        for seed in seeds:
            ds = work / f"{var}_s{seed}"
            t0 = time.time()
            truth = generate(ds, var, seed, sweeps=sweeps, n_positions=n_positions,
                             overrides=overrides)
            t_gen = time.time() - t0
            rc_check, out_check, t_check = run([lidarcal, "check", str(ds), "--sheet",
                                                str(work / f"{var}_s{seed}-check.png")])
            out = work / f"{var}_s{seed}_out"
            rc, out_cal, t_cal = run([lidarcal, "calibrate", str(ds), "--out", str(out),
                                      "--no-progress"])
            row = {"variant": var, "seed": seed, "gen_s": round(t_gen, 1), "check_rc": rc_check,
                   "check_s": round(t_check, 1), "calibrate_rc": rc, "calibrate_s": round(t_cal, 1)}
            if rc == 0:
                cal = json.loads((out / "calibration.json").read_text())
                row.update(compare(cal, truth))
                if truth["measurements"]:
                    row.update(measure_row(lidarcal, ds, out, truth))
            else:
                row["calibrate_out"] = out_cal.strip().splitlines()[-3:]
            row["check_out"] = [ln for ln in out_check.splitlines() if ln.strip()][:6]
            (work / f"{var}_s{seed}-log.txt").write_text(out_check + "\n----\n" + out_cal)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


