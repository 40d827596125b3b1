"""Where the wall time of one ``lidarcal calibrate`` process goes, phase by phase (issue 15).

Runs ``python -m lidarcal.cli calibrate DATASET --out TMP --no-progress`` as a user does,
with ``LIDARCAL_TRACE=1`` (:mod:`lidarcal.trace`: the process, its decode thread and its
forked workers print phase marks with the wall clock, ``CLOCK_MONOTONIC``, shared by all
processes, and their CPU seconds), and prints one row per phase of the main thread:

  start     seconds since this script spawned the process
  wall      the phase's wall seconds
  cpu       CPU seconds spent in it by every thread and process of the run (the main
            thread, the decode thread, the workers; worker CPU interpolated between marks)
  cores     cpu / wall: 1.0 = one core busy, 2.0 = both; under 1 the critical path waits
            (on the disk, on the other processes sharing the machine, or on a worker)
  faults    minor page faults of the main process in it (memory touched for the first
            time: about 1-2 us of kernel CPU each, in "cpu")

The first row (spawn to the first mark) is the interpreter's start and ``lidarcal/__init__``;
"atexit" to "exit" is the interpreter's teardown after the last atexit handler; "main-end"
to "atexit" the pool's and the threads' shutdown. The decode thread and the workers are
summarised below the table. Best of ``--repeat`` runs (the run with the least wall time);
the machine may be shared: read "cores" and the load average printed with it. A
benchmark, never a test.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

PHASES = {  # the main thread's mark -> what ran since the previous one
    "start": "interpreter start, site, lidarcal/__init__",
    "numpy": "import numpy (one OpenBLAS thread)",
    "cli": "import lidarcal.io.dataset (cv2)",
    "args": "argparse",
    "dataset": "load_dataset",
    "early-boards": "both chessboards of the V (board.png, stored camera) while scipy imports "
                    "in a thread; decode thread starts",
    "imports": "import lidarcal.pipeline (scipy; the rest of it after the early boards)",
    "camera": "camera (dataset.json or intrinsics/)",
    "boards": "both chessboards of the V (board.png) when not found early",
    "rho": "stripe reflectance ratio (5 images)",
    "decode-stopped": "decode thread stopped and joined",
    "positions": "pool fork + every position (2 workers)",
    "pool-released": "pool shutdown(wait=False)",
    "fits": "paper and rigid pose functions",
    "joint-import": "import lidarcal.joint",
    "joint": "the joint fit",
    "calibrated": "leave calibrate (prefetch closed)",
    "hash-start": "calibration.json dict (poses, sigma)",
    "hash": "dataset hash (SHA-256 of every file)",
    "calibration-dict": "dict rest",
    "written": "json dump + atomic write",
    "main-end": "summary printed, main returns",
    "atexit": "pool and thread shutdown, atexit handlers",
    "exit": "interpreter teardown until the process is reaped",
}


@dataclass
class Mark:
    phase: str
    pid: int
    thread: str
    wall: float
    cpu: float
    tcpu: float
    info: dict = field(default_factory=dict)


def parse(stderr: str) -> list[Mark]:
    """The ``lidarcal-trace`` lines of a run's stderr."""
    out = []
    for line in stderr.splitlines():
        if not line.startswith("lidarcal-trace "):
            continue
        _, phase, *kv = line.split()
        d = dict(x.split("=", 1) for x in kv)
        out.append(Mark(phase, int(d.pop("pid")), d.pop("thread"), float(d.pop("wall")),
                        float(d.pop("cpu")), float(d.pop("tcpu")), d))
    return out


@dataclass
class Run:
    t_spawn: float
    t_exit: float
    cpu_total: float  # user + system of the process and its workers (rusage)
    marks: list[Mark]

    @property
    def parent(self) -> int:
        return self.marks[0].pid

    def cpu_at(self, t: float) -> float:
        """CPU seconds of every process of the run up to wall time ``t``: each process's
        marks interpolated (0 before its first mark, its last value after)."""
        total = 0.0
        for pid in {m.pid for m in self.marks}:
            ms = sorted((m for m in self.marks if m.pid == pid), key=lambda m: m.wall)
            walls = [m.wall for m in ms]
            cpus = [m.cpu for m in ms]
            if pid == self.parent:  # the process starts at spawn with no CPU
                walls, cpus = [self.t_spawn, *walls], [0.0, *cpus]
            else:  # a forked worker's clock starts at the fork, just before its first mark
                walls, cpus = [walls[0] - cpus[0], *walls], [0.0, *cpus]
            total += float(np.interp(t, walls, cpus, left=0.0, right=cpus[-1]))
        return total

    def phases(self) -> list[tuple[str, float, float, float, int]]:
        """(phase, start since spawn, wall, cpu, main process's page faults) of the main
        thread's phases; the last one ends when the process is reaped and takes the rest of
        the rusage CPU."""
        main = [m for m in self.marks if m.pid == self.parent and m.thread == "MainThread"]
        rows, t0, c0, f0 = [], self.t_spawn, 0.0, 0
        for m in main:
            c, f = self.cpu_at(m.wall), int(m.info["minflt"])
            rows.append((m.phase, t0 - self.t_spawn, m.wall - t0, c - c0, f - f0))
            t0, c0, f0 = m.wall, c, f
        rows.append(("exit", t0 - self.t_spawn, self.t_exit - t0, self.cpu_total - c0, 0))
        return rows

    def worker_exit_cpu(self) -> float | None:
        """CPU seconds the workers spent after their last mark (their exit), from the
        children's rusage the process reports at its last atexit handler."""
        last = next((m for m in self.marks if m.phase == "atexit"), None)
        if last is None or "children_cpu" not in last.info:
            return None
        seen = sum(max(m.cpu for m in self.marks if m.pid == pid)
                   for pid in {m.pid for m in self.marks} - {self.parent})
        return float(last.info["children_cpu"]) - seen


def run_once(dataset: Path, extra: list[str]) -> Run:
    env = {**os.environ, "LIDARCAL_TRACE": "1"}
    with tempfile.TemporaryDirectory() as out:
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-m", "lidarcal.cli", "calibrate", str(dataset),
                            "--out", out, "--no-progress", *extra], env=env,
                           capture_output=True, text=True, check=False)
        t1 = time.perf_counter()
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit(f"calibrate failed ({p.returncode}):\n{p.stderr}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return Run(t0, t1, cpu, parse(p.stderr))


def report(run: Run, runs: list[Run]) -> None:
    rows = run.phases()
    best = {}  # per phase, the least wall and CPU over all runs
    for r in runs:
        for name, _, w, c, _ in r.phases():
            bw, bc = best.get(name, (np.inf, np.inf))
            best[name] = (min(bw, w), min(bc, c))
    print(f"{'phase':16s} {'start':>6s} {'wall':>6s} {'cpu':>6s} {'cores':>5s} {'faults':>6s} "
          f"{'min wall':>8s} {'min cpu':>7s}  what ran")
    for name, start, w, c, f in rows:
        print(f"{name:16s} {start:6.3f} {w:6.3f} {c:6.3f} {c / max(w, 1e-9):5.2f} {f:6d} "
              f"{best[name][0]:8.3f} {best[name][1]:7.3f}  {PHASES.get(name, '')}")
    wall = run.t_exit - run.t_spawn
    print(f"{'total':16s} {'':6s} {wall:6.3f} {run.cpu_total:6.3f} "
          f"{run.cpu_total / wall:5.2f} {sum(r[4] for r in rows):6d}")
    dec = [m for m in run.marks if m.thread == "lidarcal-prefetch"]
    if dec:
        start = next(m for m in dec if m.phase == "decode-start")
        end = next((m for m in dec if m.phase == "decode-end"), None)
        if end is not None:
            print(f"decode thread: {start.wall - run.t_spawn:.3f}-{end.wall - run.t_spawn:.3f} s, "
                  f"{end.tcpu - start.tcpu:.3f} s CPU, {end.info.get('decoded')} of "
                  f"{end.info.get('of')} images")
    for pid in sorted({m.pid for m in run.marks} - {run.parent}):
        ms = [m for m in run.marks if m.pid == pid]
        tasks = [m for m in ms if m.phase == "task"]
        init = next(m for m in ms if m.phase == "worker-init")
        last = tasks[-1] if tasks else init
        print(f"worker {pid}: forked {init.wall - run.t_spawn:.3f} s, {len(tasks)} positions, "
              f"last done {last.wall - run.t_spawn:.3f} s, {last.cpu:.3f} s CPU, "
              f"{last.info['minflt']} page faults")
    wx = run.worker_exit_cpu()
    if wx is not None:
        print(f"workers after their last position (exit): {wx:.3f} s CPU, in the rows where "
              "they ran")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--repeat", type=int, default=3, help="best of N runs")
    ap.add_argument("extra", nargs="*", help="more calibrate options (after --)")
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    runs = [run_once(a.dataset, a.extra) for _ in range(a.repeat)]
    best = min(runs, key=lambda r: r.t_exit - r.t_spawn)
    print(f"dataset: {a.dataset}; {os.cpu_count()} cores, load average {load0:.1f} at the "
          f"start, {os.getloadavg()[0]:.1f} at the end; the fastest of {a.repeat} runs "
          "(min: per phase over all runs)")
    report(best, runs)


if __name__ == "__main__":
    main()
