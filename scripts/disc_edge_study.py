"""Disc diameters with and without a reference disc, on simulated sweeps (true poses).

For each rig preset, footprint model and seed, discs of the given diameters
are swept by the simulator (lidarcal.synthetic; sweeps only, no images) and
measured with the true pose function as :func:`lidarcal.disc.measure_dataset`
does (Lambertian energy ratio, edge spacing = beam spacing x rim stretch).
Mode "prior": no reference, every disc; mode "reference": every disc in turn
calibrates the edge model, applied to each other disc of the same rig (one
row per (rig, reference, target) triple). ``--before`` measures as before the
pose terms (symmetric footprint, rim stretch 1). Prints a summary (mean
|error|, mean sigma, 2-sigma coverage) per mode, rig and footprint.
Usage: python scripts/disc_edge_study.py [--rigs paper wide harsh] [--seeds 1 2 3]
[--diameters 100 140 200 100 140 200] [--before] [--csv OUT]
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from lidarcal.disc import (
    EdgeModel,
    beam_spacing_mm,
    edge_footprint,
    fit_edge_model,
    mixed_share,
    random_sigma_mm,
)
from lidarcal.io.dataset import LidarSpec
from lidarcal.measure import measure_disc
from lidarcal.synthetic.config import get_rig
from lidarcal.synthetic.lidar import beam_angles_deg, simulate_scans
from lidarcal.synthetic.truth import STREAM_SWEEP, _rng, make_truth


def half_share(rig_name: str, footprint: str, seed: int, diameters=(100.0, 140.0, 200.0),
               before: bool = False) -> list[dict]:
    """Half-share diameter, fit sigma, beam spacing and rim stretch of each disc of one rig."""
    rig = get_rig(rig_name).with_(footprint_model=footprint, disc_diameters_mm=tuple(diameters),
                                  n_discs=len(diameters))
    truth = make_truth(seed, rig, with_intrinsics=False)
    lidar = LidarSpec(rig.lidar_angle_min_deg, rig.lidar_angle_max_deg, rig.lidar_angle_step_deg,
                      rig.lidar_range_min_mm, rig.lidar_range_max_mm)
    angles = beam_angles_deg(rig)
    rows = []
    for j, d in enumerate(truth.discs):
        R, T = truth.poses_at(d.psi_true_deg)
        r = simulate_scans(d.surfaces, R, T, rig, _rng(seed, STREAM_SWEEP, j))
        P, B = r.shape
        sweep = pd.DataFrame({"psi_deg": np.repeat(d.psi_deg, B), "angle_deg": np.tile(angles, P),
                              "range_mm": np.where(r > 0, r, np.nan).ravel()})
        m = measure_disc(sweep, truth, lidar, footprint=None if before else edge_footprint())
        origin = truth.pose_at(float(np.median(d.psi_deg))).T
        u = beam_spacing_mm(m.center_mm, origin, rig.lidar_angle_step_deg)
        s = 1.0 if before else m.info["rim_stretch"]
        rows.append({"rig": rig_name, "footprint": footprint, "seed": seed, "disc": d.name,
                     "true_mm": 2 * d.disc.radius, "half_mm": m.diameter_mm,
                     "fit_sigma_mm": max(m.diameter_std_mm, random_sigma_mm(m)),
                     "mixed_share": mixed_share(m.info), "u_mm": u, "stretch": s, "us_mm": u * s,
                     "spot_u": m.info.get("spot_sigma_mm", np.nan) / u})
    return rows


def evaluate(rows: list[dict]) -> list[dict]:
    """Prior mode for every disc; reference mode for every (reference, target) pair of one rig."""
    out = []
    prior = EdgeModel.prior(float(np.median([r["mixed_share"] for r in rows])))
    for r in rows:
        d, s = prior.for_disc(r["spot_u"]).apply(r["half_mm"], r["fit_sigma_mm"], r["us_mm"])  # wide spot
        out.append({**r, "mode": "prior", "reference": "", "err_mm": d - r["true_mm"], "sigma_mm": s})
    for ref in rows:
        edge = fit_edge_model([ref["disc"]], *(np.array([ref[k]]) for k in
                                               ("half_mm", "fit_sigma_mm", "us_mm", "true_mm")))
        for r in rows:
            if r is ref:
                continue
            d, s = edge.apply(r["half_mm"], r["fit_sigma_mm"], r["us_mm"])
            out.append({**r, "mode": "reference", "reference": ref["disc"], "err_mm": d - r["true_mm"],
                        "sigma_mm": s})
    for o in out:
        o["covered"] = abs(o["err_mm"]) <= 2 * o["sigma_mm"]
    return out


def summary(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    g = df.groupby(by)
    return pd.DataFrame({"n": g.size(), "mean_abs_err_mm": g["err_mm"].apply(lambda e: e.abs().mean()),
                         "mean_sigma_mm": g["sigma_mm"].mean(), "coverage_2sigma": g["covered"].mean()})


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rigs", nargs="+", default=["paper", "wide", "harsh"])
    ap.add_argument("--footprints", nargs="+", default=["gaussian", "first-echo"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--diameters", type=float, nargs="+", default=[100.0, 140.0, 200.0, 100.0, 140.0, 200.0])
    ap.add_argument("--before", action="store_true", help="symmetric footprint, rim stretch 1")
    ap.add_argument("--csv", default=None)
    a = ap.parse_args()
    res = []
    for rig in a.rigs:
        for fp in a.footprints:
            for seed in a.seeds:
                res += evaluate(half_share(rig, fp, seed, tuple(a.diameters), a.before))
    df = pd.DataFrame(res)
    if a.csv:
        df.to_csv(a.csv, index=False)
    pd.set_option("display.width", 200)
    print(summary(df, ["mode", "rig", "footprint"]).round(3).to_string())
    print(summary(df, ["mode"]).round(3).to_string())


if __name__ == "__main__":
    main()
