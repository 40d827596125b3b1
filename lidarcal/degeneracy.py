"""Uncertainty and degeneracy of a one-board calibration (``lidarcal planes``).

The pose's information matrix (rotations scaled by the board points' RMS range, so
both kinds are mm) is eigen-analysed: a direction whose 1-sigma exceeds
:data:`UNDETERMINED_MM` is undetermined and its sigma is reported as ``null``. Some
directions are named from the boards' geometry instead (every board normal
perpendicular to one direction: the translation along it, and with a scan plane
nearly perpendicular to it the scan plane's tilt), since a drifted estimate makes
them look weakly determined. A view-level chi-square (Birge ratio) scales the sigmas
when the views disagree beyond the corner and range noise.

Convention: ``X_cam = R X_lidar + T``; ``omega`` a small rotation vector left-multiplying
``R`` (camera frame, rad), translations mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import Plane, plane_basis

#: A pose direction whose 1-sigma exceeds this (mm; rotations count as the displacement they
#: cause at the board points' RMS range) is reported as undetermined, its sigma as null.
UNDETERMINED_MM = 50.0
#: Boards count as all parallel when the second singular value of their stacked normals is below
#: this share of the first (about 3 deg of spread); as sharing one direction when the third is.
PARALLEL_LIMIT = 0.05
#: an axis whose squared component in the undetermined directions exceeds this has sigma None
#: (a component above ~3 %; numerical mixing of exact degeneracies stays below 1e-5)
AXIS_SHARE = 1e-3
#: Views needed at all (each view constrains two of the six pose parameters).
MIN_VIEWS = 3

@dataclass(frozen=True)
class Undetermined:
    """A pose direction the views do not determine: ``kind`` "rotation" or "translation",
    ``direction_cam`` its unit axis / direction in the camera frame, ``sigma_mm`` its
    1-sigma (inf when exactly undetermined) as the displacement it causes at the board
    points' RMS range."""

    kind: str
    direction_cam: np.ndarray
    sigma_mm: float
    vector6: np.ndarray


@dataclass(frozen=True)
class Uncertainty:
    """1-sigma per camera axis (``None`` where undetermined), the 6x6 covariance of
    ``(omega rad, T mm)`` (pseudo-inverse over the determined directions) and the
    undetermined directions."""

    rotation_deg: list[float | None]
    translation_mm: list[float | None]
    covariance: np.ndarray
    undetermined: list[Undetermined]
    lever_mm: float


def unobservable_directions(normals: np.ndarray, R: np.ndarray, T: np.ndarray,
                            max_tilt_deg: float = 30.0) -> list[np.ndarray]:
    """Pose directions ``(omega, dT)`` (6-vectors) the geometry cannot see when every board normal
    is perpendicular to one direction ``u`` (smallest singular vector, below
    :data:`PARALLEL_LIMIT`): the translation along ``u`` always; and while the scan plane's normal
    is within ``max_tilt_deg`` of ``u`` (every board vertical, scan plane horizontal), the
    rotations about the LiDAR's centre about both axes perpendicular to ``u``,
    ``(a, -a x T)``. To first order these change no residual at the exact degenerate pose but
    become weakly (and wrongly) visible once the estimate has drifted along them, so they are
    named from the geometry, not from the information matrix."""
    _, sv, vt = np.linalg.svd(np.asarray(normals, float))
    if len(sv) < 3 or sv[2] >= PARALLEL_LIMIT * sv[0]:
        return []
    u = vt[2]
    out = [np.concatenate([np.zeros(3), u])]
    if abs(R[:, 2] @ u) >= np.cos(np.radians(max_tilt_deg)):
        a = plane_basis(u)
        out += [np.concatenate([a[k], -np.cross(a[k], T)]) for k in range(2)]
    return out


def pose_uncertainty(information: np.ndarray, noise_scale: float, lever_mm: float,
                     limit_mm: float = UNDETERMINED_MM, unobservable: list[np.ndarray] = ()
                     ) -> Uncertainty:
    """Eigen-analysis of the pose information, rotations scaled by ``lever_mm`` (the board
    points' RMS range) so both kinds are mm: an eigen-direction whose 1-sigma exceeds
    ``limit_mm`` is undetermined; an axis with a share above :data:`AXIS_SHARE` in one has
    sigma None.
    ``unobservable`` directions (from :func:`unobservable_directions`) are removed from the
    information first, so they come out undetermined."""
    S = np.diag([lever_mm] * 3 + [1.0] * 3)
    Si = np.linalg.inv(S)
    info = Si @ information @ Si
    if len(unobservable):  # project the named directions (scaled coordinates) out
        Q, _ = np.linalg.qr(np.array([S @ v for v in unobservable]).T)
        Pm = np.eye(6) - Q @ Q.T
        info = Pm @ info @ Pm
    lam, V = np.linalg.eigh(info)
    top = max(float(lam.max()), 1e-300)
    sig = np.where(lam > 1e-12 * top, noise_scale / np.sqrt(np.maximum(lam, 1e-300)), np.inf)
    bad = sig > limit_mm
    und = []
    for k in np.flatnonzero(bad):
        v = V[:, k]
        rot, tr = v[:3], v[3:]
        kind = "rotation" if np.linalg.norm(rot) >= np.linalg.norm(tr) else "translation"
        axis = rot if kind == "rotation" else tr
        axis = axis / np.linalg.norm(axis)
        if axis[np.argmax(np.abs(axis))] < 0:
            axis = -axis
        und.append(Undetermined(kind, axis, float(sig[k]), v))
    good = ~bad
    cov_y = (V[:, good] * (sig[good] ** 2)) @ V[:, good].T
    cov = Si @ cov_y @ Si  # y = S x  ->  cov_x = S^-1 cov_y S^-1: (omega rad, T mm)
    # an axis is undetermined when it has a real component (above ~3 %, share 1e-3) in an
    # undetermined direction: its sigma would be unbounded, never a confident number
    share = np.sum(V[:, bad] ** 2, axis=1) if bad.any() else np.zeros(6)
    lost = share > AXIS_SHARE
    sd = np.sqrt(np.diag(cov))
    rot = [None if lost[i] else float(np.degrees(sd[i])) for i in range(3)]
    tr = [None if lost[3 + i] else float(sd[3 + i]) for i in range(3)]
    return Uncertainty(rot, tr, cov, und, lever_mm)


def describe_degeneracy(planes: list[Plane], unc: Uncertainty) -> list[str]:
    """Words for the undetermined directions, with the board geometry that explains them."""
    out = []
    if not unc.undetermined:
        return out
    N = np.array([p.normal for p in planes])
    _, s, vt = np.linalg.svd(N)
    why = ""
    if len(planes) < MIN_VIEWS:
        why = f"only {len(planes)} usable view(s) (each view fixes two of the six pose parameters)"
    elif s[1] < 0.05 * s[0]:
        why = ("every board is (nearly) parallel to the others (normals within "
               f"{np.degrees(np.arcsin(min(1.0, s[1] / s[0]))):.1f} deg); tilt the board differently")
    elif s[2] < 0.05 * s[0]:
        u = vt[2] * np.sign(vt[2][np.argmax(np.abs(vt[2]))])
        why = ("every board normal is perpendicular to camera-frame direction "
               f"[{u[0]:.3f}, {u[1]:.3f}, {u[2]:.3f}] (e.g. every board vertical while the scan "
               "plane is horizontal): positions along that direction and the scan plane's tilt "
               "are not observed; tilt the board forwards/backwards in some views")
    parts = []
    for d in unc.undetermined:
        v = d.direction_cam
        sig = "infinite" if not np.isfinite(d.sigma_mm) else f"{d.sigma_mm:.0f} mm"
        what = "translation along" if d.kind == "translation" else "rotation about"
        parts.append(f"{what} camera-frame [{v[0]:.3f}, {v[1]:.3f}, {v[2]:.3f}] (1-sigma {sig})")
    out.append("undetermined pose direction(s): " + "; ".join(parts)
               + (f"; cause: {why}" if why else "") + "; their sigma is null")
    return out


def view_level_chi2(views: list, R: np.ndarray, T: np.ndarray) -> tuple[float, int]:
    """Birge-ratio test at the level of whole views (``lidarcal.planes.ViewData``): each view's residuals to its measured board
    plane are summarised by the line ``r = a + b s`` (``s`` along the board returns); under the
    noise model ``(a, b)`` has the covariance of the board plane (from the corners) plus the
    range noise's share, and ``sum_i [a b] Sigma_i^-1 [a b]^T`` is chi-square with
    ``2 n - 6`` degrees of freedom. Returns ``(chi2, dof)``. Effects the point noise cannot
    average away (a bent board, a range bias on black squares, corner bias) show here, not
    in the per-point residuals."""
    chi2 = 0.0
    for v in views:
        p = v.points_mm
        X = np.column_stack([p, np.zeros(len(p))]) @ R.T + T
        r = v.board.plane.distance(X)
        c = X.mean(0)
        t = X[-1] - X[0]
        t = t / np.linalg.norm(t)
        sk = (X - c) @ t
        A = np.column_stack([np.ones(len(sk)), sk])
        ab, *_ = np.linalg.lstsq(A, r, rcond=None)
        G = np.array([[c @ v.board.basis[:, 0], c @ v.board.basis[:, 1], -1.0],
                      [t @ v.board.basis[:, 0], t @ v.board.basis[:, 1], 0.0]])
        noise = v.sigma_range_mm ** 2 * np.linalg.inv(A.T @ A)
        cov = G @ v.board.cov @ G.T + noise
        chi2 += float(ab @ np.linalg.solve(cov, ab))
    return chi2, 2 * len(views) - 6


#: Restarts of the refinement: the pose turned by +-this angle (deg) about each LiDAR axis through
#: the board returns' centroid (the returns stay near their boards, so the fit can slide into
#: another valley). On the real TAPAS views, subsets whose boards are all within ~20 deg of
#: perpendicular to the scan plane have a second valley ~20 deg and 100-200 mm away.
RESTART_DEG = 30.0
#: A second minimum is as good as the best when its robust chi-square exceeds the best's by
#: less than this many squared noise scales (4 = two sigma of one parameter).
AMBIGUITY_CHI2 = 4.0
#: ... and distinct when it lies more than this many sigmas (Mahalanobis, the best fit's
#: covariance) from the best.
DISTINCT_SIGMA = 3.0


def restart_poses(R: np.ndarray, T: np.ndarray, centre: np.ndarray,
                  angle_deg: float = RESTART_DEG) -> list[tuple[np.ndarray, np.ndarray]]:
    """Start poses for a multi-start refinement: ``X_cam = R p + T`` turned by ``+-angle_deg``
    about each LiDAR axis (columns of ``R``) through ``centre`` (camera frame, mm):
    ``R' = Q R``, ``T' = Q (T - c) + c``."""
    from scipy.spatial.transform import Rotation

    out = []
    for k in range(3):
        for s in (-1.0, 1.0):
            Q = Rotation.from_rotvec(s * np.radians(angle_deg) * R[:, k]).as_matrix()
            out.append((Q @ R, Q @ (T - centre) + centre))
    return out


def pose_difference(Ra: np.ndarray, Ta: np.ndarray, Rb: np.ndarray, Tb: np.ndarray) -> np.ndarray:
    """``(omega, dT)`` (rad, mm) taking pose b to pose a: ``Ra = exp(omega) Rb``, ``Ta = Tb + dT``."""
    from scipy.spatial.transform import Rotation

    return np.concatenate([Rotation.from_matrix(Ra @ Rb.T).as_rotvec(), Ta - Tb])


def is_distinct(diff6: np.ndarray, covariance: np.ndarray, sigmas: float = DISTINCT_SIGMA) -> bool:
    """Whether a pose ``diff6`` away (:func:`pose_difference`) lies outside ``sigmas`` of a fit
    with this 6x6 ``covariance`` (pseudo-inverse: undetermined directions count as covered)."""
    P = np.linalg.pinv(covariance, rcond=1e-12, hermitian=True)
    return bool(np.sqrt(max(float(diff6 @ P @ diff6), 0.0)) > sigmas)


def describe_ambiguity(diff6: np.ndarray, chi2_best: float, chi2_other: float, scale: float,
                       lever_mm: float) -> str:
    """Words for a second minimum (a pose ``diff6`` away, :func:`pose_difference`) that fits the
    views about as well as the best (robust chi-squares, noise scale ``scale``)."""
    w, t = diff6[:3], diff6[3:]
    ang = float(np.degrees(np.linalg.norm(w)))
    ax = w / max(np.linalg.norm(w), 1e-12)
    return (f"a second pose fits the views about as well (robust chi-square {chi2_other:.0f} "
            f"against {chi2_best:.0f}, within {AMBIGUITY_CHI2:.0f} x the noise scale {scale:.1f} "
            f"squared): {ang:.1f} deg about camera-frame "
            f"[{ax[0]:.3f}, {ax[1]:.3f}, {ax[2]:.3f}] and {np.linalg.norm(t):.0f} mm away "
            f"({ang * np.pi / 180 * lever_mm + np.linalg.norm(t):.0f} mm at the boards); the pose "
            "is undetermined along that difference and its sigma is null there; add views with "
            "the board tilted forwards/backwards against the scan plane")
