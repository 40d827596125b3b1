"""Shared geometry: identities (hypothesis) and seeded fits against known truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from lidarcal.geometry import (
    Line3D,
    Plane,
    Pose,
    angle_between_deg,
    fit_circle_2d,
    fit_circle_2d_algebraic,
    fit_circle_3d,
    fit_plane,
    fit_plane_algebraic,
    intersect_planes,
    line_difference,
    nearest_rotation,
    plane_basis,
    rotate_perpendicular,
    rotation_about_axis,
)

unit_vectors = st.tuples(*[st.floats(-1, 1)] * 3).map(np.array).filter(
    lambda v: np.linalg.norm(v) > 0.1).map(lambda v: v / np.linalg.norm(v))
angles = st.floats(-np.pi, np.pi)


@given(unit_vectors, angles)
def test_rotation_about_axis_is_a_rotation_fixing_its_axis(k, t):
    R = rotation_about_axis(k, t)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R @ k, k, atol=1e-12)
    np.testing.assert_allclose(Rotation.from_matrix(R).as_rotvec(), k * t, atol=1e-9) \
        if abs(t) < np.pi - 1e-6 else None


@given(unit_vectors, unit_vectors, angles)
def test_rodrigues_perpendicular_matches_general_rotation(k, a, t):
    v = np.cross(k, a)
    if np.linalg.norm(v) < 1e-3:
        return
    np.testing.assert_allclose(rotate_perpendicular(v, k, t), rotation_about_axis(k, t) @ v, atol=1e-9)
    assert np.linalg.norm(rotate_perpendicular(v, k, t)) == pytest.approx(np.linalg.norm(v))


@given(st.integers(0, 2**31 - 1))
def test_nearest_rotation_recovers_a_perturbed_rotation(seed):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed).as_matrix()
    Rn, dist = nearest_rotation(R)
    np.testing.assert_allclose(Rn, R, atol=1e-12)
    assert dist < 1e-12
    M = R + 1e-3 * rng.standard_normal((3, 3))
    Rm, dist = nearest_rotation(M)
    assert np.linalg.det(Rm) == pytest.approx(1.0)
    assert dist == pytest.approx(np.linalg.norm(M - Rm))
    assert dist <= np.linalg.norm(M - R) + 1e-12  # optimality: no rotation is nearer than Rm
    assert np.linalg.norm(Rm - R) <= 2 * np.linalg.norm(M - R)
    # a reflection is never returned
    Rr, _ = nearest_rotation(-R)
    assert np.linalg.det(Rr) == pytest.approx(1.0)


@given(st.integers(0, 2**31 - 1))
def test_pose_apply_inverse_round_trip(seed):
    rng = np.random.default_rng(seed)
    pose = Pose(Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 500, 3))
    X = rng.normal(0, 1000, (20, 3))
    np.testing.assert_allclose(pose.inverse_apply(pose.apply(X)), X, atol=1e-9)
    assert Pose.from_dict(pose.to_dict()).apply(X) == pytest.approx(pose.apply(X))


@pytest.mark.parametrize("seed", range(5))
def test_fit_plane_tls_beats_algebraic_on_noisy_points(seed):
    rng = np.random.default_rng(seed)
    n = np.array([0.2, -0.9, 0.3])
    n /= np.linalg.norm(n)
    truth = Plane(n, 1100.0)
    B = plane_basis(n)
    pts = n * truth.d + rng.uniform(-200, 200, (400, 2)) @ B
    pts += rng.normal(0, 0.5, (400, 1)) * n  # 0.5 mm noise across the plane
    fit = fit_plane(pts)
    assert angle_between_deg(fit.normal, n) < 0.05
    assert abs(fit.d - truth.d) < 0.2
    assert np.abs(fit.distance(pts)).mean() < 0.6
    alg = fit_plane_algebraic(pts)
    assert angle_between_deg(alg.normal, n) < 1.0  # close, but not the geometric optimum
    assert np.sum(fit.distance(pts) ** 2) <= np.sum(alg.distance(pts) ** 2) + 1e-9


def test_intersect_planes_and_rays():
    p1 = Plane(np.array([1.0, 0, 0]), 2.0)
    p2 = Plane(np.array([0, 1.0, 0]), 3.0)
    p3 = Plane(np.array([0, 0, 1.0]), 4.0)
    np.testing.assert_allclose(intersect_planes(p1, p2, p3), [2, 3, 4])
    hits = p3.intersect_rays(np.array([[0, 0, 1.0], [1, 1, 2.0]]))
    np.testing.assert_allclose(hits, [[0, 0, 4], [2, 2, 4]])
    with pytest.raises(ValueError, match="single point"):
        intersect_planes(p1, p1, p3)


@pytest.mark.parametrize("seed", range(5))
def test_circle_fits_on_a_short_arc(seed):
    rng = np.random.default_rng(seed)
    c, r = np.array([40.0, -25.0]), 60.0
    t = np.radians(rng.uniform(0, 20, 87))  # ~20 deg of arc, as in the paper's turntable sweep
    pts = c + r * np.column_stack([np.cos(t), np.sin(t)]) + rng.normal(0, 0.01, (87, 2))
    cg, rg = fit_circle_2d(pts)
    assert np.linalg.norm(cg - c) < 1.0 and abs(rg - r) < 1.0
    exact = c + r * np.column_stack([np.cos(t), np.sin(t)])
    ca, ra = fit_circle_2d_algebraic(exact)
    assert abs(ra - r) < 1e-6 and np.linalg.norm(ca - c) < 1e-6  # exact data: both are exact


def test_fit_circle_3d_recovers_truth():
    rng = np.random.default_rng(3)
    n = np.array([0.1, 0.2, 0.97])
    n /= np.linalg.norm(n)
    B = plane_basis(n)
    centre, r = np.array([10.0, 20.0, 900.0]), 45.0
    t = rng.uniform(0, 2 * np.pi, 50)
    pts = centre + r * (np.cos(t)[:, None] * B[0] + np.sin(t)[:, None] * B[1])
    circ = fit_circle_3d(pts + rng.normal(0, 0.01, pts.shape))
    assert np.linalg.norm(circ.centre - centre) < 0.02
    assert abs(circ.radius - r) < 0.02
    assert angle_between_deg(circ.normal, n) < 0.05 or angle_between_deg(-circ.normal, n) < 0.05


def test_skew_is_the_cross_product_matrix_of_stacked_vectors():
    """``skew(v) @ u == v x u`` for single and stacked vectors; antisymmetric, zero diagonal."""
    from lidarcal.geometry import skew

    rng = np.random.default_rng(3)
    for shape in ((3,), (7, 3), (2, 5, 3)):
        v, u = rng.normal(size=shape), rng.normal(size=shape)
        S = skew(v)
        assert S.shape == shape[:-1] + (3, 3)
        np.testing.assert_allclose((S @ u[..., None])[..., 0], np.cross(v, u), atol=1e-14)
        np.testing.assert_array_equal(S, -np.swapaxes(S, -1, -2))
        assert np.all(np.diagonal(S, axis1=-2, axis2=-1) == 0)



@given(unit_vectors, unit_vectors, st.floats(0.0, 0.5), st.floats(0.0, 50.0), st.floats(-500.0, 500.0))
def test_line_difference_is_the_tilt_and_the_offset_near_a_point(k, a, tilt, shift, t):
    """Two estimates of a line: a parallel copy ``shift`` mm away gives (0 deg, shift); a copy
    tilted by ``tilt`` (rad) about a perpendicular through the point nearest ``near`` gives
    (tilt, 0); whichever way round either direction points."""
    p = np.cross(k, a)
    if np.linalg.norm(p) < 0.1:
        return
    p /= np.linalg.norm(p)
    base = Line3D(np.zeros(3), k)
    near = t * k + 30.0 * p  # 30 mm beside the line, at ``t`` along it
    parallel = Line3D(shift * np.cross(k, p) + 11.0 * k, -k)
    angle, dist = line_difference(base, parallel, near)
    assert angle == pytest.approx(0.0, abs=1e-5) and dist == pytest.approx(shift, abs=1e-6)
    tilted = Line3D(t * k, rotation_about_axis(p, tilt) @ k)
    angle, dist = line_difference(base, tilted, near)
    assert angle == pytest.approx(np.degrees(tilt), abs=1e-5) and dist == pytest.approx(0.0, abs=1e-6)
