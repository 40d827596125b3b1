"""Sweep point clouds (eq. 28): files round-trip, every valid return, the disc on the TRUE plane."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidarcal.api import load_calibration
from lidarcal.io.clouds import read_cloud, read_pcd, write_cloud
from lidarcal.io.dataset import CALIBRATION_FORMAT, DatasetError, load_dataset, read_sweep

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT / "data" / "paper_rig"


def truth_calibration(dataset: Path, out: Path) -> Path:
    """A calibration.json holding the TRUE pose function (rigid rotation about the true axis)."""
    t = json.loads((dataset / "truth.json").read_text())
    p0 = t["poses"][0]
    model = {"type": "rigid", "axis": t["axis"], "psi_ref_deg": p0.get("psi_true_deg", p0["psi_deg"]),
             "pose_ref": {"R": p0["R"], "T_mm": p0["T_mm"]}}
    out.mkdir(parents=True, exist_ok=True)
    path = out / "calibration.json"
    path.write_text(json.dumps({"format": CALIBRATION_FORMAT, "method": "rigid", "model": model,
                                "axis": t["axis"]}))
    return path


@pytest.fixture(scope="module")
def truth_cal(tmp_path_factory) -> Path:
    return truth_calibration(SIM, tmp_path_factory.mktemp("cal"))


def _lidarcal(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *args], capture_output=True, text=True, check=False)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".vtp", ".csv"])
def test_round_trip_each_format(tmp_path, suffix):
    rng = np.random.default_rng(3)
    pts = rng.normal(scale=1000.0, size=(500, 3))
    attrs = {"range_mm": rng.uniform(700, 3000, 500), "psi_deg": rng.uniform(-30, 30, 500),
             "angle_deg": rng.uniform(-35, 35, 500), "intensity": rng.uniform(0, 1, 500)}
    path = write_cloud(tmp_path / f"c{suffix}", pts, attrs)
    back, battrs = read_cloud(path)
    tol = 1e-3 if suffix in (".ply", ".pcd") else 1e-5  # float32 x y z in PLY/PCD
    np.testing.assert_allclose(back, pts, atol=tol * 3000)
    assert set(battrs) == set(attrs)
    for k, v in attrs.items():
        np.testing.assert_allclose(battrs[k], v, rtol=1e-6, atol=1e-6)
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind


def test_ply_is_binary_and_pcd_header(tmp_path):
    from plyfile import PlyData

    pts = np.arange(12, dtype=float).reshape(4, 3)
    ply = PlyData.read(str(write_cloud(tmp_path / "a.ply", pts, {"psi_deg": np.ones(4)})))
    assert not ply.text and ply.byte_order == "<"
    head = (write_cloud(tmp_path / "a.pcd", pts, {"psi_deg": np.ones(4)})).read_bytes()[:400]
    assert b"FIELDS x y z psi_deg\n" in head and b"DATA binary\n" in head and b"POINTS 4\n" in head
    back, _attrs = read_pcd(tmp_path / "a.pcd")
    np.testing.assert_allclose(back, pts)


def test_bad_format_and_shape(tmp_path):
    with pytest.raises(ValueError, match="unknown point-cloud format"):
        write_cloud(tmp_path / "a.xyz", np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        write_cloud(tmp_path / "a.ply", np.zeros((2, 2)))


@pytest.mark.skipif(not (SIM / "truth.json").is_file(), reason="bundled dataset not generated")
def test_disc_returns_on_the_true_plane(truth_cal):
    ds = load_dataset(SIM)
    truth = {m["name"]: m for m in json.loads((SIM / "truth.json").read_text())["measurements"]}
    cal = load_calibration(truth_cal)
    for spec in ds.measurements[:3]:
        sweep = read_sweep(spec.sweep, ds.lidar)
        cloud = cal.cloud(spec.sweep, lidar=ds.lidar)
        assert len(cloud) == int(np.isfinite(sweep["range_mm"]).sum())  # every valid return
        t = truth[spec.name]
        c, n = np.asarray(t["center_mm"]), np.asarray(t["normal"])
        d = (cloud.points - c) @ n
        inplane = np.linalg.norm((cloud.points - c) - np.outer(d, n), axis=1)
        # the disc's returns: well inside the rim (mixed rim returns excluded), near the plane
        on = (inplane < t["diameter_mm"] / 2 - 5.0) & (np.abs(d) < 20.0)
        assert on.sum() > 500
        assert abs(np.median(d[on])) <= 0.4, np.median(d[on])
        assert np.mean(np.abs(d[on])) <= 1.5  # 1 mm range noise: E|d| ~ 0.8 mm
        # eq. (28) row by row, and the attributes
        k = np.flatnonzero(on)[0]
        th = np.radians(cloud.angle_deg[k])
        want = cal.pose(cloud.psi_deg[k]).apply(cloud.range_mm[k] * np.array([np.cos(th), np.sin(th), 0.0]))
        np.testing.assert_allclose(cloud.points[k], want[0], atol=1e-9)


@pytest.mark.skipif(not (SIM / "truth.json").is_file(), reason="bundled dataset not generated")
def test_home_frame_is_the_lidar_frame_at_psi_zero(truth_cal):
    ds = load_dataset(SIM)
    cal = load_calibration(truth_cal)
    spec = ds.measurements[0]
    cam = cal.cloud(spec.sweep, lidar=ds.lidar)
    home = cal.cloud(spec.sweep, frame="home", lidar=ds.lidar)
    np.testing.assert_allclose(cal.pose(0.0).apply(home.points), cam.points, atol=1e-6)
    with pytest.raises(ValueError, match="frame"):
        cal.cloud(spec.sweep, frame="lidar")


def test_intensity_column_is_kept(tmp_path, truth_cal):
    ds = load_dataset(SIM)
    sw = read_sweep(ds.measurements[0].sweep, ds.lidar).head(3000).copy()
    sw["intensity"] = np.linspace(0, 1, len(sw))
    path = tmp_path / "s.csv.gz"
    sw.fillna({"range_mm": 0.0}).to_csv(path, index=False)
    cloud = load_calibration(truth_cal).cloud(path, lidar=ds.lidar)
    ok = np.isfinite(sw["range_mm"].to_numpy())
    np.testing.assert_allclose(cloud.intensity, sw["intensity"].to_numpy()[ok])
    assert "intensity" in cloud.attributes()


@pytest.mark.skipif(not (SIM / "truth.json").is_file(), reason="bundled dataset not generated")
def test_cli_cloud_one_sweep_and_all(tmp_path, truth_cal):
    ds = load_dataset(SIM)
    r = _lidarcal("cloud", str(SIM), "--calibration", str(truth_cal), "--sweep", "trial_02",
                  "--out", str(tmp_path / "t2.ply"))
    assert r.returncode == 0, r.stderr
    pts, attrs = read_cloud(tmp_path / "t2.ply")
    n = int(np.isfinite(read_sweep(ds.measurements[1].sweep, ds.lidar)["range_mm"]).sum())
    assert len(pts) == n and {"range_mm", "psi_deg", "angle_deg"} <= set(attrs)
    r = _lidarcal("cloud", str(SIM), "--calibration", str(truth_cal), "--all", "--format", "pcd",
                  "--frame", "home", "--out", str(tmp_path / "all"))
    assert r.returncode == 0, r.stderr
    files = sorted((tmp_path / "all").glob("*.pcd"))
    assert [f.stem for f in files] == [m.name for m in ds.measurements]


def test_cli_cloud_bad_input_one_line(tmp_path, truth_cal):
    r = _lidarcal("cloud", str(SIM), "--calibration", str(truth_cal), "--sweep", "nope",
                  "--out", str(tmp_path / "x.ply"))
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1 and "no measurement named nope" in r.stderr
    r = _lidarcal("cloud", str(SIM), "--calibration", str(truth_cal), "--sweep", "trial_01",
                  "--out", str(tmp_path / "x.xyz"))
    assert r.returncode == 2 and "unknown point-cloud format" in r.stderr
    assert not (tmp_path / "x.ply").exists()
    with pytest.raises(DatasetError, match="no measurement named"):
        from lidarcal.cloud import dataset_clouds

        dataset_clouds(SIM, truth_cal, ["nope"], tmp_path / "y.ply")



@pytest.mark.parametrize(("text", "match"), [
    (None, "calibration.json: missing; run 'lidarcal calibrate"),
    ("{not json", "calibration.json: not valid JSON .*; run 'lidarcal calibrate' again"),
    ("[1, 2]", "calibration.json: must hold a JSON object"),
    ('{"format": "lidarcal-measurements/1"}', "unknown format 'lidarcal-measurements/1', expected"),
])
def test_bad_calibration_json_one_line(tmp_path, text, match):
    """A missing, unreadable, non-object or foreign calibration.json: DatasetError naming the
    file from load_calibration and from the report's reader; the CLI prints one line, exit 2."""
    from lidarcal.report.inputs import _read_json

    path = tmp_path / "calibration.json"
    if text is not None:
        path.write_text(text)
    with pytest.raises(DatasetError, match=match):
        load_calibration(tmp_path)
    with pytest.raises(DatasetError, match="calibration.json: "):
        _read_json(tmp_path, "calibration.json", "lidarcal-calibration/")
    r = _lidarcal("pose", str(path), "--psi", "0")
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.count("\n") == 1 and r.stderr.startswith("error: ") and str(path) in r.stderr
