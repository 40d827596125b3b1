"""The dataset contract: what is read, and a one-line error naming the file for everything else."""

from __future__ import annotations

import gzip
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.io.dataset import (
    DatasetError,
    load_dataset,
    read_image,
    read_scan,
    read_sweep,
    write_json_atomic,
)

DATASET_JSON = {
    "format": "lidarcal-dataset/1",
    "camera": {"image_size": [64, 48], "K": [[50, 0, 32], [0, 50, 24], [0, 0, 1]],
               "dist": [-0.1, 0.05]},
    "v_board": {"inner_corners": [14, 20], "square_mm": 20.0},
    "lidar": {"angle_min_deg": -1.0, "angle_max_deg": 1.0, "angle_step_deg": 0.5,
              "range_min_mm": 100.0, "range_max_mm": 3000.0},
}


def make_dataset(root: Path, n: int = 3, meta: dict | None = None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "dataset.json").write_text(json.dumps(meta or DATASET_JSON))
    cv2.imwrite(str(root / "board.png"), np.zeros((48, 64), np.uint8))
    (root / "stripes").mkdir(exist_ok=True)
    (root / "scans").mkdir(exist_ok=True)
    rows = ["index,psi_deg,stripe_image,scan"]
    for i in range(n):
        cv2.imwrite(str(root / f"stripes/{i:04d}.png"), np.zeros((48, 64), np.uint8))
        (root / f"scans/{i:04d}.csv").write_text(
            "angle_deg,range_mm\n-1.0,1000.5\n-0.5,0\n0.0,\n0.5,1200\n1.0,5000\n")
        rows.append(f"{i},{0.25 * i:.2f},stripes/{i:04d}.png,scans/{i:04d}.csv")
    (root / "positions.csv").write_text("\n".join(rows) + "\n")
    return root


@pytest.mark.parametrize("dist", [[], [-0.1], [-0.1, 0.05, 0.001], [-0.1, 0.05, 0.001, -0.002],
                                  [-0.1, 0.05, 0.001, -0.002, 0.01, 0.0, 0.0, 0.0]])
def test_a_shorter_dist_means_the_rest_are_zero(tmp_path, dist):
    """The contract: camera.dist is k1, k2, p1, p2, k3; a shorter list means the rest are 0."""
    meta = json.loads(json.dumps(DATASET_JSON))
    meta["camera"]["dist"] = dist
    ds = load_dataset(make_dataset(tmp_path / "ds", meta=meta))
    np.testing.assert_array_equal(ds.camera.dist, (dist + [0.0] * 5)[:5])


def test_reads_a_valid_dataset(tmp_path):
    ds = load_dataset(make_dataset(tmp_path / "ds"))
    assert ds.camera is not None and ds.camera.image_size == (64, 48)
    np.testing.assert_allclose(ds.camera.dist, [-0.1, 0.05, 0, 0, 0])
    assert ds.v_board.inner_corners == (14, 20) and ds.v_board.square_mm == 20.0
    assert ds.lidar.z_axis_hint == (0.0, -1.0, 0.0)
    assert ds.lidar.n_beams == 5
    np.testing.assert_allclose(ds.lidar.angles_deg(), [-1, -0.5, 0, 0.5, 1])
    assert [p.psi_deg for p in ds.positions] == [0.0, 0.25, 0.5]
    assert ds.positions[1].scan == (tmp_path / "ds/scans/0001.csv").resolve()


def test_unknown_keys_are_ignored(tmp_path):
    meta = {**DATASET_JSON, "future_key": {"x": 1}}
    assert load_dataset(make_dataset(tmp_path / "ds", meta=meta)).v_board.square_mm == 20.0


def test_scan_no_return_and_range_limits(tmp_path):
    ds = load_dataset(make_dataset(tmp_path / "ds"))
    ang, rng = read_scan(ds.positions[0].scan, ds.lidar)
    np.testing.assert_allclose(ang, [-1, -0.5, 0, 0.5, 1])
    assert rng[0] == 1000.5 and rng[3] == 1200
    assert np.isnan(rng[[1, 2, 4]]).all()  # 0, empty, beyond range_max


def test_ros_spellings_of_no_return_read_as_no_return(tmp_path):
    """ROS exports a LaserScan's beams without a return as inf, -inf or nan (REP 117)."""
    p = tmp_path / "scan.csv"
    p.write_text("angle_deg,range_mm\n-1,1000\n-0.5,inf\n0,-inf\n0.5,NaN\n1,+Infinity\n1.5,1200\n")
    _, rng = read_scan(p)
    assert rng[0] == 1000 and rng[5] == 1200
    assert np.isnan(rng[1:5]).all()


@pytest.mark.parametrize("mutate, match", [
    (lambda m: m.update(format="lidarcal-dataset/9"), "unknown format"),
    (lambda m: m.pop("v_board"), "missing key 'v_board'"),
    (lambda m: m["v_board"].update(inner_corners=[14]), "inner_corners"),
    (lambda m: m["v_board"].update(square_mm=-2), "square_mm' must be positive"),
    (lambda m: m["camera"].update(K=[[1, 2], [3, 4]]), r"camera.K"),
    (lambda m: m["lidar"].update(angle_step_deg="x"), "angle_step_deg"),
    (lambda m: m["lidar"].update(angle_max_deg=-5), "angle_min < angle_max"),
    (lambda m: (m.pop("camera"), m.pop("intrinsics_board", None)), "needs 'camera'"),
])
def test_bad_dataset_json(tmp_path, mutate, match):
    meta = json.loads(json.dumps(DATASET_JSON))
    mutate(meta)
    root = make_dataset(tmp_path / "ds", meta=meta)
    with pytest.raises(DatasetError, match=match) as e:
        load_dataset(root)
    assert "dataset.json" in str(e.value) and "\n" not in str(e.value)


def test_malformed_json(tmp_path):
    root = make_dataset(tmp_path / "ds")
    (root / "dataset.json").write_text("{not json")
    with pytest.raises(DatasetError, match=r"dataset.json: not valid JSON"):
        load_dataset(root)


@pytest.mark.parametrize("text, match", [
    ("index,psi_deg,stripe_image\n0,0,a.png\n", "missing column"),
    ("index,psi_deg,stripe_image,scan\n0,0,a,b\n1,1,a,b\n", "at least 3"),
    ("index,psi_deg,stripe_image,scan\n0,0,a,b\n1,0,a,b\n2,1,a,b\n", "duplicate psi_deg 0"),
    ("index,psi_deg,stripe_image,scan\n0,0,a,b\n1,x,a,b\n2,1,a,b\n", "row 3: 'psi_deg' is not a number"),
    ("", "not a readable CSV"),
])
def test_bad_positions(tmp_path, text, match):
    root = make_dataset(tmp_path / "ds")
    (root / "positions.csv").write_text(text)
    with pytest.raises(DatasetError, match=match) as e:
        load_dataset(root)
    assert "positions.csv" in str(e.value)


@pytest.mark.parametrize("text, match", [
    ("angle_deg,range_mm\n-1,1000\n0,1e400x\n", r"row 3: 'range_mm' is not a finite number"),
    ("angle_deg,range_mm\n-1,1000\nnan,1000\n", r"row 3: 'angle_deg' is not a"),
    ("angle_deg,range_mm\n-1,1000\n0,-4\n", "negative range"),
    ("angle_deg,range_mm\n-1,1000\n0,abc\n", "not a finite number"),
    ("angle_deg,rng\n-1,1000\n", "missing column"),
    ("angle_deg,range_mm\n0,1000\n-1,1000\n", "ascending"),
    ("angle_deg,range_mm\n", "no rows"),
])
def test_bad_scans(tmp_path, text, match):
    p = tmp_path / "scan.csv"
    p.write_text(text)
    with pytest.raises(DatasetError, match=match) as e:
        read_scan(p)
    assert str(e.value).startswith(str(p))


def test_bad_images(tmp_path):
    with pytest.raises(DatasetError, match="missing image"):
        read_image(tmp_path / "nope.png")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    with pytest.raises(DatasetError, match="cannot be decoded"):
        read_image(bad)
    ok = tmp_path / "ok.png"
    cv2.imwrite(str(ok), np.zeros((10, 20, 3), np.uint8))
    assert read_image(ok).shape == (10, 20)
    with pytest.raises(DatasetError, match="image is 20x10, expected 64x48"):
        read_image(ok, (64, 48))
    with pytest.raises(ValueError, match="colour must be"):
        read_image(ok, colour="red")


def test_sweep_reader(tmp_path):
    p = tmp_path / "s.csv.gz"
    with gzip.open(p, "wt") as f:
        f.write("psi_deg,angle_deg,range_mm\n1.0,-1,1500.5\n1.0,0,0\n1.05,-1,\n")
    df = read_sweep(p)
    assert list(df.columns) == ["psi_deg", "angle_deg", "range_mm"]
    assert df["range_mm"].iloc[0] == 1500.5 and df["range_mm"].isna().sum() == 2
    p.write_bytes(b"not gzip")
    with pytest.raises(DatasetError):
        read_sweep(p)


def test_write_json_atomic_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out" / "x.json"
    write_json_atomic(target, {"a": np.arange(3)})
    assert json.loads(target.read_text()) == {"a": [0, 1, 2]}
    with pytest.raises(TypeError):
        write_json_atomic(target, {"a": object()})
    assert json.loads(target.read_text()) == {"a": [0, 1, 2]}
    assert [p.name for p in target.parent.iterdir()] == ["x.json"]


def test_spreadsheet_exports_are_read(tmp_path):
    """Files saved by spreadsheets and Windows editors: a UTF-8 byte-order mark and CRLF
    line endings in dataset.json, positions.csv, scans and sweeps read as the plain files."""
    root = make_dataset(tmp_path / "ds")
    for f in [root / "dataset.json", root / "positions.csv", *sorted((root / "scans").glob("*.csv"))]:
        f.write_bytes(b"\xef\xbb\xbf" + f.read_bytes().replace(b"\n", b"\r\n"))
    ds = load_dataset(root)
    assert [p.psi_deg for p in ds.positions] == [0.0, 0.25, 0.5]
    ang, rng = read_scan(ds.positions[0].scan, ds.lidar)
    np.testing.assert_allclose(ang, [-1, -0.5, 0, 0.5, 1])
    assert rng[0] == 1000.5 and np.isnan(rng[1]) and np.isnan(rng[2])
    p = tmp_path / "s.csv.gz"
    with gzip.open(p, "wb") as f:
        f.write(b"\xef\xbb\xbfpsi_deg,angle_deg,range_mm\r\n1.0,-1,1500.5\r\n1.0,0,0\r\n")
    df = read_sweep(p)
    assert list(df["psi_deg"]) == [1.0, 1.0] and df["range_mm"].iloc[0] == 1500.5


def test_ranges_in_metres_are_named(tmp_path):
    """A scan exported in metres: every return falls below range_min_mm; the error says so."""
    ds = load_dataset(make_dataset(tmp_path / "ds"))
    p = tmp_path / "m.csv"
    p.write_text("angle_deg,range_mm\n" + "".join(f"{a / 10:.1f},{1.2 + a / 100:.3f}\n" for a in range(-10, 11)))
    with pytest.raises(DatasetError, match=r"every return is outside .*ranges must be in mm") as e:
        read_scan(p, ds.lidar)
    assert str(e.value).startswith(str(p))


def test_scan_angles_must_fit_the_lidar_of_dataset_json(tmp_path):
    """Beam angles in radians (or from a LiDAR configured wider than dataset.json says) are named;
    rounded angles, a step given to 4 digits and omitted rows are accepted."""
    from lidarcal.io.dataset import LidarSpec

    lidar = LidarSpec(-35.0, 35.0, 0.0833, 700.0, 3000.0)
    ang = -35.0 + np.arange(841) / 12.0

    def scan(name, a, keep=slice(None), digits=2):
        p = tmp_path / name
        rows = [f"{x:.{digits}f},{1500 + 100 * np.cos(np.radians(x)):.1f}\n" for x in a[keep]]
        p.write_text("angle_deg,range_mm\n" + "".join(rows))
        return p

    got, _ = read_scan(scan("ok.csv", ang, slice(None, None, 2)), lidar)
    assert len(got) == 421
    p = scan("rad.csv", np.radians(ang), digits=6)
    with pytest.raises(DatasetError, match=r"beam angles .* radians") as e:
        read_scan(p, lidar)
    assert str(e.value).startswith(str(p))
    with pytest.raises(DatasetError, match=r"outside dataset.json's lidar.angle_min_deg"):
        read_scan(scan("wide.csv", -135.0 + np.arange(1081) / 4.0), lidar)


def test_atomic_writes_get_the_umask_permissions_not_mkstemp_private_ones(tmp_path):
    """calibration.json and every other output are readable as the user's umask says (mkstemp's
    0600 survived the rename: a lab's other accounts could not read the results)."""
    old = os.umask(0o022)
    try:
        write_json_atomic(tmp_path / "c.json", {"a": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "c.json").stat().st_mode & 0o777 == 0o644


@pytest.mark.parametrize("rmin,rmax", [(5000.0, 3000.0), (-10.0, 3000.0)])
def test_lidar_range_limits_must_be_ordered_and_non_negative(tmp_path, rmin, rmax):
    """range_min_mm above range_max_mm was found only scan by scan (every return 'outside');
    dataset.json is named instead."""
    meta = json.loads(json.dumps(DATASET_JSON))
    meta["lidar"].update(range_min_mm=rmin, range_max_mm=rmax)
    root = make_dataset(tmp_path / "ds", meta=meta)
    with pytest.raises(DatasetError, match=r"range_min_mm .* range_max_mm") as e:
        load_dataset(root)
    assert str(e.value).startswith(str(root / "dataset.json"))


@pytest.mark.parametrize("variant", ["plain", "crlf_bom", "blank_lines", "extra_column",
                                     "quoted", "ros_inf", "empty_range", "columns_swapped"])
def test_scan_readers_agree(tmp_path, variant):
    """read_scan reads plain files with numpy's C reader and the rest with the careful csv
    reader: both give the values ``float`` gives, whatever the file looks like."""
    rng = np.random.default_rng(3)
    ang = np.sort(rng.uniform(-30, 30, 200)).round(6)
    r = rng.uniform(800, 2900, 200).round(1)
    rows = [f"{a!r},{b!r}" for a, b in zip(ang.tolist(), r.tolist())]
    head, nl = "angle_deg,range_mm", "\n"
    want = r.copy()
    if variant == "extra_column":
        head, rows = head + ",intensity", [f"{x},{k % 7}" for k, x in enumerate(rows)]
    elif variant == "quoted":
        rows[5] = f'"{ang[5]}",{r[5]}'
    elif variant == "ros_inf":
        rows[7], want[7] = f"{ang[7]},inf", np.nan
    elif variant == "empty_range":
        rows[9], want[9] = f"{ang[9]},", np.nan
    elif variant == "columns_swapped":
        head, rows = "range_mm,angle_deg", [",".join(x.split(",")[::-1]) for x in rows]
    elif variant == "blank_lines":
        rows[3:3] = ["", "  "]
    elif variant == "crlf_bom":
        nl = "\r\n"
    p = tmp_path / "scan.csv"
    text = nl.join([head, *rows]) + nl
    p.write_bytes((("\ufeff" if variant == "crlf_bom" else "") + text).encode())
    got_a, got_r = read_scan(p)
    assert np.array_equal(got_a, ang)
    assert np.array_equal(got_r, want, equal_nan=True)
