"""The rig simulator: truth is self-consistent, files follow the contract, output is reproducible."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.geometry import Pose, rotation_about_axis
from lidarcal.io.dataset import load_dataset, read_image, read_scan, read_sweep
from lidarcal.synthetic import RIGS, make_truth, project_points, simulate, simulate_scans
from lidarcal.synthetic.scene import InfinitePlane, Rect

ROOT = Path(__file__).resolve().parents[1]
BUNDLED = ROOT / "data" / "paper_rig"


def small(rig: str, **kw):
    return RIGS[rig].with_(n_discs=2, **kw)


@pytest.fixture(scope="module")
def paper_ds(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("paper") / "ds"
    return simulate(out, seed=3, rig=small("paper"), n_positions=4, with_intrinsics=False)


# ---------------------------------------------------------------- truth (no rendering)

@pytest.mark.parametrize("rig", ["paper", "wide", "harsh"])
@pytest.mark.parametrize("seed", [0, 7])
def test_truth_follows_the_axis_model(rig: str, seed: int) -> None:
    t = make_truth(seed, rig, with_discs=False, with_intrinsics=False)
    cfg = t.rig
    k, a = t.axis_direction, t.axis_point
    assert np.isclose(np.linalg.norm(k), 1.0)
    assert np.degrees(np.arccos(abs(k[0]))) <= cfg.axis_tilt_deg + 1e-9
    lever = np.linalg.norm(np.cross(t.pose_ref.T - a, k))
    assert cfg.lever_arm_mm[0] - 1e-6 <= lever <= cfg.lever_arm_mm[1] + 1e-6
    poses = t.poses
    for i, pose in enumerate(poses):
        assert np.allclose(pose.R.T @ pose.R, np.eye(3), atol=1e-12) and np.linalg.det(pose.R) > 0
        # LiDAR upright (z ~ camera -y), looking forward (x ~ camera +z)
        assert pose.z_axis @ np.array([0, -1.0, 0]) > np.cos(np.radians(20))
        assert pose.x_axis[2] > np.cos(np.radians(25))
        # any two poses differ by the rotation about the axis by their psi difference
        j = (i * 7 + 3) % len(poses)
        Rk = rotation_about_axis(k, np.radians(t.psi_true_deg[j] - t.psi_true_deg[i]))
        assert np.allclose(poses[j].R, Rk @ pose.R, atol=1e-12)
        assert np.allclose(poses[j].T, a + Rk @ (pose.T - a), atol=1e-9)
    assert np.allclose(np.diff(t.psi_deg), cfg.psi_step_deg)
    assert np.abs(t.psi_true_deg - t.psi_deg).max() <= 6 * cfg.encoder_noise_deg + 1e-12


@pytest.mark.parametrize("rig", ["paper", "wide"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_v_board_visible_and_stripes_on_both_boards(rig: str, seed: int) -> None:
    t = make_truth(seed, rig, with_discs=False, with_intrinsics=False)
    cfg = t.rig
    w, h = cfg.image_size
    assert cfg.v_angle_deg[0] <= t.v_angle_deg <= cfg.v_angle_deg[1]
    n0, n1 = (b.plane.normal for b in t.boards)
    assert np.isclose(np.degrees(np.arccos(abs(n0 @ n1))), 180 - t.v_angle_deg, atol=1e-6)
    for b in t.boards:
        s = np.linspace(0, 1, 30)
        r = b.rect
        edge = np.vstack([r.point(s * r.width, 0 * s), r.point(s * r.width, 0 * s + r.height),
                          r.point(0 * s, s * r.height), r.point(0 * s + r.width, s * r.height)])
        px = project_points(edge, t.K, t.dist)
        assert px.min() >= 0 and px[:, 0].max() <= w - 1 and px[:, 1].max() <= h - 1
        # the board faces the camera
        centre = r.point(r.width / 2, r.height / 2)
        assert abs(r.normal @ centre / np.linalg.norm(centre)) > 0.2
    for pose in t.poses:
        n, d = pose.z_axis, pose.z_axis @ pose.T
        for b in t.boards:
            r = b.rect
            for u in (0.0, r.width):  # the stripe crosses the board from hinge to outer edge
                v = (d - n @ r.origin - u * (n @ r.e_u)) / (n @ r.e_v)
                assert 0 < v < r.height


def test_truth_is_deterministic_and_seed_dependent() -> None:
    a, b, c = (make_truth(s, "paper", with_discs=False, with_intrinsics=False) for s in (5, 5, 6))
    assert np.array_equal(a.pose_ref.R, b.pose_ref.R) and a.psi_deg.tolist() == b.psi_deg.tolist()
    assert not np.allclose(a.pose_ref.T, c.pose_ref.T)


def test_disc_trials_cross_the_scan_plane() -> None:
    t = make_truth(4, small("paper"), with_intrinsics=False)
    for d in t.discs:
        R, T = t.poses_at(d.psi_true_deg)
        s = np.einsum("ij,ij->i", R[:, :, 2], d.disc.centre - T)
        assert s.min() < -d.disc.radius * 0.3 and s.max() > d.disc.radius * 0.3  # sweep covers it
        assert np.isclose(np.diff(d.psi_deg), t.rig.sweep_step_deg).all()


# ---------------------------------------------------------------- LiDAR return model

def test_footprint_model_mixes_at_a_depth_edge() -> None:
    """A half-plane 1 m away in front of a wall 2 m away; beams sweep across its edge."""
    rig = RIGS["paper"].with_(range_noise_mm=0.0, beam_divergence_mrad=20.0, beam_exit_mm=0.0,
                              lidar_range_max_mm=5000.0, footprint_rings=4)
    near = Rect(np.array([-2000.0, -500, 1000]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 2000, 1000)
    wall = InfinitePlane(np.array([0, 0, 1.0]), 2000.0)
    R = np.column_stack([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])   # x forward, z up
    ang = np.linspace(-3, 3, 601)                   # edge at x = 0: beam angle 0
    r = simulate_scans([near, wall], R, np.zeros(3), rig, np.random.default_rng(0), ang)[0]
    # beam angle > 0 points to camera -x: the half plane (x < 0) is hit there
    on_near = ang > 0.8      # footprint radius 10 mrad * 1 m = 10 mm = 0.57 deg
    on_wall = ang < -0.8
    # tolerance: 0.05 mm of rounding plus the footprint-mean range on an oblique plane
    # (energy-weighted over a 20 mrad spot: <= ~0.1 mm at 3 deg incidence here)
    assert np.allclose(r[on_near], 1000 / np.cos(np.radians(ang[on_near])), atol=0.15)
    assert np.allclose(r[on_wall], 2000 / np.cos(np.radians(ang[on_wall])), atol=0.15)
    mid = r[np.abs(ang) < 0.3]
    # monotone across the edge, up to one 0.1 mm rounding step of the written ranges
    assert np.all(np.diff(r[np.abs(ang) < 0.8]) <= 0.1 + 1e-9)
    assert np.any((mid > 1100) & (mid < 1900))                    # mixed pixels float between


# ---------------------------------------------------------------- rendered datasets

def test_contract_paper(paper_ds: Path) -> None:
    ds = load_dataset(paper_ds)
    truth = ds.truth()
    assert ds.camera is not None and len(ds.positions) == 4 and len(ds.measurements) == 2
    assert [p["index"] for p in truth["poses"]] == [p.index for p in ds.positions]
    for p in ds.positions:
        img = read_image(p.stripe_image, ds.image_size)
        ang, rng = read_scan(p.scan, ds.lidar)
        assert img.dtype == np.uint8 and np.allclose(ang, ds.lidar.angles_deg(), atol=5e-7)
        assert np.isfinite(rng).sum() > 100
    sw = read_sweep(ds.measurements[0].sweep, ds.lidar)
    assert sw["psi_deg"].nunique() > 50 and np.isfinite(sw["range_mm"]).any()
    assert read_image(ds.board_image, ds.image_size).std() > 30


@pytest.mark.parametrize("rig", ["wide", "harsh"])
def test_contract_other_rigs(rig: str, tmp_path: Path) -> None:
    out = simulate(tmp_path / rig, seed=1, rig=small(rig, n_intrinsics_views=4 if rig == "wide" else 0),
                   n_positions=3)
    ds = load_dataset(out)
    raw = json.loads((out / "dataset.json").read_text())
    if rig == "wide":
        assert "camera" not in raw and len(ds.intrinsics_images()) == 4
        assert ds.v_board.inner_corners == (7, 10) and ds.lidar.angle_step_deg == 0.25
    else:
        assert ds.camera is not None
        psi = [p["psi_deg"] for p in ds.truth()["poses"]]
        psi_true = [p["psi_true_deg"] for p in ds.truth()["poses"]]
        assert psi != psi_true                               # encoder noise
    for p in ds.positions:
        read_image(p.stripe_image, ds.image_size)
        read_scan(p.scan, ds.lidar)
    for m in ds.measurements:
        read_sweep(m.sweep, ds.lidar)


def _stripe_rows(img: np.ndarray, col: int, row_guess: float, half: int = 12) -> float | None:
    r0 = round(row_guess) - half
    prof = img[r0:r0 + 2 * half + 1, col].astype(float)
    prof = prof - np.median(img[:, col])
    prof[prof < 0] = 0
    if prof.max() < 40 or prof.max() >= 250:   # too dim (black square) or saturated
        return None
    k = int(prof.argmax())
    lo, hi = max(k - 6, 0), min(k + 7, len(prof))
    w = prof[lo:hi]
    return r0 + lo + float((w * np.arange(len(w))).sum() / w.sum())


def test_stripe_pixels_lie_on_the_projected_laser_lines(paper_ds: Path) -> None:
    truth = json.loads((paper_ds / "truth.json").read_text())
    K, dist = np.array(truth["camera"]["K"]), np.array(truth["camera"]["dist"])
    for p in truth["poses"][::3]:
        pose = Pose.from_dict(p)
        img = cv2.imread(str(paper_ds / "stripes" / f"{p['index']:04d}.png"), 0)
        n, d = pose.z_axis, pose.z_axis @ pose.T
        for b in truth["boards"]:
            o = np.array(b["outline_mm"][0])
            eu, ev = np.array(b["u_axis"]), np.array(b["v_axis"])
            w = b["size_mm"][0]
            u = np.linspace(0.15 * w, 0.85 * w, 400)
            v = (d - n @ o - u * (n @ eu)) / (n @ ev)
            px = project_points(o + np.outer(u, eu) + np.outer(v, ev), K, dist)
            errs = []
            for col in range(int(px[:, 0].min()) + 1, int(px[:, 0].max()), 3):
                row = np.interp(col, *zip(*sorted(zip(px[:, 0], px[:, 1]))))
                found = _stripe_rows(img, col, row)
                if found is not None:
                    errs.append(found - row)
            assert len(errs) > 50
            assert abs(np.median(errs)) < 0.3, np.median(errs)


def test_board_returns_lie_on_the_truth_planes(paper_ds: Path) -> None:
    ds = load_dataset(paper_ds)
    truth = ds.truth()
    sigma = RIGS["paper"].range_noise_mm
    res = []
    for p, tp in zip(ds.positions, truth["poses"]):
        pose = Pose.from_dict(tp)
        ang, rng = read_scan(p.scan, ds.lidar)
        ok = np.isfinite(rng)
        a = np.radians(ang[ok])
        X = pose.apply(np.column_stack([rng[ok] * np.cos(a), rng[ok] * np.sin(a), np.zeros(ok.sum())]))
        for b in truth["boards"]:
            n, dd = np.array(b["normal"]), b["d_mm"]
            o, eu, ev = (np.array(b[k]) for k in ("outline_mm", "u_axis", "v_axis"))
            q = X - o[0]
            uu, vv = q @ eu, q @ ev
            inner = (uu > 20) & (uu < b["size_mm"][0] - 20) & (vv > 0) & (vv < b["size_mm"][1])
            dist = X[inner] @ n - dd
            res.append(dist[np.abs(dist) < 10 * sigma])
            assert inner.sum() > 100
    res = np.concatenate(res)
    assert abs(res.mean()) < 0.1 * sigma
    assert 0.6 * sigma < res.std() < 1.05 * sigma    # range noise projected on the normal


def test_disc_returns_lie_on_the_disc(paper_ds: Path) -> None:
    ds = load_dataset(paper_ds)
    truth = ds.truth()
    t = make_truth(3, small("paper").with_(n_positions=4), with_intrinsics=False)
    for m, d in zip(ds.measurements, t.discs):
        sw = read_sweep(m.sweep, ds.lidar).dropna()
        R, T = t.poses_at(np.interp(sw["psi_deg"], d.psi_deg, d.psi_true_deg))
        a = np.radians(sw["angle_deg"].to_numpy())
        r = sw["range_mm"].to_numpy()
        X = np.einsum("nij,nj->ni", R, np.column_stack([r * np.cos(a), r * np.sin(a), 0 * r])) + T
        c, nrm = np.array(truth["measurements"][0]["center_mm"]), d.disc.normal
        c = d.disc.centre
        h = (X - c) @ nrm
        rad = np.linalg.norm((X - c) - np.outer(h, nrm), axis=1)
        on = (np.abs(h) < 5) & (rad < d.disc.radius + 10)
        assert on.sum() > 500
        assert np.abs(h[on & (rad < d.disc.radius - 5)]).std() < 1.5 * RIGS["paper"].range_noise_mm
        above = X[:, 1] < c[1]          # the post holds the disc from below (camera y down)
        assert d.disc.radius - 3 < rad[on & above].max() < d.disc.radius + 2


# ---------------------------------------------------------------- reproducibility

def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_same_seed_same_bytes_other_seed_differs(tmp_path: Path) -> None:
    kw = {"rig": "paper", "n_positions": 3, "with_sweeps": False, "with_intrinsics": False}
    a = _files(simulate(tmp_path / "a", seed=11, **kw))
    b = _files(simulate(tmp_path / "b", seed=11, **kw))
    c = _files(simulate(tmp_path / "c", seed=12, **kw))
    assert a == b
    assert a["stripes/0001.png"] != c["stripes/0001.png"] and a["truth.json"] != c["truth.json"]


def test_refuses_to_overwrite(tmp_path: Path) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="not empty"):
        simulate(tmp_path, seed=0, n_positions=3, with_sweeps=False, with_intrinsics=False)
    with pytest.raises(ValueError, match="unknown rig"):
        simulate(tmp_path / "x", rig="nope")


def _approx_equal(a, b, rel: float = 1e-12) -> bool:
    """Same JSON structure; numbers equal to ``rel`` (relative, with an absolute floor of ``rel``)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_approx_equal(a[k], b[k], rel) for k in a)
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(_approx_equal(x, y, rel) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        return abs(a - b) <= rel * max(1.0, abs(a), abs(b))
    return a == b


@pytest.mark.skipif(not (BUNDLED / "dataset.json").is_file(), reason="bundled dataset not generated")
def test_bundled_dataset_regenerates(tmp_path: Path) -> None:
    """``simulate('data/paper_rig', seed=0, rig='paper')`` reproduces the bundled files (subset)."""
    idx = [0, 43, 86]
    out = simulate(tmp_path / "re", seed=0, rig="paper", positions=idx, with_intrinsics=False,
                   with_sweeps=False)
    for i in idx:
        for f in (f"stripes/{i:04d}.png", f"scans/{i:04d}.csv"):
            assert (out / f).read_bytes() == (BUNDLED / f).read_bytes(), f
    assert (out / "board.png").read_bytes() == (BUNDLED / "board.png").read_bytes()
    rows = (BUNDLED / "positions.csv").read_text().splitlines()
    assert (out / "positions.csv").read_text().splitlines() == [rows[0]] + [rows[i + 1] for i in idx]
    new, old = (json.loads((p / "truth.json").read_text()) for p in (out, BUNDLED))
    # geometry to the last few ulps: the rendered bytes above are the real check, and
    # BLAS / SIMD paths may round a normal's last digit differently on another CPU
    assert _approx_equal(new["poses"], [old["poses"][i] for i in idx])
    for key in ("camera", "boards", "axis", "pose_ref", "hinge", "wall", "posts"):
        assert _approx_equal(new[key], old[key]), key
    dnew, dold = (json.loads((p / "dataset.json").read_text()) for p in (out, BUNDLED))
    for key in ("format", "camera", "v_board", "lidar", "synthetic"):
        assert dnew[key] == dold[key], key
    assert len(old["measurements"]) == 10 and len(old["poses"]) == 87
