"""The LiDAR ranging model (lidarcal.ranging) and its estimation in the joint fit, against truth."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest
from ranging_data import dark_hits

from lidarcal.evaluate import pose_error
from lidarcal.io.dataset import DatasetError, load_dataset, read_scan
from lidarcal.joint import fit_joint_data, joint_data
from lidarcal.ranging import (
    RangingModel,
    RangingPrior,
    black_parity,
    dark_returns,
    ranging_prior,
    ranging_text,
)
from lidarcal.study import StudySetting, simulate_rig

RIG = StudySetting(n_positions=22)


@pytest.fixture(scope="module")
def sim():
    return simulate_rig(11, RIG)


def _biased(sim, offset_mm: float, dark_extra_mm: float, give_dark: bool):
    """The rig's joint data with every board range ``offset_mm`` farther and returns from black
    squares (truth: the simulator's colour rule at the true hit) ``dark_extra_mm`` farther."""
    d = joint_data(sim.result, "pnp")
    truth = {"boards": [b.to_dict() for b in sim.truth.boards]}
    spec = sim.result.dataset.v_board
    X = np.zeros((len(d.scan_xy), 3))
    for i, idx in enumerate(d.indices):
        m = d.scan_pos == i
        p = sim.true_poses[int(idx)]
        X[m] = d.scan_xy[m, :1] * p.R[:, 0] + d.scan_xy[m, 1:] * p.R[:, 1] + p.T
    dark = dark_hits(truth, spec.square_mm, spec.inner_corners, X).astype(float)
    u = d.scan_xy / np.linalg.norm(d.scan_xy, axis=1)[:, None]
    xy = d.scan_xy + (offset_mm + dark_extra_mm * dark)[:, None] * u
    return replace(d, scan_xy=xy, scan_dark=dark if give_dark else None)


def _fit(sim, data, **kw):
    res = sim.result
    m = fit_joint_data(data, [res.rigid_model, res.paper_model], **kw)
    err = [pose_error(m.pose(p.psi_deg), sim.true_poses[p.index]) for p in res.positions]
    sig = m.sigma(res.psi_deg)
    return m, {q: np.array([e[q] for e in err]) for q in ("centre_mm", "z_axis_deg", "x_axis_deg")}, sig


def test_offset_recovered_with_the_rig(sim):
    """Ranges 8 mm too far: the fit finds the offset within 3 sigma and the pose stays within
    3 sigma of the truth; without the model the centre is several mm off."""
    data = _biased(sim, 8.0, 0.0, give_dark=False)
    m, err, sig = _fit(sim, data)
    r = m.ranging
    # the boards' blackness maps let the fit see black squares too: dark_extra, if estimated,
    # is not significant here and is held at its prior's mean
    assert r.estimated[0] == "offset" and "offset" in r.determined and "offset" not in r.held
    assert set(r.estimated) - {"offset"} <= set(r.held)
    assert abs(r.offset_mm - 8.0) <= 3 * r.offset_sigma_mm
    assert r.offset_sigma_mm < 1.0
    for q in err:
        assert np.all(err[q] <= 3 * sig[q].to_numpy()), q
    _, err0, _ = _fit(sim, data, ranging=False)
    assert err0["centre_mm"].mean() > 3.0 > 3 * err["centre_mm"].mean()


def test_dark_extra_recovered(sim):
    """Black squares 6 mm farther, plus a 3 mm offset: both terms within 3 sigma."""
    m, err, sig = _fit(sim, _biased(sim, 3.0, 6.0, give_dark=True))
    r = m.ranging
    assert r.estimated == ("offset", "dark_extra")
    assert abs(r.dark_extra_mm - 6.0) <= 3 * r.dark_extra_sigma_mm + 1e-3
    assert abs(r.offset_mm - 3.0) <= 3 * r.offset_sigma_mm
    for q in err:
        assert np.all(err[q] <= 3 * sig[q].to_numpy()), q


def test_clean_rig_keeps_its_accuracy_and_shows_the_cost(sim):
    """No ranging error: the offset is not significant, so it is held at the prior's mean and
    the poses are those of exact ranges; the pose sigmas still grow by the extra parameter
    (the covariance is marginal over it)."""
    data = _biased(sim, 0.0, 0.0, give_dark=False)
    m, err, sig = _fit(sim, data)
    assert set(m.ranging.held) == set(m.ranging.estimated) and m.ranging.offset_mm == 0.0
    m0, err0, sig0 = _fit(sim, data, ranging=False)
    assert m0.ranging is None
    assert err["centre_mm"].mean() == pytest.approx(err0["centre_mm"].mean(), abs=0.02)
    assert sig["centre_mm"].mean() > 1.2 * sig0["centre_mm"].mean()


def test_tight_prior_decides_and_says_so(sim):
    """A prior far tighter than the data: the prior decides, a warning says the data do not
    separate the offset, and the pose sigmas come back to those of exact ranges."""
    data = _biased(sim, 0.0, 0.0, give_dark=False)
    m, _, sig = _fit(sim, data, ranging_prior=RangingPrior(0.0, 0.01, source="datasheet"))
    assert abs(m.ranging.offset_mm) < 0.01 and m.ranging.offset_sigma_mm < 0.011
    assert "offset" not in m.ranging.determined
    assert any("do not separate the range offset" in w and "datasheet prior 0 +- 0.01 mm" in w
               for w in m.warnings)
    _, _, sig0 = _fit(sim, data, ranging=False)
    assert sig["centre_mm"].mean() == pytest.approx(sig0["centre_mm"].mean(), rel=0.05)


def test_ranging_prior_from_dataset_json(tmp_path):
    assert ranging_prior({"lidar": {}}, tmp_path) == RangingPrior()
    p = ranging_prior({"lidar": {"range_offset_mm": 4, "range_offset_sigma_mm": 30}}, tmp_path)
    assert (p.offset_mm, p.offset_sigma_mm, p.source) == (4.0, 30.0, "dataset.json")
    with pytest.raises(DatasetError, match="range_offset_mm' must be a finite number"):
        ranging_prior({"lidar": {"range_offset_mm": "4 mm"}}, tmp_path / "dataset.json")
    with pytest.raises(DatasetError, match="range_offset_sigma_mm' must be > 0"):
        ranging_prior({"lidar": {"range_offset_sigma_mm": 0}}, tmp_path / "dataset.json")


def test_black_squares_as_the_simulator_colours_them(small_dataset):
    """Colour of the square each beam hits, from the bright image and the PnP board pose,
    against the simulator's own rule at the true hit (every return of every position)."""
    from lidarcal.pipeline import camera_for, find_boards

    ds = load_dataset(small_dataset)
    truth = ds.truth()
    camera, _ = camera_for(ds)
    boards = find_boards(ds, camera)
    parity = [black_parity(b, camera, ds.v_board) for b in boards]
    assert all(p in (0, 1) for p in parity)
    poses = {int(p["index"]): p for p in truth["poses"]}
    agree, n = 0, 0
    for pos in ds.positions:
        ang, rng = read_scan(pos.scan, ds.lidar)
        ok = np.isfinite(rng)
        th = np.radians(ang[ok])
        R, T = np.asarray(poses[pos.index]["R"]), np.asarray(poses[pos.index]["T_mm"])
        dirs = np.column_stack([np.cos(th), np.sin(th)]) @ R[:, :2].T
        X = T + rng[ok, None] * dirs
        want = dark_hits(truth, ds.v_board.square_mm, ds.v_board.inner_corners, X, tol_mm=3.0)
        on = np.zeros(len(X), bool)
        got = np.zeros(len(X))
        for b, view in enumerate(boards):
            n_b = view.R_pnp[:, 2]
            near = np.abs((X - view.T_pnp) @ n_b) < 3.0
            on |= near
            got[near] = dark_returns(np.broadcast_to(T, (near.sum(), 3)), dirs[near], view.R_pnp,
                                     view.T_pnp, ds.v_board, parity[b], blend_mm=0.0)[near[near]]
        agree += int(np.sum((got[on] > 0.5) == want[on]))
        n += int(on.sum())
    assert n > 500
    assert agree / n > 0.97  # the rest: within ~1 mm of a square edge (pose and range noise)


def test_ranging_model_round_trip_and_text():
    r = RangingModel(8.1, 0.3, 5.9, 0.05, estimated=("offset", "dark_extra"),
                     determined=("offset",))
    assert RangingModel.from_dict(json.loads(json.dumps(r.to_dict()))).offset_mm == 8.1
    got = r.correct(np.array([1000.0, np.nan, 0.0, 2000.0]), dark=np.array([0, 0, 0, 1.0]))
    np.testing.assert_allclose(got, [991.9, np.nan, 0.0, 2000.0 - 8.1 - 5.9])
    txt = ranging_text(r.to_dict())
    assert "+8.10 mm +- 0.30 mm" in txt and "prior decides" in txt
    typ = ranging_text(r, fmt="typst")
    assert typ.startswith("#table(") and "[+5.90]" in typ
    assert "no ranging model" in ranging_text(None)


def test_cli_writes_ranging_and_points_apply_it(small_dataset, tmp_path):
    """`lidarcal calibrate` writes the ranging block; Calibration.points subtracts the offset."""
    from lidarcal.api import load_calibration

    out = tmp_path / "cal"
    p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(small_dataset), "--out",
                        str(out), "--no-progress"], capture_output=True, text=True, check=False)
    assert p.returncode == 0, p.stderr
    data = json.loads((out / "calibration.json").read_text())
    rg = data["ranging"]
    for key in ("offset_mm", "offset_sigma_mm", "dark_extra_mm", "dark_extra_sigma_mm", "model"):
        assert key in rg
    assert np.isfinite(rg["offset_sigma_mm"]) and rg["offset_sigma_mm"] > 0
    data["ranging"]["offset_mm"] = 10.0
    data["model"]["ranging"]["offset_mm"] = 10.0
    (out / "calibration.json").write_text(json.dumps(data))
    cal = load_calibration(out)
    a = cal.points(0.0, [0.0], [1500.0])
    b = cal.points(0.0, [0.0], [1510.0])
    T = cal.pose(0.0).T
    np.testing.assert_allclose(np.linalg.norm(a - T), 1490.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(b - T), 1500.0, atol=1e-6)


def test_measure_corrects_ranges_before_eq28():
    """measure's points (eq. 28) subtract the calibration's range offset first."""
    import pandas as pd

    from lidarcal.geometry import Pose
    from lidarcal.measure import sweep_points

    class Fn:  # a pose function carrying a ranging model, as a loaded joint calibration does
        def __init__(self, offset_mm: float):
            self.ranging = RangingModel(offset_mm=offset_mm)

        def pose(self, psi_deg: float) -> Pose:
            return Pose(np.eye(3), np.array([10.0, 20.0, 30.0]))

    sweep = pd.DataFrame({"psi_deg": [0.0, 0.0], "angle_deg": [0.0, 30.0], "range_mm": [1500.0, 0.0]})
    biased = sweep.assign(range_mm=[1507.0, 0.0])
    a = sweep_points(sweep, Fn(0.0))
    b = sweep_points(biased, Fn(7.0))
    np.testing.assert_allclose(b[0], a[0])
    np.testing.assert_allclose(b[1], a[1])  # no return stays no return (range 0)


def test_cli_bad_range_offset_prior_exits_2(dataset_copy, tmp_path):
    """A non-positive lidar.range_offset_sigma_mm: one line naming dataset.json, exit 2, no output."""
    path = dataset_copy / "dataset.json"
    meta = json.loads(path.read_text())
    meta["lidar"]["range_offset_sigma_mm"] = -3
    path.write_text(json.dumps(meta))
    out = tmp_path / "cal"
    p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(dataset_copy), "--out",
                        str(out), "--no-progress"], capture_output=True, text=True, check=False)
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and "dataset.json" in lines[0]
    assert "range_offset_sigma_mm' must be > 0" in lines[0]
    assert not (out / "calibration.json").exists()


def test_fragmented_scan_segments_are_named(sim):
    """A V split that kept only fragments of the boards (as a staircase of ranges can make it)
    is named in a warning; whole segments are not."""
    d = _biased(sim, 0.0, 0.0, give_dark=False)
    m, _, _ = _fit(sim, d)
    assert not any("fragments" in w for w in m.warnings)
    keep = np.zeros(len(d.scan_xy), bool)
    for g in np.unique(d.scan_pos * 2 + d.scan_board):  # the middle fifth of every segment
        idx = np.flatnonzero(d.scan_pos * 2 + d.scan_board == g)
        keep[idx[2 * len(idx) // 5:3 * len(idx) // 5]] = True
    cut = replace(d, scan_xy=d.scan_xy[keep], scan_pos=d.scan_pos[keep],
                  scan_board=d.scan_board[keep])
    m, _, _ = _fit(sim, cut)
    assert any("fragments" in w and f"at {d.n_positions} of {d.n_positions}" in w
               for w in m.warnings)


def test_dark_extra_sigma_spans_the_unknown_edge_width():
    """The dark extra's sigma beyond the data (``_ranging_sigmas``' edge term) is the error of
    reading a return near a square edge with the EDGE_BLEND_MM ramp when the footprint's true
    profile across the edge is unknown: least squares of ``offset + extra * share`` on the
    ramp's shares, with the true shares those of a step (footprint -> 0) or of a ramp twice as
    wide, moves the extra by +3.6 % and -8.7 % (checkerboard of 20 mm squares, uniform hits).
    The term must cover both within 2 sigma and be no larger than the larger of the two:
    rendered rigs (offset 8 mm, extra 6 mm, 22 positions, seeds 31-36) read 5.84-5.92 mm with
    sigma 0.26-0.32 mm."""
    from lidarcal.io.dataset import BoardSpec
    from lidarcal.joint.fit import _ranging_sigmas
    from lidarcal.joint.params import N_RIG
    from lidarcal.ranging import EDGE_BLEND_MM

    board = BoardSpec((14, 20), 20.0)
    rng = np.random.default_rng(3)
    xy = rng.uniform([0.0, 0.0], [260.0, 380.0], (200_000, 2))
    origins = np.column_stack([xy, np.full(len(xy), -1000.0)])
    dirs = np.tile([0.0, 0.0, 1.0], (len(xy), 1))

    def shares(blend_mm: float) -> np.ndarray:
        return dark_returns(origins, dirs, np.eye(3), np.zeros(3), board, 0, blend_mm)

    read = shares(EDGE_BLEND_MM)
    X = np.column_stack([np.ones(len(read)), read])
    extra = 6.0
    moved = [np.linalg.lstsq(X, extra * shares(b), rcond=None)[0][1] - extra
             for b in (1e-6, 2.0 * EDGE_BLEND_MM)]
    assert moved[0] > 0 > moved[1]  # a step reads the extra high, a wider profile low
    sigma = _ranging_sigmas(np.zeros((N_RIG + 2, N_RIG + 2)), None, np.array([0.0, extra]), read)[1]
    assert max(abs(m) for m in moved) <= 2 * sigma, (moved, sigma)
    assert sigma <= max(abs(m) for m in moved), (moved, sigma)
