"""Corrupted inputs, every command: one line ``error: FILE: what is wrong; what to do``, exit 2,
no traceback, nothing half-written; damage that is local and recoverable (one bad photo of a
folder) is skipped with a warning naming the file and the rest used.

Each case breaks one input of a working command line (small copies of the bundled rig and of
the real TAPAS views, the 4-position simulated rig of ``conftest.small_dataset``) and runs
``python -m lidarcal`` in a subprocess.
"""

from __future__ import annotations

import gzip
import json
import shutil
from pathlib import Path

import pytest
from conftest import BUNDLED, REPO
from corrupt_kit import (
    CAMERA_BREAKS,
    FILE_BREAKS,
    IMAGE_BREAKS,
    JSON_BREAKS,
    SCAN_BREAKS,
    Case,
    assert_accepted,
    break_camera,
    break_file,
    break_image,
    break_json,
    break_scan,
    edit_csv,
    edit_json,
    first_per_command,
    lidarcal,
    refused,
    registrars,
    rig_copy,
    tolerated_scan,
)

CASES: list[Case] = []
case, _many = registrars(CASES)


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


@pytest.mark.parametrize("c", CASES, ids=[c.id for c in CASES])
def test_refused_with_one_line(tmp_path, cli, c: Case):
    refused(tmp_path, c, cli)


@pytest.mark.parametrize("c", first_per_command(CASES), ids=lambda c: c.id)
def test_refused_by_a_real_process(tmp_path, c: Case):
    refused(tmp_path, c, lambda *a: lidarcal(*a, cwd=tmp_path))


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
