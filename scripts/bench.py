"""Benchmark: the calibration versus only reading its inputs, both as whole processes (issue 15).

Times, in one run, best of ``--repeat``:

(a) the read-only floor: a fresh process that imports cv2, numpy and pandas,
    decodes ``board.png`` and every stripe image (``cv2.imread``) and reads every
    scan (``pandas.read_csv``): what any tool must at least spend on the dataset;
(b) ``lidarcal calibrate`` on it as a user runs it (a fresh process: interpreter
    start, imports, board detection, every position, the pose functions, the
    joint fit, the JSON), for the default method (joint fit) and ``--method rigid``;

and prints both, their ratio and the machine's load average (the machine may be
shared: compare the ratio, measured in the same run). A benchmark, never a unit test.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FLOOR = """
import sys
from pathlib import Path
import cv2, numpy, pandas
root = Path(sys.argv[1])
pos = pandas.read_csv(root / "positions.csv")
assert cv2.imread(str(root / "board.png"), cv2.IMREAD_UNCHANGED) is not None
for img, scan in zip(pos["stripe_image"], pos["scan"]):
    assert cv2.imread(str(root / img), cv2.IMREAD_UNCHANGED) is not None
    pandas.read_csv(root / scan)
"""


def _run(cmd: list[str]) -> float:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def read_only(root: Path) -> float:
    """(a): the whole-process read-only floor, seconds."""
    return _run([sys.executable, "-c", FLOOR, str(root)])


def calibrate(root: Path, *extra: str) -> float:
    """(b): ``lidarcal calibrate`` as a whole process, seconds."""
    with tempfile.TemporaryDirectory() as out:
        return _run([sys.executable, "-m", "lidarcal.cli", "calibrate", str(root), "--out", out,
                     "--no-progress", *extra])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs")
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    t_read, t_cal, t_rigid = [], [], []
    for _ in range(a.repeat):  # interleaved: a load change hits all three alike
        t_read.append(read_only(a.dataset))
        t_cal.append(calibrate(a.dataset))
        t_rigid.append(calibrate(a.dataset, "--method", "rigid"))
    n = len((a.dataset / "positions.csv").read_text().splitlines()) - 1
    r, c, g = min(t_read), min(t_cal), min(t_rigid)
    print(f"dataset: {a.dataset} ({n} positions); {os.cpu_count()} cores, load average "
          f"{load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end")
    print(f"(a) read-only floor (process: imports, board.png, stripes, scans): {r:6.2f} s")
    print(f"(b) lidarcal calibrate (default, joint):                           {c:6.2f} s")
    print(f"(b') lidarcal calibrate --method rigid:                            {g:6.2f} s")
    print(f"ratio (b)/(a):                                                     {c / r:6.2f}")
    print(f"ratio (b')/(a):                                                    {g / r:6.2f}")


if __name__ == "__main__":
    main()
