"""Turntable pose functions (section 2, eqs. 15-27) against simulated truth.

Truth: a rigid rotation of a LiDAR about an axis roughly along the camera x axis,
20-80 mm from the LiDAR centre; LiDAR z roughly camera -y. Samples are the truth
poses with Gaussian noise (centre 0.5 mm per component; z axis tilted ~0.02 deg,
x axis turned ~0.05 deg; see ``perturb_pose``).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from lidarcal.evaluate import axis_direction_error_deg, pose_error
from lidarcal.geometry import Pose, check_rotation, plane_basis, rotate_perpendicular, unit
from lidarcal.turntable import (
    Axis,
    PaperModel,
    PoseFunction,
    RigidModel,
    _solve_x_axis,
    axis_distance_mm,
    fit_paper,
    fit_rigid,
    model_from_dict,
    perturb_pose,
    sensitivity_study,
    table1,
    table1_summary,
)

NOISE = {"centre_mm": 0.5, "z_deg": 0.02, "x_deg": 0.05}
LAYOUTS = {"87x0.25": (87, 0.25), "40x0.5": (40, 0.5)}


def random_truth(rng: np.random.Generator, sign: float = 1.0, lever_mm=(20.0, 80.0)) -> RigidModel:
    """A random rig: axis ~ camera x (times ``sign``), LiDAR z ~ camera -y, x ~ camera z."""
    k = sign * unit(np.array([1.0, 0, 0]) + rng.normal(0, 0.1, 3))
    R0 = np.column_stack([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]).astype(float)
    R0 = (Rotation.from_rotvec(rng.normal(0, 0.1, 3)).as_matrix() @ R0
          @ Rotation.from_euler("z", rng.uniform(-30, 30), degrees=True).as_matrix())
    T0 = np.array([rng.uniform(-150, 150), rng.uniform(-200, 0), rng.uniform(-100, 100)])
    a = T0 + rng.uniform(*lever_mm) * unit(np.cross(k, rng.normal(size=3)))
    return RigidModel(Axis.from_point_direction(a, k), 0.0, R0, T0)


def rig(seed: int, n: int, step: float, noise: dict | None = NOISE, sign: float = 1.0, **kw):
    rng = np.random.default_rng(seed)
    truth = random_truth(rng, sign, **kw)
    psi = rng.uniform(-20, 20) + np.arange(n) * step
    true = truth.pose(psi)
    samples = true if noise is None else [perturb_pose(p, rng, **noise) for p in true]
    return truth, psi, true, samples


def mean_errors(poses, true) -> np.ndarray:
    """Mean true errors (centre mm, z deg, x deg)."""
    return np.mean([list(pose_error(p, t).values()) for p, t in zip(poses, true)], axis=0)


def max_errors(poses, true) -> np.ndarray:
    return np.max([list(pose_error(p, t).values()) for p, t in zip(poses, true)], axis=0)


# ------------------------------------------------------------------ exact recovery


@pytest.mark.parametrize("fit", [fit_paper, lambda p, s: fit_paper(p, s, circle="algebraic"),
                                 fit_rigid], ids=["paper", "paper-algebraic", "rigid"])
@pytest.mark.parametrize("n,step", [(87, 0.25), (3, 0.5), (5, 4.0)])
@pytest.mark.parametrize("seed,sign", [(0, 1.0), (1, -1.0), (2, 1.0)])
def test_zero_noise_exact(fit, n, step, seed, sign):
    truth, psi, true, samples = rig(seed, n, step, noise=None, sign=sign)
    model = fit(psi, samples)
    assert isinstance(model, PoseFunction)
    assert np.all(max_errors(model.pose(psi), true) < 1e-6)
    # between and beyond the samples too: the function, not just the fit
    psi_new = np.linspace(psi[0] - 5, psi[-1] + 5, 7)
    assert np.all(max_errors(model.pose(psi_new), truth.pose(psi_new)) < 1e-6)
    assert model.axis.direction @ truth.axis.direction > 1 - 1e-12  # sign: psi up = right-handed
    assert axis_distance_mm(model.axis, truth.axis, true[0].T) < 1e-6
    assert abs(model.axis.point @ model.axis.direction) < 1e-9  # canonical foot


# ------------------------------------------------------------------ noisy accuracy


@pytest.mark.parametrize("layout", list(LAYOUTS))
@pytest.mark.parametrize("seed", range(4))
def test_noisy_rigid_better_than_samples(layout, seed):
    truth, psi, true, samples = rig(seed, *LAYOUTS[layout])
    rigid = fit_rigid(psi, samples)
    paper = fit_paper(psi, samples)
    e_smp, e_rig, e_pap = (mean_errors(s, true) for s in (samples, rigid.pose(psi), paper.pose(psi)))
    # the rigid function is better than every kind of sample it was fitted to
    assert np.all(e_rig < e_smp)
    assert e_rig[0] < 0.5 * e_smp[0]
    # axis within a few standard errors (std from the fit's Jacobian, i.e. from the noise)
    std = rigid.info["std"]
    assert axis_direction_error_deg(rigid.axis.direction, truth.axis.direction) \
        < 4 * std["axis_direction_deg"]
    assert axis_distance_mm(rigid.axis, truth.axis, true[len(psi) // 2].T) \
        < 4 * std["axis_point_mm"]
    # noise scales estimated from the data, not constants: centre sigma ~ 0.5 mm
    assert rigid.info["sigma"]["centre_mm"] == pytest.approx(NOISE["centre_mm"], rel=0.3)
    # the paper's chain: z axis averaged over all samples, both senses agree with truth
    assert e_pap[1] < e_smp[1]
    assert paper.axis.direction @ truth.axis.direction > 0
    assert rigid.axis.direction @ truth.axis.direction > 0


def test_init_from_paper_gives_same_fit():
    _truth, psi, _true, samples = rig(5, 40, 0.5)
    a = fit_rigid(psi, samples)
    b = fit_rigid(psi, samples, init=fit_paper(psi, samples))
    assert max_errors(a.pose(psi), b.pose(psi))[0] < 1e-4


def test_bad_init_does_not_hurt():
    """A poor start (the paper's chain on a 1 deg arc) loses to the closed-form start."""
    truth, psi, _true, samples = rig(1, 5, 0.25)
    paper = fit_paper(psi, samples)
    wrong = RigidModel(Axis.from_point_direction(paper.axis.point, -truth.axis.direction), psi[0],
                       samples[0].R, samples[0].T)
    a = fit_rigid(psi, samples)
    b = fit_rigid(psi, samples, init=wrong)
    assert b.info["start"] == "closed_form"
    assert max_errors(a.pose(psi), b.pose(psi))[0] < 1e-6


@pytest.mark.parametrize("seed", range(3))
def test_three_positions(seed):
    truth, psi, true, samples = rig(seed, 3, 0.5)
    paper, rigid = fit_paper(psi, samples), fit_rigid(psi, samples)
    for model in (paper, rigid):
        for p in model.pose(psi):
            check_rotation(p.R, tol=1e-9)
    # 1 deg of arc: the rigid fit still finds the axis direction from the relative rotations
    assert rigid.axis.direction @ truth.axis.direction > 0.99
    assert mean_errors(rigid.pose(psi), true)[0] < 3 * NOISE["centre_mm"]
    # the paper's z-tip plane (eq. 16) through 3 almost collinear tips is undetermined
    # there; with 3 positions 10 deg apart it is fine
    truth, psi, true, samples = rig(seed, 3, 10.0)
    paper = fit_paper(psi, samples)
    assert paper.axis.direction @ truth.axis.direction > 0.99
    assert mean_errors(paper.pose(psi), true)[1] < 3 * mean_errors(samples, true)[1]


# --------------------------------------------------------- conditioning demonstration


def test_free_circle_is_ill_conditioned_rigid_is_not():
    """Eq. (18) on ~21 deg of arc: the axis point wanders by mm; known angles pin it.

    Rotations exact (the paper's axis direction is then exact), centres 0.5 mm noise.
    """
    paper_off, rigid_off, rigid_std = [], [], []
    for seed in range(6):
        rng = np.random.default_rng(100 + seed)
        truth = random_truth(rng)
        psi = np.arange(87) * 0.25
        true = truth.pose(psi)
        samples = [Pose(p.R, p.T + rng.normal(0, NOISE["centre_mm"], 3)) for p in true]
        near = true[43].T
        paper, rigid = fit_paper(psi, samples), fit_rigid(psi, samples)
        assert axis_direction_error_deg(paper.axis.direction, truth.axis.direction) < 1e-6
        paper_off.append(axis_distance_mm(paper.axis, truth.axis, near))
        rigid_off.append(axis_distance_mm(rigid.axis, truth.axis, near))
        rigid_std.append(rigid.info["std"]["axis_point_mm"])
    assert np.median(paper_off) > 2.0  # millimetres off with every sample good
    assert np.median(paper_off) > 4 * np.median(rigid_off)
    assert np.all(np.array(rigid_off) < 4 * np.array(rigid_std))


# ---------------------------------------------------------------------- outliers


def plant_outlier(samples, j):
    bad = list(samples)
    bad[j] = Pose(Rotation.from_rotvec([0.03, 0.02, -0.04]).as_matrix() @ samples[j].R,
                  samples[j].T + np.array([15.0, -10.0, 8.0]))
    return bad


@pytest.mark.parametrize("seed", range(3))
def test_single_outlier_is_harmless(seed):
    _truth, psi, true, samples = rig(seed, 40, 0.5)
    clean = mean_errors(fit_rigid(psi, samples).pose(psi), true)
    bad = plant_outlier(samples, 17)
    robust = fit_rigid(psi, bad)
    e_rob = mean_errors(robust.pose(psi), true)
    e_lin = mean_errors(fit_rigid(psi, bad, loss="linear").pose(psi), true)
    assert np.all(e_rob < mean_errors(samples, true))
    assert np.all(e_rob < 1.5 * clean + np.array([0.05, 0.002, 0.005]))
    assert e_lin[1] > 2 * e_rob[1]  # without the robust loss the bad sample drags the fit
    assert pd.DataFrame(robust.info["residuals"])["outlier"].iloc[17]
    assert pd.DataFrame(robust.info["residuals"])["outlier"].sum() <= 3
    # a zero weight removes it: same as the fit without it
    w = np.ones(len(psi))
    w[17] = 0
    dropped = fit_rigid(np.delete(psi, 17), [s for i, s in enumerate(bad) if i != 17],
                        psi_ref_deg=float(np.mean(np.delete(psi, 17))))
    weighted = fit_rigid(psi, bad, weights=w)
    assert max_errors(dropped.pose(psi), weighted.pose(psi))[0] < 1e-3


# --------------------------------------------------------------- the p_L sense trap


@pytest.mark.parametrize("fit", [fit_paper, fit_rigid], ids=["paper", "rigid"])
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_sample_order_and_axis_sign(fit, sign):
    truth, psi, _true, samples = rig(7, 40, 0.5, sign=sign)
    ref = fit(psi, samples)
    assert ref.axis.direction @ truth.axis.direction > 0.99
    for order in (np.arange(len(psi))[::-1], np.random.default_rng(0).permutation(len(psi))):
        m = fit(psi[order], [samples[i] for i in order])
        # identical up to the optimiser's convergence (rigid) or rounding (paper)
        assert max_errors(m.pose(psi), ref.pose(psi))[0] < 1e-5
        assert m.axis.direction @ ref.axis.direction > 1 - 1e-9


def test_sense_from_all_samples_not_first_and_last():
    """On a 1 deg arc with a 20 mm lever, samples 1 and N alone (the paper's p_L) often give the
    wrong sense; the regression over all samples (z tips decide) does not."""
    disagree = 0
    for seed in range(12):
        truth, psi, _true, samples = rig(seed, 5, 0.25, lever_mm=(20.0, 20.0),
                                        noise={"centre_mm": 0.5, "z_deg": 1e-4, "x_deg": 1e-4})
        m = fit_paper(psi, samples)
        assert m.axis.direction @ truth.axis.direction > 0.99
        disagree += not m.info["paper_sense_agrees"]
    assert disagree >= 1


# ---------------------------------------------------------------- serialisation


@pytest.mark.parametrize("fit", [fit_paper, fit_rigid], ids=["paper", "rigid"])
def test_serialisation_round_trip(fit):
    _truth, psi, _true, samples = rig(3, 40, 0.5)
    model = fit(psi, samples)
    d = json.loads(json.dumps(model.to_dict()))
    assert d["type"] in ("paper", "rigid") and "axis" in d
    again = model_from_dict(d)
    assert type(again) is type(model)
    psi_new = np.concatenate([psi, [psi[0] - 3.3, psi[-1] + 7.1]])
    for a, b in zip(model.pose(psi_new), again.pose(psi_new)):
        assert np.max(np.abs(a.R - b.R)) < 1e-9 and np.max(np.abs(a.T - b.T)) < 1e-9
    p = again.pose(float(psi[3]))
    assert isinstance(p, Pose)


def test_model_from_dict_rejects_unknown_type():
    with pytest.raises(ValueError, match="Unknown pose-function type"):
        model_from_dict({"type": "spline"})


# ------------------------------------------------------------------- Table 1


def test_table1_and_summary():
    truth, psi, true, samples = rig(4, 87, 0.25)
    model = fit_paper(psi, samples)
    t = table1(model, psi, samples)
    assert list(t.columns) == ["psi_deg", "centre_mm", "z_axis_deg", "x_axis_deg"]
    assert len(t) == len(psi)
    s = table1_summary(t)
    assert list(s.index) == ["mean", "max"]
    assert np.all(s.loc["max"] >= s.loc["mean"])
    # against the truth the same table gives zero for the truth itself
    assert table1_summary(table1(truth, psi, true)).to_numpy().max() < 1e-9
    # self-consistency (Table 1) ~ the sample noise for a good fit
    rigid = fit_rigid(psi, samples)
    assert table1_summary(pd.DataFrame(rigid.info["residuals"])).loc["mean", "centre_mm"] == \
        pytest.approx(mean_errors(samples, true)[0], rel=0.25)


# ------------------------------------------------------------------ bad input


def test_bad_input_messages():
    _truth, psi, _true, samples = rig(0, 5, 0.5)
    with pytest.raises(ValueError, match="one psi per sample"):
        fit_paper(psi[:4], samples)
    with pytest.raises(ValueError, match="at least 3 positions"):
        fit_rigid(psi[:2], samples[:2])
    with pytest.raises(ValueError, match="duplicate"):
        fit_rigid(np.array([0, 0, 1, 2, 3.0]), samples)
    with pytest.raises(ValueError, match="circle must be"):
        fit_paper(psi, samples, circle="kasa")
    with pytest.raises(ValueError, match="weights"):
        fit_rigid(psi, samples, weights=np.zeros(5))


# ------------------------------------------------------------ property tests

seeds = st.integers(0, 2**32 - 1)


@settings(max_examples=50, deadline=None)
@given(seeds, st.floats(-np.pi, np.pi))
def test_rodrigues_perpendicular_preserves_norm(seed, angle):
    rng = np.random.default_rng(seed)
    k = unit(rng.normal(size=3))
    v = rng.uniform(0.1, 100) * plane_basis(k)[0]
    r = rotate_perpendicular(v, k, angle)
    assert np.linalg.norm(r) == pytest.approx(np.linalg.norm(v), rel=1e-12)
    assert abs(r @ k) < 1e-9 * np.linalg.norm(v)
    assert np.allclose(r, Rotation.from_rotvec(angle * k).apply(v), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seeds, st.floats(-180, 180), st.floats(-180, 180))
def test_rigid_model_invariants(seed, psi_ref, psi):
    truth = random_truth(np.random.default_rng(seed))
    m = RigidModel(truth.axis, psi_ref, truth.R_ref, truth.T_ref)
    p0 = m.pose(psi_ref)
    assert np.allclose(p0.R, m.R_ref, atol=1e-12) and np.allclose(p0.T, m.T_ref, atol=1e-9)
    p = m.pose(psi)
    check_rotation(p.R, tol=1e-9)
    line = m.axis.line
    assert line.distance(p.T)[0] == pytest.approx(line.distance(m.T_ref)[0], abs=1e-9)
    k = m.axis.direction
    assert p.z_axis @ k == pytest.approx(m.R_ref[:, 2] @ k, abs=1e-12)
    # a right-handed turn: the centre moves like k x (centre - axis) for a small increase
    d = m.pose(psi + 1e-4).T - p.T
    assert d @ np.cross(k, p.T - m.axis.point) >= 0


@settings(max_examples=25, deadline=None)
@given(seeds, st.floats(-90, 90))
def test_paper_model_invariants(seed, psi):
    _truth, psi_s, _true, samples = rig(seed % 1000, 10, 2.0)
    m = fit_paper(psi_s, samples)
    p = m.pose(psi)
    check_rotation(p.R, tol=1e-9)
    k = m.axis.direction
    assert np.linalg.norm(p.T - m.centre_G) == pytest.approx(np.linalg.norm(m.centre_v1), rel=1e-9)
    assert p.z_axis @ k == pytest.approx(m.z_G @ k, abs=1e-9)  # on Pi_Z, eq. (16)
    if abs(m.d_X) < np.sqrt(1 - (p.z_axis @ k) ** 2):
        assert p.x_axis @ k == pytest.approx(m.d_X, abs=1e-9)  # on Pi_X, eq. (17)


@settings(max_examples=50, deadline=None)
@given(seeds, st.floats(0.0, 0.99), st.sampled_from([1.0, -1.0]))
def test_eq25_roots(seed, frac, branch):
    rng = np.random.default_rng(seed)
    k, n_z = unit(rng.normal(size=3)), unit(rng.normal(size=3))
    s = np.linalg.norm(k - (k @ n_z) * n_z)
    d_X = frac * s * rng.choice([-1, 1])
    n_x = _solve_x_axis(k, n_z, d_X, branch)[0]
    assert np.linalg.norm(n_x) == pytest.approx(1.0, abs=1e-12)
    assert n_x @ n_z == pytest.approx(0.0, abs=1e-12)
    assert n_x @ k == pytest.approx(d_X, abs=1e-12)
    other = _solve_x_axis(k, n_z, d_X, -branch)[0]
    assert other @ k == pytest.approx(d_X, abs=1e-12)


# ---------------------------------------------------------------- sensitivity


def test_sensitivity_study_small():
    truth = random_truth(np.random.default_rng(0))
    df = sensitivity_study(truth, n_positions=(3, 20), ranges_deg=(1.0, 20.0), seeds=(0,))
    assert len(df) == 2 * 2 * 3
    rig_ = df[df.model == "rigid"].set_index(["n_positions", "span_deg"])
    smp = df[df.model == "samples"].set_index(["n_positions", "span_deg"])
    assert rig_.loc[(20, 20.0), "centre_mm"] < smp.loc[(20, 20.0), "centre_mm"]
    # the axis gets better with the span
    assert rig_.loc[(20, 20.0), "axis_offset_mm"] < rig_.loc[(20, 1.0), "axis_offset_mm"]
    assert isinstance(PaperModel, type)


@settings(max_examples=25, deadline=None)
@given(st.floats(-60, 60), st.integers(0, 10_000))
def test_stored_rigid_formula_is_what_pose_computes(psi, seed):
    """calibration.json states the rigid/joint formula so other tools can evaluate 'model'
    without lidarcal: applying it by hand to the stored numbers gives pose(psi)."""
    rng = np.random.default_rng(seed)
    k = unit(rng.normal(size=3))
    R0 = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    m = RigidModel(Axis.from_point_direction(rng.normal(0, 100, 3), k), 10.0, R0,
                   rng.normal(0, 200, 3))
    d = json.loads(json.dumps(m.to_dict()))
    assert "Rot(direction, psi - psi_ref_deg)" in d["formula"]
    kk, a = np.array(d["axis"]["direction"]), np.array(d["axis"]["point_mm"])
    Q = Rotation.from_rotvec(np.radians(psi - d["psi_ref_deg"]) * kk).as_matrix()
    R = Q @ np.array(d["pose_ref"]["R"])
    T = a + Q @ (np.array(d["pose_ref"]["T_mm"]) - a)
    p = m.pose(psi)
    assert np.allclose(R, p.R, atol=1e-12) and np.allclose(T, p.T, atol=1e-9)


# ------------------------------------------------------------------ the reported angles' scale


@pytest.mark.parametrize("seed", range(3))
def test_angle_scale_is_one_for_degrees_and_names_radians_and_gears(seed):
    # the samples turn by |dpsi| whatever the axis: ratio 1 in degrees (to the sample noise),
    # 1/57.3 for the same angles written in radians, 1/0.9 for a 0.9 gear ratio
    from lidarcal.turntable import angle_scale

    _truth, psi, _true, samples = rig(seed, 40, 0.5)
    sc = angle_scale(psi, samples)
    assert abs(sc.turned_deg - sc.reported_deg) < 0.05 and sc.pairs > 100
    assert abs(angle_scale(np.radians(psi), samples).ratio - 1.0) > 10
    assert angle_scale(psi / 0.9, samples).ratio == pytest.approx(0.9, abs=0.01)
    assert angle_scale(np.degrees(psi), samples).ratio < 0.5  # wrapped past 180 deg, still far off


# ------------------------------------------------------------ derivatives and batches


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), step_scale=st.sampled_from([0.0, 1e-9, 0.05, 0.5]))
def test_rigid_jacobian_matches_central_differences(seed, step_scale):
    """fit_rigid's analytic Jacobian (Rodrigues' derivative wrt the axis, SO(3)'s left
    Jacobian for the reference rotation) against central differences of the prediction, at
    the base (x = 0), next to it and at parameter steps far from it."""
    from lidarcal.turntable import _rigid_jacobian, _rigid_predict

    rng = np.random.default_rng(seed)
    truth = random_truth(rng)
    k0 = truth.axis.direction
    base = (k0, plane_basis(k0), truth.axis.point, truth.R_ref, truth.T_ref)
    t = np.radians(rng.uniform(-30, 30, 6))
    x = rng.normal(size=10) * step_scale * np.r_[1, 1, 100, 100, 1, 1, 1, 100, 100, 100]

    def f(v):
        return np.concatenate(_rigid_predict(v, base, t)[:3], axis=1).ravel()

    h = np.r_[np.full(2, 1e-6), np.full(2, 1e-4), np.full(3, 1e-6), np.full(3, 1e-4)]
    numeric = np.column_stack([(f(x + h[j] * e) - f(x - h[j] * e)) / (2 * h[j])
                               for j, e in enumerate(np.eye(10))])
    analytic = _rigid_jacobian(x, base, t).reshape(-1, 10)
    # central differences are exact to O(h^2) (~1e-10 relative here) plus rounding
    np.testing.assert_allclose(analytic, numeric, atol=1e-6 * np.abs(numeric).max())


@pytest.mark.parametrize("seed", [3, 8])
def test_pose_arrays_is_pose_at_every_angle(seed):
    """``pose_arrays`` (every angle in one pass, as calibration.json's poses use it) gives the
    poses ``pose`` gives one angle at a time, for both pose functions."""
    _, psi, _, samples = rig(seed, 12, 1.5)
    for model in (fit_paper(psi, samples), fit_rigid(psi, samples)):
        R, T = model.pose_arrays(psi)
        for j, a in enumerate(psi):
            p = model.pose(float(a))
            np.testing.assert_allclose(R[j], p.R, atol=1e-14)
            np.testing.assert_allclose(T[j], p.T, atol=1e-9)
