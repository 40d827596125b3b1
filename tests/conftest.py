"""Shared fixtures: small simulated datasets (made once per test session and worker)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from lidarcal.synthetic import simulate

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "data" / "paper_rig"
OPENCV_LEFT = REPO / "tests" / "data" / "opencv_left"


@pytest.fixture(scope="session")
def small_dataset(tmp_path_factory) -> Path:
    """Paper rig, 4 positions, no intrinsics views, no sweeps (read-only: copy before editing)."""
    out = tmp_path_factory.mktemp("sim") / "paper4"
    return simulate(out, seed=11, rig="paper", n_positions=4, with_intrinsics=False,
                    with_sweeps=False)


@pytest.fixture(scope="session")
def opencv_photos() -> list[Path]:
    """OpenCV's sample chessboard photos (left*.jpg, 9x6; tests/data/opencv_left/README.md)."""
    paths = sorted(OPENCV_LEFT.glob("left*.jpg"))
    assert len(paths) >= 10, "OpenCV's sample photos belong in tests/data/opencv_left"
    return paths


@pytest.fixture
def dataset_copy(small_dataset, tmp_path) -> Path:
    """A private, editable copy of :func:`small_dataset`."""
    dst = tmp_path / "ds"
    shutil.copytree(small_dataset, dst)
    return dst


def bundled_dataset(dst: Path, n: int | None = None, copy: tuple[str, ...] = (),
                    link: tuple[str, ...] = ("board.png",)) -> Path:
    """The bundled dataset in ``dst``: its own dataset.json and positions.csv (the first ``n``
    positions, or all), the entries in ``copy`` copied (to break them), those in ``link``
    linked, and the stripe images and scans referenced by absolute path (not copied)."""
    dst.mkdir()
    shutil.copy(BUNDLED / "dataset.json", dst / "dataset.json")
    for name in copy:
        shutil.copy(BUNDLED / name, dst / name)
    for name in link:
        (dst / name).symlink_to(BUNDLED / name)
    rows = (BUNDLED / "positions.csv").read_text().splitlines()
    rows = rows if n is None else rows[: n + 1]
    out = [rows[0]]
    for r in rows[1:]:
        i, psi, img, scan = r.split(",")
        out.append(",".join([i, psi, str(BUNDLED / img), str(BUNDLED / scan)]))
    (dst / "positions.csv").write_text("\n".join(out) + "\n")
    return dst


@pytest.fixture
def cli(capfd, tmp_path, monkeypatch):
    """``lidarcal ARGS`` run by :func:`lidarcal.cli.main` in this process (the imports paid
    once for the whole matrix), its file descriptors 1 and 2 captured (so whatever OpenCV or
    libjpeg print there is seen too), in ``tmp_path``; a :class:`subprocess.CompletedProcess`."""
    from lidarcal.cli import main

    monkeypatch.chdir(tmp_path)

    def run(*args) -> subprocess.CompletedProcess:
        capfd.readouterr()
        try:
            code = main([str(a) for a in args])
        except SystemExit as e:  # argparse
            code = e.code
        out, err = capfd.readouterr()
        return subprocess.CompletedProcess(args, code, out, err)
    return run
