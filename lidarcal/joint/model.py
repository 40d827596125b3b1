"""The joint fit's result: :class:`JointModel` and its pose uncertainties."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..geometry import Pose
from ..ranging import RangingModel
from ..turntable import RIGID_FORMULA, Axis, RigidModel
from .params import N_RIG, _Base, _rig

if TYPE_CHECKING:
    import pandas as pd


@dataclass(frozen=True, eq=False)
class JointModel:
    """The rigid turntable model from the joint fit, with its covariance.

    ``pose(psi)`` is :meth:`lidarcal.turntable.RigidModel.pose`. ``cov`` (10, 10)
    is the covariance of the minimal parameters around the solution: axis
    direction step (2, in ``plane_basis(axis.direction)``, rad), axis point step
    (2, same basis, mm), reference rotation vector (3, rad, applied on the left
    of ``R_ref``), reference centre (3, mm). ``noise`` holds the estimated noise
    scales, ``warnings`` the weak-setup warnings; ``info`` (not serialised) the
    residuals and optimiser details. ``jitter_deg`` is the estimated turntable
    angle jitter (1-sigma; 0: none detected) and ``angle_corrections`` maps a
    dataset position index to its angle correction and that correction's
    1-sigma (deg): the turntable stood at ``psi + correction`` (:func:`angle_jitter`).
    ``ranging`` (:class:`lidarcal.ranging.RangingModel`): the range offset and
    dark-square extra fitted with the rig (None: ranges taken as exact); ``cov``
    is then marginal over them. Serialised as calibration.json ``ranging``.
    """

    axis: Axis
    psi_ref_deg: float
    R_ref: np.ndarray
    T_ref: np.ndarray
    cov: np.ndarray
    noise: dict = field(default_factory=dict)
    warnings: tuple[str, ...] = ()
    info: dict = field(default_factory=dict, repr=False)
    jitter_deg: float = 0.0
    angle_corrections: dict = field(default_factory=dict)
    ranging: RangingModel | None = None

    @property
    def rigid(self) -> RigidModel:
        return RigidModel(self.axis, self.psi_ref_deg, self.R_ref, self.T_ref)

    @property
    def pose_ref(self) -> Pose:
        return Pose(self.R_ref, self.T_ref)

    def pose(self, psi_deg: float | np.ndarray) -> Pose | list[Pose]:
        """LiDAR pose(s) at turntable angle(s) ``psi_deg`` (the rigid model)."""
        return self.rigid.pose(psi_deg)

    def pose_arrays(self, psi_deg: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`lidarcal.turntable.RigidModel.pose_arrays`: ``R`` (N, 3, 3), ``T`` (N, 3) mm."""
        return self.rigid.pose_arrays(psi_deg)

    def position_psi(self, index: int, psi_deg: float) -> float:
        """The turntable angle of dataset position ``index``: the reported ``psi_deg`` plus
        its estimated jitter correction, if any."""
        return float(psi_deg) + self.angle_corrections.get(int(index), (0.0, 0.0))[0]

    def position_sigma_columns(self, indices, psi_deg) -> dict[str, np.ndarray]:
        """:meth:`sigma_columns` at dataset positions: at their corrected angles, with the
        remaining uncertainty of each angle (its correction's 1-sigma, or ``jitter_deg``
        without one) in place of the jitter."""
        idx = [int(i) for i in indices]
        psi = np.array([self.position_psi(i, p) for i, p in zip(idx, np.atleast_1d(psi_deg))])
        e = np.array([self.angle_corrections.get(i, (0.0, self.jitter_deg))[1] for i in idx])
        return self._with_angle_sigma(self.sigma_columns(psi, jitter=False), psi, e)

    def _with_angle_sigma(self, cols: dict, psi: np.ndarray, e_deg: np.ndarray) -> dict:
        """Add an angle uncertainty ``e_deg`` (per angle) in quadrature: it turns the pose
        about the axis, moving the centre by the angle times its distance from the axis and
        tilting the z and x axes by the angle times the sine of their angle to the axis."""
        e = np.radians(np.broadcast_to(np.asarray(e_deg, float), psi.shape))
        if not np.any(e > 0):
            return cols
        k, a = self.axis.direction, self.axis.point
        R, T = self.pose_arrays(psi)  # every angle at once
        dist = np.linalg.norm(np.cross(T - a, k), axis=1)
        cols["centre_mm"] = np.hypot(cols["centre_mm"], e * dist)
        for name, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
            sin = np.linalg.norm(np.cross(R[:, :, col], k), axis=1)
            cols[name] = np.hypot(cols[name], np.degrees(e * sin))
        return cols

    def _base(self) -> _Base:
        return _Base.make(self.axis.direction, self.axis.point, self.R_ref, self.T_ref,
                          np.zeros((2, 3, 3)), np.zeros((2, 3)))

    def sigma(self, psi_deg: float | np.ndarray) -> dict | pd.DataFrame:
        """1-sigma uncertainties at turntable angle(s) ``psi_deg``.

        ``centre_mm``: RMS length of the centre error, ``sqrt(trace cov(T))``;
        ``z_axis_deg`` / ``x_axis_deg``: RMS angle of the axis error (the
        rotation error's components perpendicular to that axis);
        ``axis_direction_deg``: RMS angle of the axis direction;
        ``axis_point_mm``: RMS perpendicular displacement of the axis line at the
        foot of the LiDAR's reference centre. A scalar psi gives a dict, an
        array a DataFrame (one row per angle). ``inf`` marks a quantity the
        data do not determine.
        """
        import pandas as pd

        cols = self.sigma_columns(psi_deg)
        if np.ndim(psi_deg) == 0:
            return {k: float(v[0]) for k, v in cols.items() if k != "psi_deg"}
        return pd.DataFrame(cols)

    def sigma_columns(self, psi_deg: float | np.ndarray, jitter: bool = True) -> dict[str, np.ndarray]:
        """:meth:`sigma` as a dict of columns (``psi_deg`` first), numpy arrays. With
        ``jitter`` the encoder's estimated jitter (``jitter_deg``) is included: the pose at
        a *reported* angle carries it."""
        psi = np.atleast_1d(np.asarray(psi_deg, dtype=float))
        out = _pose_sigmas(self._base(), self.cov, np.radians(psi - self.psi_ref_deg),
                           self.info.get("null", np.zeros((N_RIG, 0))))
        cols = {"psi_deg": psi, **out}
        return self._with_angle_sigma(cols, psi, self.jitter_deg) if jitter else cols

    def to_dict(self) -> dict:
        return {"type": "joint", "formula": RIGID_FORMULA, "axis": self.axis.to_dict(),
                "psi_ref_deg": float(self.psi_ref_deg),
                "pose_ref": {"R": self.R_ref.tolist(), "T_mm": self.T_ref.tolist()},
                "covariance": np.where(np.isfinite(self.cov), self.cov, 1e300).tolist(),
                "covariance_parameters": ["axis_direction_u", "axis_direction_v", "axis_point_u_mm",
                                          "axis_point_v_mm", "rotvec_x", "rotvec_y", "rotvec_z",
                                          "centre_x_mm", "centre_y_mm", "centre_z_mm"],
                "unobservable": np.asarray(self.info.get("null", np.zeros((N_RIG, 0)))).T.tolist(),
                "noise": {k: float(v) for k, v in self.noise.items()},
                "warnings": list(self.warnings),
                **({"angle_jitter": {
                    "sigma_deg": float(self.jitter_deg),
                    "positions": [{"index": i, "correction_deg": c, "sigma_deg": e}
                                  for i, (c, e) in sorted(self.angle_corrections.items())]}}
                   if self.angle_corrections else {}),
                **({"ranging": self.ranging.to_dict()} if self.ranging is not None else {})}

    @staticmethod
    def from_dict(d: dict) -> JointModel:
        cov = np.asarray(d.get("covariance", np.full((N_RIG, N_RIG), np.nan)), dtype=float)
        null = np.asarray(d.get("unobservable", []), dtype=float).reshape(-1, N_RIG).T
        jit = d.get("angle_jitter") or {}
        return JointModel(Axis.from_dict(d["axis"]), float(d["psi_ref_deg"]),
                          np.asarray(d["pose_ref"]["R"], dtype=float),
                          np.asarray(d["pose_ref"]["T_mm"], dtype=float), cov,
                          dict(d.get("noise", {})), tuple(d.get("warnings", ())), {"null": null},
                          float(jit.get("sigma_deg", 0.0)),
                          {int(r["index"]): (float(r["correction_deg"]), float(r["sigma_deg"]))
                           for r in jit.get("positions", [])},
                          RangingModel.from_dict(d["ranging"]) if d.get("ranging") else None)


def _pose_sigmas(base: _Base, cov: np.ndarray, t: np.ndarray, null: np.ndarray
                 ) -> dict[str, np.ndarray]:
    """Propagate ``cov`` (10, 10) to centre, z, x sigmas at angles ``t`` (first order, with the
    rigid model's analytic derivatives :func:`lidarcal.joint.problem.pose_jacobian`).

    The rotation error is the left rotation vector ``w`` of ``R R0^T``: at the solution
    ``dR = [dw]x R0``, so ``dw = 1/2 sum_c R0_c x dR_c`` over the columns ``c`` (the
    antisymmetric part of ``dR R0^T``)."""
    from .problem import pose_jacobian

    R0, _, G = pose_jacobian(np.zeros(N_RIG), base, t)  # G rows [R_x, R_y, R_z, T]
    GT = G[:, 9:12]
    Gw = 0.5 * sum(np.cross(R0[:, :, c][:, :, None], G[:, 3 * c:3 * c + 3], axis=1)
                   for c in range(3))
    C = np.where(np.isfinite(cov), cov, 0.0)
    cT = GT @ C @ GT.transpose(0, 2, 1)
    cw = Gw @ C @ Gw.transpose(0, 2, 1)
    rows = {"centre_mm": np.sqrt(np.clip(np.trace(cT, axis1=1, axis2=2), 0, None))}
    for name, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
        v = R0[:, :, col]
        P = np.eye(3) - v[:, :, None] * v[:, None, :]
        rows[name] = np.degrees(np.sqrt(np.clip(np.trace(P @ cw @ P, axis1=1, axis2=2), 0, None)))
    Ck = C[:2, :2]
    rows["axis_direction_deg"] = np.full(len(t), np.degrees(np.sqrt(max(np.trace(Ck), 0.0))))
    # axis line near the LiDAR: foot of the reference centre on the axis, perpendicular part
    Gf = _foot_jacobian(base, base.T)
    Pk = np.eye(3) - np.outer(base.k, base.k)
    cf = Pk @ Gf @ C @ Gf.T @ Pk
    rows["axis_point_mm"] = np.full(len(t), np.sqrt(max(np.trace(cf), 0.0)))
    out = {k: np.asarray(v, dtype=float) for k, v in rows.items()}
    if null.shape[1]:  # quantities moved by an unobservable direction are undetermined
        def moved(G):  # G (..., m, 10)
            g = np.abs(G @ null)
            return (g > 1e-6 * (np.abs(G).max() + 1e-300)).any(axis=(-1, -2))
        out["centre_mm"][moved(GT)] = np.inf
        for name, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
            v = R0[:, :, col]
            P = np.eye(3) - v[:, :, None] * v[:, None, :]
            out[name][moved(P @ Gw)] = np.inf
        if (np.abs(null[:2]) > 1e-6).any():
            out["axis_direction_deg"][:] = np.inf
        if moved((Pk @ Gf)[None]).any():
            out["axis_point_mm"][:] = np.inf
    return out


def _foot_jacobian(base: _Base, p: np.ndarray) -> np.ndarray:
    """d foot / d rig (3, 10) at the solution: the foot ``f = a + k ((p - a) . k)`` of ``p`` on
    the axis moves with the direction steps (``dk``, :func:`lidarcal.joint.problem.pose_jacobian`)
    and the point steps (``da = B_i``)."""
    k, a, _, _ = _rig(np.zeros(N_RIG), base)
    dk = (base.B - np.outer(base.B @ k, k)) / np.linalg.norm(base.k)  # (2, 3)
    q = p - a
    Gf = np.zeros((3, N_RIG))
    Gf[:, 0:2] = (dk * float(q @ k) + np.outer(dk @ q, k)).T
    Gf[:, 2:4] = (base.B - np.outer(base.B @ k, k)).T
    return Gf
