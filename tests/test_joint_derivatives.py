"""Analytic derivatives of the joint fit (lidarcal.joint.problem.pose_jacobian) against
central differences, over random rigs and parameter steps (property test)."""

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
