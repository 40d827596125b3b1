"""The simulator's LiDAR ranging errors: zero offset, dark-square bias, range quantisation."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import BUNDLED

from lidarcal.synthetic import RIGS, make_truth, simulate_scans
from lidarcal.synthetic.lidar import beam_materials
from lidarcal.synthetic.scene import BLACK, WALL, WHITE
from lidarcal.synthetic.truth import STREAM_SCAN, _rng


def _scans(seed: int, rig: str = "paper", n: int = 3, **ranging):
    """Ranges (n, B) of the first n positions with and without the ranging errors (same noise)."""
    t = make_truth(seed, rig, with_discs=False, with_intrinsics=False)
    R, T = t.poses_at(t.psi_true_deg[:n])
    base = simulate_scans(t.surfaces, R, T, t.rig, _rng(seed, STREAM_SCAN, 0))
    err = simulate_scans(t.surfaces, R, T, t.rig.with_(**ranging), _rng(seed, STREAM_SCAN, 0))
    return t, R, T, base, err


def test_defaults_are_off_and_truth_has_no_ranging_block(small_dataset: Path) -> None:
    for rig in RIGS.values():
        assert (rig.range_offset_mm, rig.dark_extra_mm, rig.range_quantum_mm) == (0.0, 0.0, 0.0)
    assert "ranging" not in json.loads((small_dataset / "truth.json").read_text())
    if (BUNDLED / "truth.json").is_file():  # the bundled dataset was made without them
        assert "ranging" not in json.loads((BUNDLED / "truth.json").read_text())


@pytest.mark.parametrize("seed", [3, 8])
def test_offset_shifts_every_return_by_exactly_the_offset(seed: int) -> None:
    _, _, _, base, err = _scans(seed, range_offset_mm=8.0)
    both = (base > 0) & (err > 0)
    assert both.sum() > 0.9 * (base > 0).sum()
    d = err[both] - base[both]
    # both written to 0.1 mm: the same noise draw rounds to the same tenth, or one tenth apart
    assert np.all(np.abs(d - 8.0) <= 0.1 + 1e-9)
    assert np.mean(np.abs(d - 8.0) < 1e-6) > 0.99


@pytest.mark.parametrize("seed,rig", [(3, "paper"), (2, "wide")])
def test_dark_returns_read_dark_extra_farther(seed: int, rig: str) -> None:
    t, R, T, base, err = _scans(seed, rig, dark_extra_mm=6.0)
    mat = beam_materials(t.surfaces, R, T, t.rig)
    both = (base > 0) & (err > 0)
    d = np.where(both, err - base, np.nan)
    # a beam whose neighbours' centres hit the same material lies wholly on it (footprint <
    # 2 beam spacings); one straddling a square edge reads between 0 and dark_extra
    same = np.zeros_like(mat, bool)
    same[:, 1:-1] = (mat[:, :-2] == mat[:, 1:-1]) & (mat[:, 2:] == mat[:, 1:-1])
    black, white = both & same & (mat == BLACK), both & same & (mat == WHITE)
    assert black.sum() > 100 and white.sum() > 100
    assert np.median(d[black]) == pytest.approx(6.0, abs=1e-6)
    assert np.median(d[white]) == pytest.approx(0.0, abs=1e-6)
    board = both & np.isin(mat, [BLACK, WHITE])
    assert np.all((d[board] >= -0.1 - 1e-9) & (d[board] <= 6.1 + 1e-9))
    wall = both & same & (mat == WALL)
    assert wall.sum() > 0 and np.all(np.abs(d[wall]) <= 0.1 + 1e-9)


def test_quantised_ranges_are_multiples_of_the_quantum() -> None:
    _, _, _, base, err = _scans(4, range_quantum_mm=1.0)
    v = err > 0
    assert np.all(err[v] == np.round(err[v]))
    both = v & (base > 0)
    assert np.all(np.abs(err[both] - base[both]) <= 0.5 + 0.05 + 1e-9)


def test_cli_flags_are_recorded_in_truth(tmp_path: Path) -> None:
    out = tmp_path / "sim"
    cmd = [sys.executable, "-m", "lidarcal", "simulate", str(out), "--seed", "5", "--positions", "3",
           "--no-sweeps", "--no-intrinsics", "--range-offset-mm", "8", "--dark-extra-mm", "6", "--range-quantum-mm", "1"]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert p.returncode == 0, p.stderr
    truth = json.loads((out / "truth.json").read_text())
    assert truth["ranging"] == {"offset_mm": 8.0, "dark_extra_mm": 6.0, "quantum_mm": 1.0}
    ranges = np.loadtxt(out / "scans" / "0001.csv", delimiter=",", skiprows=1)[:, 1]
    assert (ranges > 0).sum() > 100 and np.all(ranges == np.round(ranges))
    # the rig description handed to calibrate does not leak the truth
    assert "ranging" not in json.dumps(json.loads((out / "dataset.json").read_text()))


def test_cli_rejects_a_negative_quantum(tmp_path: Path) -> None:
    cmd = [sys.executable, "-m", "lidarcal", "simulate", str(tmp_path / "x"), "--range-quantum-mm", "-1"]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert p.returncode == 2 and "--range-quantum-mm" in p.stderr and ">= 0" in p.stderr
    assert not (tmp_path / "x").exists()
