"""The kit of the corrupted-input tests (tests/test_corrupt_inputs.py, tests/test_corrupt_photos.py):
running a command, breaking a file, the working inputs to copy, and the case registry.

Every refused case must give one line ``error: FILE: what is wrong; what to do``, exit 2, no
traceback, nothing half-written (:func:`refused`).
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import BUNDLED, OPENCV_LEFT, REPO

CAL = REPO / "reports" / "calibration" / "calibration.json"
TAPAS = REPO / "data" / "real_tapas"
ROOT = os.geteuid() == 0 if hasattr(os, "geteuid") else False


def lidarcal(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """``python -m lidarcal ARGS`` in a subprocess."""
    return subprocess.run([sys.executable, "-m", "lidarcal", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, timeout=600, check=False)


def snapshot(path: Path):
    """What is at ``path``: None, a file's bytes or a folder's {name: bytes} (recursively)."""
    if path.is_symlink() and not path.exists():
        return "dangling"
    if not path.exists():
        return None
    if path.is_file():
        return path.read_bytes()
    return {str(p.relative_to(path)): (p.read_bytes() if p.is_file() else "dir")
            for p in sorted(path.rglob("*"))}


def assert_refused(p: subprocess.CompletedProcess, named: str) -> str:
    """Exit 2, stderr exactly one line ``error: FILE: what; what to do`` whose FILE ends with
    ``named``, no traceback, nothing on stdout."""
    lines = p.stderr.splitlines()
    assert p.returncode == 2, (p.returncode, p.stderr, p.stdout)
    assert len(lines) == 1, p.stderr
    line = lines[0]
    assert line.startswith("error: ") and "Traceback" not in p.stderr, line
    assert "unexpected" not in line, line  # a bug, not a diagnosis
    file, _, problem = line[len("error: "):].partition(": ")
    assert file.rstrip("/").endswith(named), (named, line)
    assert ";" in problem, line  # what is wrong; what to do
    assert p.stdout == "", p.stdout
    return line


def assert_accepted(p: subprocess.CompletedProcess, warned: str | None = None) -> None:
    """Exit 0; with ``warned``, exactly one warning line naming that file (and no error)."""
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr and "error:" not in p.stderr, p.stderr
    if warned is not None:
        hits = [ln for ln in p.stderr.splitlines() if ln.startswith("warning: ") and warned in ln]
        assert len(hits) == 1, p.stderr


# --- breaking files ----------------------------------------------------------------------------

def _img(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def _write_img(path: Path, img: np.ndarray) -> None:
    path.unlink()  # a linked file is replaced, never written through
    assert cv2.imwrite(str(path), img)


def break_file(path: Path, how: str) -> None:
    """Break ``path`` one way (a file of any kind)."""
    data = path.read_bytes() if path.is_file() else b""
    if path.is_symlink() or path.exists():
        path.unlink()
    if how == "missing":
        return
    if how == "empty":
        path.write_bytes(b"")
    elif how == "truncated":
        path.write_bytes(data[: len(data) // 3])
    elif how == "folder":  # a folder where the file should be (as unreadable as it gets)
        path.mkdir()
    elif how == "text":
        path.write_text("this is not what you think it is\n")
    elif how == "binary":
        path.write_bytes(bytes(range(256)) * 4)
    elif how == "unreadable":
        path.write_bytes(data)
        path.chmod(0)
    else:
        raise AssertionError(how)


def break_image(path: Path, how: str) -> None:
    img = _img(path)
    if how == "wrong size":
        _write_img(path, cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))
    elif how == "16-bit":
        _write_img(path, img.astype(np.uint16) * 16)  # 12-bit counts, not scaled to 16 bits
    elif how == "float":
        base = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        path.unlink()
        # a 32-bit float image under a .png name (OpenCV writes it as TIFF when asked)
        ok, buf = cv2.imencode(".tiff", base.astype(np.float32) / 255)
        assert ok
        path.write_bytes(buf.tobytes())
    elif how == "truncated jpeg":
        ok, buf = cv2.imencode(".jpg", img)
        assert ok
        path.unlink()
        path.write_bytes(buf.tobytes()[: len(buf) // 2])
    else:
        break_file(path, how)


def edit_csv(path: Path, fn: Callable[[list[str]], list[str]], newline: str = "\n",
             encoding: str = "utf-8") -> None:
    lines = path.read_text().splitlines()
    if path.is_symlink():
        path.unlink()
    path.write_bytes((newline.join(fn(lines)) + newline).encode(encoding))


def break_scan(path: Path, how: str) -> None:
    """A scan CSV ``angle_deg,range_mm``."""
    def cell(lines, row, col, value):
        f = lines[row].split(",")
        f[col] = value
        lines[row] = ",".join(f)
        return lines

    if how == "wrong header":
        edit_csv(path, lambda ls: ["theta,r"] + ls[1:])
    elif how == "missing column":
        edit_csv(path, lambda ls: [ln.split(",")[0] for ln in ls])
    elif how == "non-numeric":
        edit_csv(path, lambda ls: cell(ls, 5, 1, "12.3.4"))
    elif how == "negative range":
        edit_csv(path, lambda ls: cell(ls, 5, 1, "-250"))
    elif how == "descending angles":
        edit_csv(path, lambda ls: [ls[0]] + ls[1:][::-1])
    elif how == "duplicate angle":
        edit_csv(path, lambda ls: ls[:6] + [ls[5]] + ls[6:])
    elif how == "metres":
        edit_csv(path, lambda ls: [ls[0]] + [
            f"{a},{float(r) / 1000:.6f}" if r.strip() else f"{a},"
            for a, r in (ln.split(",")[:2] for ln in ls[1:])])
    elif how == "semicolons, decimal commas":
        edit_csv(path, lambda ls: [ln.replace(",", ";") for ln in ls[:1]] + [
            ln.replace(",", ";").replace(".", ",") for ln in ls[1:]])
    elif how == "extra field":
        edit_csv(path, lambda ls: cell(ls, 5, 1, ls[5].split(",")[1] + ",7,8,9"))
    elif how == "header only":
        edit_csv(path, lambda ls: ls[:1])
    else:
        break_file(path, how)


def tolerated_scan(path: Path, how: str) -> None:
    """Harmless spellings of the same scan: read as the original."""
    if how == "BOM":
        edit_csv(path, lambda ls: ls, encoding="utf-8-sig")
    elif how == "CRLF":
        edit_csv(path, lambda ls: ls, newline="\r\n")
    elif how == "semicolons":
        edit_csv(path, lambda ls: [ln.replace(",", ";") for ln in ls])
    elif how == "nan and inf":  # ROS's no-return spellings (REP 117)
        def f(ls):
            for k, v in ((3, "nan"), (4, "inf"), (6, "-inf")):
                a = ls[k].split(",")[0]
                ls[k] = f"{a},{v}"
            return ls
        edit_csv(path, f)
    else:
        raise AssertionError(how)


def edit_json(path: Path, fn: Callable[[dict], object]) -> None:
    """``fn`` edits the JSON object of ``path`` in place."""
    d = json.loads(path.read_text())
    fn(d)
    if path.is_symlink():
        path.unlink()
    path.write_text(json.dumps(d))


def break_json(path: Path, how: str) -> None:
    """A JSON file: invalid, or one of the generic file breaks."""
    if how == "invalid":
        text = path.read_text()
        path.unlink()
        path.write_text(text[: len(text) // 2])
    elif how == "not an object":
        path.write_text(json.dumps([json.loads(path.read_text())]))
    else:
        break_file(path, how)


def break_camera(d: dict, how: str) -> None:
    """A ``camera`` block (dataset.json, camera.json, RIG.json)."""
    if how == "K string":
        d["K"][0][0] = str(d["K"][0][0])
    elif how == "K negative focal":
        d["K"][1][1] = -abs(d["K"][1][1])
    elif how == "K singular":
        d["K"] = [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    elif how == "K transposed":
        d["K"] = np.array(d["K"], float).T.tolist()
    elif how == "K 2x2":
        d["K"] = [r[:2] for r in d["K"][:2]]
    elif how == "dist rational":
        d["dist"] = (list(d["dist"]) + [0.0] * 5)[:5] + [0.1, 0.0, 0.0]
    elif how == "dist string":
        d["dist"] = "0 0 0 0 0"
    elif how == "image_size mismatch":
        d["image_size"] = [d["image_size"][0] + 64, d["image_size"][1]]
    elif how == "image_size missing":
        del d["image_size"]
    elif how == "K missing":
        del d["K"]
    else:
        raise AssertionError(how)


# --- inputs that work ------------------------------------------------------------------------

def rig_copy(tmp: Path, n: int = 4, sweeps: int = 2) -> tuple[Path, Path]:
    """The bundled rig's first ``n`` positions and ``sweeps`` sweeps copied to ``tmp/ds``, and
    its calibration (reports/calibration) copied to ``tmp/cal/calibration.json`` (its
    ``dataset`` this copy, so that no warning says it was made from another dataset)."""
    ds = tmp / "ds"
    (ds / "stripes").mkdir(parents=True)
    (ds / "scans").mkdir()
    (ds / "measure").mkdir()
    meta = json.loads((BUNDLED / "dataset.json").read_text())
    meta["measurements"] = meta["measurements"][:sweeps]
    for m in meta["measurements"]:
        shutil.copy(BUNDLED / m["sweep"], ds / m["sweep"])
    (ds / "dataset.json").write_text(json.dumps(meta, indent=1))
    shutil.copy(BUNDLED / "board.png", ds / "board.png")
    rows = (BUNDLED / "positions.csv").read_text().splitlines()[: n + 1]
    for r in rows[1:]:
        _, _, img, scan = r.split(",")
        shutil.copy(BUNDLED / img, ds / img)
        shutil.copy(BUNDLED / scan, ds / scan)
    (ds / "positions.csv").write_text("\n".join(rows) + "\n")
    cal = tmp / "cal" / "calibration.json"
    cal.parent.mkdir()
    d = json.loads(CAL.read_text())
    d["dataset"] = str(ds.resolve())
    cal.write_text(json.dumps(d))
    return ds, cal


def tapas_copy(tmp: Path, n: int = 7) -> Path:
    """The real TAPAS view pairs (photo + scan), camera.json and board.json, copied."""
    d = tmp / "tapas"
    d.mkdir(parents=True)
    for k in range(n):
        for ext in ("png", "csv"):
            shutil.copy(TAPAS / f"{k:02d}.{ext}", d / f"{k:02d}.{ext}")
    for name in ("camera.json", "board.json"):
        shutil.copy(TAPAS / name, d / name)
    return d


def photos_copy(tmp: Path, n: int = 11) -> Path:
    d = tmp / "photos"
    d.mkdir()
    for p in sorted(OPENCV_LEFT.glob("left*.jpg"))[:n]:
        shutil.copy(p, d / p.name)
    return d


# --- the matrix --------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One command with one broken input: ``setup(tmp)`` breaks it and returns
    ``(argv, named, watched)``: the command line, the file the error must name, the output
    paths that must be left as they were."""

    id: str
    setup: Callable[[Path], tuple[list, str, list[Path]]]
    root_can_read: bool = True  # False: the case needs a user who cannot read a 0o000 file


def registrars(cases: list[Case]) -> tuple[Callable, Callable]:
    """The decorators that register a test module's cases in ``cases``: ``case(id)`` for
    ``fn(tmp)``, ``many(prefix, hows)`` for ``fn(tmp, how)`` once per ``how``."""
    def case(cid: str, **kw):
        def deco(fn):
            cases.append(Case(cid, fn, **kw))
            return fn
        return deco

    def many(prefix: str, hows, **kw):
        def deco(fn):
            for how in hows:
                cases.append(Case(f"{prefix}-{how.replace(' ', '_')}",
                                  functools.partial(fn, how=how),
                                  root_can_read=how != "unreadable", **kw))
            return fn
        return deco
    return case, many


FILE_BREAKS = ["missing", "empty", "folder", "unreadable"]
IMAGE_BREAKS = FILE_BREAKS + ["truncated", "text", "wrong size", "16-bit", "float"]
SCAN_BREAKS = FILE_BREAKS + ["binary", "wrong header", "missing column", "non-numeric",
                             "negative range", "descending angles", "duplicate angle", "metres",
                             "semicolons, decimal commas", "extra field", "header only"]
JSON_BREAKS = FILE_BREAKS + ["invalid", "not an object"]
CAMERA_BREAKS = ["K string", "K negative focal", "K singular", "K transposed", "K 2x2",
                 "dist rational", "dist string", "image_size missing", "K missing"]


def refused(tmp_path: Path, c: Case, run) -> None:
    if ROOT and not c.root_can_read:
        pytest.skip("root reads a 0o000 file")
    argv, named, watched = c.setup(tmp_path)
    before = {w: snapshot(w) for w in watched}
    p = run(*argv)
    assert_refused(p, named)
    for w in watched:
        assert snapshot(w) == before[w], f"{w} was written"
    left = [q.name for q in tmp_path.rglob(".*") if q.name.startswith(".")]
    assert not left, left  # no temporary file left behind


def first_per_command(cases: list[Case]) -> list[Case]:
    """The first case of every command (its id's first word), to run again as a whole
    process: exit status, nothing else printed."""
    return list({c.id.split("-")[0]: c for c in reversed(cases)}.values())
