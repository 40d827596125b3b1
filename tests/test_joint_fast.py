"""The joint fit's fast forms against their direct ones: analytic pose derivatives
(lidarcal.joint.problem.pose_jacobian) against central differences over random rigs and
parameter steps (property test); the moment covariance, angle steps and solver against the
row-by-row ones; the second start's step; the stripe rays from section 1."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal.joint.params import N_RIG, _Base, _poses, _rig
from lidarcal.joint.problem import pose_jacobian


def _columns(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    return np.concatenate([R.transpose(0, 2, 1).reshape(-1, 9), T], 1)


@pytest.mark.parametrize("seed", range(6))
def test_pose_jacobian_equals_central_differences(seed):
    rng = np.random.default_rng(seed)
    base = _Base.make(rng.normal(size=3), rng.normal(size=3) * 100,
                      Rotation.random(random_state=seed).as_matrix(), rng.normal(size=3) * 300,
                      np.zeros((2, 3, 3)), np.zeros((2, 3)))
    # seed 0: a rotation step below the series threshold of the left Jacobian
    w = rng.normal(size=3) * (1e-9 if seed == 0 else 0.3)
    x = np.r_[rng.normal(size=2) * 0.1, rng.normal(size=2) * 10, w, rng.normal(size=3) * 10]
    t = rng.uniform(-1.0, 1.0, 7)
    R, T, G = pose_jacobian(x, base, t)
    R0, T0 = _poses(*_rig(x, base), t)
    assert np.allclose(R, R0) and np.allclose(T, T0)
    h = 1e-6
    for j in range(N_RIG):
        dx = np.zeros(N_RIG)
        dx[j] = h
        num = (_columns(*_poses(*_rig(x + dx, base), t))
               - _columns(*_poses(*_rig(x - dx, base), t))) / (2 * h)
        # central differences: truncation ~h^2 |f'''|, rounding ~1e-16 |f| / h (|T| ~ 1e3 mm)
        assert np.allclose(G[:, :, j], num, rtol=1e-6, atol=1e-6), j


@pytest.fixture(scope="module")
def noisy_problem():
    """A held-planes joint problem of a small noisy simulated rig, set up as fit_joint does
    (dark returns, stripe scales, correlated noise model, rejection)."""
    from lidarcal.joint import joint_data
    from lidarcal.joint.fit import _start_bases
    from lidarcal.joint.params import N_BOARD
    from lidarcal.joint.problem import _Problem
    from lidarcal.ranging import RangingPrior
    from lidarcal.study import StudySetting, simulate_rig

    res = simulate_rig(21, StudySetting(n_positions=6)).result
    data = joint_data(res, "pnp")
    psi_ref = float(np.mean(data.psi_deg))
    base = _start_bases([res.rigid_model], data, psi_ref)[0]
    pr = RangingPrior()
    prior = (np.array([pr.offset_mm, pr.dark_extra_mm]),
             np.array([pr.offset_sigma_mm, pr.dark_extra_sigma_mm]))
    prob = _Problem(data, base, psi_ref, 2, prior)
    full = np.zeros(N_RIG + 2 * N_BOARD + 2)
    prob.classify(full)
    prob.set_stripe_scale(full)
    prob.estimate_noise(np.zeros(N_RIG + 2), True)
    prob.reject(full)
    prob.corner_floor_px = 0.1
    return prob


def test_moment_covariance_equals_row_covariance(noisy_problem):
    """The covariance from the group moments (rig, ranging, consider term, s^2, the
    cluster-robust sandwich) is the row-by-row one, to rounding."""
    from lidarcal.joint.moments import moments_covariance
    from lidarcal.joint.solver import _covariance_rows

    prob = noisy_problem
    C0, null0, s20 = _covariance_rows(prob, False, "soft_l1", 2.5)
    sw0 = prob.sandwich
    C1, null1, s21 = moments_covariance(prob, "soft_l1", 2.5)
    sig = np.sqrt(np.diag(C0))
    assert np.all(np.isfinite(sig)) and null0.shape == null1.shape
    assert np.allclose(C1 / np.outer(sig, sig), C0 / np.outer(sig, sig), rtol=0, atol=1e-8)
    assert s21 == pytest.approx(s20, rel=1e-10)
    ss = np.sqrt(np.diag(sw0))
    assert np.allclose(prob.sandwich / np.outer(ss, ss), sw0 / np.outer(ss, ss), rtol=0, atol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_start_step_reproduces_the_other_start(seed):
    """A second start expressed as a step in the first start's parametrisation gives the
    same pose function (axis line, reference pose) at every angle."""
    from lidarcal.joint.problem import start_step

    rng = np.random.default_rng(seed)
    k0 = rng.normal(size=3)
    k1 = k0 / np.linalg.norm(k0) + rng.normal(size=3) * 0.05  # a few degrees apart
    z = (np.zeros((2, 3, 3)), np.zeros((2, 3)))
    b0 = _Base.make(k0, rng.normal(size=3) * 100, Rotation.random(random_state=seed).as_matrix(),
                    rng.normal(size=3) * 300, *z)
    b1 = _Base.make(k1, b0.a + rng.normal(size=3) * 5,
                    Rotation.from_rotvec(rng.normal(size=3) * 0.02).as_matrix() @ b0.R,
                    b0.T + rng.normal(size=3) * 2, *z)
    t = rng.uniform(-1.0, 1.0, 9)
    R0, T0 = _poses(*_rig(start_step(b0, b1), b0), t)
    R1, T1 = _poses(b1.k, b1.a, b1.R, b1.T, t)
    assert np.allclose(R0, R1, atol=1e-12) and np.allclose(T0, T1, atol=1e-9)
    flipped = _Base.make(-k0, b0.a, b0.R, b0.T, *z)
    assert start_step(b0, flipped) is None


def test_group_moments_in_blocks_equal_the_direct_sums(noisy_problem, monkeypatch):
    """The group moments ``Q = sum W h~ h~^T`` computed a few groups at a time
    (:data:`lidarcal.joint.moments.MOMENT_GROUPS`) are those of one batch bit for bit, and
    equal the sums over each group's rows of the whitened observations."""
    from lidarcal.joint import moments as mo

    mp = mo._MomentProblem(noisy_problem)
    rng = np.random.default_rng(5)
    Ws, Wp = rng.uniform(0.2, 1.0, mp.hs[:, 0].size), rng.uniform(0.2, 1.0, mp.hp[:, 0].size)
    Qs, Qp = mp.moments(Ws, Wp, grid=True)
    monkeypatch.setattr(mo, "MOMENT_GROUPS", 5)  # several blocks, a short last one
    Qs5, Qp5 = mp.moments(Ws, Wp, grid=True)
    np.testing.assert_array_equal(Qs5, Qs)
    np.testing.assert_array_equal(Qp5, Qp)
    for h, W, Q in ((mp.hs, Ws, Qs), (mp.hp, Wp, Qp)):
        W = W.reshape(h.shape[0], h.shape[2])
        direct = np.array([(h[g] * W[g]) @ h[g].T for g in range(len(h))])
        np.testing.assert_allclose(Q, direct, rtol=1e-12, atol=1e-12 * np.abs(direct).max())


@pytest.mark.parametrize("step", [0.0, 1.0])
def test_board_derivatives_equal_central_differences(noisy_problem, step):
    """The analytic derivatives of the board planes (normal, d) and of the corners'
    reprojections wrt the board parameters (:meth:`_Problem.plane_derivatives`,
    :meth:`_Problem.corner_jacobian`) equal central differences of the planes and of
    ``cv2.projectPoints``, at the held boards and at a board step."""
    from lidarcal.joint.params import _STEPS, N_BOARD, _boards

    prob = noisy_problem
    rng = np.random.default_rng(6)
    x = np.zeros(N_RIG + 2 * N_BOARD)
    x[N_RIG:] = step * rng.normal(size=2 * N_BOARD) * np.tile([2e-3] * 3 + [1.0] * 3, 2)  # rad, mm
    m = len(prob.corner_residuals(*_boards(x, prob.base)))
    assert m > 0
    Jc, Gb = np.zeros((m, 2 * N_BOARD)), np.zeros((2, 4, N_BOARD))
    for i in range(N_RIG, N_RIG + 2 * N_BOARD):
        b, j = divmod(i - N_RIG, N_BOARD)
        dx = np.zeros(len(x))
        dx[i] = _STEPS[i]
        (Rp, Tp), (Rm, Tm) = _boards(x + dx, prob.base), _boards(x - dx, prob.base)
        Jc[:, i - N_RIG] = (prob.corner_residuals(Rp, Tp) - prob.corner_residuals(Rm, Tm)) / (2 * dx[i])
        fp = np.append(Rp[b][:, 2], Rp[b][:, 2] @ Tp[b])
        fm = np.append(Rm[b][:, 2], Rm[b][:, 2] @ Tm[b])
        Gb[b, :, j] = (fp - fm) / (2 * dx[i])
    # central differences: truncation ~h^2 and rounding ~1e-16 / h (h = 1e-6 rad, 1e-3 mm)
    np.testing.assert_allclose(prob.corner_jacobian(x), Jc, rtol=0, atol=1e-6 * np.abs(Jc).max())
    np.testing.assert_allclose(prob.plane_derivatives(x), Gb, rtol=0, atol=1e-8 * np.abs(Gb).max())


def test_angle_steps_from_moments_equal_central_differences(noisy_problem, monkeypatch):
    """Each position's angle step and its variance (the jitter test): the analytic moment
    form equals one central difference of the angles on the rows."""
    from lidarcal.joint import jitter

    prob = noisy_problem
    x = np.zeros(N_RIG + prob.n_ranging)
    x[4:7] = [2e-4, -1e-4, 3e-4]  # off the optimum: steps and weights away from trivial
    step, var = jitter._angle_steps(prob, x, "soft_l1", 2.5)
    monkeypatch.setattr(jitter, "moments_usable", lambda *a: False)
    step0, var0 = jitter._angle_steps(prob, x, "soft_l1", 2.5)
    assert np.all(np.isfinite(var0)) and np.any(np.abs(step0) > 3 * np.sqrt(var0))
    assert np.allclose(step, step0, rtol=0, atol=1e-6 * np.sqrt(var0).min())
    assert np.allclose(var, var0, rtol=1e-6)


@pytest.mark.parametrize("loss", ["soft_l1", "huber", "cauchy"])
def test_moment_solver_reaches_the_row_solver_optimum(noisy_problem, loss):
    """On one problem (noise model held), the moment solver's Newton passes end at the
    optimum of the row-by-row robust Levenberg-Marquardt: same robust cost, parameters
    within a small fraction of a sigma (the information of the fit)."""
    from lidarcal.joint import irls_lm
    from lidarcal.joint.moments import irls_moments

    prob = noisy_problem
    x0 = np.zeros(N_RIG + prob.n_ranging)
    x0[7:10] = [0.5, -0.3, 0.2]  # start half a millimetre off
    a = irls_moments(prob, x0, loss, 2.5)
    b = irls_lm(lambda v: prob.normalised(v, False), lambda v: prob.jacobian(v, False), x0,
                loss, 2.5, max_iter=200)
    assert a.status == 1 and b.status == 1
    assert a.cost == pytest.approx(b.cost, rel=1e-9)
    dx = a.x - b.x
    assert float(dx @ a.information @ dx) < 1e-4  # below 0.01 sigma


def test_stripe_rays_from_section1_points_equal_undistortion():
    """The rays of the stripe centres taken from section 1's back-projected points are the
    undistorted pixels' rays; points that do not belong to the pixels are not used."""
    from lidarcal.camera import pixel_rays
    from lidarcal.joint import joint_data
    from lidarcal.joint.data import _stripe_rays
    from lidarcal.study import StudySetting, simulate_rig

    res = simulate_rig(22, StudySetting(n_positions=4)).result
    d = joint_data(res, "pnp")
    assert np.allclose(d.stripe_rays, pixel_rays(d.camera, d.stripe_px), rtol=0, atol=1e-14)
    pts = d.stripe_rays * 500.0
    shifted = np.roll(pts, 1, axis=0)  # one row off: a sample reprojects elsewhere
    assert np.array_equal(_stripe_rays(d.camera, d.stripe_px, shifted),
                          pixel_rays(d.camera, d.stripe_px))


@pytest.mark.parametrize("seed", range(3))
def test_stripe_pixel_jacobian_equals_opencv(seed):
    """d pixel / d point of the stripe scale (lidarcal.pixel_jacobian.pixel_jacobian) from the
    camera's distortion Jacobian equals cv2.projectPoints' Jacobian wrt the translation, for
    random cameras with all five distortion coefficients, over the image (a skew in K:
    ignored by both, as cv2.projectPoints does)."""
    import cv2

    from lidarcal.io.dataset import CameraModel
    from lidarcal.pixel_jacobian import pixel_jacobian

    rng = np.random.default_rng(seed)
    K = np.array([[rng.uniform(800, 2000), rng.uniform(-2, 2), rng.uniform(600, 700)],
                  [0.0, rng.uniform(800, 2000), rng.uniform(400, 500)], [0.0, 0.0, 1.0]])
    dist = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(-1e-3, 1e-3),
                     rng.uniform(-1e-3, 1e-3), rng.uniform(-0.05, 0.05)])
    cam = CameraModel(K, dist, (1280, 960))
    z = rng.uniform(300, 1500, 200)
    P = np.column_stack([rng.uniform(-0.5, 0.5, 200) * z, rng.uniform(-0.4, 0.4, 200) * z, z])
    _, J = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    J0 = J[:, 3:6].reshape(-1, 2, 3)
    assert np.allclose(pixel_jacobian(cam, P), J0, rtol=1e-9, atol=1e-12 * np.abs(J0).max())


@pytest.mark.parametrize("seed", range(3))
def test_pixel_jacobian_forms_equal_those_of_opencvs_jacobian(seed):
    """The Binet-Cauchy forms of d pixel / d point (row cross product, J^T J) computed from the
    distortion's Jacobian (lidarcal.pixel_jacobian.pixel_jacobian_forms) equal those of
    cv2.projectPoints' Jacobian wrt the translation, for random five-coefficient cameras."""
    import cv2

    from lidarcal.io.dataset import CameraModel
    from lidarcal.pixel_jacobian import jacobian_forms, pixel_jacobian_forms

    rng = np.random.default_rng(10 + seed)
    K = np.array([[rng.uniform(800, 2000), 0.0, rng.uniform(600, 700)],
                  [0.0, rng.uniform(800, 2000), rng.uniform(400, 500)], [0.0, 0.0, 1.0]])
    dist = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2), rng.uniform(-1e-3, 1e-3),
                     rng.uniform(-1e-3, 1e-3), rng.uniform(-0.05, 0.05)])
    z = rng.uniform(300, 1500, 200)
    P = np.column_stack([rng.uniform(-0.5, 0.5, 200) * z, rng.uniform(-0.4, 0.4, 200) * z, z])
    _, J = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    F0 = jacobian_forms(J[:, 3:6].reshape(-1, 2, 3))
    F1 = pixel_jacobian_forms(CameraModel(K, dist, (1280, 960)), P)
    assert np.allclose(F1, F0, rtol=1e-9, atol=1e-12 * np.abs(F0).max(axis=0))


def test_pixel_jacobian_forms_in_blocks_equal_all_at_once(monkeypatch):
    """The forms computed block by block (:data:`lidarcal.pixel_jacobian.FORMS_BLOCK`) are the
    numbers of one pass over all centres, bit for bit (each row on its own), with a block
    size that leaves a short last block."""
    from lidarcal import pixel_jacobian as pj
    from lidarcal.io.dataset import CameraModel

    rng = np.random.default_rng(4)
    K = np.array([[1400.0, 0.0, 640.0], [0.0, 1390.0, 470.0], [0.0, 0.0, 1.0]])
    cam = CameraModel(K, np.array([-0.2, 0.1, 4e-4, -3e-4, -0.02]), (1280, 960))
    z = rng.uniform(300, 1500, 1000)
    P = np.column_stack([rng.uniform(-0.5, 0.5, 1000) * z, rng.uniform(-0.4, 0.4, 1000) * z, z])
    whole = pj.pixel_jacobian_forms(cam, P)
    monkeypatch.setattr(pj, "FORMS_BLOCK", 97)
    np.testing.assert_array_equal(pj.pixel_jacobian_forms(cam, P), whole)
    np.testing.assert_allclose(whole, pj.jacobian_forms(pj.pixel_jacobian(cam, P)), rtol=1e-9,
                               atol=1e-12 * np.abs(whole).max())


def test_stripe_scale_equals_the_imaged_directions(noisy_problem):
    """The stripe scale from the Binet-Cauchy forms (:meth:`_Problem.set_stripe_scale`) equals
    the direct one: board direction u and stripe direction l imaged by each centre's pixel
    Jacobian, |J u x J l| / |J l| per mm of laser offset, at the start and at a rig step."""
    from lidarcal.geometry import unit
    from lidarcal.joint.params import _poses, _rig
    from lidarcal.joint.problem import _stripe_points
    from lidarcal.pixel_jacobian import pixel_jacobian

    prob = noisy_problem
    d = prob.data
    J = pixel_jacobian(d.camera, _stripe_points(d, d.board_R, d.board_T)["P"])
    saved = prob.scale_px, prob.scale_depth
    try:
        for step in (0.0, 0.02):
            x = np.zeros(N_RIG + 12 + 2)
            x[[0, 5]] = step
            prob.set_stripe_scale(x)
            R, _ = _poses(*_rig(x[:N_RIG], prob.base), prob.t)
            g = 2 * d.stripe_pos + d.stripe_board
            n, zL = d.board_R[d.stripe_board, :, 2], R[d.stripe_pos, :, 2]
            line = unit(np.cross(n, zL))
            u = unit(np.cross(n, line))
            pu, pl = np.einsum("mij,mj->mi", J, u), np.einsum("mij,mj->mi", J, line)
            perp = np.abs(pu[:, 0] * pl[:, 1] - pu[:, 1] * pl[:, 0]) / np.hypot(*pl.T)
            want = perp / np.maximum(np.abs(np.einsum("ij,ij->i", zL, u)), 1e-9)
            assert len(np.unique(g)) > 2
            assert np.allclose(prob.scale_px, want, rtol=1e-10, atol=0), step
    finally:
        prob.scale_px, prob.scale_depth = saved


def test_grid_layout_equals_the_rows():
    """The moment solver's grid layout (:meth:`_Groups.pad_columns`, groups of unequal size,
    one empty): the whitening there (:func:`whiten_padded`) is the row whitening times the
    mask, per-row dot products (:func:`padded_rows_dot`) and the moments ``sum W h h^T`` and
    ``sum v h`` are those of the rows group by group."""
    from lidarcal.joint.noise import _Groups, padded_rows_dot, whiten_padded

    rng = np.random.default_rng(7)
    n_pos = 3
    size = np.array([5, 40, 0, 17, 60, 33])  # rows of group 2 i + b
    gid = np.repeat(np.arange(2 * n_pos), size)
    g = _Groups(gid // 2, gid % 2, rng.normal(size=(len(gid), 2)) * [50.0, 2.0], n_pos)
    g.set_mask(rng.random(len(gid)) > 0.1)
    g.set([0.7, 1.3], [0.2, 0.05], [1e-4, 3e-4], rng.uniform(0.1, 0.3, 2 * n_pos), None)
    h = rng.normal(size=(len(gid), 4))
    H = whiten_padded(g, g.pad_columns(h))
    assert H.shape == (2 * n_pos, 4, size.max())
    rows = g.whiten_columns(h) * g.w[:, None]
    assert np.allclose(H.transpose(0, 2, 1).reshape(-1, 4)[g._grid], rows, rtol=0, atol=1e-13)
    c, W = rng.normal(size=(2 * n_pos, 4)), rng.uniform(0.2, 1.0, len(gid))
    assert np.allclose(padded_rows_dot(g, H, c), np.einsum("mk,mk->m", rows, c[gid]),
                       rtol=0, atol=1e-13)
    Q = np.matmul(H * g.pad(W)[:, None, :], H.transpose(0, 2, 1))
    b = np.matmul(H, g.pad(W)[:, :, None])[:, :, 0]
    for k in range(2 * n_pos):
        m = gid == k
        assert np.allclose(Q[k], (rows[m] * W[m, None]).T @ rows[m], rtol=0, atol=1e-12)
        assert np.allclose(b[k], W[m] @ rows[m], rtol=0, atol=1e-12)
    assert np.array_equal(g.unpad(g.pad(W)), W)
    g.set([0.7, 1.3], [0.0, 0.0], [0.0, 0.0])  # white noise: whitening is a scaling
    rows = g.whiten_columns(h) * g.w[:, None]
    H = whiten_padded(g, g.pad_columns(h)).transpose(0, 2, 1).reshape(-1, 4)[g._grid]
    assert np.array_equal(H, rows)


def test_whitening_of_large_groups_equals_the_row_gather():
    """The noise model's whitening (GLS, per-group offset and tilt) group by group (large
    groups, rows grouped) equals the same on the rows in another order (gathered by group)
    and the column-by-column whitening, with a mask and per-group components."""
    from lidarcal.joint.noise import BLOCK_ROWS, _Groups

    rng = np.random.default_rng(5)
    n_pos, per = 3, 2 * BLOCK_ROWS
    pos = np.repeat(np.arange(n_pos), 2 * per)
    board = np.tile(np.repeat([0, 1], per), n_pos)
    coords = rng.normal(size=(len(pos), 2)) * [50.0, 2.0]
    J = rng.normal(size=(len(pos), 4))
    keep = rng.random(len(pos)) > 0.05
    perm = rng.permutation(len(pos))
    var0_g = rng.uniform(0.1, 0.3, 2 * n_pos)  # per-group components
    out = []
    for idx in (np.arange(len(pos)), perm):
        g = _Groups(pos[idx], board[idx], coords[idx], n_pos)
        g.set_mask(keep[idx])
        g.set([0.7, 1.3], [0.2, 0.05], [1e-4, 3e-4], var0_g, np.full(2 * n_pos, 2e-4))
        assert g._sorted == (idx is not perm)
        w = g.whiten_columns(J[idx])
        cols = np.column_stack([g.whiten(J[idx][:, j]) for j in range(J.shape[1])])
        assert np.allclose(w, cols, rtol=0, atol=1e-12)
        out.append(np.empty_like(w))
        out[-1][idx] = w
    assert np.allclose(out[0], out[1], rtol=0, atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 3, 10, 11, 1000, 1001, 36561])
def test_median_equals_numpys(n):
    """The one partition median (lidarcal.geometry.median, used by the scan and stripe steps
    and the joint fit's noise model) is numpy's, bit for bit, for odd and even counts and
    ties; the joint fit's robust sigma keeps numpy's NaN."""
    from lidarcal.geometry import median
    from lidarcal.joint.params import _robust_sigma

    rng = np.random.default_rng(n)
    for a in (np.abs(rng.standard_t(3, n)), np.round(rng.normal(size=n), 1)):
        b = a.copy()
        assert median(a) == np.median(a) and np.array_equal(a, b)  # copied by default
        assert median(b, overwrite=True) == np.median(a)
    a = rng.normal(size=n)
    a[n // 3] = np.nan
    assert np.isnan(_robust_sigma(a, 0.0))


def test_observation_grids_equal_the_rows(noisy_problem):
    """The moment solver's raw observations laid out on the grids (constant parts once per
    data and planes, lidarcal.joint.moments.raw_observations_grid) are the rows of
    raw_observations, and rows with a non-finite entry are found as numpy's all() finds them."""
    from lidarcal.joint.data import _finite_rows
    from lidarcal.joint.moments import raw_observations, raw_observations_grid

    prob = noisy_problem
    for grp, rows, grid in zip((prob.scan, prob.stripe), raw_observations(prob),
                               raw_observations_grid(prob)):
        assert np.array_equal(grid, grp.pad_columns(rows))
    a = np.random.default_rng(3).normal(size=(50, 3))
    a[[3, 9, 20], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    assert np.array_equal(_finite_rows(a), np.all(np.isfinite(a), axis=1))


def test_dark_classification_equals_the_beams_cut_with_the_boards():
    """The joint fit's dark shares (per group, hits in board coordinates from the LiDAR plane,
    _Problem.classify) equal lidarcal.ranging.dark_returns on every beam in the camera frame,
    at the start and at a rig step, with returns on both colours."""
    import copy

    from lidarcal.joint import joint_data
    from lidarcal.joint.fit import _start_bases
    from lidarcal.joint.params import _boards
    from lidarcal.joint.problem import _Problem
    from lidarcal.ranging import dark_returns
    from lidarcal.study import StudySetting, simulate_rig

    res = simulate_rig(21, StudySetting(n_positions=6)).result
    data = joint_data(res, "pnp")
    assert data.can_see_dark and data.scan_dark is None
    prob = _Problem(data, _start_bases([res.rigid_model], data, 0.0)[0], 0.0)
    for step in (0.0, 0.01):
        x = np.zeros(N_RIG + 12)
        x[[1, 4, 8]] = [step, step, 50 * step]
        q = copy.copy(prob)
        q.classify(x)
        R, T = _poses(*_rig(x[:N_RIG], prob.base), prob.t)
        bR, bT = _boards(x, prob.base)
        p, u = data.scan_pos, prob.scan_u
        dirs = R[p, :, 0] * u[:, :1] + R[p, :, 1] * u[:, 1:]
        want = np.zeros(len(p))
        for b in range(2):
            m = data.scan_board == b
            want[m] = dark_returns(T[p][m], dirs[m], bR[b], bT[b], data.board_spec,
                                   data.black_parity[b])
        assert 0.1 < np.mean(want > 0.5) < 0.9
        assert np.allclose(q.dark, want, rtol=0, atol=1e-9), step
