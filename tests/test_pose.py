"""Section 1.5: pose from two line pairs (eqs. 13-14), the mirror choice, refinement; against truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from vscan_truth import BOARD1, make_truth, simulate_scan

from lidarcal.evaluate import pose_error
from lidarcal.geometry import Line3D, Pose, check_rotation
from lidarcal.pose import pose_from_line_pairs, refine_pose, single_shot_pose
from lidarcal.scan import fit_v_lines, split_v

finite = {"allow_nan": False, "allow_infinity": False}


@settings(max_examples=80, deadline=None)
@given(q=st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4).filter(
           lambda q: np.linalg.norm(q) > 0.1),
       T=st.lists(st.floats(-2000, 2000, **finite), min_size=3, max_size=3),
       E=st.lists(st.floats(-2000, 2000, **finite), min_size=2, max_size=2),
       th=st.floats(0, 2 * np.pi), alpha=st.floats(0.2, np.pi - 0.2), sign=st.sampled_from([-1, 1]))
def test_pose_from_exact_line_pairs_is_exact(q, T, E, th, alpha, sign):
    R = Rotation.from_quat(q).as_matrix()
    T = np.asarray(T)
    l_l = np.array([[np.cos(th), np.sin(th), 0.0],
                    [np.cos(th + sign * alpha), np.sin(th + sign * alpha), 0.0]])
    E_l = np.array([E[0], E[1], 0.0])
    p = pose_from_line_pairs(l_l @ R.T, l_l, R @ E_l + T, E_l)
    np.testing.assert_allclose(p.R, R, atol=1e-9)
    np.testing.assert_allclose(p.T, T, atol=1e-6)
    assert p.residual < 1e-9
    check_rotation(p.R)


def test_pose_residual_reports_unequal_angles():
    l_l = np.array([[1.0, 0, 0], [np.cos(2.0), np.sin(2.0), 0]])
    l_c = np.array([[1.0, 0, 0], [np.cos(2.1), np.sin(2.1), 0]])
    p = pose_from_line_pairs(l_c, l_l, np.zeros(3), np.zeros(3))
    check_rotation(p.R)
    assert p.residual > 0.05  # the raw eq. (13) product is 0.1 rad off a rotation
    with pytest.raises(ValueError, match="parallel"):
        pose_from_line_pairs(np.array([[1.0, 0, 0], [1, 0, 0]]), l_l, np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="shape"):
        pose_from_line_pairs(np.zeros((3, 3)), l_l, np.zeros(3), np.zeros(3))


def _scan_solution(seed, sigma=1.0, upright=True, step=0.083333, half=35.0, weighting="range"):
    rng = np.random.default_rng(seed)
    tr = make_truth(rng, upright=upright)
    ang, rho, lab = simulate_scan(tr, rng, sigma_mm=sigma, angle_min_deg=-half,
                                  angle_max_deg=half, angle_step_deg=step)
    v = split_v(ang, rho)
    L = fit_v_lines(v.points1, v.points2, tr.alpha, weighting=weighting)
    hint = (0.0, -1.0, 0.0) if upright else (0.0, 1.0, 0.0)
    p = single_shot_pose(tr.l_cam, tr.E_cam, tr.alpha, L, z_axis_hint=hint)
    truth_pairs = (0, 1) if lab[v.index1[len(v.index1) // 2]] == BOARD1 else (1, 0)
    return tr, v, L, p, truth_pairs


@pytest.mark.parametrize("upright", [True, False])
def test_single_shot_picks_truth_not_mirror_exact_lines(upright):
    """Noise-free LiDAR lines from the truth: the chosen pose is the truth, the other its mirror."""
    for seed in range(6):
        rng = np.random.default_rng(seed)
        tr = make_truth(rng, upright=upright)
        E_l = tr.E_lidar
        l_l = (tr.l_cam @ tr.pose.R)[:, :2]  # stripe directions in the LiDAR plane
        # the scan lists the segments in beam order: segment 1 = the lower beam angle
        order = np.argsort([np.arctan2(*(E_l + 200 * lk)[::-1]) for lk in l_l])
        pts = [E_l + np.linspace(250, 5, 50)[:, None] * l_l[order[0]],
               E_l + np.linspace(5, 250, 50)[:, None] * l_l[order[1]]]
        L = fit_v_lines(pts[0], pts[1], tr.alpha)
        hint = (0.0, -1.0, 0.0) if upright else (0.0, 1.0, 0.0)
        p = single_shot_pose(tr.l_cam, tr.E_cam, tr.alpha, L, z_axis_hint=hint)
        np.testing.assert_allclose(p.R, tr.pose.R, atol=1e-9)
        np.testing.assert_allclose(p.T, tr.pose.T, atol=1e-6)
        assert p.info["pairs"] == tuple(int(i) for i in order)
        other = p.info["candidates"]["swapped" if p.info["assignment"] == "direct" else "direct"]
        check_rotation(other.R)  # the mirror is a proper rotation too ...
        assert other.residual < 1e-9
        assert other.z_axis @ tr.pose.z_axis < 0  # ... with the z axis flipped
        # both explain the camera lines: same E, l1, l2 images
        np.testing.assert_allclose(other.apply(L.E_lidar)[0], tr.E_cam, atol=1e-6)
        # and the wrong hint picks the mirror
        q = single_shot_pose(tr.l_cam, tr.E_cam, tr.alpha, L, z_axis_hint=-np.asarray(hint))
        np.testing.assert_allclose(q.R, other.R, atol=1e-12)


def test_single_shot_refuses_unconstrained_lines():
    tr, _v, L, _p, _ = _scan_solution(0)
    with pytest.raises(ValueError, match="camera's alpha"):
        single_shot_pose(tr.l_cam, tr.E_cam, tr.alpha, L.free)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
@pytest.mark.parametrize("step,half", [(0.083333, 35.0), (0.25, 60.0)])
def test_single_shot_accuracy_over_seeds(sigma, step, half, capsys):
    """Pipeline scan -> split_v -> fit_v_lines -> single_shot_pose, 20 seeds, both mountings.

    Camera lines are exact here, so the z axis (the laser-plane normal) is exact and the
    errors come from the scan: the in-plane angle (x axis) and E. Bounds: 5 x the fit's
    own standard errors.
    """
    rows = []
    for seed in range(20):
        upright = seed % 2 == 0
        tr, _v, L, p, pairs = _scan_solution(seed, sigma, upright, step, half)
        assert p.info["pairs"] == pairs  # the truth, not the mirror
        e = pose_error(p, tr.pose)
        phi_std = L.info["phi_std_rad"]
        E_std = np.sqrt(np.trace(L.E_cov))
        assert e["z_axis_deg"] < 1e-6
        assert e["x_axis_deg"] < 5 * np.degrees(phi_std)
        assert e["centre_mm"] < 5 * (E_std + phi_std * np.linalg.norm(L.E))
        rows.append([e["centre_mm"], e["z_axis_deg"], e["x_axis_deg"]])
    rows = np.array(rows)
    with capsys.disabled():
        print(f"\n[sigma {sigma} mm, step {step} deg] centre mm mean/max "
              f"{rows[:, 0].mean():.3f}/{rows[:, 0].max():.3f}; x axis deg mean/max "
              f"{rows[:, 2].mean():.4f}/{rows[:, 2].max():.4f}; z axis deg max {rows[:, 1].max():.1e}")


def test_refine_pose_agrees_with_constrained_fit_and_recovers_from_a_perturbation():
    # refine_pose minimises orthogonal distances: it meets the orthogonal constrained fit
    tr, v, _L, p, _pairs = _scan_solution(4, sigma=2.0, weighting="orthogonal")
    cam_lines = [Line3D(tr.E_cam, tr.l_cam[0]), Line3D(tr.E_cam, tr.l_cam[1])]
    segs = [(v.points1, v.points2)[k] for k in p.info["pairs"]]
    r = refine_pose(p, cam_lines, segs)
    # with fixed camera lines the optimum is the constrained fit + eqs. (13)-(14)
    assert np.degrees(np.arccos(np.clip((np.trace(r.R.T @ p.R) - 1) / 2, -1, 1))) < 1e-4
    assert np.linalg.norm(r.T - p.T) < 1e-3
    # from a pose 2 deg / 20 mm off it comes back
    dR = Rotation.from_rotvec(np.radians(2) * np.array([0.3, -0.5, 0.8])).as_matrix()
    bad = Pose(dR @ p.R, p.T + [20.0, -10, 5])
    r2 = refine_pose(bad, cam_lines, segs)
    assert np.linalg.norm(r2.T - p.T) < 1e-3
    assert r2.info["refine_rms_mm"] < 1.2 * 2.0
    e = pose_error(r2, tr.pose)
    assert e["centre_mm"] < 5 and e["x_axis_deg"] < 0.5
