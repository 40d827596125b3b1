"""Corrupted inputs, every command: one line ``error: FILE: what is wrong; what to do``, exit 2,
no traceback, nothing half-written; damage that is local and recoverable (one bad photo of a
folder) is skipped with a warning naming the file and the rest used.

Each case breaks one input of a working command line (small copies of the bundled rig and of
the real TAPAS views, the 4-position simulated rig of ``conftest.small_dataset``) and runs
``python -m lidarcal`` in a subprocess.
"""

from __future__ import annotations

import functools
import gzip
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


CASES: list[Case] = []


def case(cid: str, **kw):
    def deco(fn):
        CASES.append(Case(cid, fn, **kw))
        return fn
    return deco


def _many(prefix: str, hows, **kw):
    """Register ``fn(tmp, how)`` once per ``how``."""
    def deco(fn):
        for how in hows:
            CASES.append(Case(f"{prefix}-{how.replace(' ', '_')}",
                              functools.partial(fn, how=how),
                              root_can_read=how != "unreadable", **kw))
        return fn
    return deco


FILE_BREAKS = ["missing", "empty", "folder", "unreadable"]
IMAGE_BREAKS = FILE_BREAKS + ["truncated", "text", "wrong size", "16-bit", "float"]
SCAN_BREAKS = FILE_BREAKS + ["binary", "wrong header", "missing column", "non-numeric",
                             "negative range", "descending angles", "duplicate angle", "metres",
                             "semicolons, decimal commas", "extra field", "header only"]
JSON_BREAKS = FILE_BREAKS + ["invalid", "not an object"]
CAMERA_BREAKS = ["K string", "K negative focal", "K singular", "K transposed", "K 2x2",
                 "dist rational", "dist string", "image_size missing", "K missing"]


# calibrate: what test_cli.py does not cover (dataset.json, board.png, positions.csv details;
# every position-local break is covered there)

def _calibrate(tmp, ds):
    out = tmp / "out"
    return ["calibrate", ds, "--out", out, "--method", "rigid"], [out]


@_many("calibrate-dataset.json", JSON_BREAKS)
def _(tmp, how):
    ds, _ = rig_copy(tmp)
    break_json(ds / "dataset.json", how)
    argv, w = _calibrate(tmp, ds)
    return argv, "dataset.json", w


@_many("calibrate-dataset.json-camera", CAMERA_BREAKS)
def _(tmp, how):
    ds, _ = rig_copy(tmp)
    edit_json(ds / "dataset.json", lambda d: break_camera(d["camera"], how))
    argv, w = _calibrate(tmp, ds)
    return argv, "dataset.json", w


@case("calibrate-dataset.json-camera-image_size_mismatch")
def _(tmp):
    """dataset.json's image_size is not board.png's: board.png is named (with the size)."""
    ds, _ = rig_copy(tmp)
    edit_json(ds / "dataset.json", lambda d: break_camera(d["camera"], "image_size mismatch"))
    argv, w = _calibrate(tmp, ds)
    return argv, "board.png", w


@_many("calibrate-dataset.json-field", [
    "lidar.angle_step string", "v_board.square_mm string", "v_board.inner_corners too large",
    "v_board.inner_corners 1", "lidar missing", "v_board missing", "measurements not a list",
    "lidar.range_max string"])
def _(tmp, how):
    ds, _ = rig_copy(tmp)

    def f(d):
        if how == "lidar.angle_step string":
            d["lidar"]["angle_step_deg"] = "0.083"
        elif how == "v_board.square_mm string":
            d["v_board"]["square_mm"] = "20 mm"
        elif how == "v_board.inner_corners too large":
            d["v_board"]["inner_corners"] = [40, 50]
        elif how == "v_board.inner_corners 1":
            d["v_board"]["inner_corners"] = [1, 20]
        elif how == "lidar missing":
            del d["lidar"]
        elif how == "v_board missing":
            del d["v_board"]
        elif how == "measurements not a list":
            d["measurements"] = {"name": "trial_01"}
        elif how == "lidar.range_max string":
            d["lidar"]["range_max_mm"] = "3000"
    edit_json(ds / "dataset.json", f)
    argv, w = _calibrate(tmp, ds)
    return argv, ("board.png" if "too large" in how else "dataset.json"), w


@_many("calibrate-board.png", IMAGE_BREAKS + ["truncated jpeg"])
def _(tmp, how):
    ds, _ = rig_copy(tmp)
    break_image(ds / "board.png", how)
    argv, w = _calibrate(tmp, ds)
    return argv, "board.png", w


def _positions(ds: Path, fn) -> None:
    edit_csv(ds / "positions.csv", fn)


@_many("calibrate-positions.csv", FILE_BREAKS + [
    "binary", "duplicate index", "duplicate psi", "two rows", "header only", "missing column",
    "non-numeric psi", "nan psi", "inf psi", "empty path", "index not an integer",
    "semicolons, decimal commas", "extra field"])
def _(tmp, how):
    ds, _ = rig_copy(tmp)
    p = ds / "positions.csv"

    def cell(ls, row, col, v):
        f = ls[row].split(",")
        f[col] = v
        ls[row] = ",".join(f)
        return ls
    fns = {
        "duplicate index": lambda ls: cell(ls, 2, 0, ls[1].split(",")[0]),
        "duplicate psi": lambda ls: cell(ls, 3, 1, ls[2].split(",")[1]),
        "two rows": lambda ls: ls[:3],
        "header only": lambda ls: ls[:1],
        "missing column": lambda ls: [",".join(ln.split(",")[:3]) for ln in ls],
        "non-numeric psi": lambda ls: cell(ls, 2, 1, "16,77"),
        "nan psi": lambda ls: cell(ls, 2, 1, "nan"),
        "inf psi": lambda ls: cell(ls, 2, 1, "inf"),
        "empty path": lambda ls: cell(ls, 2, 2, ""),
        "index not an integer": lambda ls: cell(ls, 2, 0, "1.5"),
        "semicolons, decimal commas": lambda ls: [ln.replace(",", ";").replace(".", ",")
                                                  for ln in ls],
        "extra field": lambda ls: cell(ls, 2, 3, ls[2].split(",")[3] + ",x"),
    }
    if how in fns:
        _positions(ds, fns[how])
    else:
        break_file(p, how)
    argv, w = _calibrate(tmp, ds)
    return argv, "positions.csv", w


@case("calibrate-out-is-a-file")
def _(tmp):
    ds, _ = rig_copy(tmp)
    out = tmp / "out"
    out.write_text("precious\n")
    return ["calibrate", ds, "--out", out, "--method", "rigid"], "out", [out]


@case("calibrate-out-parent-is-a-file")
def _(tmp):
    ds, _ = rig_copy(tmp)
    (tmp / "f").write_text("precious\n")
    return ["calibrate", ds, "--out", tmp / "f" / "out"], "f", [tmp / "f"]


@case("calibrate-dataset-is-a-file")
def _(tmp):
    (tmp / "ds").write_text("x\n")
    return ["calibrate", tmp / "ds", "--out", tmp / "out"], "ds", [tmp / "out"]


# pose / measure / cloud / overlay / report: calibration.json

CAL_BREAKS = JSON_BREAKS + ["dataset.json instead", "extrinsics.json instead",
                            "measurements.json instead", "format 2", "no model",
                            "model string", "model number string", "model wrong type",
                            "no format"]


# the same reader (lidarcal.api.load_calibration) serves measure, cloud and overlay: a few each
CAL_SOME = ["empty", "invalid", "extrinsics.json instead", "format 2", "model string",
            "model number string"]


def break_calibration(cal: Path, how: str, ds: Path | None = None) -> None:
    if how in JSON_BREAKS:
        break_json(cal, how)
    elif how == "dataset.json instead":
        shutil.copy(BUNDLED / "dataset.json", cal)
    elif how == "extrinsics.json instead":
        shutil.copy(REPO / "reports" / "real_tapas" / "extrinsics.json", cal)
    elif how == "measurements.json instead":
        shutil.copy(REPO / "reports" / "calibration" / "measurements.json", cal)
    elif how == "format 2":
        edit_json(cal, lambda d: d.update(format="lidarcal-calibration/2"))
    elif how == "no format":
        edit_json(cal, lambda d: d.pop("format"))
    elif how == "no model":
        edit_json(cal, lambda d: d.pop("model"))
    elif how == "model string":
        edit_json(cal, lambda d: d.update(model="joint"))
    elif how == "model number string":
        def f(d):
            a = d["model"]["axis"]
            a["point_mm"] = [str(x) for x in a["point_mm"]]
        edit_json(cal, f)
    elif how == "model wrong type":
        edit_json(cal, lambda d: d["model"].update(type="quantum"))
    else:
        raise AssertionError(how)


@_many("pose-calibration.json", CAL_BREAKS)
def _(tmp, how):
    _, cal = rig_copy(tmp, sweeps=0)
    break_calibration(cal, how)
    return ["pose", cal, "--psi", "17"], "calibration.json", []


@_many("measure-calibration.json", CAL_SOME)
def _(tmp, how):
    ds, cal = rig_copy(tmp)
    break_calibration(cal, how)
    return ["measure", ds, "--calibration", cal, "--out", tmp / "m"], "calibration.json", \
        [tmp / "m"]


@_many("cloud-calibration.json", CAL_SOME)
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=1)
    break_calibration(cal, how)
    return ["cloud", ds, "--calibration", cal, "--sweep", "trial_01", "--out",
            tmp / "c.ply"], "calibration.json", [tmp / "c.ply"]


@_many("overlay-calibration.json", CAL_SOME)
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    break_calibration(cal, how)
    return ["overlay", ds, "--calibration", cal, "--index", "1", "--out", tmp / "o.png"], \
        "calibration.json", [tmp / "o.png"]


@_many("report-calibration.json", ["invalid", "dataset.json instead", "format 2", "no model",
                                   "model wrong type"])
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    break_calibration(cal, how)
    return ["report", ds, "--calibration", cal, "--out", tmp / "r.pdf"], "calibration.json", \
        [tmp / "r.pdf"]


@_many("report-measurements.json", ["missing", "invalid", "calibration.json instead"])
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    m = tmp / "measurements.json"
    shutil.copy(REPO / "reports" / "calibration" / "measurements.json", m)
    if how == "calibration.json instead":
        shutil.copy(cal, m)
    else:
        break_json(m, how)
    return ["report", ds, "--calibration", cal, "--measurements", m, "--out", tmp / "r.pdf"], \
        "measurements.json", [tmp / "r.pdf"]


# measure / cloud: the sweeps

SWEEP_BREAKS = FILE_BREAKS + ["truncated", "binary", "not gzip", "wrong header", "non-numeric",
                              "negative range", "metres", "header only"]


def break_sweep(path: Path, how: str) -> None:
    if how == "truncated":  # a gzip stream cut short
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
        return
    if how in FILE_BREAKS or how == "binary":
        break_file(path, how)
        return
    with gzip.open(path, "rt") as f:
        lines = f.read().splitlines()
    if how == "not gzip":
        path.write_text("\n".join(lines) + "\n")
        return
    if how == "wrong header":
        lines[0] = "a,b,c"
    elif how == "non-numeric":
        lines[7] = lines[7].rsplit(",", 1)[0] + ",abc"
    elif how == "negative range":
        lines[7] = lines[7].rsplit(",", 1)[0] + ",-5"
    elif how == "metres":
        out = [lines[0]]
        for ln in lines[1:]:
            psi, ang, r = ln.split(",")[:3]
            out.append(f"{psi},{ang},{float(r) / 1000 if r.strip() else ''}")
        lines = out
    elif how == "header only":
        lines = lines[:1]
    with gzip.open(path, "wt") as f:
        f.write("\n".join(lines) + "\n")


@_many("measure-sweep", SWEEP_BREAKS)
def _(tmp, how):
    ds, cal = rig_copy(tmp)
    break_sweep(ds / "measure" / "trial_02.csv.gz", how)
    return ["measure", ds, "--calibration", cal, "--out", tmp / "m"], "trial_02.csv.gz", \
        [tmp / "m"]


@_many("cloud-sweep", SWEEP_BREAKS)
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=1)
    break_sweep(ds / "measure" / "trial_01.csv.gz", how)
    return ["cloud", ds, "--calibration", cal, "--sweep", "trial_01", "--out", tmp / "c.ply"], \
        "trial_01.csv.gz", [tmp / "c.ply"]


@_many("measure-dataset.json", ["invalid", "measurement path escapes", "measurement absolute missing",
                                "reference string", "no measurements"])
def _(tmp, how):
    ds, cal = rig_copy(tmp)
    j = ds / "dataset.json"
    if how == "invalid":
        break_json(j, how)
        named = "dataset.json"
    elif how == "measurement path escapes":
        edit_json(j, lambda d: d["measurements"][1].update(sweep="../../elsewhere/t.csv.gz"))
        named = "t.csv.gz"
    elif how == "measurement absolute missing":
        edit_json(j, lambda d: d["measurements"][1].update(sweep=str(tmp / "gone.csv.gz")))
        named = "gone.csv.gz"
    elif how == "reference string":
        edit_json(j, lambda d: d["measurements"][0].update(reference_diameter_mm="140"))
        named = "dataset.json"
    else:
        edit_json(j, lambda d: d.update(measurements=[]))
        named = "dataset.json"
    return ["measure", ds, "--calibration", cal, "--out", tmp / "m"], named, [tmp / "m"]


@case("measure-out-is-a-file")
def _(tmp):
    ds, cal = rig_copy(tmp)
    (tmp / "m").write_text("precious\n")
    return ["measure", ds, "--calibration", cal, "--out", tmp / "m"], "m", [tmp / "m"]


@case("measure-unknown-reference")
def _(tmp):
    ds, cal = rig_copy(tmp)
    return ["measure", ds, "--calibration", cal, "--out", tmp / "m", "--reference", "trial_9"], \
        "dataset.json", [tmp / "m"]


@case("cloud-out-is-a-folder")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=1)
    (tmp / "c.ply").mkdir()
    (tmp / "c.ply" / "keep").write_text("x")
    return ["cloud", ds, "--calibration", cal, "--sweep", "trial_01", "--out", tmp / "c.ply"], \
        "c.ply", [tmp / "c.ply"]


@case("cloud-all-out-is-a-file")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=1)
    (tmp / "clouds").write_text("precious\n")
    return ["cloud", ds, "--calibration", cal, "--all", "--out", tmp / "clouds"], "clouds", \
        [tmp / "clouds"]


@case("cloud-unknown-suffix")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=1)
    return ["cloud", ds, "--calibration", cal, "--sweep", "trial_01", "--out", tmp / "c.xyz"], \
        "c.xyz", [tmp / "c.xyz"]


@case("cloud-unknown-sweep")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=1)
    return ["cloud", ds, "--calibration", cal, "--sweep", "trial_7", "--out", tmp / "c.ply"], \
        "dataset.json", [tmp / "c.ply"]


# overlay: the position's own files are what it draws: fatal

@_many("overlay-stripe", IMAGE_BREAKS)
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    break_image(ds / "stripes" / "0001.png", how)
    return ["overlay", ds, "--calibration", cal, "--index", "1", "--out", tmp / "o.png"], \
        "0001.png", [tmp / "o.png"]


@_many("overlay-scan", SCAN_BREAKS)
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    break_scan(ds / "scans" / "0001.csv", how)
    return ["overlay", ds, "--calibration", cal, "--index", "1", "--out", tmp / "o.png"], \
        "0001.csv", [tmp / "o.png"]


@_many("overlay-board.png", ["truncated", "wrong size", "folder"])
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    break_image(ds / "board.png", how)
    return ["overlay", ds, "--calibration", cal, "--index", "1", "--out", tmp / "o.png"], \
        "board.png", [tmp / "o.png"]


@case("overlay-out-is-a-folder")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=0)
    (tmp / "o.png").mkdir()
    return ["overlay", ds, "--calibration", cal, "--index", "1", "--out", tmp / "o.png"], \
        "o.png", [tmp / "o.png"]


@case("overlay-unknown-index")
def _(tmp):
    ds, cal = rig_copy(tmp, sweeps=0)
    return ["overlay", ds, "--calibration", cal, "--index", "99", "--out", tmp / "o.png"], \
        "positions.csv", [tmp / "o.png"]


# check: an unreadable dataset is exit 2 (a position's problems are exit 1, below)

@_many("check-dataset.json", ["missing", "invalid", "K string", "dist rational"])
def _(tmp, how):
    ds, _ = rig_copy(tmp, sweeps=0)
    if how in ("K string", "dist rational"):
        edit_json(ds / "dataset.json", lambda d: break_camera(d["camera"], how))
    else:
        break_json(ds / "dataset.json", how)
    return ["check", ds, "--sheet", tmp / "s.png"], "dataset.json", [tmp / "s.png"]


@_many("check-positions.csv", ["missing", "duplicate index", "two rows"])
def _(tmp, how):
    ds, _ = rig_copy(tmp, sweeps=0)
    if how == "missing":
        break_file(ds / "positions.csv", how)
    elif how == "two rows":
        _positions(ds, lambda ls: ls[:3])
    else:
        _positions(ds, lambda ls: ls[:2] + [ls[1].split(",")[0] + "," + ls[2].split(",", 1)[1]]
                   + ls[3:])
    return ["check", ds, "--sheet", tmp / "s.png"], "positions.csv", [tmp / "s.png"]


@_many("check-board.png", ["truncated", "text", "wrong size", "16-bit"])
def _(tmp, how):
    ds, _ = rig_copy(tmp, sweeps=0)
    break_image(ds / "board.png", how)
    return ["check", ds, "--sheet", tmp / "s.png"], "board.png", [tmp / "s.png"]


@_many("check-sheet", ["not png or pdf", "is a folder"])
def _(tmp, how):
    ds, _ = rig_copy(tmp, sweeps=0)
    sheet = tmp / ("s.txt" if how == "not png or pdf" else "s.png")
    if how == "is a folder":
        sheet.mkdir()
    return ["check", ds, "--sheet", sheet], sheet.name, [sheet]


# report / workbook: the dataset and the output path

@_many("report-dataset", ["dataset.json invalid", "positions.csv two rows"])
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    if how == "dataset.json invalid":
        break_json(ds / "dataset.json", "invalid")
    elif how == "positions.csv two rows":
        _positions(ds, lambda ls: ls[:3])
    else:
        break_file(ds / "board.png", "text")
    named = how.split()[0]
    return ["report", ds, "--calibration", cal, "--out", tmp / "r.pdf"], named, [tmp / "r.pdf"]


@_many("report-out", ["is a folder", "parent is a file"])
def _(tmp, how):
    ds, cal = rig_copy(tmp, sweeps=0)
    if how == "is a folder":
        out = tmp / "r.pdf"
        out.mkdir()
        watched = out
    else:
        (tmp / "f").write_text("precious\n")
        out = tmp / "f" / "r.pdf"
        watched = tmp / "f"
    return ["report", ds, "--calibration", cal, "--out", out], out.name if how == "is a folder" \
        else "f", [watched]


@_many("workbook", ["dataset.json invalid", "positions.csv missing", "out is a folder",
                    "unknown notebook", "notebook dir missing"])
def _(tmp, how):
    ds, _ = rig_copy(tmp, sweeps=0)
    out = tmp / "w.pdf"
    extra = []
    named = ""
    if how == "dataset.json invalid":
        break_json(ds / "dataset.json", "invalid")
        named = "dataset.json"
    elif how == "positions.csv missing":
        break_file(ds / "positions.csv", "missing")
        named = "positions.csv"
    elif how == "out is a folder":
        out.mkdir()
        named = "w.pdf"
    elif how == "unknown notebook":
        extra = ["--notebooks", "99"]
        named = "notebooks"
    else:
        extra = ["--notebook-dir", tmp / "nb"]
        named = "nb"
    return ["workbook", ds, "--out", out, *extra], named, [out]


# intrinsics, laser-plane, planes: folders of photos

@_many("intrinsics-folder", ["missing", "empty", "a file", "all text", "pattern too large",
                             "out is a folder", "negative square", "one photo"])
def _(tmp, how):
    d = photos_copy(tmp)
    out = tmp / "camera.json"
    args = ["--pattern", "9x6", "--square-mm", "25"]
    named = "photos"
    if how == "missing":
        shutil.rmtree(d)
    elif how == "empty":
        shutil.rmtree(d)
        d.mkdir()
    elif how == "a file":
        shutil.rmtree(d)
        d.write_text("x\n")
    elif how == "all text":
        for p in d.iterdir():
            p.write_text("no\n")
    elif how == "pattern too large":
        args = ["--pattern", "19x16", "--square-mm", "25"]
    elif how == "out is a folder":
        out.mkdir()
        named = "camera.json"
    elif how == "negative square":
        args = ["--pattern", "9x6", "--square-mm", "-25"]
        named = "--square-mm"
    elif how == "one photo":
        for p in sorted(d.iterdir())[1:]:
            p.unlink()
    return ["intrinsics", d, *args, "-o", out], named, [out]


@case("intrinsics-photos-of-two-sizes")
def _(tmp):
    d = photos_copy(tmp, n=10)
    for p in sorted(d.iterdir())[:5]:  # half the views resized: which size is the camera's?
        img = _img(p)
        p.unlink()
        cv2.imwrite(str(p), cv2.resize(img, (320, 240)))
    return ["intrinsics", d, "--pattern", "9x6", "--square-mm", "25", "-o", tmp / "c.json"], \
        "photos", [tmp / "c.json"]


LOCAL_PHOTO_BREAKS = ["empty", "truncated", "text", "truncated jpeg", "wrong size", "16-bit",
                      "folder"]


@pytest.mark.parametrize("how", LOCAL_PHOTO_BREAKS)
def test_intrinsics_one_bad_photo_is_skipped(tmp_path, cli, how):
    """One broken photo of 6: a warning naming it, the other 5 calibrate the camera."""
    d = photos_copy(tmp_path, n=6)
    bad = sorted(d.iterdir())[3]
    break_image(bad, how)
    out = tmp_path / "camera.json"
    p = cli("intrinsics", d, "--pattern", "9x6", "--square-mm", "25", "-o", out)
    assert_accepted(p, warned=bad.name)
    assert "views used 5 of 6" in p.stdout, p.stdout
    cam = json.loads(out.read_text())
    assert bad.name in cam.get("rejected", [])


def _laser_photos(tmp: Path) -> Path:
    from lidarcal.synthetic.laserphotos import LaserPhotoConfig, write_laser_photos

    cfg = LaserPhotoConfig(image_size=(800, 600), f_px=760.0, sheet_sigma_mm=0.8)
    return write_laser_photos(tmp / "laser", seed=5, n_photos=6, cfg=cfg)


def _laser_copy(tmp: Path) -> Path:
    src = Path(os.environ["LIDARCAL_TEST_LASER"])
    d = tmp / "laser"
    shutil.copytree(src, d)
    return d


def _laser_argv(d: Path, out: Path, camera: Path | None = None) -> list:
    t = json.loads((d / "truth.json").read_text())
    pattern = "x".join(str(v) for v in t["pattern"])
    return ["laser-plane", d, "--pattern", pattern, "--square-mm", t["square_mm"], "--camera",
            camera or d / "camera.json", "--out", out]


@_many("laser-plane-camera.json", JSON_BREAKS + CAMERA_BREAKS + ["image_size mismatch"])
def _(tmp, how):
    d = _laser_copy(tmp)
    cam = d / "camera.json"
    if how in JSON_BREAKS:
        break_json(cam, how)
        named = "camera.json"
    else:
        edit_json(cam, lambda c: break_camera(c, how))
        named = "camera.json"
    return _laser_argv(d, tmp / "plane.json"), named, [tmp / "plane.json"]


@_many("laser-plane-folder", ["missing", "empty", "all text", "out is a folder"])
def _(tmp, how):
    d = _laser_copy(tmp)
    shutil.copy(d / "camera.json", tmp / "camera.json")
    shutil.copy(d / "truth.json", tmp / "truth.json")
    argv = _laser_argv(d, tmp / "plane.json", tmp / "camera.json")
    argv[argv.index(d)] = tmp / "photos"
    named = "photos"
    if how == "missing":
        pass
    elif how == "empty":
        (tmp / "photos").mkdir()
    elif how == "all text":
        (tmp / "photos").mkdir()
        for p in sorted(d.glob("*.png")):
            (tmp / "photos" / p.name).write_text("no\n")
    else:
        argv[argv.index(tmp / "photos")] = d
        (tmp / "plane.json").mkdir()
        named = "plane.json"
    return argv, named, [tmp / "plane.json"]


@pytest.mark.parametrize("how", [h for h in LOCAL_PHOTO_BREAKS if h != "16-bit"])
def test_laser_plane_one_bad_photo_is_skipped(tmp_path, cli, how):
    """(A 16-bit photo is read, scaled to 8 bits.)"""
    d = _laser_copy(tmp_path)
    bad = d / "02.png"
    break_image(bad, how)
    p = cli(*_laser_argv(d, tmp_path / "plane.json"))
    assert_accepted(p, warned="02.png")
    plane = json.loads((tmp_path / "plane.json").read_text())
    assert [i["used"] for i in plane["images"] if i["name"] == "02.png"] == [False]


def _planes_argv(d: Path, out: Path, camera: Path | None = None) -> list:
    return ["planes", d, "--camera", camera or d / "camera.json", "--out", out, "--no-figures"]


@_many("planes-camera.json", JSON_BREAKS + CAMERA_BREAKS + ["image_size mismatch"])
def _(tmp, how):
    d = tapas_copy(tmp)
    cam = d / "camera.json"
    if how in JSON_BREAKS:
        break_json(cam, how)
    else:
        edit_json(cam, lambda c: break_camera(c, how))
    return _planes_argv(d, tmp / "out"), "camera.json", [tmp / "out"]


@_many("planes-board.json", JSON_BREAKS + ["inner_corners string", "square_mm negative",
                                           "inner_corners too large"])
def _(tmp, how):
    d = tapas_copy(tmp)
    b = d / "board.json"
    named = "board.json"
    if how in JSON_BREAKS:
        break_json(b, how)
    elif how == "inner_corners string":
        edit_json(b, lambda x: x.update(inner_corners="8x5"))
    elif how == "square_mm negative":
        edit_json(b, lambda x: x.update(square_mm=-100))
    else:
        edit_json(b, lambda x: x.update(inner_corners=[18, 15]))
        named = "tapas"
    return _planes_argv(d, tmp / "out"), named, [tmp / "out"]


@_many("planes-folder", ["missing", "empty", "photo without scan", "scan without photo",
                         "out is a file"])
def _(tmp, how):
    d = tapas_copy(tmp)
    named = "tapas"
    out = tmp / "out"
    cam = tmp / "camera.json"
    shutil.copy(d / "camera.json", cam)
    if how == "missing":
        shutil.rmtree(d)
    elif how == "empty":
        shutil.rmtree(d)
        d.mkdir()
        shutil.copy(TAPAS / "board.json", d / "board.json")
    elif how == "photo without scan":
        (d / "03.csv").unlink()
        named = "03.png"
    elif how == "scan without photo":
        (d / "03.png").unlink()
        named = "03.csv"
    else:
        out.write_text("precious\n")
        named = "out"
    return _planes_argv(d, out, cam), named, [out]


@_many("planes-scan", SCAN_BREAKS[1:])
def _(tmp, how):
    """A broken scan of a view pair (the photo's partner): its error, not a fit's."""
    d = tapas_copy(tmp)
    if how == "empty" or how == "folder" or how == "unreadable":
        break_file(d / "03.csv", how)
    else:
        break_scan(d / "03.csv", how)
    return _planes_argv(d, tmp / "out"), "03.csv", [tmp / "out"]


@pytest.mark.parametrize("how", ["empty", "truncated", "text", "wrong size", "16-bit", "folder"])
def test_planes_one_bad_photo_is_skipped(tmp_path, cli, how):
    """A view whose photo cannot be read is left out with a warning naming it (like a view
    whose board is not found); 6 real views remain."""
    d = tapas_copy(tmp_path)
    break_image(d / "03.png", how)
    p = cli(*_planes_argv(d, tmp_path / "out"))
    assert_accepted(p, warned="03.png")
    ext = json.loads((tmp_path / "out" / "extrinsics.json").read_text())
    assert "views used 6 of 7" in p.stdout, p.stdout
    assert ext


@pytest.fixture(scope="module")
def tapas_reference(tmp_path_factory) -> dict:
    """extrinsics.json of ``lidarcal planes`` on the TAPAS views as they are."""
    from lidarcal.cli import main

    tmp = tmp_path_factory.mktemp("tapas_ref")
    assert main([str(a) for a in _planes_argv(tapas_copy(tmp), tmp / "out")]) == 0
    return json.loads((tmp / "out" / "extrinsics.json").read_text())


@pytest.mark.parametrize("how", ["BOM", "CRLF", "semicolons", "nan and inf"])
def test_planes_tolerated_scan_spellings(tmp_path, cli, tapas_reference, how):
    """The same scan with a byte-order mark, CRLF line ends, ';' separators (and '.' decimals:
    unambiguous) or ROS's nan/inf no-returns: the same extrinsics as the plain file."""
    d = tapas_copy(tmp_path / "b")
    for k in range(7):
        tolerated_scan(d / f"{k:02d}.csv", how)
    pb = cli(*_planes_argv(d, tmp_path / "ob"))
    assert_accepted(pb)
    ea = tapas_reference
    eb = json.loads((tmp_path / "ob" / "extrinsics.json").read_text())
    if how == "nan and inf":  # three returns fewer per view: close, not equal
        assert np.allclose(ea["T_mm"], eb["T_mm"], atol=5.0)
    else:
        assert ea["R"] == eb["R"] and ea["T_mm"] == eb["T_mm"]


# import: ROS bags

def _bag_case(tmp: Path, how: str) -> tuple[list, str, list[Path]]:
    src, rig = Path(os.environ["LIDARCAL_TEST_BAG"]), Path(os.environ["LIDARCAL_TEST_RIG"])
    b, r = tmp / "rig.bag", tmp / "rig.json"
    shutil.copy(src, b)
    shutil.copy(rig, r)
    out = tmp / "ds"
    named = "rig.bag"
    if how == "truncated bag":
        break_file(b, "truncated")
    elif how == "empty bag":
        break_file(b, "empty")
    elif how == "text bag":
        break_file(b, "text")
    elif how == "no LaserScan":
        _bag_without_scans(src, b)
    elif how.startswith("RIG.json "):
        named = "rig.json"
        what = how[len("RIG.json "):]
        if what in JSON_BREAKS:
            break_json(r, what)
        elif what in CAMERA_BREAKS + ["image_size mismatch"]:
            edit_json(r, lambda d: break_camera(d["camera"], what))
        elif what == "no v_board":
            edit_json(r, lambda d: d.pop("v_board"))
        elif what == "z hint string":
            edit_json(r, lambda d: d["lidar"].update(z_axis_hint="up"))
        elif what == "intrinsics folder missing":
            edit_json(r, lambda d: d.update(intrinsics="nowhere", intrinsics_board={
                "inner_corners": [9, 6], "square_mm": 25}))
        elif what == "dataset.json instead":
            shutil.copy(BUNDLED / "dataset.json", r)
        else:
            raise AssertionError(what)
    elif how == "out is a file":
        out.write_text("precious\n")
        named = "ds"
    elif how == "out not empty":
        out.mkdir()
        (out / "keep.txt").write_text("x")
        named = "ds"
    elif how == "board image truncated":
        shutil.copy(BUNDLED / "board.png", tmp / "board.png")
        break_file(tmp / "board.png", "truncated")
        return ["import", b, "--rig", r, "--out", out, "--board-image", tmp / "board.png"], \
            "board.png", [out]
    else:
        raise AssertionError(how)
    return ["import", b, "--rig", r, "--out", out], named, [out]


def _bag_without_scans(src: Path, dst: Path) -> None:
    """``src`` (ROS 1) rewritten without its LaserScan topic."""
    from rosbags.rosbag1 import Reader, Writer

    dst.unlink()
    with Reader(src) as reader, Writer(dst) as writer:
        conns = {}
        for c in reader.connections:
            if c.msgtype.endswith("LaserScan"):
                continue
            conns[c.id] = writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data,
                                                md5sum=c.digest)
        for c, t, raw in reader.messages():
            if c.id in conns:
                writer.write(conns[c.id], t, raw)


for _how in ["truncated bag", "empty bag", "text bag", "no LaserScan", "out is a file",
             "out not empty", "board image truncated"] + [
        f"RIG.json {w}" for w in JSON_BREAKS + ["K string", "dist rational", "K transposed",
                                                "image_size mismatch", "no v_board",
                                                "z hint string", "intrinsics folder missing",
                                                "dataset.json instead"]]:
    CASES.append(Case(f"import-{_how.replace(' ', '_')}",
                      functools.partial(_bag_case, how=_how),
                      root_can_read="unreadable" not in _how))


# simulate: bad arguments and outputs

@_many("simulate", ["positions 2", "positions 0", "positions -3", "unknown rig", "out is a file",
                    "out not empty", "negative quantum", "disc diameters bad",
                    "seed not a number"])
def _(tmp, how):
    out = tmp / "sim"
    args: list = ["--positions", "4", "--no-sweeps"]
    named = "--positions"
    if how.startswith("positions"):
        args = ["--positions", how.split()[1], "--no-sweeps"]
    elif how == "unknown rig":
        args += ["--rig", "huge"]
        named = "--rig"
    elif how == "out is a file":
        out.write_text("precious\n")
        named = "sim"
    elif how == "out not empty":
        out.mkdir()
        (out / "keep.txt").write_text("x")
        named = "sim"
    elif how == "negative quantum":
        args += ["--range-quantum-mm", "-1"]
        named = "--range-quantum-mm"
    elif how == "disc diameters bad":
        args += ["--disc-diameters", "100,abc"]
        named = "--disc-diameters"
    else:
        args += ["--seed", "x1"]
        named = "--seed"
    return ["simulate", out, *args], named, [out]


@pytest.fixture(scope="module", autouse=True)
def _shared_inputs(tmp_path_factory, small_dataset):
    """The laser photos and the bag, made once for the cases that copy them."""
    root = tmp_path_factory.mktemp("shared")
    laser = _laser_photos(root)
    from lidarcal.synthetic.bag import write_bag

    b = root / "rig.bag"
    write_bag(small_dataset, b, storage="rosbag1", images="png", rig_json=root / "rig.json",
              seed=1, sweeps=False)
    old = {k: os.environ.get(k) for k in ("LIDARCAL_TEST_LASER", "LIDARCAL_TEST_BAG",
                                          "LIDARCAL_TEST_RIG")}
    os.environ.update(LIDARCAL_TEST_LASER=str(laser), LIDARCAL_TEST_BAG=str(b),
                      LIDARCAL_TEST_RIG=str(root / "rig.json"))
    yield
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def _refused(tmp_path: Path, c: Case, run) -> None:
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


@pytest.mark.parametrize("c", CASES, ids=[c.id for c in CASES])
def test_refused_with_one_line(tmp_path, cli, c: Case):
    _refused(tmp_path, c, cli)


# the first case of every command again as a whole process: exit status, nothing else printed
FIRST = list({c.id.split("-")[0]: c for c in reversed(CASES)}.values())


@pytest.mark.parametrize("c", FIRST, ids=[c.id for c in FIRST])
def test_refused_by_a_real_process(tmp_path, c: Case):
    _refused(tmp_path, c, lambda *a: lidarcal(*a, cwd=tmp_path))


# --- recoverable and tolerated damage ---------------------------------------------------------

@pytest.mark.parametrize("how", ["missing", "truncated", "text", "wrong size", "16-bit",
                                 "truncated jpeg", "empty", "folder"])
def test_calibrate_skips_one_bad_stripe_image(tmp_path, cli, how):
    """One stripe image of 5 broken: skipped with a warning naming it, 4 calibrated."""
    ds, _ = rig_copy(tmp_path, n=5, sweeps=0)
    break_image(ds / "stripes" / "0002.png", how)
    p = cli("calibrate", ds, "--out", tmp_path / "out", "--method", "rigid")
    assert_accepted(p, warned="0002.png")
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert [s["index"] for s in cal["skipped"]] == [2]


@pytest.mark.parametrize("how", ["binary", "wrong header", "missing column", "descending angles",
                                 "duplicate angle", "metres", "semicolons, decimal commas",
                                 "extra field", "header only", "empty", "folder"])
def test_calibrate_skips_one_bad_scan(tmp_path, cli, how):
    ds, _ = rig_copy(tmp_path, n=5, sweeps=0)
    break_scan(ds / "scans" / "0002.csv", how)
    p = cli("calibrate", ds, "--out", tmp_path / "out", "--method", "rigid")
    assert_accepted(p, warned="0002.csv")
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert [s["index"] for s in cal["skipped"]] == [2]


@pytest.mark.parametrize("how", ["BOM", "CRLF", "semicolons", "nan and inf"])
def test_calibrate_reads_tolerated_scan_spellings(tmp_path, cli, how):
    """BOM, CRLF, ';' with '.' decimals, nan/inf no-returns: every position used. (The output
    folder held another file: calibrate writes its own files there, the other is kept.)"""
    ds, _ = rig_copy(tmp_path, n=4, sweeps=0)
    for f in sorted((ds / "scans").iterdir()):
        tolerated_scan(f, how)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "notes.txt").write_text("mine\n")
    p = cli("calibrate", ds, "--out", tmp_path / "out", "--method", "rigid")
    assert_accepted(p)
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert not cal.get("skipped")
    assert (tmp_path / "out" / "notes.txt").read_text() == "mine\n"


def test_positions_csv_with_bom_crlf_absolute_and_outside_paths(tmp_path, cli):
    """positions.csv: a byte-order mark and CRLF are read; a path outside the dataset folder
    (absolute or ../) is used as written when the file exists (datasets may share files)."""
    ds, _ = rig_copy(tmp_path, n=4, sweeps=0)
    shared = tmp_path / "shared"
    shared.mkdir()
    shutil.move(ds / "scans" / "0001.csv", shared / "0001.csv")
    shutil.move(ds / "stripes" / "0002.png", shared / "0002.png")

    def f(ls):
        a = ls[2].split(",")
        a[3] = str(shared / "0001.csv")
        ls[2] = ",".join(a)
        b = ls[3].split(",")
        b[2] = "../shared/0002.png"
        ls[3] = ",".join(b)
        return ls
    edit_csv(ds / "positions.csv", f, newline="\r\n", encoding="utf-8-sig")
    p = cli("check", ds, "--no-sheet")
    assert p.returncode == 0, p.stderr


def test_check_names_a_bad_position_and_exits_1(tmp_path, cli):
    ds, _ = rig_copy(tmp_path, n=4, sweeps=0)
    break_image(ds / "stripes" / "0002.png", "truncated")
    break_scan(ds / "scans" / "0003.csv", "metres")
    p = cli("check", ds, "--sheet", tmp_path / "s.png")
    assert p.returncode == 1, p.stderr
    assert "Traceback" not in p.stderr
    text = p.stdout + p.stderr
    assert "0002.png" in text and "0003.csv" in text
