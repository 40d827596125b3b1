"""``lidarcal import``: ROS 1 / ROS 2 bags written by rosbags' own writers from a simulated rig.

The bags carry scans and stripe frames during the moves too (wrong content: ranges 3 %
long and shifted, frames shifted and blurred), invalid returns in every still scan (0,
inf, NaN, beyond the range limits) and, for one bag, an encoder quantum. The import must
give back the simulated folder: every position at its angle, each scan equal to the
folder's (the per-beam clipped mean of the valid returns), each stripe image equal (lossless
images) and the sweeps equal; any scan or frame from a move would break the equality.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.io.bag import import_bag
from lidarcal.io.dataset import DatasetError, load_dataset, read_scan, read_sweep
from lidarcal.synthetic import get_rig, simulate
from lidarcal.synthetic.bag import write_bag


@pytest.fixture(scope="module")
def rig_folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bagsim") / "sim"
    return simulate(out, seed=23, rig=get_rig("paper").with_(n_discs=2), n_positions=6,
                    with_intrinsics=False)


@pytest.fixture(scope="module")
def bags(rig_folder) -> dict[str, tuple[Path, Path]]:
    """name -> (bag, RIG.json)."""
    root = rig_folder.parent
    out = {}
    for name, kw in {
        "ros1_raw": {"storage": "rosbag1", "images": "raw", "extra_joint": True},
        "ros2_png": {"storage": "sqlite3", "images": "png", "angle_msg": "float64"},
        "mcap_jpeg": {"storage": "mcap", "images": "jpeg", "encoder_step_deg": 0.001,
                      "sweeps": False},
        "lidar_clock": {"storage": "sqlite3", "images": "raw", "sweeps": False,
                        "scan_clock_offset_s": -3600.0},
        "deg_angle": {"storage": "mcap", "images": "png", "sweeps": False,
                      "angle_msg": "float64_deg"},
        "one_camera": {"storage": "sqlite3", "images": "png", "single_camera_topic": True},
        "lit_first_stop": {"storage": "mcap", "images": "raw", "sweeps": False,
                           "single_camera_topic": True, "lit_s": 2.0},
        "two_steppers": {"storage": "sqlite3", "images": "png", "sweeps": False,
                         "extra_joint": True, "stepping_joint": True},
    }.items():
        bag = root / (f"{name}.bag" if kw["storage"] == "rosbag1" else name)
        write_bag(rig_folder, bag, rig_json=root / f"{name}.json", seed=1, **kw)
        out[name] = (bag, root / f"{name}.json")
    return out


def lidarcal(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *map(str, args)],
                          check=False, capture_output=True, text=True)


def assert_same_dataset(a: Path, b: Path, exact_images: bool = True) -> None:
    da, db = load_dataset(a), load_dataset(b)
    assert [p.psi_deg for p in db.positions] == pytest.approx([p.psi_deg for p in da.positions],
                                                               abs=1e-9)
    for pa, pb in zip(da.positions, db.positions):
        ang_a, ra = read_scan(pa.scan, da.lidar)
        ang_b, rb = read_scan(pb.scan, db.lidar)
        assert np.allclose(ang_a, ang_b, atol=1e-5)
        assert np.array_equal(np.isnan(ra), np.isnan(rb)), pa.scan
        assert np.allclose(ra[~np.isnan(ra)], rb[~np.isnan(rb)], atol=1e-9), pa.scan
        ia = cv2.imread(str(pa.stripe_image), cv2.IMREAD_UNCHANGED)
        ib = cv2.imread(str(pb.stripe_image), cv2.IMREAD_UNCHANGED)
        assert ia.shape == ib.shape
        if exact_images:
            assert np.array_equal(ia, ib), pb.stripe_image
        else:  # jpeg q95
            assert np.abs(ia.astype(int) - ib).mean() < 1.0
    assert (cv2.imread(str(db.board_image)).shape == cv2.imread(str(da.board_image)).shape)
    assert da.lidar.angle_min_deg == pytest.approx(db.lidar.angle_min_deg, abs=1e-5)
    assert da.lidar.n_beams == db.lidar.n_beams


def test_ros1_raw_images_cli(bags, rig_folder, tmp_path):
    bag, rig = bags["ros1_raw"]
    out = tmp_path / "ds"
    # two joints, one holding still (pan_dummy), one stepping: the stepping one is the turntable
    r = lidarcal("import", bag, "--rig", rig, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "joint 'turntable' is the turntable (the only joint of pan_dummy, turntable" in r.stderr
    assert_same_dataset(rig_folder, out)
    r = lidarcal("import", bag, "--rig", rig, "--out", out, "--joint", "turntable", "--overwrite")
    assert r.returncode == 0, r.stderr
    assert "is the turntable" not in r.stderr
    assert "6 positions" in r.stdout and "2 sweep(s)" in r.stdout
    assert_same_dataset(rig_folder, out)
    meta = json.loads((out / "dataset.json").read_text())
    assert meta["import"]["scans_while_moving"] > 0 and meta["import"]["stripe_frames_while_moving"] > 0
    assert [m["name"] for m in meta["measurements"]] == ["trial_01", "trial_02"]
    ds, orig = load_dataset(out), load_dataset(rig_folder)
    for ma, mb in zip(orig.measurements, ds.measurements):
        sa, sb = read_sweep(ma.sweep, orig.lidar), read_sweep(mb.sweep, ds.lidar)
        assert len(sa) == len(sb)
        # psi interpolated at each scan's mid-time equals the angle the scan was taken at
        assert np.allclose(sa.psi_deg, sb.psi_deg, atol=1e-6)
        ra, rb = sa.range_mm.to_numpy(), sb.range_mm.to_numpy()
        assert np.array_equal(np.isnan(ra), np.isnan(rb))
        assert np.allclose(ra[~np.isnan(ra)], rb[~np.isnan(rb)])
        assert mb.reference_diameter_mm == ma.reference_diameter_mm


def assert_calibrates_like_the_folder(imported, rig_folder, tmp_path, n_positions: int):
    """``lidarcal calibrate`` on the imported dataset and on the folder give the same true errors
    (the same inputs up to the LaserScan's float32 beam angles, ~1e-7 relative: equal to 1e-4
    mm / deg, measured differences ~3e-6, far below any noise)."""
    from lidarcal.evaluate import pose_errors
    from lidarcal.geometry import Pose

    shutil.copy(rig_folder / "truth.json", imported / "truth.json")
    truth = json.loads((rig_folder / "truth.json").read_text())
    errs = {}
    for name, ds in (("bag", imported), ("folder", rig_folder)):
        r = lidarcal("calibrate", ds, "--out", tmp_path / f"cal_{name}", "--method", "rigid",
                     "--no-progress")
        assert r.returncode == 0, r.stderr
        cal = json.loads((tmp_path / f"cal_{name}" / "calibration.json").read_text())
        errs[name] = pose_errors({p["index"]: Pose.from_dict(p) for p in cal["poses"]}, truth)
    assert len(errs["bag"]) == n_positions
    for col in ("centre_mm", "z_axis_deg", "x_axis_deg"):
        assert np.allclose(errs["bag"][col], errs["folder"][col], atol=1e-4)
    return errs


def test_ros2_png_import_then_calibrate_matches_the_folder(bags, rig_folder, tmp_path):
    bag, rig = bags["ros2_png"]
    res = import_bag(bag, rig, tmp_path / "ds")  # Float64 angle: bag log times for every topic
    assert len(res.positions) == 6 and all(p.n_frames >= 2 and p.n_scans >= 30
                                           for p in res.positions)
    assert_same_dataset(rig_folder, tmp_path / "ds")
    errs = assert_calibrates_like_the_folder(tmp_path / "ds", rig_folder, tmp_path, 6)
    assert errs["bag"]["centre_mm"].mean() < 1.0  # 6 positions, 0.25 deg apart


def test_mcap_jpeg_quantised_encoder(bags, rig_folder, tmp_path):
    bag, rig = bags["mcap_jpeg"]
    res = import_bag(bag, rig, tmp_path / "ds", stripe_topic="/camera/stripes/image_raw")
    assert len(res.positions) == 6
    # twice the smallest step seen: 1 count (flicker) or 2 (the smallest step of these moves)
    counts = res.tolerance_deg / 0.001
    assert 2 - 1e-6 <= counts <= 4 + 1e-6 and abs(counts - round(counts)) < 1e-6
    assert_same_dataset(rig_folder, tmp_path / "ds", exact_images=False)
    assert "measurements" in json.loads((tmp_path / "ds" / "dataset.json").read_text())


def test_scans_stamped_on_another_clock_use_receive_times(bags, rig_folder, tmp_path):
    bag, rig = bags["lidar_clock"]
    res = import_bag(bag, rig, tmp_path / "ds")
    assert "/scan: header stamps are -3.6e+03 s from the bag's receive times" in res.warnings[0]
    assert_same_dataset(rig_folder, tmp_path / "ds")
    clock = json.loads((tmp_path / "ds" / "dataset.json").read_text())["import"]["clock"]
    assert clock == {"/turntable/joint_states": "header", "/scan": "log",
                     "/camera/stripes/image_raw": "header", "/camera/board/image_raw": "header"}


def test_float64_angle_in_degrees(bags, rig_folder, tmp_path):
    bag, rig = bags["deg_angle"]
    import_bag(bag, rig, tmp_path / "ds", angle_unit="deg")
    assert_same_dataset(rig_folder, tmp_path / "ds")
    res = import_bag(bag, rig, tmp_path / "wrong")  # read as radians: ~600 deg
    assert "beyond a turn; if a Float64 angle is in degrees, pass --angle-unit deg" in res.warnings[0]


def test_errors_one_line(bags, tmp_path):
    bag, rig = bags["ros2_png"]
    r = lidarcal("import", bag, "--rig", rig, "--out", tmp_path / "x", "--scan-topic", "/laser")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "no topic /laser (--scan-topic); the bag has: /camera/board/image_raw/compressed" in r.stderr
    assert "/scan (sensor_msgs/LaserScan)" in r.stderr
    r = lidarcal("import", bag, "--rig", rig, "--out", tmp_path / "x", "--min-duration-s", "1000")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "no stationary period on /turntable/angle: the angle spans" in r.stderr
    assert not (tmp_path / "x").exists()
    with pytest.raises(DatasetError, match="is sensor_msgs/msg/LaserScan, expected"):
        import_bag(bag, rig, tmp_path / "x", stripe_topic="/scan")
    with pytest.raises(DatasetError, match="no such bag"):
        import_bag(tmp_path / "nope.bag", rig, tmp_path / "x")
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    with pytest.raises(DatasetError, match="cannot be read as a ROS 1 or ROS 2 bag"):
        import_bag(tmp_path / "junk.bag", rig, tmp_path / "x")
    ros1, ros1_rig = bags["ros1_raw"]
    data = ros1.read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])  # recording cut short
    r = lidarcal("import", tmp_path / "cut.bag", "--rig", ros1_rig, "--out", tmp_path / "x")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "reindex" in r.stderr
    assert not (tmp_path / "x").exists()


def test_rig_file_checks(bags, tmp_path):
    bag, rig = bags["ros2_png"]
    good = json.loads(rig.read_text())
    bad = dict(good, lidar={**good["lidar"], "range_max_mm": 5000.0})
    (tmp_path / "rig.json").write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match=r"lidar.range_max_mm is 5000 but the LaserScan messages "
                                           r"on /scan give 3000"):
        import_bag(bag, tmp_path / "rig.json", tmp_path / "x")
    (tmp_path / "rig.json").write_text(json.dumps({k: v for k, v in good.items() if k != "camera"}))
    with pytest.raises(DatasetError, match="needs 'camera'"):
        import_bag(bag, tmp_path / "rig.json", tmp_path / "x")
    bad = dict(good, measurements=[{"name": "m", "start_s": 5.0, "end_s": 1.0}])
    (tmp_path / "rig.json").write_text(json.dumps(bad))
    with pytest.raises(DatasetError, match="end_s must be after start_s"):
        import_bag(bag, tmp_path / "rig.json", tmp_path / "x")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "f").write_text("x")
    with pytest.raises(DatasetError, match="exists and is not empty"):
        import_bag(bag, rig, tmp_path / "taken")


def test_board_image_file_and_overwrite(bags, rig_folder, tmp_path):
    bag, rig = bags["ros2_png"]
    out = tmp_path / "ds"
    out.mkdir()
    (out / "old").write_text("x")
    board = tmp_path / "board.png"
    shutil.copy(rig_folder / "board.png", board)
    import_bag(bag, rig, out, board_image=board, overwrite=True)
    assert not (out / "old").exists()
    assert np.array_equal(cv2.imread(str(out / "board.png")), cv2.imread(str(board)))
    assert not list(tmp_path.glob(".ds.*"))  # no temporary folder left behind


@pytest.fixture(scope="module")
def ros2_types():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.LATEST).types


def _hdr(types):
    return types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=1, nanosec=0),
                                        frame_id="cam")


@pytest.mark.parametrize("enc", ["mono8", "mono16", "bgr8", "rgb8", "rgba8"])
def test_image_encodings(ros2_types, enc):
    from lidarcal.io.bag import IMAGE, image_from_msg

    rng = np.random.default_rng(0)
    h, w = 5, 7
    bgr = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    gray = bgr[:, :, 1].copy()
    pad = 3  # row padding: step > width * bytes per pixel
    if enc == "mono8":
        rows, want = gray, gray
    elif enc == "mono16":
        rows, want = (gray.astype("<u2") * 256 + 100).view(np.uint8).reshape(h, 2 * w), gray
    elif enc == "bgr8":
        rows, want = bgr.reshape(h, 3 * w), bgr
    elif enc == "rgb8":
        rows, want = bgr[:, :, ::-1].reshape(h, 3 * w), bgr
    else:
        rgba = np.concatenate([bgr[:, :, ::-1], np.full((h, w, 1), 255, np.uint8)], axis=2)
        rows, want = rgba.reshape(h, 4 * w), bgr
    data = np.concatenate([rows, np.zeros((h, pad), np.uint8)], axis=1)
    msg = ros2_types[IMAGE](header=_hdr(ros2_types), height=h, width=w, encoding=enc,
                            is_bigendian=0, step=data.shape[1], data=data.reshape(-1))
    assert np.array_equal(image_from_msg(msg, IMAGE, "t"), want)
    bad = ros2_types[IMAGE](header=_hdr(ros2_types), height=h, width=w, encoding="nv12",
                            is_bigendian=0, step=2 * w, data=np.zeros(2 * w * h, np.uint8))
    with pytest.raises(DatasetError, match="'nv12' is not supported"):
        image_from_msg(bad, IMAGE, "t")


@pytest.mark.parametrize("enc,pattern", [("bayer_rggb8", "RGGB"), ("bayer_bggr8", "BGGR"),
                                         ("bayer_gbrg8", "GBRG"), ("bayer_grbg8", "GRBG")])
def test_bayer_frames_keep_their_colour(ros2_types, enc, pattern):
    """A uniform colour mosaiced in the named pattern comes back as that colour (a wrong
    pattern mapping would swap red and blue)."""
    from lidarcal.io.bag import IMAGE, image_from_msg

    h, w = 8, 10
    val = {"R": 200, "G": 120, "B": 30}
    raw = np.zeros((h, w), np.uint8)
    for i, ch in enumerate(pattern):
        raw[i // 2::2, i % 2::2] = val[ch]
    msg = ros2_types[IMAGE](header=_hdr(ros2_types), height=h, width=w, encoding=enc,
                            is_bigendian=0, step=w, data=raw.reshape(-1))
    img = image_from_msg(msg, IMAGE, "t")
    assert img.shape == (h, w, 3)
    assert np.array_equal(img[2:-2, 2:-2].reshape(-1, 3).min(0), [30, 120, 200])  # B, G, R
    assert np.array_equal(img[2:-2, 2:-2].reshape(-1, 3).max(0), [30, 120, 200])


@pytest.mark.parametrize("enc,order", [("yuv422", "UYVY"), ("yuv422_yuy2", "YUYV")])
def test_yuv422_frames(ros2_types, enc, order):
    from lidarcal.io.bag import IMAGE, image_from_msg

    h, w = 4, 6
    y = np.tile(np.arange(w, dtype=np.uint8) * 40, (h, 1))  # a gray ramp: U = V = 128
    px = np.zeros((h, w, 2), np.uint8)
    iy = order.index("Y")  # Y is byte 1 (UYVY) or byte 0 (YUYV) of each pixel
    px[:, :, iy], px[:, :, 1 - iy] = y, 128
    msg = ros2_types[IMAGE](header=_hdr(ros2_types), height=h, width=w, encoding=enc,
                            is_bigendian=0, step=2 * w, data=px.reshape(-1))
    img = image_from_msg(msg, IMAGE, "t")
    # BT.601 video range (OpenCV, cv_bridge): gray = 255/219 (Y - 16)
    want = np.clip(np.round((y.astype(float) - 16) * 255 / 219), 0, 255)
    assert img.shape == (h, w, 3) and np.abs(img - want[:, :, None]).max() <= 1


def test_compressed_png16_and_bad_data(ros2_types):
    from lidarcal.io.bag import COMPRESSED, image_from_msg

    img16 = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000)
    _, buf = cv2.imencode(".png", img16)
    msg = ros2_types[COMPRESSED](header=_hdr(ros2_types), format="mono16; png compressed",
                                 data=buf.reshape(-1))
    assert np.array_equal(image_from_msg(msg, COMPRESSED, "t"),
                          np.clip((img16.astype(int) + 128) // 256, 0, 255))
    junk = ros2_types[COMPRESSED](header=_hdr(ros2_types), format="png",
                                  data=np.frombuffer(b"nope", np.uint8))
    with pytest.raises(DatasetError, match="cannot be decoded"):
        image_from_msg(junk, COMPRESSED, "t")


def test_laserscan_units_invalid_returns_and_clockwise(ros2_types):
    from lidarcal.io.bag import LASERSCAN, scan_from_msg

    r = np.array([0.0, 1.0, np.inf, np.nan, 0.05, 31.0, 2.5], dtype=np.float32)
    msg = ros2_types[LASERSCAN](header=_hdr(ros2_types), angle_min=np.radians(10.0),
                                angle_max=np.radians(-20.0), angle_increment=np.radians(-5.0),
                                time_increment=0.001, scan_time=0.025, range_min=0.1,
                                range_max=30.0, ranges=r, intensities=np.zeros(0, np.float32))
    s = scan_from_msg(msg, 7.0)
    assert s.angle_min_deg == pytest.approx(-20.0) and s.angle_step_deg == pytest.approx(5.0)
    want = np.array([2500.0, np.nan, np.nan, np.nan, np.nan, 1000.0, np.nan])  # reversed, mm
    assert np.array_equal(np.isnan(s.range_mm), np.isnan(want))
    assert np.allclose(s.range_mm[~np.isnan(want)], want[~np.isnan(want)])
    assert (s.t0, s.t1, s.t_mid) == pytest.approx((7.0, 7.006, 7.003))


def test_intrinsics_folder_is_copied(bags, tmp_path):
    bag, rig = bags["ros2_png"]
    photos = tmp_path / "photos"
    photos.mkdir()
    img = np.random.default_rng(0).integers(0, 256, (40, 60), dtype=np.uint8)
    cv2.imwrite(str(photos / "a.png"), img)
    cv2.imwrite(str(photos / "b.jpg"), img)
    (photos / "notes.txt").write_text("not a photo")
    spec = {k: v for k, v in json.loads(rig.read_text()).items() if k != "camera"}
    spec.update(intrinsics="photos", intrinsics_board={"inner_corners": [9, 6], "square_mm": 25.0})
    (tmp_path / "rig.json").write_text(json.dumps(spec))
    import_bag(bag, tmp_path / "rig.json", tmp_path / "ds")
    ds = load_dataset(tmp_path / "ds")
    assert ds.camera is None and [p.name for p in ds.intrinsics_images()] == ["a.png", "b.png"]
    assert np.array_equal(cv2.imread(str(tmp_path / "ds" / "intrinsics" / "a.png"), 0), img)


@pytest.mark.parametrize("m", [3, 5, 12])
def test_combine_scans_is_a_clipped_mean_at_the_mean_s_noise(m):
    """A position's still scans are combined per beam by the mean of the returns near the
    beam's median (issue 13): against the true ranges, the combined error's variance is the
    mean's ``sigma^2 / m`` (2000 beams: the ratio's standard error is ~3 %, bounds 0.85..1.15)
    and clearly below the plain median's (1.35x for 3 scans, 1.43x for 5, ~1.5x for 12);
    a spurious return on 5 % of the beams (one scan far off; beams valid in every scan, as
    with two returns the median is no better) and invalid returns (NaN, inf)
    are left out, a beam without any valid return stays NaN, and ranges quantised far
    coarser than their noise combine to their median."""
    from lidarcal.io.bag import combine_scans

    rng = np.random.default_rng(m)
    sigma, n = 2.0, 2000
    true = rng.uniform(300.0, 5000.0, n)
    scans = [true + rng.normal(0.0, sigma, n) for _ in range(m)]
    bad = rng.choice(np.arange(n // 5, n - 1), n // 20, replace=False)  # beams valid in every scan
    scans[1][bad] = true[bad] + rng.choice([-1.0, 1.0], len(bad)) * rng.uniform(50, 3000, len(bad))
    scans[2][: n // 10] = np.nan
    scans[0][n // 10: n // 5] = np.inf
    for s in scans:
        s[-1] = np.nan
    got = combine_scans(scans)
    assert np.isnan(got[-1]) and np.isfinite(got[:-1]).all()
    clean = np.setdiff1d(np.arange(n // 5, n - 1), bad)
    ratio = np.var(got[clean] - true[clean]) / (sigma ** 2 / m)
    assert 0.85 < ratio < 1.15, ratio
    med = np.median(np.vstack(scans)[:, clean], axis=0)
    assert np.var(got[clean] - true[clean]) < 0.82 * np.var(med - true[clean])
    # the spurious returns left out: the outlier beams as noisy as a mean of m - 1
    assert np.abs(got[bad] - true[bad]).max() < 5 * sigma / np.sqrt(m - 1)
    # integer ranges with 0.1 mm noise: the clip keeps only the median's value
    q = [np.round(true[:200] + rng.normal(0.0, 0.1, 200)) for _ in range(m)]
    assert np.array_equal(combine_scans(q), np.median(np.vstack(q), axis=0))


@pytest.mark.parametrize("k", [2, 3, 4, 5, 8, 27])
def test_combine_frames_is_the_per_pixel_median(k):
    from lidarcal.io.bag import combine_frames

    rng = np.random.default_rng(k)
    frames = [rng.integers(0, 256, (6, 9, 3), dtype=np.uint8) for _ in range(k)]
    want = np.floor(np.median(np.stack(frames).astype(float), axis=0) + 0.5)
    got = combine_frames(frames)
    assert got.dtype == np.uint8 and np.array_equal(got, want)


def test_one_camera_topic_lit_board_then_dark_stripes(bags, rig_folder, tmp_path):
    """One /camera/image_raw/compressed: lit frames at the first stop, then dark ones."""
    bag, rig = bags["one_camera"]
    r = lidarcal("import", bag, "--rig", rig, "--out", tmp_path / "ds", "--no-progress")
    assert r.returncode == 0, r.stderr
    assert "6 positions" in r.stdout and "2 sweep(s)" in r.stdout
    assert_same_dataset(rig_folder, tmp_path / "ds")
    # the board is the median of the lit frames: the folder's board image, pixel for pixel
    assert np.array_equal(cv2.imread(str(tmp_path / "ds" / "board.png"), cv2.IMREAD_UNCHANGED),
                          cv2.imread(str(rig_folder / "board.png"), cv2.IMREAD_UNCHANGED))
    meta = json.loads((tmp_path / "ds" / "dataset.json").read_text())["import"]
    assert meta["topics"]["stripe"] == meta["topics"]["board"] == "/camera/image_raw/compressed"
    cam = meta["camera"]
    assert cam["single_camera_topic"] and cam["board_period"]["lit_frames"] == 2
    assert cam["board_period"]["psi_deg"] == pytest.approx(load_dataset(rig_folder).positions[0].psi_deg)
    # the first stop: two lit frames (the board) and two dark ones (its stripes)
    assert meta["positions"][0]["stripe_frames"] == 2
    # both topics named the same is the same one-camera import
    res = import_bag(bag, rig, tmp_path / "ds2", stripe_topic="/camera/image_raw",
                     board_topic="/camera/image_raw")
    assert len(res.positions) == 6
    assert_same_dataset(tmp_path / "ds", tmp_path / "ds2")
    assert_calibrates_like_the_folder(tmp_path / "ds", rig_folder, tmp_path, 6)


def test_a_stop_with_lit_frames_only_is_the_board_not_a_position(bags, rig_folder, tmp_path):
    bag, rig = bags["lit_first_stop"]  # /camera/image_raw, lights on for the whole first stop
    res = import_bag(bag, rig, tmp_path / "ds")
    first = load_dataset(rig_folder).positions[0].psi_deg
    assert len(res.positions) == 5 and all(abs(p.psi_deg - first) > 0.1 for p in res.positions)
    msg = [w for w in res.warnings if "lit frames only" in w]
    assert len(msg) == 1 and msg[0].startswith("/camera/image_raw: the still period at -0.00..2.0")
    assert f"(psi {first:.4f} deg) has lit frames only (the board): not a stripe position" in msg[0]
    assert np.array_equal(cv2.imread(str(tmp_path / "ds" / "board.png"), cv2.IMREAD_UNCHANGED),
                          cv2.imread(str(rig_folder / "board.png"), cv2.IMREAD_UNCHANGED))
    got, orig = load_dataset(tmp_path / "ds"), load_dataset(rig_folder)
    for pa, pb in zip(orig.positions[1:], got.positions):  # the other stops: as in the folder
        assert pb.psi_deg == pytest.approx(pa.psi_deg, abs=1e-9)
        assert np.array_equal(cv2.imread(str(pa.stripe_image), cv2.IMREAD_UNCHANGED),
                              cv2.imread(str(pb.stripe_image), cv2.IMREAD_UNCHANGED))


def test_one_camera_topic_without_lit_frames_is_one_line(bags, tmp_path):
    bag, rig = bags["ros2_png"]  # its stripe topic has dark frames only
    topic = "/camera/stripes/image_raw"
    r = lidarcal("import", bag, "--rig", rig, "--out", tmp_path / "x", "--stripe-topic", topic,
                 "--board-topic", topic)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert "no lit frame was found among its" in r.stderr and "--board-image" in r.stderr
    assert "(frame medians 2..2 of 255, one cluster)" in r.stderr
    assert not (tmp_path / "x").exists()


def test_several_stepping_joints_is_one_line(bags, tmp_path):
    bag, rig = bags["two_steppers"]
    r = lidarcal("import", bag, "--rig", rig, "--out", tmp_path / "x")
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert ("/turntable/joint_states has 2 joints (pan_dummy (6 still angles), turntable "
            "(6 still angles)) and 2 of them steps like a turntable; name the turntable with "
            "--joint") in r.stderr
    res = import_bag(bag, rig, tmp_path / "ds", joint="turntable")
    assert len(res.positions) == 6


class _Topic:
    def __init__(self, msgtype: str):
        self.msgtype = msgtype


class _Reader:
    """What pick_topic reads of a bag: its topics and their types."""

    def __init__(self, **topics: str):
        self.topics = {t.replace("__", "/").replace("_C", "/compressed"): _Topic(m)
                       for t, m in topics.items()}


def test_topic_auto_detection():
    from lidarcal.io.bag import COMPRESSED, IMAGE, IMAGE_TYPES, LASERSCAN, pick_topic

    # the same stream raw and compressed: the raw one, counted once
    rd = _Reader(__camera__image_raw=IMAGE, __camera__image_raw_C=COMPRESSED, __scan=LASERSCAN)
    for prefer in ("stripe", "board"):
        assert pick_topic(rd, None, IMAGE_TYPES, "image", "--stripe-topic", Path("b"),
                          prefer=prefer) == "/camera/image_raw"
    # only the compressed copy: that one
    rd = _Reader(__camera__image_raw_C=COMPRESSED)
    assert pick_topic(rd, None, IMAGE_TYPES, "image", "--x", Path("b"),
                      prefer="stripe") == "/camera/image_raw/compressed"
    # two cameras without 'stripe'/'board' in their names: ask
    rd = _Reader(__left__image_raw=IMAGE, __right__image_raw=IMAGE)
    with pytest.raises(DatasetError, match=r"2 stripe image topics .* name it with --stripe-topic; "
                                           r"the bag has: /left/image_raw \(sensor_msgs/Image\)"):
        pick_topic(rd, None, IMAGE_TYPES, "stripe image", "--stripe-topic", Path("b"),
                   prefer="stripe")
    # two LaserScan topics (/scan, /scan_filtered): ask for --scan-topic, listing both
    rd = _Reader(__scan=LASERSCAN, __scan_filtered=LASERSCAN)
    with pytest.raises(DatasetError, match=r"2 LaserScan topics \(sensor_msgs/msg/LaserScan\); "
                                           r"name it with --scan-topic; the bag has: /scan "
                                           r"\(sensor_msgs/LaserScan\), /scan_filtered"):
        pick_topic(rd, None, (LASERSCAN,), "LaserScan", "--scan-topic", Path("b"))
    assert pick_topic(rd, "/scan_filtered", (LASERSCAN,), "LaserScan", "--scan-topic",
                      Path("b")) == "/scan_filtered"


@pytest.mark.parametrize("dark,lit", [([2, 2, 3, 2, 2, 2], [61, 60]), ([10, 14, 12, 11], [90]),
                                      ([0, 1, 0, 0, 2], [40, 120, 41])])
def test_lit_dark_split_from_the_frame_medians(dark, lit):
    from lidarcal.io.bag_frames import split_lit_dark

    s = split_lit_dark(np.array(dark + lit, dtype=float))
    assert s.has_lit and max(dark) <= s.threshold < min(lit) and s.separability > 0.5
    # dark only (the dark level flickering by a few gray levels, or spread): no lit frame
    for one_cluster in (dark, [30, 31, 29, 30], [5], list(range(5, 41)), [2, 2, 2]):
        assert not split_lit_dark(np.array(one_cluster, dtype=float)).has_lit


class _JointReader:
    """A /joint_states topic fed by two publishers, each with its own joint (as a robot's
    joint_state_publisher and a turntable driver do): messages alternate between them."""

    def __init__(self, types):
        from types import SimpleNamespace

        self.connections = [SimpleNamespace(topic="/joint_states", msgtype=JOINT, id=0)]
        self.msgs = []
        for i in range(400):  # 50 Hz: 8 s, the turntable steps 1 deg every 2 s
            t = i * 0.02
            turn = math.radians(10.0 + np.floor(t / 2.0)) if (t % 2.0) < 1.6 else math.radians(
                10.0 + np.floor(t / 2.0) + ((t % 2.0) - 1.6) / 0.4)
            for name, val in (("turntable", turn), ("wheel", 0.3 * t)):
                ns = int(1e9 + t * 1e9)
                hdr = types["std_msgs/msg/Header"](
                    stamp=types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                    frame_id="")
                self.msgs.append((ns, types[JOINT](header=hdr, name=[name], position=np.array([val]),
                                                   velocity=np.zeros(0), effort=np.zeros(0))))

    def messages(self, connections):
        for ns, m in self.msgs:
            yield self.connections[0], ns, m

    def deserialize(self, raw, msgtype):
        return raw


JOINT = "sensor_msgs/msg/JointState"


def test_joint_states_from_two_publishers(ros2_types):
    """One joint per message, two joints on the topic: never mixed; the stepping one wins."""
    from lidarcal.io.bag import Clock, read_angles

    clock = Clock()
    a = read_angles(_JointReader(ros2_types), "/joint_states", None, "rad", Path("b"), clock)
    assert a.psi_deg.size == 400 and a.psi_deg.min() == pytest.approx(10.0)
    assert np.all(np.diff(a.psi_deg) >= -1e-9)  # the turntable only, no wheel readings mixed in
    assert "joint 'turntable' is the turntable (the only joint of turntable, wheel" in clock.notes[0]
    b = read_angles(_JointReader(ros2_types), "/joint_states", "wheel", "rad", Path("b"), Clock())
    assert np.allclose(np.diff(b.psi_deg), np.degrees(0.3 * 0.02))
    with pytest.raises(DatasetError, match=r"/joint_states: no joint 'pan' \(--joint\); its "
                                           r"joints: turntable, wheel"):
        read_angles(_JointReader(ros2_types), "/joint_states", "pan", "rad", Path("b"), Clock())
