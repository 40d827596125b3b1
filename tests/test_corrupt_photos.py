"""Corrupted inputs of the photo commands (intrinsics, laser-plane, planes), of ``import`` (ROS
bags) and of ``simulate``: one line ``error: FILE: what is wrong; what to do``, exit 2, no
traceback, nothing half-written; one bad photo of a folder is skipped with a warning naming it.
The kit is tests/corrupt_kit.py; the dataset commands are in tests/test_corrupt_inputs.py.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import BUNDLED
from corrupt_kit import (
    CAMERA_BREAKS,
    JSON_BREAKS,
    SCAN_BREAKS,
    TAPAS,
    Case,
    _img,
    assert_accepted,
    break_camera,
    break_file,
    break_image,
    break_json,
    break_scan,
    edit_json,
    first_per_command,
    lidarcal,
    photos_copy,
    refused,
    registrars,
    tapas_copy,
    tolerated_scan,
)

CASES: list[Case] = []
case, _many = registrars(CASES)


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


@pytest.mark.parametrize("c", CASES, ids=[c.id for c in CASES])
def test_refused_with_one_line(tmp_path, cli, c: Case):
    refused(tmp_path, c, cli)


@pytest.mark.parametrize("c", first_per_command(CASES), ids=lambda c: c.id)
def test_refused_by_a_real_process(tmp_path, c: Case):
    refused(tmp_path, c, lambda *a: lidarcal(*a, cwd=tmp_path))
