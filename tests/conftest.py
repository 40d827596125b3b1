"""Shared fixtures: small simulated datasets (made once per test session and worker)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from lidarcal.synthetic import simulate

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "data" / "paper_rig"


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """Paper rig, 4 positions, no intrinsics views, no sweeps (read-only: copy before editing)."""
    out = tmp_path_factory.mktemp("sim") / "paper4"
    return simulate(out, seed=11, rig="paper", n_positions=4, with_intrinsics=False,
                    with_sweeps=False)


@pytest.fixture
def dataset_copy(small_dataset, tmp_path) -> Path:
    """A private, editable copy of :func:`small_dataset`."""
    dst = tmp_path / "ds"
    shutil.copytree(small_dataset, dst)
    return dst
