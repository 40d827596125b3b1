"""``lidarcal import BAG --views``: one-board recordings (ROS 1 / ROS 2) -> view pairs -> planes.

The bags are written by rosbags' own writers from a simulated one-board rig
(:func:`lidarcal.synthetic.oneboard_bag.write_oneboard_bag`): 7 views, each held still for
1 s, scans at 40 Hz with fresh 3 mm noise and 2 % dropouts per scan, frames at 15 Hz with
fresh pixel noise, moving scans and frames in between. The truth: the hold windows, the
noise-free ranges of each view and the LiDAR pose.
"""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal.io.bag_views import (
    K_SIGMA,
    AgreeTest,
    StillInterval,
    beam_noise_mm,
    camera_from_info,
    import_views,
    sort_holds,
    still_runs,
)
from lidarcal.io.dataset import DatasetError
from lidarcal.io.pairs import read_view_pairs
from lidarcal.synthetic.bag import bag_start_s
from lidarcal.synthetic.oneboard import simulate_oneboard
from lidarcal.synthetic.oneboard_bag import true_ranges_mm, write_oneboard_bag

N_VIEWS = 7


def lidarcal(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *map(str, args)], capture_output=True,
                          text=True, check=False)


@pytest.fixture(scope="module")
def rig():
    return simulate_oneboard(0, N_VIEWS)


@pytest.fixture(scope="module")
def bags(rig, tmp_path_factory) -> dict:
    """name -> (bag, holds)."""
    root = tmp_path_factory.mktemp("oneboard_bags")
    out = {}
    for name, kw in {"ros1_raw": {"storage": "rosbag1", "images": "raw"},
                     "mcap_png": {"storage": "mcap", "images": "png",
                                  "distortion_model": "rational_polynomial"}}.items():
        bag = root / (f"{name}.bag" if kw["storage"] == "rosbag1" else name)
        out[name] = (bag, write_oneboard_bag(rig, bag, seed=3, **kw))
    return out


def assert_views_are_the_holds(folder: Path, bag: Path, holds, rig, n_scans_min: int = 30):
    """One view per hold, its frame inside the hold, its scan the hold's true ranges within
    the noise of a per-beam median of its scans."""
    meta = json.loads((folder / "views.json").read_text())
    pairs = read_view_pairs(folder)
    assert len(pairs) == len(meta["views"]) == len(holds)
    t0 = bag_start_s(bag)
    sigma = rig.range_noise_mm
    for pair, v, hold in zip(pairs, meta["views"], holds):
        assert pair.name == v["name"] and v["name"].startswith(f"view_{hold.index:03d}_t")
        t = v["t_s"] + t0
        assert hold.t_start_s <= t <= hold.t_end_s, (v, hold)
        assert hold.t_start_s - 0.03 <= v["t_start_s"] + t0 and v["t_end_s"] + t0 <= hold.t_end_s + 0.03
        n = v["scans"]
        assert n >= n_scans_min and v["frames"] >= 10
        truth = true_ranges_mm(rig, rig.views[hold.index].rect)
        np.testing.assert_array_equal(np.isfinite(pair.range_mm), np.isfinite(truth))  # dropouts gone
        d = (pair.range_mm - truth)[np.isfinite(truth)]
        # the median of n scans of N(0, sigma) integer-mm readings: sd sigma sqrt(pi / (2 n)),
        # plus the 1 mm rounding (1/12 mm^2)
        sd = math.sqrt(sigma**2 * math.pi / (2 * n) + 1 / 12)
        assert np.sqrt(np.mean(d**2)) < 1.25 * sd, (pair.name, np.sqrt(np.mean(d**2)), sd)
        assert np.abs(d).max() < 5 * sd
        np.testing.assert_allclose(pair.angle_deg, rig.views[0].angle_deg, atol=1e-5)
    # the measured noise is the injected one (3 mm, integer readings)
    assert abs(meta["scan_noise_mm"]["median"] - sigma) < 0.1 * sigma, meta["scan_noise_mm"]
    assert meta["range_quantum_mm"] == pytest.approx(1.0, abs=1e-3)


def test_import_views_cli_then_planes(bags, rig, tmp_path):
    """The documented commands: ``lidarcal import rec.bag --views --pattern 8x5 --square-mm 80
    --out VIEWS`` then ``lidarcal planes VIEWS --camera VIEWS/camera.json --out OUT`` (the
    board read from VIEWS/board.json)."""
    bag, holds = bags["ros1_raw"]
    views = tmp_path / "VIEWS"
    p = lidarcal("import", bag, "--views", "--pattern", "8x5", "--square-mm", "80", "--out", views)
    assert p.returncode == 0, p.stderr
    assert "warning" not in p.stderr, p.stderr
    assert f"{N_VIEWS} still interval(s) -> {N_VIEWS} views (0 merged" in p.stdout
    assert "camera.json written" in p.stdout and "board.json written" in p.stdout
    assert json.loads((views / "board.json").read_text()) == {"inner_corners": [8, 5],
                                                              "square_mm": 80.0}
    meta = json.loads((views / "views.json").read_text())
    assert [iv["view"] for iv in meta["still_intervals"]] == [v["name"] for v in meta["views"]]
    assert_views_are_the_holds(views, bag, holds, rig)
    cam = json.loads((views / "camera.json").read_text())
    np.testing.assert_allclose(cam["K"], rig.camera.K)
    np.testing.assert_allclose(cam["dist"], rig.camera.dist)
    assert cam["image_size"] == list(rig.camera.image_size)
    assert not [f for f in views.parent.iterdir() if f.name.startswith(".")]  # no temp folder left

    out = tmp_path / "OUT"
    p = lidarcal("planes", views, "--camera", views / "camera.json", "--out", out, "--no-figures")
    assert p.returncode == 0, p.stderr
    doc = json.loads((out / "extrinsics.json").read_text())
    assert all(v["used"] for v in doc["views"]) and len(doc["views"]) == N_VIEWS
    R, T = np.array(doc["R"]), np.array(doc["T_mm"])
    d_rot = np.degrees(Rotation.from_matrix(R @ rig.R.T).as_rotvec())
    sig_r = np.array(doc["sigma"]["rotation_deg"], float)
    sig_t = np.array(doc["sigma"]["translation_mm"], float)
    assert np.all(np.abs(d_rot) <= 4 * sig_r), (d_rot, sig_r)
    assert np.all(np.abs(T - rig.T) <= 4 * sig_t), (T - rig.T, sig_t)
    assert sig_r.max() < 0.5 and sig_t.max() < 12  # a usable calibration, not inflated


def test_ros2_mcap_compressed_gives_the_same_views(bags, rig, tmp_path):
    # the same recording as mcap with PNG CompressedImage frames: byte-identical view pairs;
    # rational_polynomial with k4..k6 = 0 is the same 5-coefficient camera
    a, b = tmp_path / "ros1", tmp_path / "mcap"
    ra = import_views(bags["ros1_raw"][0], a)
    rb = import_views(bags["mcap_png"][0], b)
    assert [v.name for v in ra.views] == [v.name for v in rb.views]
    assert rb.topics["image"] == "/camera/image_raw/compressed" and not rb.warnings
    for v in rb.views:
        for ext in (".png", ".csv"):
            assert (a / f"{v.name}{ext}").read_bytes() == (b / f"{v.name}{ext}").read_bytes()
    assert json.loads((a / "camera.json").read_text())["dist"] == \
        json.loads((b / "camera.json").read_text())["dist"]
    assert_views_are_the_holds(b, bags["mcap_png"][0], bags["mcap_png"][1], rig)


def test_sqlite3_jpeg_equidistant_camera_is_a_warning(tmp_path):
    # another rig, ROS 2 sqlite3, JPEG frames (their noise is not Gaussian), a fisheye
    # CameraInfo: the views are found, camera.json is not written and the warning says why
    rig = simulate_oneboard(1, 5)
    bag = tmp_path / "rec"
    holds = write_oneboard_bag(rig, bag, storage="sqlite3", images="jpeg", seed=5,
                               distortion_model="equidistant", hold_s=0.8)
    res = import_views(bag, tmp_path / "v")
    assert len(res.views) == 5 and not res.camera_written
    assert not (tmp_path / "v" / "camera.json").exists()
    assert any("equidistant (fisheye)" in w and "lidarcal intrinsics" in w for w in res.warnings)
    assert_views_are_the_holds(tmp_path / "v", bag, holds, rig, n_scans_min=24)


@pytest.fixture(scope="module")
def small_rig():
    return simulate_oneboard(4, 3)


def _one_line_error(p: subprocess.CompletedProcess, *needles: str) -> None:
    assert p.returncode == 2, (p.stdout, p.stderr)
    assert p.stderr.count("\n") == 1 and p.stderr.startswith("error: "), p.stderr
    for n in needles:
        assert n in p.stderr, (n, p.stderr)


def test_bad_recordings_are_one_line_and_write_nothing(small_rig, tmp_path):
    out = tmp_path / "views"
    # no LaserScan topic
    bag = tmp_path / "noscan.bag"
    write_oneboard_bag(small_rig, bag, with_scans=False, distortion_model=None)
    p = lidarcal("import", bag, "--views", "--out", out)
    _one_line_error(p, "noscan.bag", "no LaserScan topics", "--scan-topic", "/camera/image_raw")
    assert not out.exists()
    # two cameras, no option: ambiguous; --image-topic picks one (3 views: a warning)
    bag = tmp_path / "two"
    write_oneboard_bag(small_rig, bag, storage="mcap", second_camera=True)
    p = lidarcal("import", bag, "--views", "--out", out)
    _one_line_error(p, "2 camera image topics", "--image-topic", "/camera2/image_raw")
    assert not out.exists()
    p = lidarcal("import", bag, "--views", "--out", out, "--image-topic", "/camera2/image_raw")
    assert p.returncode == 0, p.stderr
    assert "only 3 view(s)" in p.stderr and "3 views" in p.stdout
    assert len(list(out.glob("*.csv"))) == 3
    # an existing output folder needs --overwrite
    p = lidarcal("import", bag, "--views", "--out", out, "--image-topic", "/camera2/image_raw")
    _one_line_error(p, "--overwrite")
    p = lidarcal("import", bag, "--views", "--out", out, "--image-topic", "/camera/image_raw",
                 "--overwrite")
    assert p.returncode == 0 and len(list(out.glob("*.png"))) == 3, p.stderr
    # the board never held still
    bag = tmp_path / "moving.bag"
    write_oneboard_bag(small_rig, bag, hold_s=0.0, move_s=1.0, profile="linear")
    p = lidarcal("import", bag, "--views", "--out", tmp_path / "none")
    _one_line_error(p, "moving.bag", "no still interval", "hold the board still")
    assert not (tmp_path / "none").exists()
    assert not [f.name for f in tmp_path.iterdir() if f.name.startswith(".")]


def _planes_vs_truth(folder: Path, rig) -> tuple[np.ndarray, np.ndarray]:
    """|error| / sigma of ``lidarcal planes`` on a views folder: rotation (x, y, z), T (x, y, z)."""
    from lidarcal.planes import run_planes

    res = run_planes(folder, folder / "camera.json", rig.board)
    assert all(res.used)
    d_rot = np.degrees(Rotation.from_matrix(res.R @ rig.R.T).as_rotvec())
    return (np.abs(d_rot) / np.array(res.uncertainty.rotation_deg, float),
            np.abs(res.T - rig.T) / np.array(res.uncertainty.translation_mm, float))


def test_a_pose_held_twice_is_one_view(tmp_path):
    # the board paused twice at view 1 (carried 150 mm sideways and back between the holds)
    # and brought back exactly to view 0 at the end: 7 holds of 5 poses -> 5 views, each
    # merged view the union of its holds' scans (median noise of 2n scans) and one frame
    rig = simulate_oneboard(2, 5)
    bag = tmp_path / "twice.bag"
    order = [0, 1, 1, 2, 3, 0, 4]
    holds = write_oneboard_bag(rig, bag, seed=7, order=order, hold_s=0.8)
    res = import_views(bag, tmp_path / "v")
    assert res.n_intervals == 7 and res.n_drifting == 0 and len(res.views) == 5
    assert [[holds[i].index for i in v.intervals] for v in res.views] == \
        [[0, 0], [1, 1], [2], [3], [4]]
    assert not [w for w in res.warnings if "moved slowly" in w]
    meta = json.loads((tmp_path / "v" / "views.json").read_text())
    assert [iv["view"] for iv in meta["still_intervals"]] == \
        [meta["views"][k]["name"] for k in (0, 1, 1, 2, 3, 0, 4)]
    pairs = read_view_pairs(tmp_path / "v")
    for pair, v in zip(pairs, meta["views"]):
        truth = true_ranges_mm(rig, rig.views[holds[v["intervals"][0]].index].rect)
        d = (pair.range_mm - truth)[np.isfinite(truth)]
        n = v["scans"]
        assert n >= 24 * len(v["intervals"])
        sd = math.sqrt(rig.range_noise_mm**2 * math.pi / (2 * n) + 1 / 12)
        assert np.sqrt(np.mean(d**2)) < 1.25 * sd, (pair.name, np.sqrt(np.mean(d**2)), sd)
    r, t = _planes_vs_truth(tmp_path / "v", rig)
    assert r.max() < 4 and t.max() < 4, (r, t)


@pytest.mark.parametrize("drift_mm", [3.0, 40.0])
def test_a_drifting_hold_is_not_a_view(drift_mm, tmp_path):
    # holds 1, 3 and 5 of 6 slide by drift_mm while "held" (3 mm: the range noise; consecutive
    # scans and frames agree, the drift only adds up): none of them gives a view, every other
    # hold gives exactly one
    rig = simulate_oneboard(2, 6)
    bag = tmp_path / "drift.bag"
    holds = write_oneboard_bag(rig, bag, seed=12, drift_mm=drift_mm, drift_holds=[1, 3, 5])
    res = import_views(bag, tmp_path / "v")
    t0 = bag_start_s(bag)
    inside = [[i for i, h in enumerate(holds) if h.t_start_s - 0.03 <= v.t_start_s + t0
               and v.t_end_s + t0 <= h.t_end_s + 0.03] for v in res.views]
    assert inside == [[0], [2], [4]], (inside, res.warnings)
    assert all(v.n_scans >= 30 for v in res.views)
    meta = json.loads((tmp_path / "v" / "views.json").read_text())
    dropped = [iv for iv in meta["still_intervals"] if iv["view"] is None]
    assert len(dropped) == res.n_drifting and all("drifting" in iv for iv in dropped)
    assert (sum("moved slowly" in w for w in res.warnings) > 0) == (res.n_drifting > 0)


def test_bad_board_options_are_one_line(tmp_path):
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"")
    for args, needle in [(["--pattern", "8by5", "--square-mm", "80"], "--pattern: expected COLSxROWS"),
                         (["--pattern", "1x5", "--square-mm", "80"], "each >= 2"),
                         (["--pattern", "8x5", "--square-mm", "0"], "--square-mm: expected a number > 0"),
                         (["--pattern", "8x5", "--square-mm", "-3"], "--square-mm: expected a number > 0"),
                         (["--pattern", "8x5"], "go together"),
                         (["--square-mm", "80"], "go together")]:
        p = lidarcal("import", bag, "--views", "--out", tmp_path / "o", *args)
        _one_line_error(p, needle)
    p = lidarcal("import", bag, "--rig", tmp_path / "RIG.json", "--pattern", "8x5",
                 "--out", tmp_path / "o")
    _one_line_error(p, "--pattern is for a one-board recording")
    with pytest.raises(DatasetError, match="--square-mm must be a number > 0"):
        import_views(bag, tmp_path / "o", pattern=(8, 5), square_mm=float("nan"))
    assert sorted(f.name for f in tmp_path.iterdir()) == ["x.bag"]


def test_options_of_the_two_modes_do_not_mix(tmp_path):
    bag = tmp_path / "x.bag"
    bag.write_bytes(b"")
    p = lidarcal("import", bag, "--views", "--rig", tmp_path / "RIG.json", "--out", tmp_path / "o")
    _one_line_error(p, "--rig is for a turntable bag")
    p = lidarcal("import", bag, "--out", tmp_path / "o")
    _one_line_error(p, "needs --rig RIG.json", "--views")
    p = lidarcal("import", bag, "--rig", tmp_path / "RIG.json", "--image-topic", "/c",
                 "--out", tmp_path / "o")
    _one_line_error(p, "--image-topic is for a one-board recording")
    p = lidarcal("import", bag, "--rig", tmp_path / "RIG.json", "--min-scans", "9",
                 "--out", tmp_path / "o")
    _one_line_error(p, "--min-scans is for a one-board recording")
    with pytest.raises(DatasetError, match="--min-scans must be >= 3"):
        import_views(bag, tmp_path / "o", min_scans=2)


def test_truncated_and_junk_bags_are_one_line(bags, tmp_path):
    data = bags["ros1_raw"][0].read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])  # recording cut short
    p = lidarcal("import", tmp_path / "cut.bag", "--views", "--out", tmp_path / "v")
    _one_line_error(p, "cut.bag", "reindex")
    (tmp_path / "junk.bag").write_bytes(b"not a bag")
    p = lidarcal("import", tmp_path / "junk.bag", "--views", "--out", tmp_path / "v")
    _one_line_error(p, "junk.bag", "cannot be read as a ROS 1 or ROS 2 bag")
    assert sorted(f.name for f in tmp_path.iterdir()) == ["cut.bag", "junk.bag"]


# ----------------------------------------------------------------------------- pieces


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("quantised", [False, True])
def test_beam_noise_is_the_injected_noise(seed, quantised):
    # beams 0-99 see a moving board 10 % of the time: their quartile is inflated by about
    # Phi^-1((1 + 0.25 / 0.9) / 2) / Phi^-1(0.625) = 1.11, never deflated
    rng = np.random.default_rng(seed)
    sigma = rng.uniform(0.8, 12.0, 400)
    r = 2000 + rng.normal(0, 1, (600, 400)) * sigma
    r[:60, :100] += np.linspace(0, 900, 60)[:, None]
    if quantised:
        r = np.rint(r)
    r[rng.random(r.shape) < 0.03] = np.nan
    est, q = beam_noise_mm(r)
    assert (q == 1.0) if quantised else (q < 0.05)
    ratio = est / sigma
    # the quartile of ~580 pairs: about 7.5 % sampling error per beam
    assert np.median(np.abs(ratio[100:] - 1)) < 0.07
    assert np.all(np.abs(ratio[100:] - 1) < 0.3)
    assert 1.0 < np.median(ratio[:100]) < 1.2 and np.all(ratio[:100] > 0.8)


def _differ(noise: float):
    def differ(x, ref, f):  # as for scans: 3 of the 8 channels beyond 4 sigma
        return int(np.sum(np.abs(x - ref) > 4 * f * noise)) >= 3
    return differ


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_still_runs_are_the_holds(seed):
    # holds of random length joined by cosine moves of random speed, some slow enough that
    # consecutive readings never differ: each hold lies in one run; a run may reach into
    # the slow ends of a move, or be a slow stretch of one, but never spans more than the
    # noise allows (this channel alone cannot tell slow motion from stillness: the frames do)
    rng = np.random.default_rng(seed)
    noise, seq, holds = 1.0, [], []
    level = 0.0
    for _ in range(6):
        n = int(rng.integers(20, 60))
        holds.append((len(seq), len(seq) + n - 1))
        seq += [level] * n
        m, step = int(rng.integers(10, 40)), rng.uniform(30, 200) * rng.choice([-1, 1])
        seq += list(level + step * 0.5 * (1 - np.cos(np.pi * np.arange(1, m) / m)))
        level += step
    x = np.array(seq)[:, None] + rng.normal(0, noise, (len(seq), 8))
    runs = still_runs(x, _differ(noise), 5)
    for h0, h1 in holds:
        assert sum(a <= h0 + 1 and b >= h1 - 1 for a, b in runs) == 1, (h0, h1, runs)
    for a, b in runs:
        # every reading within 4 sigma (x sqrt(1 + pi / 10)) of the run's median, plus noise
        assert np.ptp(seq[a:b + 1]) <= 2 * 4 * (1 + math.sqrt(1 + math.pi / 10)) * noise
    assert not any(b1 >= a2 for (_, b1), (a2, _) in itertools.pairwise(runs))  # disjoint, in order


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sort_holds_merges_one_pose_and_drops_drift(seed):
    # one reading = a scan (60 beams, sigma 3 mm) and a frame's block means (6 x 8, sigma 0.5)
    # per step. Holds of 30 readings: A, B, B again after an excursion, C sliding by 10 sigma,
    # E sliding by 6 sigma in two pieces of 2 sigma each (their halves agree) with 3 readings
    # between them and no move, A again, D; moves of 10 readings between the holds.
    # -> views [A, A], [B, B], [D]; the three drifting intervals dropped
    rng = np.random.default_rng(seed)
    sig_s, sig_f = 3.0, 0.5
    poses = {k: (rng.uniform(1000, 3000, 60), rng.uniform(20, 230, (6, 8))) for k in "ABCDEX"}
    scans, blocks, intervals = [], [], []

    def add(pose_a, pose_b, n, hold: bool):
        (sa, fa), (sb, fb) = poses[pose_a], poses[pose_b]
        first = len(scans)
        for u in np.linspace(0, 1, n):
            scans.append((1 - u) * sa + u * sb + rng.normal(0, sig_s, 60))
            blocks.append((1 - u) * fa + u * fb + rng.normal(0, sig_f, (6, 8)))
        if hold:
            idx = list(range(first, len(scans)))
            intervals.append(StillInterval(first, len(scans) - 1, idx, idx, idx[n // 2]))

    # a slide of 10 sigma: C -> C' and E -> E' (the primed poses 10 sigma away)
    poses["C'"] = (poses["C"][0] + 10 * sig_s, poses["C"][1] + 10 * sig_f)
    for k, m in (("E1", 2), ("E2", 4), ("E'", 6)):
        poses[k] = (poses["E"][0] + m * sig_s, poses["E"][1] + m * sig_f)
    plan = [("A", 30), ("B", 30), ("X", 0), ("B", 30), ("C", 30), ("E", 15), ("A", 30),
            ("D", 30)]
    prev = None
    for pose, n in plan:
        if prev is not None:
            add(prev, pose, 10, False)  # carried
        if pose == "C":
            add("C", "C'", 30, True)
            prev = "C'"
        elif pose == "E":
            add("E", "E1", 15, True)
            add("E1", "E2", 3, False)  # a stretch the still runs left out, no move
            add("E2", "E'", 15, True)
            prev = "E'"
        else:
            if n:
                add(pose, pose, n, True)
            prev = pose
    test = AgreeTest(np.array(scans), np.array(blocks), np.full(60, K_SIGMA * sig_s), 0.0, sig_f)
    holds = sort_holds(intervals, test)
    # intervals: 0 A, 1 B, 2 B, 3 C (slides), 4 E1, 5 E2 (pieces of one slide), 6 A, 7 D
    assert holds.groups == [[0, 6], [1, 2], [7]], holds
    assert [ch for ch, _ in holds.drifting] == [[3], [4, 5]]
    assert "halves differ" in holds.why(3) and "2 still piece(s)" in holds.why(5)
    assert holds.why(0) is None


def _info(model: str, d, k=(650.0, 0, 320, 0, 650, 240, 0, 0, 1), size=(640, 480), ros1=False,
          binning=0, roi_w=0):
    f = {"distortion_model": model, "width": size[0], "height": size[1], "binning_x": binning,
         "binning_y": binning, "roi": SimpleNamespace(width=roi_w, height=0)}
    f.update({"D": list(d), "K": list(k)} if ros1 else {"d": list(d), "k": list(k)})
    return SimpleNamespace(**f)


def test_camera_info_to_camera_json():
    cam, why = camera_from_info(_info("plumb_bob", [-0.1, 0.02, 0.001, -0.002, 0.003]), "/c")
    assert why is None and cam["dist"] == [-0.1, 0.02, 0.001, -0.002, 0.003]
    assert cam["K"] == [[650, 0, 320], [0, 650, 240], [0, 0, 1]] and cam["image_size"] == [640, 480]
    cam, why = camera_from_info(_info("rational_polynomial", [-0.1, 0.02, 0.001, -0.002, 0.003,
                                                              0, 0, 0], ros1=True), "/c")
    assert why is None and cam["dist"] == [-0.1, 0.02, 0.001, -0.002, 0.003]
    cam, why = camera_from_info(_info("", []), "/c")
    assert cam["dist"] == [0.0] * 5
    for info, needle in [
            (_info("rational_polynomial", [0.1, 0, 0, 0, 0, 0.2, 0, 0]), "k4..k6"),
            (_info("equidistant", [0.1, 0, 0, 0]), "equidistant (fisheye)"),
            (_info("plumb_bob", [0] * 5, k=[0] * 9), "no calibration"),
            (_info("plumb_bob", [0] * 5, binning=2), "binning"),
            (_info("plumb_bob", [0] * 5, roi_w=100), "region of interest")]:
        cam, why = camera_from_info(info, "/cam/info")
        assert cam is None and needle in why and why.startswith("/cam/info: ")
        assert "lidarcal intrinsics" in why
