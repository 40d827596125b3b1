"""Measure ``lidarcal import --views`` against the simulator's holds (one-board recordings).

For a few seeds, three recordings of a ``simulate_oneboard`` rig
(:func:`lidarcal.synthetic.oneboard_bag.write_oneboard_bag`): ``plain`` (each view held once),
``twice`` (a pause twice at one pose and returns to earlier poses: holds of one pose must
become one view) and ``drift`` (two holds slide by ``--drift-mm`` while held: no view from
them). Prints per recording: holds, still intervals, views, drifting intervals dropped,
whether every still hold gave exactly one view, whether the merges are the true ones, no view
from a drifting hold, and ``lidarcal planes`` on the views against the true LiDAR pose
(max |error| / sigma over the 3 rotation and the 3 translation components).

    .venv/bin/python scripts/bag_views_holds.py /tmp/bvh --seeds 0 1 2
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np


def planes_vs_truth(folder: Path, rig) -> tuple[float, float, int]:
    from scipy.spatial.transform import Rotation

    from lidarcal.planes import run_planes

    res = run_planes(folder, folder / "camera.json", rig.board)
    d_rot = np.degrees(Rotation.from_matrix(res.R @ rig.R.T).as_rotvec())
    r = np.abs(d_rot) / np.array(res.uncertainty.rotation_deg, float)
    t = np.abs(res.T - rig.T) / np.array(res.uncertainty.translation_mm, float)
    return float(r.max()), float(t.max()), int(sum(res.used))


def one(work: Path, name: str, seed: int, n_views: int, **kw) -> dict:
    from lidarcal.io.bag_views import import_views
    from lidarcal.synthetic.bag import bag_start_s
    from lidarcal.synthetic.oneboard import simulate_oneboard
    from lidarcal.synthetic.oneboard_bag import write_oneboard_bag

    rig = simulate_oneboard(seed, n_views)
    bag = work / f"{name}_{seed}.bag"
    if bag.exists():
        bag.unlink()
    holds = write_oneboard_bag(rig, bag, seed=seed + 10, **kw)
    out = work / f"{name}_{seed}"
    res = import_views(bag, out, overwrite=True)
    t0 = bag_start_s(bag)
    # the hold each view's interval lies in (30 ms: a scan's beam span and the log delay)
    where = [[i for i, h in enumerate(holds) if h.t_start_s - 0.03 <= v.t_start_s + t0
              and v.t_end_s + t0 <= h.t_end_s + 0.03] for v in res.views]
    still = [i for i, h in enumerate(holds) if h.drift_mm == 0]
    poses = {holds[i].index for i in still}
    # a view per pose: its interval inside a still hold of that pose, every pose once
    view_pose = [holds[w[0]].index if len(w) == 1 and w[0] in still else None for w in where]
    found = sorted(p for p in view_pose if p is not None) == sorted(poses)
    from_drift = sum(1 for w in where if any(holds[i].drift_mm for i in w))
    # how far the board slid within a view taken from a drifting hold (its interval's share)
    slid = [holds[w[0]].drift_mm * (v.t_end_s - v.t_start_s) / (holds[w[0]].t_end_s
                                                                - holds[w[0]].t_start_s)
            for v, w in zip(res.views, where) if len(w) == 1 and holds[w[0]].drift_mm]
    merged_ok = all(len({holds[i].index for i in w}) == 1 for w in where)
    n_merged = sum(len(v.intervals) - 1 for v in res.views)
    true_merges = len(still) - len(poses)
    from lidarcal.io.dataset import DatasetError

    try:
        r, t, used = planes_vs_truth(out, rig)
    except DatasetError as e:  # too few views left (a drift sweep)
        print(f"  {name} s{seed}: planes: {e}")
        r, t, used = np.nan, np.nan, 0
    return {"rec": f"{name} s{seed}", "holds": len(holds), "poses": len(poses),
            "intervals": res.n_intervals, "views": len(res.views), "merged": n_merged,
            "true_merges": true_merges, "drifting": res.n_drifting,
            "one_view_per_still_pose": found, "merges_right": merged_ok,
            "views_from_drifting_holds": from_drift,
            "slid_within_mm": round(max(slid), 2) if slid else 0.0, "planes_used": used,
            "rot_err/sigma": round(r, 2), "T_err/sigma": round(t, 2)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--drift-mm", type=float, default=3.0)
    ap.add_argument("--drift-sweep", type=float, nargs="*", default=None,
                    help="only drifting recordings, one per drift (mm per hold), first seed")
    a = ap.parse_args()
    import pandas as pd

    shutil.rmtree(a.work, ignore_errors=True)
    a.work.mkdir(parents=True)
    rows = []
    if a.drift_sweep:
        for d in a.drift_sweep:
            rows.append(one(a.work, f"drift{d:g}", a.seeds[0], 7, drift_mm=d,
                            drift_holds=[1, 3, 5]))
        print(pd.DataFrame(rows).to_string(index=False))
        return
    for s in a.seeds:
        rows.append(one(a.work, "plain", s, 7))
        rows.append(one(a.work, "twice", s, 7, order=[0, 1, 1, 2, 3, 4, 0, 5, 6, 3]))
        rows.append(one(a.work, "drift", s, 7, drift_mm=a.drift_mm, drift_holds=[1, 4]))
        print(pd.DataFrame(rows[-3:]).to_string(index=False), flush=True)
    print(pd.DataFrame(rows).to_string(index=False))


if __name__ == "__main__":
    main()
