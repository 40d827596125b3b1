"""The command line: results on a simulated rig, and one clear line + exit 2 for every bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from lidarcal.cli import main
from lidarcal.evaluate import axis_direction_error_deg, pose_errors
from lidarcal.geometry import Pose


def run(argv, capsys):
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def test_calibrate_writes_the_contract_and_is_accurate(small_dataset, tmp_path, capsys):
    code, _, err = run(["calibrate", str(small_dataset), "--out", str(tmp_path / "cal")], capsys)
    assert code == 0, err
    cal = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    truth = json.loads((small_dataset / "truth.json").read_text())
    assert cal["format"] == "lidarcal-calibration/1"
    assert cal["camera"]["source"] == "dataset.json"
    assert {"samples", "poses", "axis", "model"} <= set(cal)
    assert [s["index"] for s in cal["samples"]] == [0, 1, 2, 3]
    for key, bars in (("samples", (1.0, 0.03, 0.08)), ("poses", (1.0, 0.03, 0.08))):
        est = {p["index"]: Pose.from_dict(p) for p in cal[key]}
        err_tab = pose_errors(est, truth)
        assert err_tab.centre_mm.mean() < bars[0], (key, err_tab)
        assert err_tab.z_axis_deg.mean() < bars[1], (key, err_tab)
        assert err_tab.x_axis_deg.mean() < bars[2], (key, err_tab)
        for p in cal[key]:
            R = np.array(p["R"])
            assert np.allclose(R.T @ R, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
    # 4 positions over 0.75 deg: the axis direction is weak, but must point the right way
    assert axis_direction_error_deg(np.array(cal["axis"]["direction"]),
                                    np.array(truth["axis"]["direction"])) < 20
    assert "positions span only" in err  # the weak setup is reported


def test_calibrate_is_deterministic(small_dataset, tmp_path, capsys):
    for k in (1, 2):
        assert run(["calibrate", str(small_dataset), "--out", str(tmp_path / f"c{k}")], capsys)[0] == 0
    a = (tmp_path / "c1" / "calibration.json").read_bytes()
    b = (tmp_path / "c2" / "calibration.json").read_bytes()
    assert a == b


def test_pose_command_matches_calibration(small_dataset, tmp_path, capsys):
    assert run(["calibrate", str(small_dataset), "--out", str(tmp_path)], capsys)[0] == 0
    cal = json.loads((tmp_path / "calibration.json").read_text())
    psi = cal["poses"][2]["psi_deg"]
    code, out, _ = run(["pose", str(tmp_path / "calibration.json"), "--psi", str(psi)], capsys)
    assert code == 0
    T = np.array(cal["poses"][2]["T_mm"])
    assert f"{T[0]:.3f}"[:6] in out.replace(" ", "") or "T_mm" in out


def _scan(path, transform):
    df = pd.read_csv(path)
    df = transform(df)
    df.to_csv(path, index=False)


def _corrupt(ds, case):
    """Apply one bad-input case to a dataset copy; return the file the error must name."""
    stripe, scan = ds / "stripes" / "0001.png", ds / "scans" / "0001.csv"
    if case == "missing png":
        stripe.unlink()
        return stripe.name
    if case == "corrupt png":
        stripe.write_bytes(stripe.read_bytes()[:200])
        return stripe.name
    if case == "wrong size":
        img = cv2.imread(str(stripe), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(stripe), img[:-10])
        return stripe.name
    if case == "board not found":
        img = cv2.imread(str(ds / "board.png"), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(ds / "board.png"), np.full_like(img, 128))
        return "board.png"
    if case == "no stripe":
        img = cv2.imread(str(stripe), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(stripe), np.zeros_like(img))
        return stripe.name
    if case == "scan no segment":
        _scan(scan, lambda d: d.assign(range_mm=0))
        return scan.name
    if case == "scan one segment":
        # a flat wall 2 m ahead instead of the V
        _scan(scan, lambda d: d.assign(range_mm=2000.0 / np.cos(np.radians(d.angle_deg))))
        return scan.name
    if case == "overflowing range":  # nan/inf are no return (ROS, REP 117); 1e999 is no range
        _scan(scan, lambda d: d.assign(range_mm=d.range_mm.astype(object)
                                       .where(d.index != 5, "1e999")))
        return scan.name
    if case == "negative range":
        _scan(scan, lambda d: d.assign(range_mm=d.range_mm.where(d.index != 5, -3.0)))
        return scan.name
    if case == "non-numeric range":
        _scan(scan, lambda d: d.assign(range_mm=d.range_mm.astype(object).where(d.index != 5, "x1")))
        return scan.name
    if case == "missing scan":
        scan.unlink()
        return scan.name
    pos = ds / "positions.csv"
    if case == "fewer than 3":
        lines = pos.read_text().splitlines()
        pos.write_text("\n".join(lines[:3]) + "\n")
        return "positions.csv"
    if case == "duplicate psi":
        df = pd.read_csv(pos)
        df.loc[1, "psi_deg"] = df.loc[0, "psi_deg"]
        df.to_csv(pos, index=False)
        return "positions.csv"
    if case == "incomplete positions":
        pos.write_text("index,psi_deg\n0,0\n1,1\n2,2\n")
        return "positions.csv"
    meta_path = ds / "dataset.json"
    meta = json.loads(meta_path.read_text())
    if case == "malformed json":
        meta_path.write_text(meta_path.read_text()[:-20])
        return "dataset.json"
    if case == "incomplete json":
        del meta["lidar"]
        meta_path.write_text(json.dumps(meta))
        return "dataset.json"
    if case == "unknown format":
        meta["format"] = "lidarcal-dataset/2"
        meta_path.write_text(json.dumps(meta))
        return "dataset.json"
    raise AssertionError(case)


# a dataset-wide input is broken: always fatal
FATAL_CASES = ["board not found", "fewer than 3", "duplicate psi", "incomplete positions",
               "malformed json", "incomplete json", "unknown format"]
# one position's files are broken: that position fails alone (skipped by default, fatal with
# --strict)
POSITION_CASES = ["missing png", "corrupt png", "wrong size", "no stripe", "scan no segment",
                  "scan one segment", "overflowing range", "negative range", "non-numeric range",
                  "missing scan"]


def _one_error_line(err: str, named: str) -> str:
    lines = [ln for ln in err.splitlines() if not ln.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert err.splitlines()[-1] == lines[0], err  # the error is the last line
    assert named in lines[0], (named, lines[0])
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("case", FATAL_CASES)
def test_bad_input_one_line_exit_2_no_output(dataset_copy, tmp_path, capsys, case):
    named = _corrupt(dataset_copy, case)
    out_dir = tmp_path / "out"
    code, out, err = run(["calibrate", str(dataset_copy), "--out", str(out_dir)], capsys)
    assert code == 2, (case, out, err)
    _one_error_line(err, named)
    assert not out_dir.exists()


@pytest.mark.parametrize("case", POSITION_CASES)
def test_a_position_that_fails_alone_is_skipped_unless_strict(dataset_copy, tmp_path, capsys, case):
    """Default: the broken position is skipped with a warning naming its file (stderr,
    ``warnings``, ``skipped``) and the other 3 are calibrated; --strict: exit 2 naming it."""
    named = _corrupt(dataset_copy, case)
    out_dir = tmp_path / "strict"
    code, out, err = run(["calibrate", str(dataset_copy), "--out", str(out_dir), "--strict",
                          "--method", "rigid"], capsys)
    assert code == 2, (case, out, err)
    _one_error_line(err, named)
    assert not out_dir.exists()
    code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path), "--method",
                        "rigid"], capsys)
    assert code == 0, (case, err)
    warned = [ln for ln in err.splitlines() if ln.startswith("warning: ") and named in ln]
    assert len(warned) == 1 and "position 1 skipped" in warned[0], err
    cal = json.loads((tmp_path / "calibration.json").read_text())
    assert [s["index"] for s in cal["samples"]] == [0, 2, 3]
    assert [s["index"] for s in cal["skipped"]] == [1] and named in cal["skipped"][0]["reason"]
    assert sum(named in w for w in cal["warnings"]) == 1


def test_skip_failed_is_a_no_op_alias(dataset_copy, tmp_path, capsys):
    """Old commands with --skip-failed still run, and do what the default does."""
    _corrupt(dataset_copy, "scan one segment")
    for k, extra in enumerate(([], ["--skip-failed"])):
        code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path / f"c{k}"),
                            "--method", "rigid", *extra], capsys)
        assert code == 0, err
    a, b = (json.loads((tmp_path / f"c{k}" / "calibration.json").read_text()) for k in (0, 1))
    assert a["skipped"] == b["skipped"] and a["poses"] == b["poses"]


def test_too_few_positions_left_names_the_first_failure(dataset_copy, tmp_path, capsys):
    """Two of 4 positions broken: 2 remain, fewer than the 3 the fit needs -> exit 2, naming
    the first broken file and the count."""
    _corrupt(dataset_copy, "corrupt png")
    (dataset_copy / "scans" / "0002.csv").unlink()
    code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path / "o")], capsys)
    assert code == 2
    line = _one_error_line(err, "0001.png")
    assert "2 of 4 positions failed, 2 usable" in line and "at least 3" in line
    assert not (tmp_path / "o").exists()


def test_explicit_skip(dataset_copy, tmp_path, capsys):
    _corrupt(dataset_copy, "no stripe")
    code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path), "--skip", "1"], capsys)
    assert code == 0, err
    cal = json.loads((tmp_path / "calibration.json").read_text())
    assert [s["index"] for s in cal["samples"]] == [0, 2, 3]


def test_real_process_exit_code_and_debug_traceback(dataset_copy, tmp_path):
    _corrupt(dataset_copy, "unknown format")
    cmd = [sys.executable, "-m", "lidarcal", "calibrate", str(dataset_copy), "--out", str(tmp_path)]
    p = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert p.returncode == 2
    assert p.stderr.count("\n") == 1 and p.stderr.startswith("error: ")
    p = subprocess.run(cmd[:3] + ["--debug"] + cmd[3:], capture_output=True, text=True,
                       check=False)
    assert p.returncode == 2 and "Traceback" in p.stderr


def test_missing_dataset_folder(tmp_path, capsys):
    code, _, err = run(["calibrate", str(tmp_path / "nope"), "--out", str(tmp_path)], capsys)
    assert code == 2 and "nope: not a dataset folder" in err


def _bundled_subset(tmp_path, n=8):
    """The first ``n`` positions of the bundled dataset (files referenced, not copied)."""
    from conftest import bundled_dataset

    return bundled_dataset(tmp_path / "sub", n)


def test_failed_position_in_worker_processes(tmp_path, capsys):
    """Enough positions for the worker pool: a broken image comes back from a worker as a
    skipped position with a warning, or as a clear error (exit 2) with --strict."""
    ds = _bundled_subset(tmp_path)
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    text = (ds / "positions.csv").read_text().splitlines()
    i, psi, _, scan = text[4].split(",")
    text[4] = ",".join([i, psi, str(bad), scan])
    (ds / "positions.csv").write_text("\n".join(text) + "\n")
    code, _, err = run(["calibrate", str(ds), "--out", str(tmp_path / "a"), "--method", "rigid",
                        "--strict"], capsys)
    assert code == 2 and err.startswith("error: ") and "broken.png" in err, err
    assert not (tmp_path / "a").exists()
    code, _, err = run(["calibrate", str(ds), "--out", str(tmp_path / "b"), "--method", "rigid"],
                       capsys)
    assert code == 0, err
    assert "warning: " + str(bad) in err and "position 3 skipped" in err
    cal = json.loads((tmp_path / "b" / "calibration.json").read_text())
    assert [s["index"] for s in cal["samples"]] == [0, 1, 2, 4, 5, 6, 7]
    assert "broken.png" in cal["skipped"][0]["reason"]


def test_dataset_error_survives_pickling():
    import pickle

    from lidarcal.io.dataset import DatasetError

    e = pickle.loads(pickle.dumps(DatasetError("a/b.png", "cannot be decoded")))
    assert isinstance(e, DatasetError) and e.path == "a/b.png" and str(e) == "a/b.png: cannot be decoded"


def test_methods_fill_poses_and_keep_the_others(small_dataset, tmp_path, capsys):
    """Default joint: 'poses' from the joint fit, a 'sigma' block, the rigid and paper
    functions kept; --method rigid: no joint fit, the paper's chain kept."""
    assert run(["calibrate", str(small_dataset), "--out", str(tmp_path / "j")], capsys)[0] == 0
    cal = json.loads((tmp_path / "j" / "calibration.json").read_text())
    assert cal["method"] == "joint" and cal["model"]["type"] == "joint"
    assert {"model_rigid", "poses_rigid", "model_paper", "poses_paper", "sigma"} <= set(cal)
    assert len(cal["model"]["covariance"]) == 10
    sig = cal["sigma"]
    assert sig["level"] == "1-sigma" and len(sig["poses"]) == len(cal["poses"])
    truth = json.loads((small_dataset / "truth.json").read_text())
    err = pose_errors({p["index"]: Pose.from_dict(p) for p in cal["poses"]}, truth)
    for row, e in zip(sig["poses"], err.itertuples()):
        assert row["index"] == e.index
        # with 4 positions the range offset's uncertainty (ranging model) is ~1 mm of it
        assert 0 < row["centre_mm"] < 2.0 and 0 < row["z_axis_deg"] < 0.05
        assert e.centre_mm <= 4 * row["centre_mm"]  # the error bars mean something
    assert run(["calibrate", str(small_dataset), "--out", str(tmp_path / "r"), "--method", "rigid"],
               capsys)[0] == 0
    cal_r = json.loads((tmp_path / "r" / "calibration.json").read_text())
    assert cal_r["method"] == "rigid" and "sigma" not in cal_r and "model_joint" not in cal_r
    assert cal_r["poses"] == cal["poses_rigid"]
    psi = cal["poses"][1]["psi_deg"]
    code, out, _ = run(["pose", str(tmp_path / "j"), "--psi", str(psi), "--model", "rigid"], capsys)
    assert code == 0 and "1-sigma" not in out
    T = np.array(cal["poses_rigid"][1]["T_mm"])
    assert np.allclose([float(v) for v in out.split("T_mm = [")[1].split("]")[0].split()], T,
                       atol=1e-5)
    code, out, _ = run(["pose", str(tmp_path / "j"), "--psi", str(psi)], capsys)
    assert code == 0
    shown = float(out.split("1-sigma: centre ")[1].split(" mm")[0])
    assert shown == pytest.approx(sig["poses"][1]["centre_mm"], rel=1e-3)


# --- clean exits: whole processes, the bundled 87 positions (the background decoding of the
# stripe images is still running when board.png fails; it used to abort the process, 134) ---

def _linked_bundled(tmp_path):
    """The bundled dataset with its own dataset.json, positions.csv and board.png (to break)
    and the 87 stripe images and scans referenced by absolute path (not copied)."""
    from conftest import bundled_dataset

    return bundled_dataset(tmp_path / "ds", copy=("board.png",), link=())


def _break(ds, case):
    """One of the issue's 10 early errors; returns the file name the error must end up naming."""
    board, meta, pos = ds / "board.png", ds / "dataset.json", ds / "positions.csv"
    if case == "corrupt board.png":
        board.write_bytes(board.read_bytes()[:3000])
    elif case == "missing board.png":
        board.unlink()
    elif case == "wrong-size board.png":
        img = cv2.imread(str(board), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(board), cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2)))
    elif case == "non-image board.png":
        board.write_text("this is not an image\n")
    elif case == "truncated dataset.json":
        meta.write_text(meta.read_text()[: len(meta.read_text()) // 2])
    elif case == "missing dataset.json":
        meta.unlink()
    elif case == "unknown-version dataset.json":
        meta.write_text(meta.read_text().replace("lidarcal-dataset/1", "lidarcal-dataset/9"))
    elif case == "too few positions":
        pos.write_text("\n".join(pos.read_text().splitlines()[:3]) + "\n")
    elif case == "non-numeric psi":
        rows = pos.read_text().splitlines()
        i, _, img, scan = rows[5].split(",")
        rows[5] = f"{i},12..5,{img},{scan}"
        pos.write_text("\n".join(rows) + "\n")
    elif case == "duplicate psi":
        rows = pos.read_text().splitlines()
        i, _, img, scan = rows[7].split(",")
        rows[7] = ",".join([i, rows[6].split(",")[1], img, scan])
        pos.write_text("\n".join(rows) + "\n")
    else:
        raise AssertionError(case)
    return {"b": "board.png", "d": "dataset.json"}.get(case.split()[-1][0], "positions.csv")


# board.png fails while the stripe images are being decoded: a race, so several runs each
EARLY_ERRORS = [("corrupt board.png", 3), ("missing board.png", 2), ("wrong-size board.png", 2),
                ("non-image board.png", 3), ("truncated dataset.json", 1),
                ("missing dataset.json", 1), ("unknown-version dataset.json", 1),
                ("too few positions", 1), ("non-numeric psi", 1), ("duplicate psi", 1)]


@pytest.mark.parametrize(("case", "runs"), EARLY_ERRORS, ids=[c for c, _ in EARLY_ERRORS])
def test_early_error_exits_cleanly(tmp_path, case, runs):
    """Exit 2, the one-line error naming the file is the last line on stderr, no traceback,
    no abort, nothing written."""
    ds = _linked_bundled(tmp_path)
    named = _break(ds, case)
    out_dir = tmp_path / "out"
    for _ in range(runs):
        p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(ds), "--out",
                            str(out_dir)], capture_output=True, text=True, check=False)
        assert p.returncode == 2, (case, p.returncode, p.stderr)
        last = p.stderr.rstrip("\n").splitlines()[-1]
        assert last.startswith("error: ") and named in last, (case, p.stderr)
        assert "Traceback" not in p.stderr and "terminate" not in p.stderr, p.stderr
        assert p.stdout == "" and not out_dir.exists()


def test_report_early_error_exits_cleanly(tmp_path):
    """`lidarcal report` runs the pipeline itself: its background decoding is stopped too."""
    ds = _linked_bundled(tmp_path)
    named = _break(ds, "non-image board.png")
    pdf = tmp_path / "r" / "report.pdf"
    for _ in range(2):
        p = subprocess.run([sys.executable, "-m", "lidarcal", "report", str(ds), "--out", str(pdf)],
                           capture_output=True, text=True, check=False)
        assert p.returncode == 2, p.stderr
        last = p.stderr.rstrip("\n").splitlines()[-1]
        assert last.startswith("error: ") and named in last and "terminate" not in p.stderr
        assert not pdf.parent.exists()


def test_skipped_position_is_listed_in_the_report(dataset_copy, tmp_path, capsys):
    from lidarcal.report import build_report_source, esc, gather_inputs

    named = _corrupt(dataset_copy, "corrupt png")
    assert run(["calibrate", str(dataset_copy), "--out", str(tmp_path), "--method", "rigid"],
               capsys)[0] == 0
    inp = gather_inputs(dataset_copy, tmp_path / "calibration.json")
    src = build_report_source(inp, tmp_path, figures=False)
    skipped = src.split("== Skipped positions")[1].split("== Warnings")[0]
    assert esc(named)[2:-1] in skipped and "[1]" in skipped
    assert "1 position(s) skipped" in src


def _calibrate_refused(dataset: Path, tmp_path: Path) -> str:
    """``lidarcal calibrate`` as a process that must exit 2 writing nothing: its last line."""
    p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(dataset), "--out",
                        str(tmp_path / "cal")], capture_output=True, text=True, check=False)
    assert p.returncode == 2, p.stderr
    assert not (tmp_path / "cal" / "calibration.json").exists()
    return p.stderr.strip().splitlines()[-1]


def test_angles_in_radians_are_refused_naming_positions_csv(dataset_copy, tmp_path):
    # psi_deg written in radians: the samples turn 57 times more than the angles say; calibrating
    # anyway gave poses a metre off with exit 0
    pos = dataset_copy / "positions.csv"
    df = pd.read_csv(pos)
    df["psi_deg"] = np.radians(df["psi_deg"])
    df.to_csv(pos, index=False)
    last = _calibrate_refused(dataset_copy, tmp_path)
    assert last.startswith(f"error: {pos}: the single-shot poses turn") and "radians?" in last


def test_skip_of_an_index_that_does_not_exist_is_refused(small_dataset, tmp_path, capsys):
    # a typo in --skip used to be recorded as a skipped position and calibrate ran on
    code, _, err = run(["calibrate", str(small_dataset), "--out", str(tmp_path), "--skip", "1", "99"],
                       capsys)
    assert code == 2
    assert err.strip() == (f"error: {small_dataset / 'positions.csv'}: --skip 99: no position with "
                           "that index; the indices are 0-3")
    assert not (tmp_path / "calibration.json").exists()


def test_a_z_axis_hint_perpendicular_to_the_lidar_z_is_refused(dataset_copy, tmp_path):
    # the hint [1, 0, 0] is 87 deg from this LiDAR's z axis (camera up): the mirror choice was a
    # coin toss, calibrated silently (a rig turned 90 deg with the default hint: 74 mm off)
    dj = dataset_copy / "dataset.json"
    meta = json.loads(dj.read_text())
    meta["lidar"]["z_axis_hint"] = [1, 0, 0]
    dj.write_text(json.dumps(meta))
    last = _calibrate_refused(dataset_copy, tmp_path)
    assert last.startswith(f"error: {dj}: lidar.z_axis_hint") and "perpendicular" in last


def test_a_z_axis_hint_far_from_the_lidar_z_warns(dataset_copy, tmp_path, capsys):
    # [0, 0, 1] is 83 deg from this LiDAR's z axis: within 90 deg of the mirror pose's, so it is
    # chosen; far from any z axis a user would write for it: said
    dj = dataset_copy / "dataset.json"
    meta = json.loads(dj.read_text())
    meta["lidar"]["z_axis_hint"] = [0, 0, 1]
    dj.write_text(json.dumps(meta))
    code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path), "--method", "rigid"],
                       capsys)
    assert code == 0
    assert f"warning: {dj}: lidar.z_axis_hint [0.0, 0.0, 1.0] is 8" in err and "mirror image" in err
