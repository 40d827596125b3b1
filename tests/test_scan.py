"""Section 1.4: scan points (eq. 6), V segmentation, constrained scan lines (eqs. 7-12), against truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import least_squares
from vscan_truth import BOARD1, BOARD2, MIXED, POST, SPURIOUS, WALL, make_truth, simulate_scan

from lidarcal.scan import (
    estimate_range_noise,
    fit_line_2d,
    fit_v_lines,
    fit_v_lines_free,
    fit_v_lines_paper,
    scan_points,
    split_v,
)

SPECS = {
    "sick_70deg": {"angle_min_deg": -35.0, "angle_max_deg": 35.0, "angle_step_deg": 0.083333},
    "wide_120deg": {"angle_min_deg": -60.0, "angle_max_deg": 60.0, "angle_step_deg": 0.25},
}


def truth_scan(seed: int, spec: str = "sick_70deg", sigma: float = 1.0, upright: bool = True):
    rng = np.random.default_rng(seed)
    tr = make_truth(rng, upright=upright)
    ang, rho, lab = simulate_scan(tr, rng, sigma_mm=sigma, **SPECS[spec])
    return tr, ang, rho, lab


def truth_line_distance(tr, points2d: np.ndarray, board: int) -> np.ndarray:
    """Orthogonal distance (LiDAR plane) of points to the true stripe line of ``board`` (0/1)."""
    E = tr.E_lidar
    d = tr.pose.R.T @ tr.l_cam[board]
    n = np.array([-d[1], d[0]]) / np.hypot(d[0], d[1])
    return np.abs((points2d - E) @ n)


# --- eq. (6) -----------------------------------------------------------------------------------

def test_scan_points_eq6_keeps_beam_index():
    ang = np.array([-90.0, 0.0, 30.0, 90.0, 180.0])
    rho = np.array([2.0, 1000.0, np.nan, 5.0, 0.0])
    p = scan_points(ang, rho)
    assert p.shape == (5, 2)
    np.testing.assert_allclose(p[0], [0, -2], atol=1e-12)
    np.testing.assert_allclose(p[1], [1000, 0], atol=1e-12)
    np.testing.assert_allclose(p[3], [0, 5], atol=1e-12)
    assert np.all(np.isnan(p[2])) and np.all(np.isnan(p[4]))  # no return: NaN row, index kept


def test_scan_points_rejects_mismatched_lengths():
    with pytest.raises(ValueError, match="equal length"):
        scan_points(np.zeros(3), np.zeros(4))


@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0])
def test_range_noise_estimate_is_robust(sigma):
    # wall scan with 1 % spurious returns and 2 % dropouts: the MAD estimate ignores them
    _tr, _ang, rho, _lab = truth_scan(3, sigma=sigma)
    est = estimate_range_noise(rho)
    assert abs(est - sigma) < 0.2 * sigma


# --- split_v -------------------------------------------------------------------------------------

@pytest.mark.parametrize("spec", list(SPECS))
@pytest.mark.parametrize("sigma", [1.0, 2.0])
@pytest.mark.parametrize("seed", range(5))
def test_split_v_recovers_board_points(spec, sigma, seed):
    tr, ang, rho, lab = truth_scan(seed, spec, sigma, upright=seed % 2 == 0)
    v = split_v(ang, rho)
    # segment 1 = lower beam angles, each segment on one board, the two on different boards
    assert v.index1[-1] < v.index2[0]
    b1, b2 = lab[v.index1[len(v.index1) // 2]], lab[v.index2[len(v.index2) // 2]]
    assert {b1, b2} == {BOARD1, BOARD2}
    for idx, pts, b in ((v.index1, v.points1, b1), (v.index2, v.points2, b2)):
        # no wall / post / mixed pixel return inside
        assert not np.any(np.isin(lab[idx], (WALL, POST, MIXED)))
        # a return of the other board only at the hinge, where it lies on both lines
        other = lab[idx] == BOARD1 + BOARD2 - b
        assert other.sum() <= 2
        assert np.all(truth_line_distance(tr, pts[other], b - BOARD1) < 4 * sigma)
        # a spurious return may only be kept when it happens to fall on the board line
        sp = lab[idx] == SPURIOUS
        assert np.all(truth_line_distance(tr, pts[sp], b - BOARD1) < 4 * sigma)
        # recall: nearly all true board returns are kept
        board = np.flatnonzero(lab == b)
        assert np.isin(board, idx).mean() > 0.95
    assert 0.8 * sigma < v.noise_mm < 1.3 * sigma
    assert abs(v.opening_deg - np.degrees(tr.alpha)) < 2.0


@pytest.mark.parametrize("seed", range(4))
def test_split_v_bridges_a_slot_at_the_hinge(seed):
    # the boards stop 15 mm short of the hinge: beams through the slot see the wall
    rng = np.random.default_rng(seed)
    tr = make_truth(rng, hinge_gap_mm=15.0)
    ang, rho, lab = simulate_scan(tr, rng, sigma_mm=1.0)
    v = split_v(ang, rho)
    assert {lab[v.index1[5]], lab[v.index2[5]]} == {BOARD1, BOARD2}
    assert not np.any(np.isin(lab[np.concatenate([v.index1, v.index2])], (WALL, POST, MIXED)))
    L = fit_v_lines(v.points1, v.points2, tr.alpha)
    d = L.E - tr.E_lidar  # the vertex is extrapolated across the slot
    assert d @ np.linalg.solve(L.E_cov, d) < 25


def test_split_v_drops_mixed_pixels_next_to_the_board():
    # every seed has mixed pixels at the boards' outer edges; none may survive
    kept_mixed = 0
    n_mixed = 0
    for seed in range(10):
        _tr, ang, rho, lab = truth_scan(seed)
        v = split_v(ang, rho)
        lo, hi = v.index1[0] - 3, v.index2[-1] + 3
        near = np.flatnonzero((lab == MIXED) & (np.arange(len(lab)) >= lo)
                              & (np.arange(len(lab)) <= hi))
        n_mixed += len(near)
        kept_mixed += np.isin(near, np.concatenate([v.index1, v.index2])).sum()
    assert n_mixed > 0 and kept_mixed == 0


def test_split_v_uses_alpha_hint_and_rejects_wrong_one():
    tr, ang, rho, lab = truth_scan(1)
    v = split_v(ang, rho, alpha=tr.alpha)
    assert {lab[v.index1[5]], lab[v.index2[5]]} == {BOARD1, BOARD2}
    with pytest.raises(ValueError, match="no pair forms the V"):
        split_v(ang, rho, alpha=tr.alpha - np.radians(30))


def test_split_v_single_line_says_found_1():
    ang = np.arange(-30, 30, 0.25)
    rho = 2000.0 / np.cos(np.radians(ang - 10))  # a flat wall only
    rho += np.random.default_rng(0).normal(0, 1, len(rho))
    with pytest.raises(ValueError, match="found 1 board segment, expected 2"):
        split_v(ang, rho)


def test_split_v_one_board_only_is_not_a_v():
    _tr, ang, rho, lab = truth_scan(2)
    rho = rho.copy()
    rho[lab == BOARD2] = np.nan  # board 2 missing from the scan
    with pytest.raises(ValueError, match="no pair forms the V"):
        split_v(ang, rho)


def test_split_v_rejects_unordered_angles():
    with pytest.raises(ValueError, match="ascending"):
        split_v(np.array([0.0, 2.0, 1.0] * 10), np.full(30, 1000.0))


# --- constrained lines, eqs. (7)-(12) ------------------------------------------------------------

def _v_points(E, l1, l2, n1=100, n2=100, length=300.0, sigma=0.0, rng=None):
    """Noise-free (or noisy) V points; segment 1 listed from its outer end, in beam order."""
    t1 = np.linspace(length, 2.0, n1)
    t2 = np.linspace(2.0, length, n2)
    p1 = E + t1[:, None] * l1
    p2 = E + t2[:, None] * l2
    if sigma:
        p1 = p1 + rng.normal(0, sigma, p1.shape)
        p2 = p2 + rng.normal(0, sigma, p2.shape)
    return p1, p2


def _rot(t):
    return np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])


def test_alpha_sign_concave_v_in_beam_order_is_beta_minus_alpha():
    """The trap of eq. (8), worked by hand: concave V (vertex far), beams counter-clockwise."""
    E = np.array([1000.0, 0.0])
    a = np.radians(120)
    l1 = np.array([np.cos(np.radians(240)), np.sin(np.radians(240))])  # segment 1: y < 0, lower angles
    l2 = _rot(-a) @ l1  # 120 deg: y > 0
    p1, p2 = _v_points(E, l1, l2)
    assert np.all(np.diff(np.arctan2(np.vstack([p1, p2])[:, 1], np.vstack([p1, p2])[:, 0])) > 0)
    L = fit_v_lines(p1, p2, a)
    assert L.sign == -1  # l2 = Rot(-alpha) l1: the paper's tan(beta - alpha)
    np.testing.assert_allclose(L.E, E, atol=1e-9)
    # a convex V (vertex near) in the same beam order turns the other way: beta + alpha
    Ec = np.array([800.0, 0.0])
    m1 = np.array([np.cos(np.radians(-60)), np.sin(np.radians(-60))])
    q1, q2 = _v_points(Ec, m1, _rot(a) @ m1)
    assert np.all(np.diff(np.arctan2(np.vstack([q1, q2])[:, 1], np.vstack([q1, q2])[:, 0])) > 0)
    Lc = fit_v_lines(q1, q2, a)
    assert Lc.sign == +1


def test_wrong_sign_is_refused():
    E = np.array([1000.0, 0.0])
    l1 = np.array([np.cos(np.radians(240)), np.sin(np.radians(240))])
    p1, p2 = _v_points(E, l1, _rot(-np.radians(120)) @ l1, sigma=1.0, rng=np.random.default_rng(0))
    with pytest.raises(ValueError, match="do not form a V"):
        fit_v_lines(p1, p2, np.radians(120), sign=+1)


@settings(max_examples=60, deadline=None)
@given(ex=st.floats(-2000, 2000), ey=st.floats(-2000, 2000), th=st.floats(0, 2 * np.pi),
       alpha=st.floats(0.3, np.pi - 0.3), sign=st.sampled_from([-1, 1]))
def test_noise_free_v_recovered_exactly(ex, ey, th, alpha, sign):
    E = np.array([ex, ey])
    l1 = np.array([np.cos(th), np.sin(th)])
    l2 = _rot(sign * alpha) @ l1
    p1, p2 = _v_points(E, l1, l2, 30, 40)
    for L in (fit_v_lines(p1, p2, alpha), fit_v_lines_free(p1, p2)):
        np.testing.assert_allclose(L.E, E, atol=1e-6 * (1 + np.abs(E).max()))
        np.testing.assert_allclose(L.l1, l1, atol=1e-8)
        np.testing.assert_allclose(L.l2, l2, atol=1e-8)
        assert L.sign == sign
        assert L.residual_rms_mm < 1e-6 * (1 + np.abs(E).max())


def _constrained_cost(x, p1, p2, alpha, sign):
    n1 = np.array([np.cos(x[0]), np.sin(x[0])])
    n2 = _rot(sign * alpha) @ n1
    return np.concatenate([p1 @ n1 - x[1], p2 @ n2 - x[2]])


@pytest.mark.parametrize("seed", range(4))
def test_constrained_fit_is_the_orthogonal_optimum(seed):
    tr, ang, rho, _lab = truth_scan(seed, sigma=2.0)
    v = split_v(ang, rho)
    L = fit_v_lines(v.points1, v.points2, tr.alpha, weighting="orthogonal")
    P = fit_v_lines_paper(v.points1, v.points2, tr.alpha)
    # angle exactly alpha, for both
    for fit in (L, P):
        assert abs(np.arccos(np.clip(fit.l1 @ fit.l2, -1, 1)) - tr.alpha) < 1e-9
        assert fit.sign == -1
    # least_squares from the paper's answer and from the free fit can not beat the closed form
    best = np.sum(_constrained_cost([np.arctan2(L.line1.normal[1], L.line1.normal[0]),
                                     L.line1.offset, L.line2.offset], v.points1, v.points2,
                                    tr.alpha, L.sign) ** 2)
    for start in (P, L.free):
        x0 = [np.arctan2(start.line1.normal[1], start.line1.normal[0]), start.line1.offset, 0.0]
        n2 = _rot(L.sign * tr.alpha) @ np.array([np.cos(x0[0]), np.sin(x0[0])])
        x0[2] = float(np.mean(v.points2 @ n2))
        sol = least_squares(_constrained_cost, x0, args=(v.points1, v.points2, tr.alpha, L.sign),
                            xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert best <= 2 * sol.cost * (1 + 1e-9)
        assert 2 * sol.cost <= best * (1 + 1e-6)
    # the paper's linearised scheme never does better (closed form = global optimum)
    assert L.residual_rms_mm <= P.residual_rms_mm * (1 + 1e-12)


def _range_cost(x, p1, p2, alpha, sign):
    """Range residuals of the V (the LiDAR's noise model): r_i - c_k / (n_k . u_i)."""
    n1 = np.array([np.cos(x[0]), np.sin(x[0])])
    out = []
    for p, n, c in ((p1, n1, x[1]), (p2, _rot(sign * alpha) @ n1, x[2])):
        r = np.hypot(p[:, 0], p[:, 1])
        out.append(r - c / ((p / r[:, None]) @ n))
    return np.concatenate(out)


@pytest.mark.parametrize("seed", range(4))
def test_range_weighted_fit_is_the_range_least_squares_optimum(seed):
    """The default fit (weighting="range") is the least-squares optimum of the ranges (the ML
    fit under range noise along the beams): scipy's least_squares from the orthogonal fit,
    the free fit and the paper's answer cannot beat it, and it beats the orthogonal fit in
    that cost while its orthogonal rms is (necessarily) no lower."""
    tr, ang, rho, _lab = truth_scan(seed, sigma=2.0)
    v = split_v(ang, rho)
    L = fit_v_lines(v.points1, v.points2, tr.alpha)
    O = fit_v_lines(v.points1, v.points2, tr.alpha, weighting="orthogonal")
    P = fit_v_lines_paper(v.points1, v.points2, tr.alpha)
    assert L.info["weighting"] == "range" and L.info["iterations"] <= 6
    assert abs(np.arccos(np.clip(L.l1 @ L.l2, -1, 1)) - tr.alpha) < 1e-9 and L.sign == -1

    def x_of(fit):  # a start: the fit's line 1, line 2's offset its points' mean projection
        n = fit.line1.normal
        n2 = _rot(L.sign * tr.alpha) @ n
        return [np.arctan2(n[1], n[0]), fit.line1.offset, float(np.mean(v.points2 @ n2))]

    n = L.line1.normal
    np.testing.assert_allclose(L.line2.normal, _rot(L.sign * tr.alpha) @ n, atol=1e-12)
    x_L = [np.arctan2(n[1], n[0]), L.line1.offset, L.line2.offset]
    best = np.sum(_range_cost(x_L, v.points1, v.points2, tr.alpha, L.sign) ** 2)
    for start in (O, L.free, P):
        sol = least_squares(_range_cost, x_of(start), args=(v.points1, v.points2, tr.alpha, L.sign),
                            xtol=1e-15, ftol=1e-15, gtol=1e-15)
        assert best <= 2 * sol.cost * (1 + 1e-9)
    x_O = [np.arctan2(O.line1.normal[1], O.line1.normal[0]), O.line1.offset, O.line2.offset]
    assert best < np.sum(_range_cost(x_O, v.points1, v.points2, tr.alpha, L.sign) ** 2)
    assert O.residual_rms_mm <= L.residual_rms_mm * (1 + 1e-12)
    # the range residuals' rms is the injected range noise (returns far from grazing)
    assert 0.8 * 2.0 < L.info["range_rms_mm"] < 1.2 * 2.0


def test_range_weighting_falls_back_at_grazing_incidence():
    """Line 1 passing 1 mm from the LiDAR (its beams run almost along it) makes the range
    model ill-posed: the fit says so and keeps the orthogonal closed form."""
    E = np.array([1000.0, 0.0])
    l1 = np.array([np.cos(np.radians(240)), np.sin(np.radians(240))])
    p1, p2 = _v_points(E, l1, _rot(-np.radians(120)) @ l1, sigma=0.5, rng=np.random.default_rng(1))
    n1 = np.array([-l1[1], l1[0]])
    shift = (E @ n1 - 1.0) * n1
    L = fit_v_lines(p1 - shift, p2 - shift, np.radians(120))
    O = fit_v_lines(p1 - shift, p2 - shift, np.radians(120), weighting="orthogonal")
    assert L.info["weighting"].startswith("orthogonal (a return at"), L.info["weighting"]
    np.testing.assert_allclose(L.E, O.E)
    np.testing.assert_allclose(L.E_cov, O.E_cov)


@pytest.mark.parametrize("yaw_deg", [0.0, 20.0])
def test_paper_linearisation_is_biased_where_closed_form_is_not(yaw_deg):
    """Eq. (11) uses cos(a)/(cos(a) + sin(a) lambda0) for d(slope2)/d(lambda); the true derivative
    is 1/(cos(a) + sin(a) lambda0)^2, so the paper's fixed point is not the least-squares optimum;
    with the V turned so that one line nears the LiDAR y axis (slope -> infinity) it breaks down."""
    E = np.array([1100.0, 0.0])
    a = np.radians(120)
    l1 = _rot(np.radians(yaw_deg)) @ np.array([np.cos(np.radians(240)), np.sin(np.radians(240))])
    err_c, err_p = [], []
    for seed in range(30):
        rng = np.random.default_rng(seed)
        p1, p2 = _v_points(E, l1, _rot(-a) @ l1, 150, 150, 300.0, 1.0, rng)
        L = fit_v_lines(p1, p2, a)
        P = fit_v_lines_paper(p1, p2, a, iterations=50)
        err_c.append(np.linalg.norm(L.E - E))
        err_p.append(np.linalg.norm(P.E - E))
        assert abs(np.arccos(np.clip(P.l1 @ P.l2, -1, 1)) - a) < 1e-9
    rms_c, rms_p = np.sqrt(np.mean(np.square(err_c))), np.sqrt(np.mean(np.square(err_p)))
    assert rms_c < 0.5  # ~ sigma * sqrt(4 / N) / sin(a) scale
    assert rms_p > 1.5 * rms_c
    if yaw_deg == 0.0:
        assert rms_p < 1.5  # usable when both lines are far from the LiDAR y axis


SEEDS = range(20)


@pytest.mark.parametrize("spec", list(SPECS))
@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_constrained_fit_E_within_its_covariance(spec, sigma):
    m2 = []
    for seed in SEEDS:
        tr, ang, rho, lab = truth_scan(seed, spec, sigma, upright=seed % 2 == 0)
        v = split_v(ang, rho)
        L = fit_v_lines(v.points1, v.points2, tr.alpha)
        assert abs(np.arccos(np.clip(L.l1 @ L.l2, -1, 1)) - tr.alpha) < 1e-9
        assert L.alpha == tr.alpha and L.sign == -1
        d = L.E - tr.E_lidar
        m2.append(d @ np.linalg.solve(L.E_cov, d))
        # rays point along the true stripe directions (in the LiDAR frame)
        b1 = lab[v.index1[len(v.index1) // 2]] - BOARD1
        for lk, b in ((L.l1, b1), (L.l2, 1 - b1)):
            true_l = tr.pose.R.T @ tr.l_cam[b]
            assert abs(true_l[2]) < 1e-12
            assert np.degrees(np.arccos(np.clip(lk @ true_l[:2], -1, 1))) < 1.0
        # residual rms ~ the orthogonal noise (range noise times cos incidence, <= sigma)
        assert 0.3 * sigma < L.residual_rms_mm < 1.2 * sigma
    m2 = np.array(m2)
    assert m2.max() < 25  # chi2(2 dof): p ~ 4e-6 per scan
    assert 0.8 < m2.mean() < 4.0  # the covariance is calibrated (expect 2)


def test_fit_v_lines_rejects_bad_input():
    p = np.zeros((5, 2))
    p[:, 0] = np.arange(5)
    with pytest.raises(ValueError, match="alpha"):
        fit_v_lines(p, p + [0, 1], 4.0)
    with pytest.raises(ValueError, match="shape"):
        fit_v_lines(np.zeros((1, 2)), p, 1.0)


def test_fit_line_2d_is_orthogonal():
    rng = np.random.default_rng(0)
    t = rng.uniform(-100, 100, 200)
    d = np.array([np.cos(1.3), np.sin(1.3)])
    p = np.array([10.0, 20.0]) + t[:, None] * d + rng.normal(0, 0.5, 200)[:, None] * [-d[1], d[0]]
    line = fit_line_2d(p)
    assert abs(abs(line.direction @ d) - 1) < 1e-4


# --- against the project's simulator (lidarcal.synthetic) ---------------------------------------

def _camera_lines(planes, centres, pose):
    """Exact camera-side E, l1, l2, alpha for a pose: board planes x laser plane (section 1.3)."""
    from lidarcal.geometry import Plane, intersect_planes, unit

    laser = Plane.from_normal_point(pose.z_axis, pose.T)
    E_c = intersect_planes(planes[0], planes[1], laser)
    ls = []
    for pl, c in zip(planes, centres):
        d = unit(np.cross(pl.normal, laser.normal))
        ls.append(d if (c - E_c) @ d > 0 else -d)
    l_c = np.vstack(ls)
    return E_c, l_c, float(np.arccos(np.clip(l_c[0] @ l_c[1], -1, 1)))


def _check_against_truth(ang, rho, planes, centres, pose, sigma):
    from lidarcal.evaluate import pose_error
    from lidarcal.pose import single_shot_pose

    E_c, l_c, alpha = _camera_lines(planes, centres, pose)
    v = split_v(ang, rho)
    L = fit_v_lines(v.points1, v.points2, alpha)
    # every kept return lies on a board plane (true pose), the two segments on different boards
    on = []
    for pts in (v.points1, v.points2):
        pc = pose.apply(np.column_stack([pts, np.zeros(len(pts))]))
        dist = np.array([np.abs(pl.distance(pc)) for pl in planes])
        assert np.all(dist.min(0) < 4.5 * sigma), dist.min(0).max()
        on.append(int(np.argmin(np.median(dist, axis=1))))
    assert sorted(on) == [0, 1]
    d = L.E - pose.inverse_apply(E_c)[0, :2]
    m2 = float(d @ np.linalg.solve(L.E_cov, d))
    assert m2 < 25
    p = single_shot_pose(l_c, E_c, alpha, L)  # default hint: LiDAR upright
    assert p.info["pairs"] == tuple(on)  # the truth, not the mirror
    e = pose_error(p, pose)
    phi_std = L.info["phi_std_rad"]
    assert e["x_axis_deg"] < 5 * np.degrees(phi_std)
    assert e["centre_mm"] < 5 * (np.sqrt(np.trace(L.E_cov)) + phi_std * np.linalg.norm(L.E))
    return m2, e


@pytest.mark.parametrize("rig", ["paper", "wide", "harsh"])
def test_split_and_fit_on_project_simulator_scans(rig):
    synthetic = pytest.importorskip("lidarcal.synthetic")
    m2 = []
    for seed in range(2):
        tr = synthetic.make_truth(seed, rig, with_discs=False, with_intrinsics=False)
        idx = np.linspace(0, len(tr.psi_true_deg) - 1, 3).astype(int)
        R, T = tr.poses_at(tr.psi_true_deg[idx])
        ranges = synthetic.simulate_scans(tr.surfaces, R, T, tr.rig, np.random.default_rng(seed))
        ang = synthetic.beam_angles_deg(tr.rig)
        centres = [b.rect.point(np.array([b.rect.width / 2]), np.array([b.rect.height / 2]))[0]
                   for b in tr.boards]
        for k, i in enumerate(idx):
            rho = np.where(ranges[k] > 0, ranges[k], np.nan)
            m, _ = _check_against_truth(ang, rho, tr.board_planes, centres,
                                        tr.pose_at(tr.psi_true_deg[i]), tr.rig.range_noise_mm)
            m2.append(m)
    assert np.mean(m2) < 6  # E's covariance roughly calibrated (2 expected)


PAPER_RIG = Path(__file__).resolve().parents[1] / "data" / "paper_rig"


@pytest.mark.skipif(not (PAPER_RIG / "truth.json").is_file(), reason="no simulated data/paper_rig")
def test_split_and_fit_on_simulated_paper_rig_dataset():
    from lidarcal.geometry import Plane, Pose
    from lidarcal.io.dataset import load_dataset, read_scan

    ds = load_dataset(PAPER_RIG)
    truth = json.loads((PAPER_RIG / "truth.json").read_text())
    planes = [Plane(np.asarray(b["normal"], float), float(b["d_mm"])) for b in truth["boards"]]
    centres = [np.mean(np.asarray(b["outline_mm"], float), axis=0) for b in truth["boards"]]
    poses = {int(p["index"]): Pose.from_dict(p) for p in truth["poses"]}
    sigma = float(truth.get("noise", {}).get("range_noise_mm", 1.0))
    errs = []
    for pos in ds.positions[:: max(1, len(ds.positions) // 5)]:
        ang, rho = read_scan(pos.scan, ds.lidar)
        _, e = _check_against_truth(ang, rho, planes, centres, poses[pos.index], sigma)
        errs.append(e["centre_mm"])
    print(f"paper_rig: single-shot centre error (exact camera lines) mean {np.mean(errs):.3f} mm, "
          f"max {np.max(errs):.3f} mm")


@pytest.mark.parametrize("opening", [(60.0, 75.0), (75.0, 88.0)])
def test_split_v_finds_a_v_outside_the_usual_opening_when_alpha_says_so(opening):
    # a V-board opened at 60-88 deg: the camera's alpha, not a fixed 90-170 deg
    # window, decides which pair of pieces is the V
    for seed in range(3):
        rng = np.random.default_rng(100 + seed)
        tr = make_truth(rng, opening_deg=opening)
        ang, rho, lab = simulate_scan(tr, rng, sigma_mm=1.0)
        v = split_v(ang, rho, alpha=tr.alpha)
        assert {lab[v.index1[5]], lab[v.index2[5]]} == {BOARD1, BOARD2}
        assert abs(v.opening_deg - np.degrees(tr.alpha)) < 2.0
