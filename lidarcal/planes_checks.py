"""Checks of the one-board refinement (:mod:`lidarcal.planes`) beyond its linearised covariance.

* :func:`other_minima`: a multi-start (the pose turned +-30 deg about each LiDAR axis through the
  board returns' centroid, :func:`lidarcal.degeneracy.restart_poses`): a better valley is
  adopted, an equally good one far away is named undetermined.
* :func:`flat_valley`: a profile of the cost along the weakest direction of the pose's
  information; a valley that bends away from its tangent (boards nearly perpendicular to the
  scan plane) makes the linearised sigma meaningless there.

Both take the refinement as ``refine`` (:func:`lidarcal.planes.refine_extrinsics`) and the views
as :class:`lidarcal.planes.ViewData`. Convention: ``X_cam = R X_lidar + T``, mm, radians inside.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from .degeneracy import (
    is_distinct,
    pose_difference,
    pose_uncertainty,
    restart_poses,
    view_level_chi2,
)

#: A restart's refinement gets this many residual evaluations; one that has not converged by
#: then while its cost is still above the best minimum found is dropped. Measured: restarts
#: that reach a minimum take 15-295 evaluations (real TAPAS views, rendered views); the slow
#: ones crawl along a valley far above the best (rendered seed 5: 1588-2400 evaluations ending
#: at 1.9-11x the best cost), where they cost 90 % of the whole calibration.
RESTART_MAX_NFEV = 400


def other_minima(views: list, ref, lever_mm: float, refine: Callable):
    """Multi-start check of the refinement: restarts from the pose turned by +-30 deg about each
    LiDAR axis (:func:`lidarcal.degeneracy.restart_poses`), each refined, then refined again
    anchored at its own minimum (so the weak prior adds nothing), and scored by the
    refinement's own robust chi-square (twice its cost: the objective it minimises; the
    view-level chi-square can prefer a wrong pose when few views leave few degrees of freedom).
    Returns the best ``(chi2, Refined)``, the other distinct minima found (each more than 3
    sigma of the best from every other; the start's own minimum first when a restart beat it)
    and the noise scale (point-level or view-level, the larger) that sets how much worse an
    equally good minimum may be. A restart that has not converged within
    :data:`RESTART_MAX_NFEV` evaluations while its cost is above the best found is dropped."""
    base = refine(views, ref.R, ref.T)
    chi2v, dof = view_level_chi2(views, ref.R, ref.T)
    scale = max(ref.noise_scale, float(np.sqrt(max(1.0, chi2v / max(dof, 1)))))
    X = np.vstack([np.column_stack([v.points_mm, np.zeros(len(v.beams))]) for v in views])
    centre = (X @ ref.R.T + ref.T).mean(0)
    found = [(2.0 * base.cost, ref)]
    cov = pose_uncertainty(ref.information, scale, lever_mm, float("inf")).covariance
    for Rs, Ts in restart_poses(ref.R, ref.T, centre):
        r = refine(views, Rs, Ts, max_nfev=RESTART_MAX_NFEV)
        if not r.converged:
            if 2.0 * r.cost >= min(f[0] for f in found):
                continue  # still crawling, above the best minimum found (RESTART_MAX_NFEV)
            r = refine(views, r.R, r.T, anchor=(Rs, Ts))  # below it: let it finish
        if any(not is_distinct(pose_difference(r.R, r.T, f.R, f.T), cov) for _, f in found):
            continue
        r = refine(views, r.R, r.T)  # anchored at its own minimum (the weak prior)
        if all(is_distinct(pose_difference(r.R, r.T, f.R, f.T), cov) for _, f in found):
            found.append((2.0 * r.cost, r))
    best = min(found, key=lambda f: f[0])
    others = [f for f in found if f is not best]
    return best, others, scale


#: The profile check (:func:`_flat_valley`): steps of this many sigmas along the weakest direction
#: and the share of the quadratic cost rise below which the valley counts as flat. On the real
#: TAPAS views the rise at 10 sigma is 47-140 % of the prediction for 5-7 views that predict
#: held-out boards, 2.6 % for views 01-04, whose fit lies 147 mm (20 sigma) from the 7-view pose.
FLAT_STEP, FLAT_SHARE = 10.0, 0.1


def direction_words(d6: np.ndarray) -> str:
    """A pose direction ``(omega, dT)`` in words: its larger part's camera-frame axis."""
    w, t = d6[:3], d6[3:]
    kind, v = ("rotation about", w) if np.linalg.norm(w) * 1000 >= np.linalg.norm(t) \
        else ("translation along", t)
    v = v / np.linalg.norm(v)
    return f"{kind} camera-frame [{v[0]:.3f}, {v[1]:.3f}, {v[2]:.3f}]"


def flat_valley(views: list, ref, lever_mm: float, refine: Callable
                ) -> tuple[np.ndarray, float] | None:
    """Profile check of the linearised covariance along its weakest direction ``e``: the pose
    stepped ``+-FLAT_STEP`` sigmas along ``e`` and the other five directions re-fitted
    (:func:`refine_extrinsics` with ``e`` fixed); where the cost rises by less than
    ``FLAT_SHARE`` of the quadratic ``0.5 (k s)^2`` (``s`` the noise scale) the valley bends away
    from its tangent (a near-degenerate geometry) and the sigma along ``e`` means nothing.
    Returns ``(e, rise share)`` then, else None."""
    S = np.diag([lever_mm] * 3 + [1.0] * 3)
    Si = np.linalg.inv(S)
    lam, V = np.linalg.eigh(Si @ ref.information @ Si)
    if lam[0] <= 1e-12 * lam[-1]:
        return None  # already undetermined
    e = Si @ V[:, 0]
    sig = 1.0 / np.sqrt(lam[0])
    base = refine(views, ref.R, ref.T).cost
    k = FLAT_STEP * ref.noise_scale
    worst = np.inf
    for sign in (-1.0, 1.0):
        step = sign * k * sig * e
        R = Rotation.from_rotvec(step[:3]).as_matrix() @ ref.R
        prof = refine(views, R, ref.T + step[3:], fixed=[e / np.linalg.norm(e)],
                                 lever_mm=lever_mm)
        worst = min(worst, (prof.cost - base) / (0.5 * FLAT_STEP ** 2 * ref.noise_scale ** 2))
    return (e / np.linalg.norm(e), float(worst)) if worst < FLAT_SHARE else None
