"""Where ``lidarcal calibrate`` spends its time, stage by stage (issue 15, item 4).

Companion of ``scripts/bench.py`` (which times whole processes): this runs the stages of
the calibration one after the other in this process, on one core, and prints wall and CPU
seconds per stage, so the remaining gap to the read-only floor can be attributed:

  imports      ``import lidarcal.pipeline, lidarcal.joint`` as ``lidarcal calibrate`` does it
               (garbage collector paused, then frozen; a fresh process, best of 3),
               next to ``import cv2, numpy, pandas`` (the floor's own imports)
  decode       every stripe image (:func:`lidarcal.io.dataset.read_stripe_image`)
  scans        every scan (:func:`lidarcal.io.dataset.read_scan`)
  boards       both chessboards of the V in board.png (section 1.2)
  rho          the dataset's stripe reflectance ratio (5 images)
  positions    section 1 at every position (stripe, scan lines, pose), per position too,
               on the images of "decode" (as calibrate's workers on its prefetched images)
  fits         the paper's and the rigid pose functions (section 2)
  joint        the joint fit (:func:`lidarcal.joint.fit_joint`)
  write        calibration.json (with the dataset hash)

``lidarcal calibrate`` overlaps decode with imports and boards (a background thread) and
runs the positions in two worker processes: its wall time is about imports + boards +
positions / 2 + fits + joint + write on an idle 2-core machine. A benchmark, never a test.

Where the wall time of one whole ``lidarcal calibrate`` process goes (interpreter start,
each import, the decode thread, the fork, the workers, the teardown at exit), as it runs:
``scripts/bench_trace.py DATASET`` (it sets ``LIDARCAL_TRACE=1``, with which the process,
its threads and its workers print phase marks to stderr, :mod:`lidarcal.trace`).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _import_seconds(stmt: str, repeat: int = 3) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", stmt], check=True)
        best = min(best, time.perf_counter() - t0)
    return best


class _Decoded:
    """Decoded stripe images by position index, served like an ``ImagePrefetch``."""

    def __init__(self, images: dict) -> None:
        self.images = images

    def get(self, pos):
        return self.images.get(pos.index)


class _Clock:
    def __init__(self) -> None:
        self.rows: list[tuple[str, float, float]] = []

    def stage(self, name: str, fn, *args, **kw):
        w0, c0 = time.perf_counter(), time.process_time()
        out = fn(*args, **kw)
        self.rows.append((name, time.perf_counter() - w0, time.process_time() - c0))
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    t_floor_imp = _import_seconds("import cv2, numpy, pandas")
    t_imp = _import_seconds("import gc; gc.disable(); import lidarcal.pipeline, lidarcal.joint; "
                            "gc.freeze(); gc.enable()")  # as lidarcal.cli imports them

    from lidarcal import pipeline as P
    from lidarcal.cli import _reuse_freed_memory
    from lidarcal.io.dataset import load_dataset, read_scan, read_stripe_image
    from lidarcal.joint import fit_joint
    from lidarcal.turntable import fit_paper, fit_rigid

    _reuse_freed_memory()  # glibc's allocator as in the command's process

    clk = _Clock()
    ds = load_dataset(a.dataset)
    camera, _ = P.camera_for(ds)
    decoded = clk.stage("decode", lambda: {p.index: read_stripe_image(p.stripe_image,
                                                                      ds.image_size,
                                                                      ds.lidar.laser_colour)
                                           for p in ds.positions})
    # the positions use the decoded images, as calibrate's workers use its prefetched ones
    P._WORKER["images"] = _Decoded(decoded)
    clk.stage("scans", lambda: [read_scan(p.scan, ds.lidar) for p in ds.positions])
    boards = clk.stage("boards", P.find_boards, ds, camera)
    rho = clk.stage("rho", P.dataset_reflectance_ratio, camera, boards, ds.positions)
    results = clk.stage("positions", lambda: [P.solve_position(p, camera, boards, ds.lidar, rho)
                                              for p in ds.positions])
    psi = [r.psi_deg for r in results]
    samples = [r.pose for r in results]

    def fits():
        paper = fit_paper(psi, samples)
        return paper, fit_rigid(psi, samples, init=paper)

    paper, rigid = clk.stage("fits", fits)
    res = P.CalibrationResult(ds, camera, None, boards, results, [], paper, rigid, "joint")
    res.joint_model = clk.stage("joint", fit_joint, res)
    with tempfile.TemporaryDirectory() as out:
        clk.stage("write", P.write_calibration, res, out)

    n = len(ds.positions)
    print(f"dataset: {a.dataset} ({n} positions); load average {load0:.1f} at the start, "
          f"{os.getloadavg()[0]:.1f} at the end; one core, stages in sequence")
    print(f"{'stage':12s} {'wall s':>8s} {'cpu s':>8s}")
    print(f"{'imports':12s} {t_imp:8.3f} {'':>8s}  (process; the floor's imports: {t_floor_imp:.3f})")
    for name, w, c in clk.rows:
        extra = f"  ({1000 * c / n:.1f} ms cpu per position)" if name == "positions" else ""
        print(f"{name:12s} {w:8.3f} {c:8.3f}{extra}")


if __name__ == "__main__":
    main()
