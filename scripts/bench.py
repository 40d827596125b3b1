"""Benchmark: the calibration versus only reading its inputs (issue: speed).

Times, in one run, (a) decoding every stripe image and reading every scan of a
dataset (in this process, after the imports) and (b) ``lidarcal calibrate`` on it
(a subprocess, as a user runs it: interpreter start, imports, board detection,
every position, the pose functions, the JSON), then prints both and their ratio;
(b) for the default method (joint fit) and for ``--method rigid`` (no joint fit).
A benchmark, never a unit test.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from lidarcal.dataset import load_dataset, read_scan, read_stripe_image


def read_only(root: Path) -> float:
    t0 = time.perf_counter()
    ds = load_dataset(root)
    for p in ds.positions:
        read_stripe_image(p.stripe_image)
        read_scan(p.scan, ds.lidar)
    return time.perf_counter() - t0


def calibrate(root: Path, *extra: str) -> float:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "lidarcal.cli", "calibrate", str(root), "--out", out,
                        "--no-progress", *extra], check=True, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL)
        return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs")
    a = ap.parse_args()
    n = len(load_dataset(a.dataset).positions)
    t_read = min(read_only(a.dataset) for _ in range(a.repeat))
    t_cal = min(calibrate(a.dataset) for _ in range(a.repeat))
    t_rigid = min(calibrate(a.dataset, "--method", "rigid") for _ in range(a.repeat))
    print(f"dataset: {a.dataset} ({n} positions)")
    print(f"(a) decode stripe images + read scans:     {t_read:6.2f} s")
    print(f"(b) lidarcal calibrate (default, joint):   {t_cal:6.2f} s")
    print(f"(b') lidarcal calibrate --method rigid:    {t_rigid:6.2f} s")
    print(f"ratio (b)/(a):                             {t_cal / t_read:6.2f}")
    print(f"ratio (b')/(a):                            {t_rigid / t_read:6.2f}")


if __name__ == "__main__":
    main()
