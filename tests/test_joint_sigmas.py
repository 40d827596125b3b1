"""The joint fit's pose sigmas (lidarcal.joint.model._pose_sigmas): the analytic propagation
agrees with central differences of the rigid model (the former implementation)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lidarcal.joint.model import _pose_sigmas
from lidarcal.joint.params import N_RIG, _Base, _poses, _rig

_STEPS = np.array([1e-6] * 2 + [1e-3] * 2 + [1e-6] * 3 + [1e-3] * 3)


def _finite_difference_jacobians(base: _Base, t: np.ndarray):
    """d centre, d rotation vector (left, of R R0^T) and d foot of the reference centre on the
    axis, by central differences of the rigid model (eqs. 15-27 with the turntable rotation)."""
    R0, _ = _poses(*_rig(np.zeros(N_RIG), base), t)
    GT, Gw, Gf = np.zeros((len(t), 3, N_RIG)), np.zeros((len(t), 3, N_RIG)), np.zeros((3, N_RIG))
    for j in range(N_RIG):
        dx = np.zeros(N_RIG)
        dx[j] = _STEPS[j]
        (Rp, Tp), (Rm, Tm) = _poses(*_rig(dx, base), t), _poses(*_rig(-dx, base), t)
        GT[:, :, j] = (Tp - Tm) / (2 * dx[j])
        Gw[:, :, j] = (Rotation.from_matrix(Rp @ R0.transpose(0, 2, 1)).as_rotvec()
                       - Rotation.from_matrix(Rm @ R0.transpose(0, 2, 1)).as_rotvec()) / (2 * dx[j])
        foot = [a + k * ((base.T - a) @ k) for k, a, _, _ in (_rig(dx, base), _rig(-dx, base))]
        Gf[:, j] = (foot[0] - foot[1]) / (2 * dx[j])
    return R0, GT, Gw, Gf


def _reference_sigmas(base: _Base, cov: np.ndarray, t: np.ndarray) -> dict[str, np.ndarray]:
    R0, GT, Gw, Gf = _finite_difference_jacobians(base, t)
    out = {"centre_mm": np.sqrt(np.trace(GT @ cov @ GT.transpose(0, 2, 1), axis1=1, axis2=2))}
    cw = Gw @ cov @ Gw.transpose(0, 2, 1)
    for name, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
        v = R0[:, :, col]
        P = np.eye(3) - v[:, :, None] * v[:, None, :]
        out[name] = np.degrees(np.sqrt(np.trace(P @ cw @ P, axis1=1, axis2=2)))
    Pk = np.eye(3) - np.outer(base.k, base.k)
    out["axis_point_mm"] = np.sqrt(np.trace(Pk @ Gf @ cov @ Gf.T @ Pk)) + 0 * t
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_analytic_pose_sigmas_match_central_differences(seed):
    rng = np.random.default_rng(seed)
    k = rng.normal(size=3)
    base = _Base.make(k, rng.normal(scale=200, size=3), Rotation.random(random_state=seed).as_matrix(),
                      rng.normal(scale=300, size=3), np.zeros((2, 3, 3)), np.zeros((2, 3)))
    A = rng.normal(size=(N_RIG, N_RIG)) * np.array([1e-3] * 2 + [0.5] * 2 + [1e-3] * 3 + [0.3] * 3)
    cov = A @ A.T
    t = np.radians(rng.uniform(-60, 60, size=25))
    got = _pose_sigmas(base, cov, t, np.zeros((N_RIG, 0)))
    ref = _reference_sigmas(base, cov, t)
    for name, v in ref.items():
        # central differences: truncation ~h^2, rounding ~1e-16 / h (h = 1e-6 rad, 1e-3 mm)
        np.testing.assert_allclose(got[name], v, rtol=1e-7, err_msg=name)
    assert np.all(got["axis_direction_deg"] == np.degrees(np.sqrt(np.trace(cov[:2, :2]))))


def test_unobservable_direction_marks_the_quantities_it_moves():
    """A null direction along the reference centre's x: the centre is undetermined, the axes
    (rotation) are not."""
    base = _Base.make([0, 0, 1.0], [10.0, 0, 0], np.eye(3), [100.0, 50, 0], np.zeros((2, 3, 3)),
                      np.zeros((2, 3)))
    null = np.zeros((N_RIG, 1))
    null[7, 0] = 1.0
    got = _pose_sigmas(base, np.eye(N_RIG) * 1e-4, np.radians([-10.0, 0, 10]), null)
    assert np.all(np.isinf(got["centre_mm"]))
    assert np.all(np.isfinite(got["z_axis_deg"])) and np.all(np.isfinite(got["x_axis_deg"]))
    assert np.all(np.isfinite(got["axis_point_mm"]))  # the axis does not move with the centre
