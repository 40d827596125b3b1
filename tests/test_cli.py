"""The command line: results on a simulated rig, and one clear line + exit 2 for every bad input."""

from __future__ import annotations

import json
import subprocess
import sys

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
    if case == "nan range":
        _scan(scan, lambda d: d.assign(range_mm=d.range_mm.where(d.index != 5, np.nan).astype(object)
                                       .where(d.index != 5, "nan")))
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


BAD_CASES = ["missing png", "corrupt png", "wrong size", "board not found", "no stripe",
             "scan no segment", "scan one segment", "nan range", "negative range",
             "non-numeric range", "missing scan", "fewer than 3", "duplicate psi",
             "incomplete positions", "malformed json", "incomplete json", "unknown format"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_bad_input_one_line_exit_2_no_output(dataset_copy, tmp_path, capsys, case):
    named = _corrupt(dataset_copy, case)
    out_dir = tmp_path / "out"
    code, out, err = run(["calibrate", str(dataset_copy), "--out", str(out_dir)], capsys)
    assert code == 2, (case, out, err)
    lines = [ln for ln in err.splitlines() if not ln.startswith("warning:")]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    assert named in lines[0], (named, lines[0])
    assert "Traceback" not in err
    assert not (out_dir / "calibration.json").exists()


def test_skip_failed_drops_a_bad_position_with_a_warning(dataset_copy, tmp_path, capsys):
    _corrupt(dataset_copy, "scan one segment")
    code, _, err = run(["calibrate", str(dataset_copy), "--out", str(tmp_path), "--skip-failed"],
                       capsys)
    assert code == 0, err
    assert "warning: skipped position 1" in err
    cal = json.loads((tmp_path / "calibration.json").read_text())
    assert [s["index"] for s in cal["samples"]] == [0, 2, 3]
    assert cal["skipped"][0]["index"] == 1 and "0001.csv" in cal["skipped"][0]["reason"]


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
    from conftest import BUNDLED

    dst = tmp_path / "sub"
    dst.mkdir()
    (dst / "dataset.json").write_text((BUNDLED / "dataset.json").read_text())
    (dst / "board.png").symlink_to(BUNDLED / "board.png")
    rows = (BUNDLED / "positions.csv").read_text().splitlines()[: n + 1]
    out = [rows[0]]
    for r in rows[1:]:
        i, psi, img, scan = r.split(",")
        out.append(",".join([i, psi, str(BUNDLED / img), str(BUNDLED / scan)]))
    (dst / "positions.csv").write_text("\n".join(out) + "\n")
    return dst


def test_failed_position_in_worker_processes(tmp_path, capsys):
    """Enough positions for the worker pool: a broken image comes back from a worker as a clear
    error (exit 2), or as a skipped position with --skip-failed."""
    ds = _bundled_subset(tmp_path)
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n not really")
    text = (ds / "positions.csv").read_text().splitlines()
    i, psi, _, scan = text[4].split(",")
    text[4] = ",".join([i, psi, str(bad), scan])
    (ds / "positions.csv").write_text("\n".join(text) + "\n")
    code, _, err = run(["calibrate", str(ds), "--out", str(tmp_path / "a"), "--method", "rigid"],
                       capsys)
    assert code == 2 and err.startswith("error: ") and "broken.png" in err, err
    assert not (tmp_path / "a" / "calibration.json").exists()
    code, _, err = run(["calibrate", str(ds), "--out", str(tmp_path / "b"), "--method", "rigid",
                        "--skip-failed"], capsys)
    assert code == 0, err
    cal = json.loads((tmp_path / "b" / "calibration.json").read_text())
    assert [s["index"] for s in cal["samples"]] == [0, 1, 2, 4, 5, 6, 7]
    assert "broken.png" in cal["skipped"][0]["reason"]


def test_dataset_error_survives_pickling():
    import pickle

    from lidarcal.dataset import DatasetError

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
