"""The benchmark scripts the README shows (``make bench``'s scripts/bench.py,
scripts/bench_stages.py, scripts/bench_trace.py) run end to end, as subprocesses, on a
small copy of the bundled dataset, and print what they promise: a documented command is a
tested command. Their numbers are timings of a shared machine, so only their presence and
consistency are checked, never their size (speed is measured by the scripts, not by tests).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from conftest import bundled_dataset

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _run(script: str, *args: str) -> str:
    p = subprocess.run([sys.executable, str(SCRIPTS / script), *args], capture_output=True,
                       text=True, timeout=600, check=False)
    assert p.returncode == 0, p.stderr
    return p.stdout


def _seconds(line: str) -> float:
    return float(line.split(":")[-1].split()[0])


def test_bench_prints_both_processes_and_their_ratio(tmp_path):
    out = _run("bench.py", str(bundled_dataset(tmp_path / "ds", n=8)), "--repeat", "1")
    rows = {line.split(":")[0].strip(): line for line in out.splitlines() if ":" in line}
    floor = _seconds(rows["(a) read-only floor (process"])
    cal = _seconds(rows["(b) lidarcal calibrate (default, joint)"])
    assert floor > 0 and cal > 0
    ratio = _seconds(rows["ratio (b)/(a)"])  # of the unrounded times; each is printed to 0.005 s
    assert abs(ratio - cal / floor) <= 0.005 + ratio * (0.005 / floor + 0.005 / cal)


def test_bench_stages_prints_every_stage(tmp_path):
    out = _run("bench_stages.py", str(bundled_dataset(tmp_path / "ds", n=8)))
    stages = {line.split()[0]: line.split()[1:] for line in out.splitlines()[2:] if line.strip()}
    for name in ("imports", "decode", "scans", "boards", "rho", "positions", "fits", "joint",
                 "write"):
        assert float(stages[name][0]) > 0, name
    assert "(8 positions)" in out.splitlines()[0]


def test_bench_trace_prints_the_phases_of_one_process(tmp_path):
    out = _run("bench_trace.py", str(bundled_dataset(tmp_path / "ds", n=8)), "--repeat", "1")
    phases = [line.split()[0] for line in out.splitlines()[2:] if line.strip()]
    for name in ("start", "imports", "rho", "positions", "joint", "written", "exit", "total"):
        assert name in phases, name
    assert phases.index("imports") < phases.index("positions") < phases.index("joint")
    assert "of 8 images" in out  # the decode thread's summary line
