"""Turntable: the LiDAR pose as a function of the turntable angle psi (section 2, eqs. 15-27).

Two pose functions of psi, both fitted to the single-shot samples of section 1:

* :class:`PaperModel` (:func:`fit_paper`): the paper's chain. Axis direction from
  the plane of the z-axis tips (eqs. 15-17), axis point from a circle through the
  projected centres (eq. 18), then the centre, the z axis and the x axis as
  separate functions of psi (eqs. 19-27).
* :class:`RigidModel` (:func:`fit_rigid`): the rigid rotation model,
  ``pose(psi) = Rot(axis, psi - psi_ref) o pose_ref``, fitted to all samples at
  once by robust least squares using the reported angles. On short arcs the
  paper's free circle fit is ill-conditioned (radius and centre trade off); the
  known angles make the rigid fit well conditioned.

Convention: increasing psi rotates the LiDAR right-handedly about
``Axis.direction``; ``Axis.point`` is the foot of the perpendicular from the
camera's optical centre to the axis line. mm and degrees at the edges, radians
inside.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.special import chdtri

if TYPE_CHECKING:
    import pandas as pd

from .evaluate import axis_direction_error_deg, pose_error
from .geometry import (
    Line3D,
    Pose,
    cross3,
    fit_circle_3d,
    fit_plane,
    plane_basis,
    rotate_perpendicular,
    rotvec_matrix,
    skew,
    so3_left_jacobian,
    unit,
)

MIN_POSITIONS = 3
RIGID_FORMULA = ("R(psi) = Rot(direction, psi - psi_ref_deg) @ pose_ref.R; T(psi) = point_mm + "
                 "Rot(direction, psi - psi_ref_deg) @ (pose_ref.T_mm - point_mm); Rot is "
                 "right-handed about axis.direction")
# median of the chi distribution with 3 and 2 degrees of freedom: converts the median
# length of an isotropic Gaussian residual vector into its per-component sigma
_CHI3_MEDIAN = float(np.sqrt(chdtri(3, 0.5)))
_CHI2_MEDIAN = float(np.sqrt(chdtri(2, 0.5)))
_CHI7_999 = float(np.sqrt(chdtri(7, 0.001)))  # 99.9 % point of chi(7): a sample's outlier test


# ---------------------------------------------------------------------------- axis


@dataclass(frozen=True, eq=False)
class Axis:
    """Turntable axis ``X = point + xi * direction`` in the camera frame (eq. 18), mm.

    Convention: increasing psi rotates right-handedly about ``direction`` (unit);
    ``point`` is the foot of the perpendicular from the camera origin (canonical).
    Build with :meth:`from_point_direction` to get the canonical point.
    """

    point: np.ndarray  # shape (3,), mm
    direction: np.ndarray  # shape (3,), unit

    @staticmethod
    def from_point_direction(point: np.ndarray, direction: np.ndarray) -> Axis:
        k = unit(np.asarray(direction, dtype=float))
        p = np.asarray(point, dtype=float)
        return Axis(p - (p @ k) * k, k)

    @property
    def line(self) -> Line3D:
        return Line3D(self.point, self.direction)

    def rotation(self, angle_rad: float | np.ndarray) -> Rotation:
        """Right-handed rotation(s) about ``direction`` by ``angle_rad``."""
        return Rotation.from_rotvec(np.multiply.outer(np.asarray(angle_rad, dtype=float),
                                                      self.direction))

    def to_dict(self) -> dict:
        return {"point_mm": self.point.tolist(), "direction": self.direction.tolist()}

    @staticmethod
    def from_dict(d: dict) -> Axis:
        return Axis(np.asarray(d["point_mm"], dtype=float), np.asarray(d["direction"], dtype=float))


def axis_distance_mm(est: Axis, truth: Axis, near: np.ndarray) -> float:
    """Distance between two axis lines near a point (e.g. the LiDAR centre), mm.

    The larger of: the distance from the true line's foot of ``near`` to the
    estimated line, and the other way round. Evaluation only.
    """
    near = np.asarray(near, dtype=float)
    a = float(est.line.distance(truth.line.foot(near))[0])
    b = float(truth.line.distance(est.line.foot(near))[0])
    return max(a, b)


@runtime_checkable
class PoseFunction(Protocol):
    """A LiDAR pose as a function of the turntable angle (what calibration.json stores)."""

    axis: Axis

    def pose(self, psi_deg: float | np.ndarray) -> Pose | list[Pose]: ...

    def pose_arrays(self, psi_deg: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def to_dict(self) -> dict: ...


def _check_inputs(psi_deg, samples: Sequence[Pose]) -> np.ndarray:
    psi = np.asarray(psi_deg, dtype=float).ravel()
    if len(psi) != len(samples):
        raise ValueError(f"Expected one psi per sample, got {len(psi)} angles and {len(samples)} poses")
    if len(psi) < MIN_POSITIONS:
        raise ValueError(f"The turntable fit needs at least {MIN_POSITIONS} positions, got {len(psi)}")
    if not np.all(np.isfinite(psi)):
        raise ValueError("psi_deg holds NaN or infinite angles")
    if len(np.unique(psi)) != len(psi):
        raise ValueError("psi_deg holds duplicate angles; turntable angles must be distinct")
    return psi


@dataclass(frozen=True)
class AngleScale:
    """How far the single-shot samples turn against the reported angles (:func:`angle_scale`)."""

    turned_deg: float     # median rotation angle between the samples of the compared pairs
    reported_deg: float   # median reported angle difference of those pairs (wrapped to 0..180)
    pairs: int

    @property
    def ratio(self) -> float:
        return self.turned_deg / self.reported_deg if self.reported_deg > 0 else np.inf


def unwrap_angles_deg(psi_deg) -> np.ndarray:
    """Turntable angles as one contiguous sweep (deg): a controller that wraps at 360 deg
    reports ..., 359.31, 0.06, ... for positions 0.75 deg apart. The angles are placed on the
    circle and cut at their largest gap; when that gives a shorter span than the reported one,
    each angle becomes ``start + (psi - start) mod 360`` (``start``: the first angle after the
    gap), which the pose function reads the same (a rotation by psi and by psi + 360 deg is one
    rotation, eq. 15). Otherwise the angles are returned unchanged (the same array values)."""
    psi = np.asarray(psi_deg, dtype=float).ravel()
    if len(psi) < 2:
        return psi
    m = np.sort(np.mod(psi, 360.0))
    gaps = np.diff(np.concatenate([m, [m[0] + 360.0]]))
    g = int(np.argmax(gaps))
    span = 360.0 - float(gaps[g])
    if span >= float(np.ptp(psi)) - 1e-6:
        return psi
    start = float(m[(g + 1) % len(m)])
    return start + np.mod(psi - start, 360.0)


def angle_scale(psi_deg, samples: Sequence[Pose]) -> AngleScale:
    """Do the reported angles measure the turn the samples show? (the premise of eq. 15).

    A rotation about a fixed axis ``k`` by ``dpsi`` turns every pose by exactly
    ``dpsi`` about ``k``: ``R_j R_i^T = Rot(k, psi_j - psi_i)`` whatever the
    axis. Over the pairs at least half the span apart, ``k`` is the median of
    the pairs' rotation vectors over their angle differences, the turn of a
    pair the component of its rotation vector along ``k`` (the samples' noise
    across ``k`` then does not lengthen it), and the medians of the turns and
    of ``|psi_i - psi_j|`` (wrapped to 0..180 deg) are compared; angles in
    radians, in encoder counts or through a gear ratio show as a ratio far
    from 1. Robust to a minority of wrong samples (medians).
    """
    psi = np.asarray(psi_deg, dtype=float).ravel()
    R = np.stack([np.asarray(q.R, float) for q in samples])
    i, j = np.triu_indices(len(psi), 1)
    dpsi = np.abs(psi[j] - psi[i])
    far = dpsi >= 0.5 * dpsi.max()
    i, j, dpsi = i[far], j[far], dpsi[far]
    rv = Rotation.from_matrix(R[j] @ np.transpose(R[i], (0, 2, 1))).as_rotvec()  # rad
    k = unit(np.median(rv / (psi[j] - psi[i])[:, None], axis=0))
    turned = np.degrees(np.abs(rv @ k))
    wrapped = np.mod(dpsi, 360.0)
    wrapped = np.minimum(wrapped, 360.0 - wrapped)
    return AngleScale(float(np.median(turned)), float(np.median(wrapped)), len(i))


def _poses_out(psi_deg, R: np.ndarray, T: np.ndarray) -> Pose | list[Pose]:
    if np.ndim(psi_deg) == 0:
        return Pose(R[0], T[0])
    return [Pose(r, t) for r, t in zip(R, T)]


# ------------------------------------------------------------------ the paper's chain


def _signed_angles(v: np.ndarray, ref: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Signed angles (rad) from ``ref`` to each row of ``v`` about ``k`` (right-handed)."""
    return np.arctan2(np.cross(ref, v) @ k, v @ ref)


def _rotation_sense(k: np.ndarray, psi_rad: np.ndarray, groups: list[np.ndarray]) -> float:
    """+1 if psi increasing turns the samples right-handedly about ``k``, else -1.

    Every group holds vectors (N, 3) from a circle's centre to its samples. In each
    group the signed angles around ``k`` are regressed on psi; the slopes' t
    statistics are summed, so the best-determined group decides (the paper's p_L
    and p_z use only samples 1 and N, which fails on short, noisy arcs).
    """
    t_sum = 0.0
    x = psi_rad - psi_rad.mean()
    for v in groups:
        ref = unit(v.mean(0)) if np.linalg.norm(v.mean(0)) > 0 else unit(v[0])
        ang = np.unwrap(_signed_angles(v, ref, k))
        slope = (x @ (ang - ang.mean())) / (x @ x)
        res = ang - ang.mean() - slope * x
        dof = max(len(x) - 2, 1)
        se = np.sqrt(max(res @ res / dof, 1e-30) / (x @ x))
        t_sum += slope / se
    return 1.0 if t_sum >= 0 else -1.0


def _solve_x_axis(k: np.ndarray, n_z: np.ndarray, d_X: float, branch: float | np.ndarray) -> np.ndarray:
    """Eq. (25): unit n_x with ``k . n_x = d_X`` and ``n_z . n_x = 0``; ``branch`` picks the root.

    With ``e2 = unit(k - (k.n_z) n_z)``, ``e3 = n_z x e2``: ``n_x = cos t e2 + sin t e3``,
    ``cos t = d_X / |k - (k.n_z) n_z|``, ``sin t = branch * sqrt(1 - cos^2 t)``.
    ``cos t`` is clipped to [-1, 1] (noise can push it out).
    """
    n_z = np.atleast_2d(n_z)
    c = n_z @ k
    w = k - c[:, None] * n_z
    s = np.linalg.norm(w, axis=1)
    e2 = w / s[:, None]
    e3 = np.cross(n_z, e2)
    cos_t = np.clip(d_X / s, -1.0, 1.0)
    sin_t = np.asarray(branch, dtype=float) * np.sqrt(1.0 - cos_t**2)
    return cos_t[:, None] * e2 + np.atleast_1d(sin_t)[:, None] * e3


@dataclass(frozen=True, eq=False)
class PaperModel:
    """The paper's pose function of psi, section 2 (eqs. 15-27).

    Centre, eqs. (19)-(21): ``O_L(psi) = G_O + Rod(v_O, k, rad(psi - psi_1) - dpsi_L)``.
    z axis, eqs. (22)-(23): ``n_z(psi) = G_Z + Rod(v_Z, k, rad(psi - psi_1) - dpsi_Z)``
    (``G_Z = d_Z k``, ``|v_Z| = sqrt(1 - d_Z^2)``). x axis, eq. (25): the root of
    ``k . n_x = d_X``, ``n_z . n_x = 0``, ``|n_x| = 1`` given by ``x_branch``. R and T,
    eqs. (26)-(27). ``Rod`` is Rodrigues' formula for vectors perpendicular to ``k``
    (:func:`lidarcal.geometry.rotate_perpendicular`); ``k = axis.direction`` is
    oriented so that psi increasing turns right-handedly (the paper's p_L = p_z).
    """

    axis: Axis
    psi1_deg: float  # reference angle: the first (smallest) psi, eq. (19)
    centre_G: np.ndarray  # G_O, circle centre on Pi_O, mm (eq. 18)
    centre_v1: np.ndarray  # G_O -> O_L^(S3)(psi_1), length r_O, perpendicular to k (eq. 20)
    centre_dpsi: float  # Delta psi_L, rad (eq. 19)
    z_G: np.ndarray  # G_Z = d_Z k (eq. 22)
    z_v1: np.ndarray  # G_Z -> V_Z^(S3)(psi_1), length sqrt(1 - d_Z^2) (eq. 23)
    z_dpsi: float  # Delta psi_Z, rad (eq. 22)
    d_X: float  # Pi_X: k . n_x = d_X (eq. 17)
    x_branch: float  # +1 or -1: the root of eq. (25) kept
    circle: str = "geometric"
    info: dict = field(default_factory=dict, repr=False)

    def pose(self, psi_deg: float | np.ndarray) -> Pose | list[Pose]:
        """LiDAR pose(s) at turntable angle(s) ``psi_deg``, eqs. (20)-(27)."""
        return _poses_out(psi_deg, *self.pose_arrays(psi_deg))

    def pose_arrays(self, psi_deg: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eqs. (20)-(27) at every angle of ``psi_deg`` in one pass: ``R`` (N, 3, 3), ``T`` (N, 3) mm."""
        k = self.axis.direction
        d = np.radians(np.atleast_1d(np.asarray(psi_deg, dtype=float)) - self.psi1_deg)
        O_L = self.centre_G + rotate_perpendicular(self.centre_v1, k, d - self.centre_dpsi)  # (20)-(21)
        n_z = self.z_G + rotate_perpendicular(self.z_v1, k, d - self.z_dpsi)  # (23)
        n_z = unit(n_z)  # unit by construction; removes rounding
        n_x = _solve_x_axis(k, n_z, self.d_X, self.x_branch)  # (25)
        R = np.stack([n_x, np.cross(n_z, n_x), n_z], axis=2)  # (26)
        return R, O_L  # (27)

    def to_dict(self) -> dict:
        return {
            "type": "paper",
            "axis": self.axis.to_dict(),
            "circle": self.circle,
            "psi1_deg": float(self.psi1_deg),
            "centre_G_mm": self.centre_G.tolist(),
            "centre_v1_mm": self.centre_v1.tolist(),
            "centre_dpsi_rad": float(self.centre_dpsi),
            "z_G": self.z_G.tolist(),
            "z_v1": self.z_v1.tolist(),
            "z_dpsi_rad": float(self.z_dpsi),
            "d_X": float(self.d_X),
            "x_branch": float(self.x_branch),
            "r_O_mm": float(np.linalg.norm(self.centre_v1)),
            "d_Z": float(self.z_G @ self.axis.direction),
        }

    @staticmethod
    def from_dict(d: dict) -> PaperModel:
        f = lambda key: np.asarray(d[key], dtype=float)
        return PaperModel(Axis.from_dict(d["axis"]), float(d["psi1_deg"]), f("centre_G_mm"),
                          f("centre_v1_mm"), float(d["centre_dpsi_rad"]), f("z_G"), f("z_v1"),
                          float(d["z_dpsi_rad"]), float(d["d_X"]), float(d["x_branch"]),
                          str(d.get("circle", "geometric")))


def _circle_function(points: np.ndarray, G: np.ndarray, radius: float, k: np.ndarray,
                     psi_rad: np.ndarray) -> tuple[np.ndarray, float]:
    """Eqs. (19)-(20) / (22)-(23): start vector on the circle and the angular offset.

    ``points`` are sorted by psi. Returns ``(v1, dpsi)``: ``v1`` from ``G`` to the
    first sample's projection pushed onto the circle (O^(S3)), ``dpsi`` =
    mean(psi_i - psi_1 - psi_i^(S2)) with signed angles about ``k`` (eq. 19).
    """
    v = points - G
    v = v - np.outer(v @ k, k)  # projection on the circle's plane (S2)
    ang = np.unwrap(_signed_angles(v, v[0], k))
    dpsi = float(np.mean(psi_rad - psi_rad[0] - ang))
    return radius * unit(v[0]), dpsi


def fit_paper(psi_deg, samples: Sequence[Pose], circle: str = "geometric") -> PaperModel:
    """The paper's pose function of psi from single-shot samples, eqs. (15)-(27).

    Parameters
    ----------
    psi_deg : array-like, shape (N,)
        Reported turntable angles (any order; sorted here, as the paper assumes).
    samples : list of Pose, length N
        Single-shot LiDAR poses (section 1).
    circle : {"geometric", "algebraic"}
        Circle fit of eq. (18): geometric (orthogonal distances) or Kasa's algebraic fit.

    Notes
    -----
    The axis direction n_w is the unit normal of the TLS plane through the z-axis
    tips (eq. 16). Its sign (the paper's p_L, p_z from samples 1 and N) is taken
    instead from a regression of the signed angles of all samples on psi
    (:func:`_rotation_sense`), so that psi increasing is right-handed about it;
    ``info["paper_sense_agrees"]`` says whether samples 1 and N gave the same.
    """
    if circle not in ("geometric", "algebraic"):
        raise ValueError(f"circle must be 'geometric' or 'algebraic', got {circle!r}")
    psi = _check_inputs(psi_deg, samples)
    order = np.argsort(psi)
    psi = psi[order]
    P = [samples[i] for i in order]
    O = np.array([p.T for p in P], dtype=float)
    Z = np.array([p.z_axis for p in P], dtype=float)
    X = np.array([p.x_axis for p in P], dtype=float)
    psi_rad = np.radians(psi)

    # (16): Pi_Z through the z tips, unit normal by total least squares
    n_w = fit_plane(Z).normal
    # (17) and (15): d_L, d_X; (18): circle through the centres projected on Pi_O
    circ = fit_circle_3d(O, normal=n_w, algebraic=(circle == "algebraic"))
    G_O = circ.centre
    G_Z = (Z @ n_w).mean() * n_w
    G_X = (X @ n_w).mean() * n_w
    # rotation sense: psi increasing must be right-handed about k
    groups = [Z - G_Z, O - G_O, X - G_X]
    sense = _rotation_sense(n_w, psi_rad, groups)
    k = sense * n_w
    # the paper's p_L from samples 1 and N, for comparison
    vO = (O - G_O) - np.outer((O - G_O) @ k, k)
    p_L = np.cross(vO[0], vO[-1]) @ k
    d_Z = float((Z @ k).mean())
    d_X = float((X @ k).mean())
    r_Z = np.sqrt(max(1.0 - d_Z**2, 0.0))

    centre_v1, centre_dpsi = _circle_function(O, G_O, circ.radius, k, psi_rad)  # (19)-(20)
    z_v1, z_dpsi = _circle_function(Z, G_Z, r_Z, k, psi_rad)  # (22)-(23)

    # (25): two roots; keep the one with the larger summed cosine similarity
    model = PaperModel(Axis.from_point_direction(G_O, k), float(psi[0]), G_O, centre_v1,
                       centre_dpsi, d_Z * k, z_v1, z_dpsi, d_X, 1.0, circle)
    nz_fit = np.array([p.z_axis for p in model.pose(psi)])
    S = [float(np.sum(_solve_x_axis(k, nz_fit, d_X, b) * X)) for b in (1.0, -1.0)]
    info = {"r_O_mm": float(circ.radius), "d_L_mm": float((O @ k).mean()), "d_Z": d_Z,
            "cosine_sums": S, "paper_sense_agrees": bool(p_L > 0)}
    return replace(model, x_branch=1.0 if S[0] >= S[1] else -1.0, info=info)


# -------------------------------------------------------------------- the rigid model


@dataclass(frozen=True, eq=False)
class RigidModel:
    """Rigid rotation about the turntable axis: ``pose(psi) = Rot(axis, psi - psi_ref) o pose_ref``.

    ``R(psi) = Rot_k(t) R_ref``, ``T(psi) = a + Rot_k(t) (T_ref - a)`` with
    ``t = rad(psi - psi_ref)``, ``k = axis.direction``, ``a = axis.point``. The
    reported angles are taken as known; a constant angle offset is absorbed by
    ``pose_ref``. ``info`` holds the fit's noise scales, per-sample residuals and
    standard errors (not serialised beyond the noise scales).
    """

    axis: Axis
    psi_ref_deg: float
    R_ref: np.ndarray  # (3, 3)
    T_ref: np.ndarray  # (3,), mm
    info: dict = field(default_factory=dict, repr=False)

    @property
    def pose_ref(self) -> Pose:
        return Pose(self.R_ref, self.T_ref)

    def pose(self, psi_deg: float | np.ndarray) -> Pose | list[Pose]:
        """LiDAR pose(s) at turntable angle(s) ``psi_deg``."""
        return _poses_out(psi_deg, *self.pose_arrays(psi_deg))

    def pose_arrays(self, psi_deg: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pose at every angle of ``psi_deg`` in one pass: ``R`` (N, 3, 3), ``T`` (N, 3) mm."""
        t = np.radians(np.atleast_1d(np.asarray(psi_deg, dtype=float)) - self.psi_ref_deg)
        rot = self.axis.rotation(t)
        R = (rot * Rotation.from_matrix(self.R_ref)).as_matrix()
        R = R.reshape(-1, 3, 3)
        T = self.axis.point + rot.apply(self.T_ref - self.axis.point).reshape(-1, 3)
        return R, T

    def to_dict(self) -> dict:
        out = {"type": "rigid", "formula": RIGID_FORMULA, "axis": self.axis.to_dict(),
               "psi_ref_deg": float(self.psi_ref_deg),
               "pose_ref": {"R": self.R_ref.tolist(), "T_mm": self.T_ref.tolist()}}
        if "sigma" in self.info:
            out["noise"] = {k: float(v) for k, v in self.info["sigma"].items()}
        return out

    @staticmethod
    def from_dict(d: dict) -> RigidModel:
        return RigidModel(Axis.from_dict(d["axis"]), float(d["psi_ref_deg"]),
                          np.asarray(d["pose_ref"]["R"], dtype=float),
                          np.asarray(d["pose_ref"]["T_mm"], dtype=float))


def _robust_mean_rotation(R: np.ndarray) -> np.ndarray:
    """Chordal mean of rotations (N, 3, 3), then moved by the median residual rotation vector."""
    mean = Rotation.from_matrix(R).mean()
    d = (mean.inv() * Rotation.from_matrix(R)).as_rotvec()
    return (mean * Rotation.from_rotvec(np.median(d, axis=0))).as_matrix()


def _axis_direction_closed_form(psi_rad: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Axis direction from relative rotations ``R_j R_i^T`` (rotation vectors / angle steps).

    Uses the pairs at least half the angle span apart; the component-wise median
    of ``rotvec(R_j R_i^T) / (psi_j - psi_i)`` is robust to a few bad samples.
    Its sign makes psi increasing right-handed.
    """
    i, j = np.triu_indices(len(psi_rad), 1)
    dpsi = psi_rad[j] - psi_rad[i]
    keep = np.abs(dpsi) >= 0.5 * np.ptp(psi_rad)
    i, j, dpsi = i[keep], j[keep], dpsi[keep]
    rel = Rotation.from_matrix(R[j] @ np.transpose(R[i], (0, 2, 1)))
    return unit(np.median(rel.as_rotvec() / dpsi[:, None], axis=0))


def _axis_point_closed_form(psi_rad: np.ndarray, T: np.ndarray, k: np.ndarray,
                            w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis point (foot from the origin) and reference centre, linear in both.

    ``T_i = (I - Q_i) a + Q_i T_ref`` with ``Q_i = Rot_k(psi_i)``, ``a = B^T e``
    (``B`` spans the plane perpendicular to ``k``): 3N equations, 5 unknowns, solved
    by weighted least squares with two Huber reweighting passes.
    """
    B = plane_basis(k)
    Q = Rotation.from_rotvec(np.outer(psi_rad, k)).as_matrix()
    A = np.concatenate([(np.eye(3) - Q) @ B.T, Q], axis=2).reshape(-1, 5)
    b = T.reshape(-1)
    ww = w.copy()
    for _ in range(3):
        sw = np.repeat(np.sqrt(ww), 3)
        x, *_ = np.linalg.lstsq(A * sw[:, None], b * sw, rcond=None)
        r = np.linalg.norm((A @ x - b).reshape(-1, 3), axis=1)
        s = max(np.median(r) / _CHI3_MEDIAN, 1e-12 * max(np.abs(T).max(), 1.0))
        ww = w * np.minimum(1.0, 2.0 * s / np.maximum(r, 1e-300))  # Huber weights at 2 sigma
    return B.T @ x[:2], x[2:]


def _rigid_init(psi_rad: np.ndarray, R: np.ndarray, T: np.ndarray, w: np.ndarray,
                psi_ref_rad: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Closed-form start for :func:`fit_rigid`: (k, a, R_ref, T_ref)."""
    k = _axis_direction_closed_form(psi_rad, R)
    t = psi_rad - psi_ref_rad
    back = Rotation.from_rotvec(np.outer(-t, k)).as_matrix()
    R_ref = _robust_mean_rotation(back @ R)
    a, T_ref = _axis_point_closed_form(t, T, k, w)
    return k, a, R_ref, T_ref


def _rigid_predict(x: np.ndarray, base: tuple, t: np.ndarray):
    """Model centres, z and x axes at angles ``t`` (rad from psi_ref) for parameters ``x``.

    ``x = [dk (2), da (2), omega (3), dT (3)]`` around ``base = (k0, B0, a0, R0, T0)``.
    """
    k0, B0, a0, R0, T0 = base
    k = unit(k0 + x[:2] @ B0)
    a = a0 + x[2:4] @ B0
    R_ref = rotvec_matrix(x[4:7]) @ R0
    T_ref = T0 + x[7:10]
    c, s = np.cos(t)[:, None], np.sin(t)[:, None]
    turn = lambda v: _rodrigues(v, k, c, s)
    return a + turn(T_ref - a), turn(R_ref[:, 2]), turn(R_ref[:, 0]), (k, a, R_ref, T_ref)


def _rigid_jacobian(x: np.ndarray, base: tuple, t: np.ndarray) -> np.ndarray:
    """d (centre, z axis, x axis) / d x of :func:`_rigid_predict`, (N, 9, 10).

    With ``Q_i = Rot_k(t_i)`` (Rodrigues): ``d(Q v)/dk = -sin t [v]_x + (1 - cos t)((k.v) I +
    k v^T)``, through ``k = unit(k0 + dk B0)`` (``dk/d dk = (I - k k^T) B0^T / |k0 + dk B0|``);
    centre ``a + Q (T_ref - a)``: ``I - Q`` on the axis point, ``Q`` on the centre; the axes
    ``Q R_ref e_j`` with ``R_ref = Exp(omega) R0``: ``d(Exp(omega) v)/d omega = -[Exp(omega)
    v]_x J_l(omega)`` (SO(3)'s left Jacobian, ``I`` at ``omega = 0``).
    """
    k0, B0, a0, R0, T0 = base
    m = k0 + x[:2] @ B0
    norm_m = float(np.sqrt(m @ m))
    k = m / norm_m
    a = a0 + x[2:4] @ B0
    w = x[4:7]
    R_ref = rotvec_matrix(w) @ R0
    T_ref = T0 + x[7:10]
    c, s = np.cos(t)[:, None, None], np.sin(t)[:, None, None]
    kkT = np.outer(k, k)
    Q = c * np.eye(3) + s * skew(k) + (1.0 - c) * kkT  # (N, 3, 3)
    dk = (np.eye(3) - kkT) @ B0.T / norm_m  # (3, 2)
    J_l = so3_left_jacobian(w)

    def d_turn_dk(v: np.ndarray) -> np.ndarray:  # (N, 3, 2)
        D = -s * skew(v) + (1.0 - c) * ((k @ v) * np.eye(3) + np.outer(k, v))
        return D @ dk

    J = np.zeros((len(t), 9, 10))
    J[:, 0:3, 0:2] = d_turn_dk(T_ref - a)
    J[:, 0:3, 2:4] = (np.eye(3) - Q) @ B0.T
    J[:, 0:3, 7:10] = Q
    for row, col in ((3, 2), (6, 0)):
        v = R_ref[:, col]
        J[:, row:row + 3, 0:2] = d_turn_dk(v)
        J[:, row:row + 3, 4:7] = Q @ (-skew(v) @ J_l)
    return J


def _rodrigues(v: np.ndarray, k: np.ndarray, cos_t: np.ndarray, sin_t: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: ``v`` (3,) turned about unit ``k`` by every angle, (N, 3).

    ``v cos t + (k x v) sin t + k (k . v)(1 - cos t)``; ``cos_t``, ``sin_t`` are (N, 1).
    """
    return v * cos_t + cross3(k, v) * sin_t + (k * (k @ v)) * (1.0 - cos_t)


def _residual_norms(pred, T, Z, X) -> np.ndarray:
    """Per-sample lengths of centre (mm), z and x (chord ~ rad) differences, shape (N, 3)."""
    return np.column_stack([np.linalg.norm(pred[0] - T, axis=1), np.linalg.norm(pred[1] - Z, axis=1),
                            np.linalg.norm(pred[2] - X, axis=1)])


def _noise_scales(norms: np.ndarray, length_mm: float) -> np.ndarray:
    """Per-component sigma of centre (mm), z and x (rad) residuals from their median lengths.

    Floors keep the weights finite and within ~1e3 of each other when a kind of
    residual is (numerically) zero, e.g. exact rotations: angles convert to mm
    through ``length_mm`` (the rig's size).
    """
    med = np.median(norms, axis=0) / np.array([_CHI3_MEDIAN, _CHI2_MEDIAN, _CHI2_MEDIAN])
    c, ang = med[0], med[1:]
    c_floor = max(1e-3 * length_mm * ang.max(), 1e-10 * length_mm)
    ang_floor = max(1e-3 * c / length_mm, 1e-3 * ang.max(), 1e-12)
    return np.array([max(c, c_floor), *np.maximum(ang, ang_floor)])


def fit_rigid(psi_deg, samples: Sequence[Pose], init: PoseFunction | None = None,
              weights: np.ndarray | None = None, loss: str = "soft_l1",
              f_scale: float = 2.0, psi_ref_deg: float | None = None) -> RigidModel:
    """Rigid rotation model fitted to all samples by robust least squares (beyond the paper).

    Parameters
    ----------
    psi_deg : array-like, shape (N,)
        Reported turntable angles (taken as known; an offset is absorbed by ``pose_ref``).
    samples : list of Pose, length N
        Single-shot LiDAR poses.
    init : PoseFunction, optional
        Starting point (its axis and its pose at ``psi_ref``). Default: closed form
        (axis direction from relative rotations, axis point and centre by linear
        least squares, reference rotation by a robust mean).
    weights : array-like, shape (N,), optional
        Per-sample weights (0 drops a sample).
    loss : str
        ``scipy.optimize.least_squares`` loss; residuals are in units of the noise
        sigma, so ``f_scale`` is in sigmas.
    psi_ref_deg : float, optional
        Reference angle of ``pose_ref``; default the mean psi (decorrelates it from the axis).

    Notes
    -----
    Residuals: centre differences (mm) / sigma_c, z-axis and x-axis differences
    (unit-vector chords, ~rad) / sigma_z, sigma_x. The sigmas are estimated from the
    data (median residual lengths after the initial fit, then after a first robust
    fit), never constants. 10 parameters: axis direction (2), axis point (2),
    reference rotation (3) and centre (3). ``info`` holds ``sigma`` (centre_mm,
    z_axis_deg, x_axis_deg), ``residuals`` (Table 1 against the samples as a dict of
    columns, :func:`table1_columns`, with an ``outlier`` column: normalised residual beyond the chi(7) 99.9 % point),
    ``std`` (standard errors from the Jacobian) and the optimiser's ``cost``/``nfev``.
    """
    psi = _check_inputs(psi_deg, samples)
    w = np.ones(len(psi)) if weights is None else np.asarray(weights, dtype=float).ravel()
    if w.shape != psi.shape or np.any(w < 0) or not np.any(w > 0):
        raise ValueError("weights must be N non-negative numbers, not all zero")
    if np.ptp(psi) <= 0:
        raise ValueError("psi_deg spans no angle")
    R = np.array([p.R for p in samples], dtype=float)
    T = np.array([p.T for p in samples], dtype=float)
    Z, X = R[:, :, 2], R[:, :, 0]
    psi_ref = float(np.average(psi, weights=w)) if psi_ref_deg is None else float(psi_ref_deg)
    t = np.radians(psi - psi_ref)

    bases = [_rigid_init(np.radians(psi), R, T, w, np.radians(psi_ref))]
    if init is not None:
        p0 = init.pose(psi_ref)
        bases.append((unit(np.asarray(init.axis.direction, dtype=float)),
                      np.asarray(init.axis.point, dtype=float),
                      np.asarray(p0.R, dtype=float), np.asarray(p0.T, dtype=float)))
    bases = [(k0, plane_basis(k0), a0, R0, T0) for k0, a0, R0, T0 in bases]
    x0 = np.zeros(10)
    length_mm = max(float(np.abs(T).max()), 1.0)
    sw = np.sqrt(w)

    def residuals(x: np.ndarray, base: tuple, sig: np.ndarray) -> np.ndarray:
        c, z, xa, _ = _rigid_predict(x, base, t)
        r = np.concatenate([(c - T) / sig[0], (z - Z) / sig[1], (xa - X) / sig[2]], axis=1)
        return (r * sw[:, None]).ravel()

    def jacobian(x: np.ndarray, base: tuple, sig: np.ndarray) -> np.ndarray:
        J = _rigid_jacobian(x, base, t) / np.repeat(sig, 3)[None, :, None]
        return (J * sw[:, None, None]).reshape(-1, 10)

    def solve(x: np.ndarray, base: tuple, sig: np.ndarray):
        return least_squares(residuals, x, jac=jacobian, args=(base, sig), loss=loss, f_scale=f_scale,
                             x_scale="jac", method="trf", xtol=1e-12, ftol=1e-12, gtol=1e-12)

    # noise scales from the closed-form start; every start (closed form, ``init``) is
    # refined with them and the lowest robust cost wins, so a poor ``init`` cannot hurt
    sig = _noise_scales(_residual_norms(_rigid_predict(x0, bases[0], t), T, Z, X)[w > 0], length_mm)
    sols = [solve(x0, b, sig) for b in bases]
    best = int(np.argmin([s.cost for s in sols]))
    base, sol = bases[best], sols[best]
    for _ in range(2):  # re-estimate the noise scales from the fit's residuals, refit
        sig = _noise_scales(_residual_norms(_rigid_predict(sol.x, base, t), T, Z, X)[w > 0], length_mm)
        sol = solve(sol.x, base, sig)
    pred = _rigid_predict(sol.x, base, t)
    k, a, R_ref, T_ref = pred[3]
    axis = Axis.from_point_direction(a, k)

    # standard errors (residuals are in sigma units): cov ~ (J^T J)^-1
    _, sv, vt = np.linalg.svd(sol.jac, full_matrices=False)
    inv = np.where(sv > sv[0] * 1e-12, 1.0 / np.maximum(sv, 1e-300) ** 2, np.inf)
    std = np.sqrt((vt.T**2) @ inv)  # inf for an undetermined parameter
    model = RigidModel(axis, psi_ref, R_ref, T_ref)
    table = table1_columns(model, psi, samples)
    norm = np.sqrt(((_residual_norms(pred, T, Z, X) / sig) ** 2).sum(1))
    table["outlier"] = norm > _CHI7_999
    info = {
        "sigma": {"centre_mm": float(sig[0]), "z_axis_deg": float(np.degrees(sig[1])),
                  "x_axis_deg": float(np.degrees(sig[2]))},
        "residuals": table,
        "std": {"axis_direction_deg": float(np.degrees(np.hypot(*std[:2]))),
                "axis_point_mm": float(np.hypot(*std[2:4])),
                "ref_rotation_deg": float(np.degrees(np.linalg.norm(std[4:7]))),
                "ref_centre_mm": float(np.linalg.norm(std[7:10]))},
        "cost": float(sol.cost), "nfev": int(sol.nfev),
        "start": "closed_form" if best == 0 else "init",
    }
    return RigidModel(axis, psi_ref, R_ref, T_ref, info)


# ------------------------------------------------------------------ shared helpers


def model_from_dict(d: dict) -> PaperModel | RigidModel:
    """Rebuild a pose function from its ``to_dict()`` (calibration.json ``model``)."""
    kind = d.get("type")
    if kind == "paper":
        return PaperModel.from_dict(d)
    if kind == "rigid":
        return RigidModel.from_dict(d)
    if kind == "joint":
        from .joint import JointModel  # lazy: joint imports this module

        return JointModel.from_dict(d)
    raise ValueError(f"Unknown pose-function type {kind!r}, expected 'paper', 'rigid' or 'joint'")


def table1(model: PoseFunction, psi_deg, samples: Sequence[Pose]) -> pd.DataFrame:
    """Table 1 of the paper: per position, the pose function against the samples.

    Columns ``psi_deg, centre_mm, z_axis_deg, x_axis_deg`` (differences between
    ``model.pose(psi_i)`` and sample i; with a simulator's truth poses instead of
    samples the same table gives true errors). See :func:`table1_summary`.
    """
    import pandas as pd

    return pd.DataFrame(table1_columns(model, psi_deg, samples))


def table1_columns(model: PoseFunction, psi_deg, samples: Sequence[Pose]) -> dict[str, np.ndarray]:
    """:func:`table1` as a dict of columns (numpy arrays; no pandas needed)."""
    psi = np.asarray(psi_deg, dtype=float).ravel()
    R, T = model.pose_arrays(psi)
    R_s = np.array([s.R for s in samples], dtype=float).reshape(-1, 3, 3)
    T_s = np.array([s.T for s in samples], dtype=float).reshape(-1, 3)
    return {"psi_deg": psi, "centre_mm": np.linalg.norm(T - T_s, axis=1),
            "z_axis_deg": _angles_deg(R[:, :, 2], R_s[:, :, 2]),
            "x_axis_deg": _angles_deg(R[:, :, 0], R_s[:, :, 0])}


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise angles (deg) between vectors (N, 3), as :func:`lidarcal.geometry.angle_between_deg`."""
    a, b = unit(a), unit(b)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))


def table1_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Mean and max of each error column, as in the paper's Table 1."""
    cols = ["centre_mm", "z_axis_deg", "x_axis_deg"]
    return table[cols].agg(["mean", "max"])


# ----------------------------------------------------------- simulation / sensitivity


def perturb_pose(pose: Pose, rng: np.random.Generator, centre_mm: float, z_deg: float,
                 x_deg: float) -> Pose:
    """A noisy single-shot sample of ``pose`` (for studies and tests).

    Centre: isotropic Gaussian, ``centre_mm`` per component. Rotation: a small
    rotation in the LiDAR frame with components about its x and y axes
    ~ N(0, ``z_deg``) (they tilt the z axis) and about its z axis ~ N(0, ``x_deg``)
    (turns the x axis within the scan plane).
    """
    omega = np.radians(rng.normal(0.0, 1.0, 3) * np.array([z_deg, z_deg, x_deg]))
    R = pose.R @ Rotation.from_rotvec(omega).as_matrix()
    return Pose(R, pose.T + rng.normal(0.0, centre_mm, 3))


def sensitivity_study(truth: PoseFunction, psi0_deg: float = 0.0,
                      n_positions: Sequence[int] = (3, 5, 10, 20, 87),
                      ranges_deg: Sequence[float] = (1.0, 5.0, 10.0, 21.5),
                      centre_mm: float = 0.5, z_deg: float = 0.02, x_deg: float = 0.05,
                      seeds: Sequence[int] = range(5)) -> pd.DataFrame:
    """True errors of both pose functions versus number of positions and angle span.

    For each (N, span, seed): N angles evenly over ``[psi0, psi0 + span]``, samples =
    ``truth`` perturbed by :func:`perturb_pose`, both models fitted. One row per
    (model in {"samples", "paper", "rigid"}, N, span, seed) with mean true errors
    (centre_mm, z_axis_deg, x_axis_deg) and, for the models, the axis direction
    error (deg) and the axis offset near the LiDAR (mm).
    """
    import pandas as pd

    rows = []
    for n in n_positions:
        for span in ranges_deg:
            psi = psi0_deg + np.linspace(0.0, span, n)
            true = truth.pose(psi)
            near = np.mean([p.T for p in true], axis=0)
            for seed in seeds:
                rng = np.random.default_rng(seed)
                smp = [perturb_pose(p, rng, centre_mm, z_deg, x_deg) for p in true]
                fits = {"samples": None, "paper": fit_paper(psi, smp), "rigid": fit_rigid(psi, smp)}
                for name, m in fits.items():
                    est = smp if m is None else m.pose(psi)
                    err = pd.DataFrame([pose_error(e, t) for e, t in zip(est, true)]).mean()
                    row = {"model": name, "n_positions": n, "span_deg": span, "seed": seed,
                           **err.to_dict()}
                    if m is not None:
                        row["axis_direction_deg"] = axis_direction_error_deg(m.axis.direction,
                                                                             truth.axis.direction)
                        row["axis_offset_mm"] = axis_distance_mm(m.axis, truth.axis, near)
                    rows.append(row)
    return pd.DataFrame(rows)
