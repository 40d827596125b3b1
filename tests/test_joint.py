"""Joint fit of the rig (lidarcal.joint) against simulated truth.

Observations come from lidarcal.study.simulate_rig: the simulator's geometry
and ray-cast scans (footprint, mixed pixels, Gaussian range noise), board
corners and stripe centres projected through the lens with Gaussian pixel
noise (see the study module's docstring). No images are rendered, so the
tests are fast.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal.evaluate import axis_direction_error_deg, pose_error
from lidarcal.geometry import Pose
from lidarcal.joint import (
    JointModel,
    build_joint_data,
    fit_joint,
    fit_joint_data,
    irls_lm,
    joint_data,
    joint_warnings,
)
from lidarcal.study import StudySetting, simulate_rig
from lidarcal.turntable import RigidModel, model_from_dict

QUIET = StudySetting(n_positions=6, range_noise_mm=0.0, stripe_noise_px=0.0, stripe_offset_px=0.0,
                     corner_noise_px=0.0, corner_tilt_deg=0.0, corner_offset_mm=0.0)
NOISY = StudySetting(n_positions=8)


@pytest.fixture(scope="module")
def noisy_rigs():
    return [simulate_rig(seed, NOISY) for seed in (11, 12)]


def _errors(model, sim):
    res = sim.result
    est = model.pose(res.psi_deg)
    true = [sim.true_poses[p.index] for p in res.positions]
    return [pose_error(e, t) for e, t in zip(est, true)]


def test_noise_free_round_trip():
    """Exact stripes and corners, range noise 0 (only 0.1 mm rounding and mixed pixels remain)."""
    sim = simulate_rig(5, QUIET)
    m = fit_joint(sim.result)
    err = _errors(m, sim)
    # 0.1 mm range rounding (uniform, sigma 0.03 mm) over ~1e3 points per board
    assert max(e["centre_mm"] for e in err) < 0.02
    assert max(e["z_axis_deg"] for e in err) < 1e-4
    assert max(e["x_axis_deg"] for e in err) < 2e-3
    assert axis_direction_error_deg(m.axis.direction, sim.truth.axis_direction) < 1e-3


@pytest.mark.parametrize("i", [0, 1])
def test_noisy_errors_within_reported_sigma(noisy_rigs, i):
    """True errors within 3 reported sigmas; better than the single-shot samples."""
    sim = noisy_rigs[i]
    m = fit_joint(sim.result)
    err = _errors(m, sim)
    sig = m.sigma(sim.result.psi_deg)
    for q in ("centre_mm", "z_axis_deg", "x_axis_deg"):
        e = np.array([x[q] for x in err])
        assert np.all(e <= 3 * sig[q].to_numpy()), q
    samples = [pose_error(p.pose, sim.true_poses[p.index]) for p in sim.result.positions]
    assert np.mean([e["centre_mm"] for e in err]) < np.mean([e["centre_mm"] for e in samples])
    assert np.mean([e["x_axis_deg"] for e in err]) < np.mean([e["x_axis_deg"] for e in samples])
    assert axis_direction_error_deg(m.axis.direction, sim.truth.axis_direction) \
        <= 3 * m.sigma(0.0)["axis_direction_deg"]
    # noise estimates: the injected stripe noise is 0.03 px, range noise 1 mm
    for b in range(2):
        assert 0.02 < m.noise[f"stripe{b}_px"] < 0.045
        assert 0.7 < m.noise[f"scan{b}_mm"] < 1.3


def test_fit_planes_refines_boards(noisy_rigs):
    sim = noisy_rigs[0]
    m = fit_joint(sim.result, fit_planes=True)
    assert m.info["fit_planes"] and "corner_px" in m.noise
    err = _errors(m, sim)
    sig = m.sigma(sim.result.psi_deg)
    assert np.all(np.array([e["centre_mm"] for e in err]) <= 3 * sig["centre_mm"].to_numpy())


def test_planted_outliers_are_harmless(noisy_rigs):
    """Gross outliers in 2 % of the scan points and stripe centres barely move the robust fit."""
    sim = noisy_rigs[1]
    res = sim.result
    d = joint_data(res, "pnp")
    starts = [res.rigid_model, res.paper_model]
    clean = fit_joint_data(d, starts)
    rng = np.random.default_rng(0)
    xy, px = d.scan_xy.copy(), d.stripe_px.copy()
    i = rng.choice(len(xy), len(xy) // 50, replace=False)
    xy[i] *= 1 + rng.uniform(0.02, 0.1, (len(i), 1))  # 20-100 mm too far
    j = rng.choice(len(px), len(px) // 50, replace=False)
    px[j] += rng.normal(0, 5.0, (len(j), 2))  # 5 px
    scans = [tuple(xy[(d.scan_pos == p) & (d.scan_board == b)] for b in range(2))
             for p in range(d.n_positions)]
    stripes = [tuple(px[(d.stripe_pos == p) & (d.stripe_board == b)] for b in range(2))
               for p in range(d.n_positions)]
    bad = build_joint_data(d.camera, d.psi_deg, scans, stripes, d.board_R, d.board_T,
                           d.corners_px, d.object_points, d.samples)
    dirty = fit_joint_data(bad, starts)
    sig = clean.sigma(res.psi_deg)
    for p, q, s in zip(clean.pose(res.psi_deg), dirty.pose(res.psi_deg), sig.itertuples()):
        e = pose_error(q, p)
        assert e["centre_mm"] < s.centre_mm
        assert e["z_axis_deg"] < s.z_axis_deg and e["x_axis_deg"] < s.x_axis_deg


def test_serialisation_round_trip(noisy_rigs):
    sim = noisy_rigs[0]
    m = fit_joint(sim.result)
    d = json.loads(json.dumps(m.to_dict()))
    assert d["type"] == "joint"
    m2 = model_from_dict(d)
    assert isinstance(m2, JointModel)
    psi = np.array([-3.0, 0.0, 7.5])
    for a, b in zip(m.pose(psi), m2.pose(psi)):
        assert np.allclose(a.R, b.R, atol=1e-12) and np.allclose(a.T, b.T, atol=1e-9)
    s1, s2 = m.sigma(psi), m2.sigma(psi)
    assert np.allclose(s1.to_numpy(), s2.to_numpy(), rtol=1e-6)


def test_pose_convention_matches_rigid_model(noisy_rigs):
    m = fit_joint(noisy_rigs[0].result)
    rigid = RigidModel(m.axis, m.psi_ref_deg, m.R_ref, m.T_ref)
    p_ref = m.pose(m.psi_ref_deg)
    assert np.allclose(p_ref.R, m.R_ref) and np.allclose(p_ref.T, m.T_ref)
    # psi increasing turns right-handedly about the axis
    a, b = m.pose(m.psi_ref_deg), m.pose(m.psi_ref_deg + 1.0)
    rot = Rotation.from_matrix(b.R @ a.R.T).as_rotvec()
    assert np.isclose(rot @ m.axis.direction, np.radians(1.0), rtol=1e-9)
    for x, y in zip(m.pose([0.0, 5.0]), rigid.pose([0.0, 5.0])):
        assert np.allclose(x.R, y.R) and np.allclose(x.T, y.T)


def test_sigma_scales_with_noise():
    """Four times the stripe and range noise: the reported sigmas grow accordingly (2x-8x)."""
    lo = simulate_rig(21, StudySetting(n_positions=6, range_noise_mm=0.5, stripe_noise_px=0.02,
                                       stripe_offset_px=0.003))
    hi = simulate_rig(21, StudySetting(n_positions=6, range_noise_mm=2.0, stripe_noise_px=0.08,
                                       stripe_offset_px=0.012))
    s_lo = fit_joint(lo.result).sigma(0.0)
    s_hi = fit_joint(hi.result).sigma(0.0)
    for q in ("centre_mm", "z_axis_deg", "x_axis_deg", "axis_direction_deg"):
        assert 2.0 < s_hi[q] / s_lo[q] < 8.0, q


def test_weak_setup_warnings():
    sim = simulate_rig(3, StudySetting(n_positions=4, span_deg=2.0))
    m = fit_joint(sim.result)
    text = " ".join(m.warnings)
    assert "only 4 positions" in text
    assert "span only 2.00 deg" in text


def test_one_board_missing_warns(noisy_rigs):
    res = noisy_rigs[0].result
    d = joint_data(res)
    keep = ~((d.scan_pos == 0) & (d.scan_board == 1))
    scans = [tuple(d.scan_xy[keep & (d.scan_pos == p) & (d.scan_board == b)] for b in range(2))
             for p in range(d.n_positions)]
    stripes = [tuple(d.stripe_px[(d.stripe_pos == p) & (d.stripe_board == b)] for b in range(2))
               for p in range(d.n_positions)]
    d2 = build_joint_data(d.camera, d.psi_deg, scans, stripes, d.board_R, d.board_T,
                          d.corners_px, d.object_points, d.samples)
    m = fit_joint_data(d2, [res.rigid_model])
    assert any("board 1 has fewer than" in w and "only one board hit" in w for w in m.warnings)


def test_scan_only_reports_the_unobservable_slide(noisy_rigs):
    """Scan points on the two planes of one V cannot fix the slide along the hinge."""
    m = fit_joint(noisy_rigs[0].result, stripes=False)
    assert any("not determined" in w for w in m.warnings)
    assert np.isinf(m.sigma(0.0)["centre_mm"])
    m2 = model_from_dict(json.loads(json.dumps(m.to_dict())))
    assert np.isinf(m2.sigma(0.0)["centre_mm"])


def test_irls_lm_matches_scipy(noisy_rigs):
    res = noisy_rigs[1].result
    d = joint_data(res)
    a = fit_joint_data(d, [res.rigid_model], solver="lm")
    b = fit_joint_data(d, [res.rigid_model], solver="scipy")
    for p, q in zip(a.pose(res.psi_deg), b.pose(res.psi_deg)):
        e = pose_error(p, q)
        assert e["centre_mm"] < 1e-3 and e["z_axis_deg"] < 1e-5 and e["x_axis_deg"] < 1e-4


@pytest.mark.parametrize("i", [0, 1])
def test_moment_solver_matches_irls_lm(noisy_rigs, i):
    """The per-segment moment form (default) reaches the optimum of the row-by-row IRLS-LM:
    same poses, same ranging terms, same robust cost (to the solvers' tolerance)."""
    res = noisy_rigs[i].result
    d = joint_data(res, "pnp")
    a = fit_joint_data(d, [res.rigid_model, res.paper_model], solver="lm")
    b = fit_joint_data(d, [res.rigid_model, res.paper_model])
    for p, q in zip(a.pose(res.psi_deg), b.pose(res.psi_deg)):
        e = pose_error(p, q)
        assert e["centre_mm"] < 1e-3 and e["z_axis_deg"] < 1e-5 and e["x_axis_deg"] < 1e-4
    assert abs(a.ranging.offset_mm - b.ranging.offset_mm) < 1e-3
    assert b.info["cost"] == pytest.approx(a.info["cost"], rel=1e-6)


def test_irls_lm_robust_line():
    """A straight line with 10 % gross outliers: soft_l1 recovers it, linear does not."""
    rng = np.random.default_rng(4)
    x = np.linspace(0, 10, 200)
    y = 2.0 * x - 1.0 + rng.normal(0, 0.1, x.size)
    y[::10] += 30.0
    fun = lambda p: (p[0] * x + p[1] - y) / 0.1
    jac = lambda p: np.column_stack([x, np.ones_like(x)]) / 0.1
    robust = irls_lm(fun, jac, np.zeros(2), "soft_l1", 2.0)
    plain = irls_lm(fun, jac, np.zeros(2), "linear", 1.0)
    assert robust.status == 1
    assert abs(robust.x[0] - 2.0) < 0.02 and abs(robust.x[1] + 1.0) < 0.1
    assert abs(plain.x[1] + 1.0) > 1.0


def test_bad_inputs():
    with pytest.raises(ValueError, match="one scan and one stripe pair per position"):
        build_joint_data(None, [0.0, 1.0], [], [], np.zeros((2, 3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="board_poses must be"):
        joint_data(None, "nonsense")


def test_axis_along_scan_normal_warns(noisy_rigs):
    """A turntable axis along the LiDAR z axis barely moves the scan plane: warned."""
    res = noisy_rigs[0].result
    m = fit_joint(res)
    z = m.R_ref[:, 2]
    bad = JointModel(type(m.axis).from_point_direction(m.T_ref, z), m.psi_ref_deg, m.R_ref, m.T_ref,
                     m.cov)
    assert any("scan-plane normal" in w for w in joint_warnings(joint_data(res), bad))
    assert not any("scan-plane normal" in w for w in m.warnings)


def test_end_to_end_rendered(tmp_path_factory):
    """Rendered images and scans through the whole pipeline (4 positions of the paper rig)."""
    from lidarcal.pipeline import calibrate
    from lidarcal.synthetic import simulate

    root = simulate(tmp_path_factory.mktemp("rig") / "ds", seed=7, rig="paper", with_sweeps=False,
                    with_intrinsics=False, positions=[0, 28, 57, 86])
    res = calibrate(root, workers=1)
    truth = json.loads((root / "truth.json").read_text())
    m = fit_joint(res)
    sig = m.sigma(res.psi_deg)
    true = {p["index"]: Pose.from_dict(p) for p in truth["poses"]}
    for p, est, s in zip(res.positions, m.pose(res.psi_deg), sig.itertuples()):
        e = pose_error(est, true[p.index])
        assert e["centre_mm"] <= 2 * s.centre_mm and e["centre_mm"] < 0.3
        assert e["z_axis_deg"] <= 2 * s.z_axis_deg and e["x_axis_deg"] <= 2 * s.x_axis_deg
    k = np.array(truth["axis"]["direction"])
    assert axis_direction_error_deg(m.axis.direction, k) <= 2 * sig["axis_direction_deg"].iloc[0]
    assert any("only 4 positions" in w for w in m.warnings)


JITTERY = StudySetting(rig="harsh", n_positions=30)  # the harsh preset: encoder jitter 0.003 deg


@pytest.mark.parametrize("seed", [31, 32])
def test_encoder_jitter_is_estimated_and_corrected(seed):
    """Encoder jitter (0.003 deg, the harsh preset): the joint fit finds its level, its
    per-position corrections follow the true angle errors, the z axis (which a jitter
    tilts one for one) gets better, and the reported sigma covers the true errors."""
    sim = simulate_rig(seed, JITTERY)
    res = sim.result
    plain = fit_joint(res, jitter=False)
    m = fit_joint(res)
    assert plain.jitter_deg == 0.0 and not plain.angle_corrections
    idx = [p.index for p in res.positions]
    truth_err = np.array([sim.truth.psi_true_deg[i] - sim.truth.psi_deg[i] for i in idx])
    # measured on seeds 31-35: level within 3-13 % of the sample jitter, correlation >= 0.97
    assert abs(m.jitter_deg - truth_err.std()) < 0.25 * truth_err.std()
    corr = np.array([m.angle_corrections[i][0] for i in idx])
    assert np.corrcoef(corr, truth_err - truth_err.mean())[0, 1] > 0.95

    def z_err(model):
        return np.mean([pose_error(model.pose(model.position_psi(p.index, p.psi_deg)),
                                   sim.true_poses[p.index])["z_axis_deg"] for p in res.positions])

    assert z_err(m) < 0.7 * z_err(plain)  # measured 0.2-0.56 on seeds 31-35
    sig = m.position_sigma_columns(idx, res.psi_deg)
    inside = [pose_error(m.pose(m.position_psi(p.index, p.psi_deg)), sim.true_poses[p.index])[q]
              <= 2 * sig[q][j] for j, p in enumerate(res.positions)
              for q in ("centre_mm", "z_axis_deg", "x_axis_deg")]
    assert np.mean(inside) >= 0.85
    m2 = model_from_dict(json.loads(json.dumps(m.to_dict())))
    assert m2.jitter_deg == m.jitter_deg and m2.angle_corrections == m.angle_corrections
    # a pose at a *reported* angle (a future scan) carries the whole jitter
    with_j, without = m.sigma_columns(res.psi_deg), m.sigma_columns(res.psi_deg, jitter=False)
    assert np.all(with_j["z_axis_deg"] > without["z_axis_deg"])
    assert np.all(with_j["z_axis_deg"] >= 0.9 * m.jitter_deg)


def test_no_jitter_no_corrections(noisy_rigs):
    """Exact encoder angles: no jitter is detected, poses are the function at the reported angles."""
    for sim in noisy_rigs:
        m = fit_joint(sim.result)
        assert m.jitter_deg == 0.0 and not m.angle_corrections
        assert "angle_jitter" not in m.to_dict()
        p = sim.result.positions[0]
        assert m.position_psi(p.index, p.psi_deg) == p.psi_deg
