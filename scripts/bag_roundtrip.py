"""Measure ``lidarcal import`` on recordings of an unseen simulated rig (issue 12, done-when 1).

Simulates a rig (default: seed 41, paper rig, 87 positions, disc sweeps), records it as a
ROS 1 bag with raw images and a ROS 2 bag with PNG-compressed images (scans and frames
also during the moves), imports both, calibrates the imported datasets and the original
folder, and prints the true pose errors, bag sizes and import times.

    .venv/bin/python scripts/bag_roundtrip.py /tmp/bagrt --seed 41 --rig paper
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 1e6


def errors(cal_json: Path, truth_json: Path) -> dict[str, float]:
    from lidarcal.evaluate import pose_errors
    from lidarcal.geometry import Pose

    cal = json.loads(cal_json.read_text())
    est = {int(p["index"]): Pose.from_dict(p) for p in cal["poses"]}
    df = pose_errors(est, json.loads(truth_json.read_text()))
    return {"positions": len(df), **{c: float(df[c].mean()) for c in ("centre_mm", "z_axis_deg",
                                                                       "x_axis_deg")}}


def run(cmd: list[str]) -> float:
    t = time.perf_counter()
    r = subprocess.run(cmd, check=False, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")
    for line in r.stderr.splitlines():
        print("   ", line)
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("work", type=Path)
    ap.add_argument("--seed", type=int, default=41)
    ap.add_argument("--rig", default="paper")
    ap.add_argument("--positions", type=int, default=None)
    a = ap.parse_args()
    from lidarcal.synthetic import simulate
    from lidarcal.synthetic.bag import write_bag

    w = a.work
    shutil.rmtree(w, ignore_errors=True)
    w.mkdir(parents=True)
    lc = [sys.executable, "-m", "lidarcal"]
    simulate(w / "sim", seed=a.seed, rig=a.rig, n_positions=a.positions)
    rows = {}
    run([*lc, "calibrate", str(w / "sim"), "--out", str(w / "cal_sim"), "--no-progress"])
    rows["original folder"] = errors(w / "cal_sim" / "calibration.json", w / "sim" / "truth.json")
    for name, storage, images in (("ros1_raw", "rosbag1", "raw"), ("ros2_png", "sqlite3", "png")):
        bag = w / (f"{name}.bag" if storage == "rosbag1" else name)
        t = time.perf_counter()
        write_bag(w / "sim", bag, storage=storage, images=images, rig_json=w / f"{name}_rig.json")
        t_write = time.perf_counter() - t
        t_imp = run([*lc, "import", str(bag), "--rig", str(w / f"{name}_rig.json"),
                     "--out", str(w / f"ds_{name}"), "--no-progress"])
        shutil.copy(w / "sim" / "truth.json", w / f"ds_{name}" / "truth.json")
        run([*lc, "calibrate", str(w / f"ds_{name}"), "--out", str(w / f"cal_{name}"),
             "--no-progress"])
        e = errors(w / f"cal_{name}" / "calibration.json", w / "sim" / "truth.json")
        e.update(bag_mb=size_mb(bag), write_s=t_write, import_s=t_imp)
        rows[name] = e
    n = len(json.loads((w / "sim" / "truth.json").read_text())["poses"])
    print(f"\nseed {a.seed}, rig {a.rig}, {n} positions")
    print(f"{'dataset':18s} {'found':>6s} {'centre mm':>10s} {'z deg':>8s} {'x deg':>8s} "
          f"{'bag MB':>8s} {'import s':>9s}")
    for k, e in rows.items():
        print(f"{k:18s} {e['positions']:>6d} {e['centre_mm']:10.4f} {e['z_axis_deg']:8.5f} "
              f"{e['x_axis_deg']:8.5f} {e.get('bag_mb', np.nan):8.1f} {e.get('import_s', np.nan):9.1f}")
    (w / "summary.json").write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
