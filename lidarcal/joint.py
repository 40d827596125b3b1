"""Joint fit of the whole rig to every stripe pixel and every scan point (beyond the paper).

The paper solves each turntable position alone (section 1) and then fits
functions of psi to those samples (section 2): every step throws information
away. Here the rigid turntable model of :class:`lidarcal.turntable.RigidModel`,
``pose(psi) = Rot(axis, psi - psi_ref) o pose_ref``, is fitted directly to the
raw observations of all positions at once by robust least squares
(maximum likelihood under the noise model below), started from the rigid
model and the paper's chain (the lower robust cost wins); the covariance of
the result comes from the Jacobian at the solution.

Unknowns (minimal parametrisation, 10 + optionally 12):
axis direction ``k`` (2: a step in the plane perpendicular to the start
direction, then normalised), axis point ``a`` (2: a step perpendicular to
``k``; the position along the axis is a gauge), the LiDAR pose at the
reference angle (rotation vector 3 and centre 3); with ``fit_planes`` the two
board poses (3 + 3 each).

Residuals:

* scan: every kept board return ``p`` of every scan (eq. 6, LiDAR frame) against
  its board's plane: ``n_b . (R(psi) p + T(psi)) - d_b`` (mm, eq. 3 and eq. 28);
* stripe: every stripe-centre pixel, back-projected onto its board's plane
  (eq. 5), against the laser plane the model predicts at that psi (the LiDAR's
  z = 0 plane): the distance in mm times the local image scale (pixels of
  stripe displacement, perpendicular to the imaged stripe, per mm of laser-
  plane offset, through the lens model), i.e. the pixel distance from the
  centre to the predicted stripe curve;
* corners (only with ``fit_planes``): reprojection of the chessboard corners
  of both boards through the lens model (pixels).

Noise model (every scale estimated from the data, never a constant): per board,
white noise (1.4826 x median absolute residual) plus, per scan segment and
per stripe, a random offset and a random tilt (:class:`_Groups`, generalised
least squares; entered only when significant). Stripe centres from real
images carry such correlated errors (measured on rendered data: lag-1
autocorrelation ~0.4, per-stripe mean errors 3-6x the white prediction);
without them the covariance is far too optimistic. After a first robust fit
(``loss``, residuals in sigmas, scale ``F_SCALE``) the noise is re-estimated
and residuals beyond ``REJECT_SIGMAS`` are dropped (a bounded loss still
pulls with constant force per outlier), twice.

Encoder jitter (:func:`angle_jitter`): a turntable whose encoder reports each
angle with a random error turns all of a position's observations together. With
the rig held, each position's own angle step is estimated from its residuals;
the jitter variance maximises the steps' marginal likelihood (random effects);
when the data show a jitter (likelihood ratio above ``JITTER_LR``) every
position's angle gets its posterior correction, the noise is re-estimated and
the rig refitted. ``poses`` are then the function at the corrected angles, and
their sigmas include each angle's remaining uncertainty. Without jitter nothing
changes.

The segment <-> board assignment of each position is the one the single-shot
solution chose (``pose.info["pairs"]``: camera board ``k`` <-> scan segment
``pairs[k]``).

Covariance: ``s^2 (J^T W J)^-1`` with ``W`` the robust loss's IRLS weights and
``s^2 >= 1`` the weighted residual variance. With ``fit_planes=False`` the
board planes are held (default: the ``cv2.solvePnP`` poses, the corners' ML
estimate); their uncertainty is propagated into the rig parameters as a
"consider" covariance, ``A P A^T`` with ``A = (J_x^T J_x)^-1 J_x^T J_b``. Corner
errors of chessboard detectors are correlated over the board, so the
reprojection residuals understate the plane error; the planes' information
assumes at least ``CORNER_FLOOR_PX`` per corner coordinate. The camera
intrinsics are taken as exact.

Solver: :func:`irls_lm`, Levenberg-Marquardt on the (n, n) normal equations
with IRLS weights (same optimum as ``scipy.optimize.least_squares`` with the
same loss, available as ``solver="scipy"``; its dense SVD of the ~1e5 x 10
Jacobian each iteration is slow on busy machines).

Convention: as :mod:`lidarcal.turntable` (increasing psi turns right-handedly
about ``axis.direction``); mm and degrees at the edges, radians inside.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .dataset import BoardSpec, CameraModel
from .geometry import Plane, Pose, plane_basis, unit
from .turntable import Axis, RigidModel

if TYPE_CHECKING:
    import pandas as pd

MAD_TO_SIGMA = 1.4826
_CHI1_MEDIAN = 0.45493642311957283  # median of the chi-square distribution with 1 dof
N_RIG = 10  # axis direction 2, axis point 2, reference rotation 3, reference centre 3
N_BOARD = 6  # per board: rotation 3, translation 3
F_SCALE = 2.5  # robust loss scale, in noise sigmas
CLIP_SIGMAS = 4.0  # residuals beyond this many sigmas do not enter the group moments
SIGNIFICANCE = 3.0  # a correlated-noise component enters when this many sigmas above zero
REJECT_SIGMAS = 5.0  # residuals beyond this many (whitened) sigmas are dropped after a first fit
CORNER_FLOOR_PX = 0.1  # chessboard corner accuracy assumed for the board planes' uncertainty
JITTER_LR = 25.0  # encoder jitter is modelled when its likelihood ratio exceeds this (~5 sigma)
MIN_POINTS_PER_BOARD = 8
# central-difference steps: rotations / directions (rad), translations (mm)
_STEPS = np.array([1e-6] * 2 + [1e-3] * 2 + [1e-6] * 3 + [1e-3] * 3 + ([1e-6] * 3 + [1e-3] * 3) * 2)


# ------------------------------------------------------------------------ observations


@dataclass(frozen=True, eq=False)
class JointData:
    """Every observation the joint fit uses, flattened over positions and boards.

    ``scan_xy`` (M, 2): kept board returns in the LiDAR plane (eq. 6) with their
    position ``scan_pos`` (M,) (index into ``psi_deg``) and board ``scan_board`` (M,).
    ``stripe_px`` (S, 2): stripe-centre pixels (distorted) with ``stripe_rays``
    (S, 3) = undistorted rays ``(x, y, 1)``, ``stripe_pos``, ``stripe_board``.
    ``board_R``, ``board_T`` (2, 3, 3), (2, 3): board poses (eq. 1) from the
    homography; ``corners_px`` the detected corners per board and
    ``object_points`` (C, 3) the board coordinates (None: no corner residuals).
    ``samples``: the single-shot poses (section 1), for the start and warnings.
    """

    camera: CameraModel
    psi_deg: np.ndarray
    indices: np.ndarray
    scan_xy: np.ndarray
    scan_pos: np.ndarray
    scan_board: np.ndarray
    stripe_px: np.ndarray
    stripe_rays: np.ndarray
    stripe_pos: np.ndarray
    stripe_board: np.ndarray
    board_R: np.ndarray
    board_T: np.ndarray
    corners_px: tuple[np.ndarray, np.ndarray] | None
    object_points: np.ndarray | None
    samples: list[Pose] = field(default_factory=list)

    @property
    def n_positions(self) -> int:
        return len(self.psi_deg)

    def without_stripes(self) -> JointData:
        """The same data with no stripe observations (the scan-only fit)."""
        e = np.zeros(0, int)
        return JointData(self.camera, self.psi_deg, self.indices, self.scan_xy, self.scan_pos,
                         self.scan_board, np.zeros((0, 2)), np.zeros((0, 3)), e, e, self.board_R,
                         self.board_T, self.corners_px, self.object_points, self.samples)


def _stripe_rays(camera: CameraModel, px: np.ndarray) -> np.ndarray:
    from .camera import pixel_rays

    return pixel_rays(camera, px) if len(px) else np.zeros((0, 3))


def build_joint_data(camera: CameraModel, psi_deg, scans: list[tuple[np.ndarray, np.ndarray]],
                     stripes: list[tuple[np.ndarray, np.ndarray]], board_R: np.ndarray,
                     board_T: np.ndarray, corners_px=None, object_points=None,
                     samples: list[Pose] | None = None, indices=None) -> JointData:
    """:class:`JointData` from per-position observations, already assigned to boards.

    Parameters
    ----------
    scans : list of (points_board0 (M0, 2), points_board1 (M1, 2)), one per position
        LiDAR-plane points (eq. 6) on board 0 and board 1.
    stripes : list of (centres_board0 (S0, 2), centres_board1 (S1, 2)), one per position
        Stripe-centre pixels (distorted) on board 0 and board 1.
    board_R, board_T : arrays (2, 3, 3), (2, 3)
        Board poses (eq. 1); the planes are ``R[:, 2] . X = R[:, 2] . T``.
    """
    psi = np.asarray(psi_deg, dtype=float).ravel()
    if len(scans) != len(psi) or len(stripes) != len(psi):
        raise ValueError(f"Expected one scan and one stripe pair per position ({len(psi)}), got "
                         f"{len(scans)} and {len(stripes)}")
    xy, sp, sb, cpx, cp, cb = [], [], [], [], [], []
    for i, (sc, st) in enumerate(zip(scans, stripes)):
        for b in range(2):
            p = np.asarray(sc[b], dtype=float).reshape(-1, 2)
            p = p[np.all(np.isfinite(p), axis=1)]
            xy.append(p)
            sp.append(np.full(len(p), i))
            sb.append(np.full(len(p), b))
            c = np.asarray(st[b], dtype=float).reshape(-1, 2)
            cpx.append(c)
            cp.append(np.full(len(c), i))
            cb.append(np.full(len(c), b))
    stripe_px = np.vstack(cpx)
    rays = _stripe_rays(camera, stripe_px)
    ok = np.all(np.isfinite(rays), axis=1)
    cat = lambda v: np.concatenate(v).astype(int)
    return JointData(camera, psi, np.arange(len(psi)) if indices is None else np.asarray(indices),
                     np.vstack(xy), cat(sp), cat(sb), stripe_px[ok], rays[ok], cat(cp)[ok],
                     cat(cb)[ok], np.asarray(board_R, float), np.asarray(board_T, float),
                     None if corners_px is None else tuple(np.asarray(c, float) for c in corners_px),
                     None if object_points is None else np.asarray(object_points, float),
                     list(samples or []))


def joint_data(result, board_poses: str = "homography") -> JointData:
    """:class:`JointData` from a :class:`lidarcal.pipeline.CalibrationResult`.

    Board ``k`` gets scan segment ``pose.info["pairs"][k]`` (``points1`` for 0,
    ``points2`` for 1) and the stripe centres ``camera_lines.centres_px[k]``.
    ``board_poses``: "homography" (eq. 2, ``BoardView.R, T``) or "pnp"
    (``cv2.solvePnP``, ``BoardView.R_pnp, T_pnp``).
    """
    if board_poses not in ("homography", "pnp"):
        raise ValueError(f"board_poses must be 'homography' or 'pnp', got {board_poses!r}")
    pnp = board_poses == "pnp"
    scans, stripes = [], []
    for p in result.positions:
        pairs = p.pose.info.get("pairs", (0, 1))
        seg = (p.segments.points1, p.segments.points2)
        scans.append((seg[pairs[0]], seg[pairs[1]]))
        stripes.append(tuple(p.camera_lines.centres_px))
    boards = result.boards
    spec: BoardSpec | None = getattr(getattr(result, "dataset", None), "v_board", None)
    obj = spec.object_points() if spec is not None else None
    return build_joint_data(result.camera, [p.psi_deg for p in result.positions], scans, stripes,
                            np.array([b.R_pnp if pnp else b.R for b in boards]),
                            np.array([b.T_pnp if pnp else b.T for b in boards]),
                            [b.corners_px for b in boards] if obj is not None else None, obj,
                            [p.pose for p in result.positions], [p.index for p in result.positions])


# --------------------------------------------------------------------------- the model


@dataclass(frozen=True)
class _Base:
    """Linearisation point of the parametrisation."""

    k: np.ndarray
    B: np.ndarray  # (2, 3) basis perpendicular to k
    a: np.ndarray
    R: np.ndarray
    T: np.ndarray
    board_R: np.ndarray  # (2, 3, 3)
    board_T: np.ndarray  # (2, 3)

    @staticmethod
    def make(k, a, R, T, board_R, board_T) -> _Base:
        k = unit(np.asarray(k, dtype=float))
        a = np.asarray(a, dtype=float)
        return _Base(k, plane_basis(k), a - (a @ k) * k, np.asarray(R, float), np.asarray(T, float),
                     np.asarray(board_R, float), np.asarray(board_T, float))


def _rig(x: np.ndarray, base: _Base):
    """(k, a, R_ref, T_ref) for rig parameters ``x[:10]``."""
    k = unit(base.k + x[0:2] @ base.B)
    a = base.a + x[2:4] @ base.B
    R = Rotation.from_rotvec(x[4:7]).as_matrix() @ base.R
    T = base.T + x[7:10]
    return k, a, R, T


def _boards(x: np.ndarray, base: _Base):
    """Board rotations (2, 3, 3) and translations (2, 3) for ``x[10:22]`` (zeros if absent)."""
    if len(x) <= N_RIG:
        return base.board_R, base.board_T
    xb = x[N_RIG:N_RIG + 2 * N_BOARD].reshape(2, N_BOARD)
    R = Rotation.from_rotvec(xb[:, :3]).as_matrix() @ base.board_R
    return R, base.board_T + xb[:, 3:]


def _poses(k, a, R_ref, T_ref, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid model at angles ``t`` (rad from psi_ref): R (N, 3, 3), T (N, 3)."""
    Q = Rotation.from_rotvec(np.outer(t, k)).as_matrix()
    return Q @ R_ref, a + (Q @ (T_ref - a)[:, None])[:, :, 0]


class _Groups:
    """Noise model of one residual kind: per-(position, board) groups with correlated errors.

    Residual ``i`` of group ``g`` (one board's scan segment or stripe at one
    position) is ``e_i + b0_g + b1_g s_i``: white noise of sigma ``sigma[board]``
    plus a random offset and a random tilt along the segment (``s_i``: centred
    coordinate along it) with variances ``var0[board]``, ``var1[board]``. Stripe
    centres carry such errors (sub-pixel locking of the centre estimator varies
    slowly along a stripe and from one position to the next); ignoring them
    makes the covariance far too optimistic. ``whiten`` applies ``V^-1/2``
    (generalised least squares): with ``u0 = 1/sqrt(n)``, ``u1 = s/|s|``,
    ``V^-1/2 = (I - g0 u0 u0^T - g1 u1 u1^T) / sigma``,
    ``g_j = 1 - sqrt(sigma^2 / (sigma^2 + lambda_j))``, ``lambda0 = n var0``,
    ``lambda1 = |s|^2 var1``.
    """

    def __init__(self, pos: np.ndarray, board: np.ndarray, coords: np.ndarray, n_pos: int):
        self.gid = pos * 2 + board
        self.n_groups = 2 * n_pos
        self.board_of_group = np.arange(self.n_groups) % 2
        self.n = np.bincount(self.gid, minlength=self.n_groups).astype(float)
        sc = np.zeros(len(pos))
        order = np.argsort(self.gid, kind="stable")
        cuts = np.searchsorted(self.gid[order], np.arange(self.n_groups + 1))
        for g in np.flatnonzero(self.n >= 3):
            m = order[cuts[g]:cuts[g + 1]]
            q = coords[m] - coords[m].mean(0)
            _, _, vt = np.linalg.svd(q, full_matrices=False)
            sc[m] = q @ vt[0]
        self.sc = sc
        # residuals come grouped (position by position, board 0 then 1): group sums of a
        # whole Jacobian are then one np.add.reduceat instead of a bincount per column
        self._sorted = bool(np.all(self.gid[1:] >= self.gid[:-1]))
        starts = np.searchsorted(self.gid, np.arange(self.n_groups))
        self._nonempty = np.flatnonzero(self.n > 0)
        self._starts = starts[self._nonempty]
        self.sigma = np.ones(2)
        self.var0 = np.zeros(2)
        self.var1 = np.zeros(2)
        self.var0_g = self.var1_g = None
        self.set_mask(np.ones(len(pos), bool))

    def set_mask(self, keep: np.ndarray) -> None:
        """Residuals that enter the fit (the group moments and the counts use only these)."""
        self.w = np.asarray(keep, float)
        self.n, self.ss = self._counts(self.w)
        self._update()

    def _counts(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = np.bincount(self.gid, w, minlength=self.n_groups)
        ss = np.maximum(np.bincount(self.gid, w * self.sc**2, minlength=self.n_groups), 1e-300)
        return n, ss

    def set(self, sigma, var0, var1, var0_g=None, var1_g=None) -> None:
        """Noise components per board; ``var*_g`` optionally per group (robust weights)."""
        self.sigma = np.asarray(sigma, float)
        self.var0 = np.asarray(var0, float)
        self.var1 = np.asarray(var1, float)
        self.var0_g = None if var0_g is None else np.asarray(var0_g, float)
        self.var1_g = None if var1_g is None else np.asarray(var1_g, float)
        self._update()

    def _update(self) -> None:
        b = self.board_of_group
        s2 = self.sigma[b] ** 2
        v0 = self.var0[b] if self.var0_g is None else self.var0_g
        v1 = self.var1[b] if self.var1_g is None else self.var1_g
        self.g0 = 1 - np.sqrt(s2 / (s2 + self.n * v0))
        self.g1 = 1 - np.sqrt(s2 / (s2 + self.ss * v1))
        self.sig_g = self.sigma[b]

    def moments(self, r: np.ndarray, w: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Per-group mean and slope (least squares along ``s``) of ``r`` over the kept residuals."""
        if w is None:
            w, n, ss = self.w, self.n, self.ss
        else:
            n, ss = self._counts(w)
        m0 = np.bincount(self.gid, w * r, minlength=self.n_groups) / np.maximum(n, 1e-300)
        m1 = np.bincount(self.gid, w * r * self.sc, minlength=self.n_groups) / ss
        return m0, m1

    def whiten(self, r: np.ndarray) -> np.ndarray:
        """``V^-1/2 r`` over the kept residuals (dropped ones do not enter the moments)."""
        if len(r) == 0:
            return r
        m0, m1 = self.moments(r)
        g = self.gid
        return (r - self.g0[g] * m0[g] - self.g1[g] * m1[g] * self.sc) / self.sig_g[g]

    def whiten_columns(self, J: np.ndarray) -> np.ndarray:
        """:meth:`whiten` applied to every column of a Jacobian."""
        if J.shape[0] == 0:
            return J
        if not self._sorted:
            return np.column_stack([self.whiten(J[:, j]) for j in range(J.shape[1])])
        wJ = J * self.w[:, None]
        m0 = self._group_sums(wJ) / np.maximum(self.n, 1e-300)[:, None]
        m1 = self._group_sums(wJ * self.sc[:, None]) / self.ss[:, None]
        g = self.gid
        return ((J - self.g0[g][:, None] * m0[g] - (self.g1[g] * self.sc)[:, None] * m1[g])
                / self.sig_g[g][:, None])

    def _group_sums(self, A: np.ndarray) -> np.ndarray:
        """Per-group column sums of ``A`` (rows grouped by ``gid``, sorted)."""
        out = np.zeros((self.n_groups, A.shape[1]))
        if len(self._nonempty):
            out[self._nonempty] = np.add.reduceat(A, self._starts, axis=0)
        return out

    def estimate(self, r: np.ndarray, floor: float) -> None:
        """Method-of-moments noise components from residuals ``r`` at a fit (see class doc).

        Residuals beyond ``CLIP_SIGMAS`` robust sigmas are left out. ``sigma``:
        1.4826 x median absolute within-group residual (group offset and tilt
        removed); ``var0 = mean(m0^2 - sigma^2 / n)``, ``var1 = mean(m1^2 -
        sigma^2 / |s|^2)`` over the board's groups, set only when significant
        (``SIGNIFICANCE`` standard errors above zero), else 0.
        """
        if len(r) == 0:
            return
        sig, v0, v1 = np.ones(2), np.zeros(2), np.zeros(2)
        g = self.gid
        w = (np.abs(r) <= CLIP_SIGMAS * _robust_sigma(r, floor)).astype(float)
        m0, m1 = self.moments(r, w)
        within = r - m0[g] - m1[g] * self.sc
        for b in range(2):
            sel = self.board_of_group[g] == b
            if not sel.any():
                continue
            sig[b] = _robust_sigma(within[sel & (w > 0)], floor)
        w = (np.abs(within) <= CLIP_SIGMAS * sig[self.board_of_group[g]]).astype(float)
        a0, a1 = self.moments(r, w)
        n, ss = self._counts(w)
        vg = [np.zeros(self.n_groups), np.zeros(self.n_groups)]
        for b in range(2):
            grp = (self.board_of_group == b) & (n >= 3)
            G = int(grp.sum())
            if G == 0:
                continue
            # a component is kept only when significant: without it, m^2 / var(m | white)
            # averages to 1 +- sqrt(2 / G) (chi-square, 1 dof, G groups)
            for v, a, nn, out in ((v0, a0, n, vg[0]), (v1, a1, ss, vg[1])):
                white = sig[b] ** 2 / np.maximum(nn[grp], 1e-300)
                if np.mean(a[grp] ** 2 / white) > 1 + SIGNIFICANCE * np.sqrt(2.0 / G):
                    # typical level from the median (chi-square 1 dof: median 0.455), and a
                    # group with a larger effect keeps its own: heavy-tailed group errors
                    # (a stripe on an unlucky pixel phase) then cannot steer the fit
                    v[b] = max(float(np.median(a[grp] ** 2) / _CHI1_MEDIAN
                                     - np.median(white)), 0.0)
                    out[grp] = np.maximum(v[b], a[grp] ** 2 - white)
        self.set(sig, v0, v1, vg[0], vg[1])


class _Problem:
    """Residual blocks of the joint fit for full parameter vectors (rig 10 + boards 12)."""

    def __init__(self, data: JointData, base: _Base, psi_ref_deg: float):
        self.data = data
        self.base = base
        self.t = np.radians(data.psi_deg - psi_ref_deg)
        self.scale_px = np.ones(len(data.stripe_px))
        n = data.n_positions
        self.scan = _Groups(data.scan_pos, data.scan_board, data.scan_xy, n)
        self.stripe = _Groups(data.stripe_pos, data.stripe_board, data.stripe_px, n)
        self.sigma_corner = 1.0
        self.corner_floor_px = 0.0

    def estimate_noise(self, x: np.ndarray, correlated: bool) -> None:
        """Noise scales of every residual kind from the residuals at ``x`` (:meth:`_Groups.estimate`);
        without ``correlated`` the per-segment / per-stripe components are zero."""
        rs, rp, rc = self.blocks(x)
        self.scan.estimate(rs, 1e-9 * max(float(np.abs(self.data.board_T).max()), 1.0))
        self.stripe.estimate(rp, 1e-6)
        if not correlated:
            self.scan.set(self.scan.sigma, [0, 0], [0, 0])
            self.stripe.set(self.stripe.sigma, [0, 0], [0, 0])
        self.sigma_corner = _robust_sigma(rc, 1e-6)

    def reject(self, x: np.ndarray) -> None:
        """Drop residuals beyond ``REJECT_SIGMAS`` (whitened) from the fit: a bounded loss
        still lets gross outliers pull with constant force; cutting them restores the
        Gaussian-noise optimum (for Gaussian data nothing is cut: P(|z| > 5) ~ 6e-7)."""
        rs, rp, _ = self.blocks(x, corners=False)
        for grp, r in ((self.scan, rs), (self.stripe, rp)):
            grp.set_mask(np.ones(len(r), bool))
            for _ in range(2):  # the kept set changes the group moments: settle it
                grp.set_mask(np.abs(grp.whiten(r)) <= REJECT_SIGMAS)

    def blocks(self, x: np.ndarray, corners: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw residuals: scan (mm), stripe (px), corners (px, x and y interleaved)."""
        d = self.data
        k, a, R_ref, T_ref = _rig(x, self.base)
        R, T = _poses(k, a, R_ref, T_ref, self.t)
        bR, bT = _boards(x, self.base)
        n = bR[:, :, 2]
        dd = np.einsum("ij,ij->i", n, bT)
        # scan points in the camera frame, eq. (28), against their board's plane, eq. (3)
        p, b = d.scan_pos, d.scan_board
        X = R[p, :, 0] * d.scan_xy[:, :1] + R[p, :, 1] * d.scan_xy[:, 1:] + T[p]
        r_scan = np.einsum("ij,ij->i", X, n[b]) - dd[b]
        # stripe centres back-projected onto their board (eq. 5), against the laser plane
        p, b = d.stripe_pos, d.stripe_board
        ray = d.stripe_rays
        P = ray * (dd[b] / np.einsum("ij,ij->i", ray, n[b]))[:, None]
        z = R[p, :, 2]
        r_stripe = np.einsum("ij,ij->i", P - T[p], z) * self.scale_px
        r_corner = self.corner_residuals(bR, bT) if corners else np.zeros(0)
        return r_scan, r_stripe, r_corner

    def jacobian(self, x: np.ndarray, use_corners: bool) -> np.ndarray:
        """Jacobian of :meth:`normalised` wrt the full parameters (rig 10 + boards 12).

        Chain rule: the residuals are linear in each position's pose columns and
        in each board's plane (normal, d), which depend on the parameters through
        small functions differentiated numerically (central differences).
        Corners: central differences.
        """
        d = self.data
        n_par = len(x)
        k, a, R_ref, T_ref = _rig(x, self.base)
        R, T = _poses(k, a, R_ref, T_ref, self.t)
        bR, bT = _boards(x, self.base)
        nb = bR[:, :, 2]
        db = np.einsum("ij,ij->i", nb, bT)
        # d (pose columns x, y, z and T at every position) / d rig parameters: (N, 12, 10)
        h = _STEPS[:N_RIG]
        G = np.zeros((len(self.t), 12, N_RIG))
        for j in range(N_RIG):
            dx = np.zeros(n_par)
            dx[j] = h[j]
            Rp, Tp = _poses(*_rig(x + dx, self.base), self.t)
            Rm, Tm = _poses(*_rig(x - dx, self.base), self.t)
            G[:, :, j] = (np.concatenate([Rp.transpose(0, 2, 1).reshape(-1, 9), Tp], 1)
                          - np.concatenate([Rm.transpose(0, 2, 1).reshape(-1, 9), Tm], 1)) / (2 * h[j])
        # d (normal, d) of both boards / d board parameters: (2, 4, 6)
        Gb = np.zeros((2, 4, N_BOARD))
        if n_par > N_RIG:
            for j in range(N_BOARD):
                for b in range(2):
                    dx = np.zeros(n_par)
                    i = N_RIG + b * N_BOARD + j
                    dx[i] = _STEPS[i]
                    Rp, Tp = _boards(x + dx, self.base)
                    Rm, Tm = _boards(x - dx, self.base)
                    fp = np.append(Rp[b][:, 2], Rp[b][:, 2] @ Tp[b])
                    fm = np.append(Rm[b][:, 2], Rm[b][:, 2] @ Tm[b])
                    Gb[b, :, j] = (fp - fm) / (2 * _STEPS[i])
        blocks = []
        # scan: r = n_b . (R_x x + R_y y + T) - d_b
        p, b = d.scan_pos, d.scan_board
        xs, ys = d.scan_xy[:, :1], d.scan_xy[:, 1:]
        n = nb[b]
        dr = np.concatenate([n * xs, n * ys, np.zeros((len(p), 3)), n], 1)  # wrt [Rx Ry Rz T]
        Js = np.zeros((len(p), n_par))
        Js[:, :N_RIG] = _rows_times(dr, G, p)
        if n_par > N_RIG:
            X = R[p, :, 0] * xs + R[p, :, 1] * ys + T[p]
            drb = np.concatenate([X, -np.ones((len(p), 1))], 1)  # wrt [n, d]
            for bb in range(2):
                m = b == bb
                c = N_RIG + bb * N_BOARD
                Js[m, c:c + N_BOARD] = _mm(drb[m], Gb[bb])
        blocks.append(self.scan.whiten_columns(Js) * self.scan.w[:, None])
        # stripe: r = s (P - T) . z,  P = ray d_b / (ray . n_b)
        p, b = d.stripe_pos, d.stripe_board
        ray, s = d.stripe_rays, self.scale_px[:, None]
        rn = np.einsum("ij,ij->i", ray, nb[b])[:, None]
        P = ray * (db[b][:, None] / rn)
        z = R[p, :, 2]
        dr = np.concatenate([np.zeros((len(p), 6)), (P - T[p]) * s, -z * s], 1)
        Jp = np.zeros((len(p), n_par))
        Jp[:, :N_RIG] = _rows_times(dr, G, p)
        if n_par > N_RIG:
            zr = np.einsum("ij,ij->i", z, ray)[:, None]
            drb = np.concatenate([-s * zr * db[b][:, None] * ray / rn**2, s * zr / rn], 1)
            for bb in range(2):
                m = b == bb
                c = N_RIG + bb * N_BOARD
                Jp[m, c:c + N_BOARD] = _mm(drb[m], Gb[bb])
        blocks.append(self.stripe.whiten_columns(Jp) * self.stripe.w[:, None])
        if use_corners:
            m = len(self.corner_residuals(bR, bT))
            Jc = np.zeros((m, n_par))
            for i in range(N_RIG, n_par):
                dx = np.zeros(n_par)
                dx[i] = _STEPS[i]
                Jc[:, i] = (self.corner_residuals(*_boards(x + dx, self.base))
                            - self.corner_residuals(*_boards(x - dx, self.base))) / (2 * _STEPS[i])
            blocks.append(Jc / self.sigma_corner)
        return np.vstack(blocks)

    def corner_residuals(self, bR: np.ndarray, bT: np.ndarray) -> np.ndarray:
        d = self.data
        if d.corners_px is None or d.object_points is None:
            return np.zeros(0)
        out = []
        K, dist = np.asarray(d.camera.K, float), np.asarray(d.camera.dist, float)
        for j in range(2):
            rvec = cv2.Rodrigues(bR[j])[0]
            proj, _ = cv2.projectPoints(d.object_points.reshape(-1, 1, 3), rvec, bT[j], K, dist)
            out.append((proj.reshape(-1, 2) - d.corners_px[j]).ravel())
        return np.concatenate(out)

    def normalised(self, x: np.ndarray, use_corners: bool) -> np.ndarray:
        r = self.blocks(x, corners=use_corners)
        parts = [self.scan.whiten(r[0]) * self.scan.w, self.stripe.whiten(r[1]) * self.stripe.w]
        if use_corners:
            parts.append(r[2] / self.sigma_corner)
        return np.concatenate(parts)

    def set_stripe_scale(self, x: np.ndarray) -> None:
        """Pixels of stripe displacement (perpendicular to the imaged stripe) per mm of laser offset."""
        d = self.data
        if len(d.stripe_px) == 0:
            return
        k, a, R_ref, T_ref = _rig(x, self.base)
        R, _ = _poses(k, a, R_ref, T_ref, self.t)
        bR, bT = _boards(x, self.base)
        n = bR[:, :, 2][d.stripe_board]
        dd = np.einsum("ij,ij->i", bR[:, :, 2], bT)[d.stripe_board]
        ray = d.stripe_rays
        P = ray * (dd / np.einsum("ij,ij->i", ray, n))[:, None]
        zL = R[d.stripe_pos, :, 2]
        line = unit(np.cross(n, zL))  # stripe direction on the board
        u = unit(np.cross(n, line))  # in the board, perpendicular to the stripe
        h = 0.05  # mm
        from .camera import project_points

        pu = (project_points(d.camera, P + h * u) - project_points(d.camera, P - h * u)) / (2 * h)
        pl = unit(project_points(d.camera, P + h * line) - project_points(d.camera, P - h * line))
        perp = np.abs(pu[:, 0] * pl[:, 1] - pu[:, 1] * pl[:, 0])  # px per mm along u
        du = np.abs(np.einsum("ij,ij->i", zL, u))  # mm of laser offset per mm along u
        self.scale_px = perp / np.maximum(du, 1e-9)


def _rows_times(dr: np.ndarray, G: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Row ``m`` of the result is ``dr[m] @ G[p[m]]``: (M, k) x (N, k, n) -> (M, n).

    Rows sorted by position (as :func:`build_joint_data` makes them) take one small
    product per position instead of gathering an (M, k, n) copy of ``G``.
    """
    if len(p) == 0 or np.any(p[1:] < p[:-1]):
        return np.einsum("mi,mij->mj", dr, G[p])
    out = np.empty((len(p), G.shape[2]))
    cuts = np.searchsorted(p, np.arange(G.shape[0] + 1))
    for i in range(G.shape[0]):
        a, b = cuts[i], cuts[i + 1]
        if b > a:
            out[a:b] = np.einsum("mi,ij->mj", dr[a:b], G[i])
    return out


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for long inner dimensions without BLAS threads (einsum's C loop).

    Threaded BLAS on an oversubscribed machine turns these small products
    ((n, 1e5) x (1e5, n)) into seconds; the plain loop takes milliseconds.
    """
    return np.einsum("ik,kj->ij", A, B)


def _robust_sigma(r: np.ndarray, floor: float) -> float:
    if len(r) == 0:
        return 1.0
    return float(max(MAD_TO_SIGMA * np.median(np.abs(r)), floor))


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

    @property
    def rigid(self) -> RigidModel:
        return RigidModel(self.axis, self.psi_ref_deg, self.R_ref, self.T_ref)

    @property
    def pose_ref(self) -> Pose:
        return Pose(self.R_ref, self.T_ref)

    def pose(self, psi_deg: float | np.ndarray) -> Pose | list[Pose]:
        """LiDAR pose(s) at turntable angle(s) ``psi_deg`` (the rigid model)."""
        return self.rigid.pose(psi_deg)

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
        poses = self.pose(psi)
        poses = poses if isinstance(poses, list) else [poses]
        dist = np.array([np.linalg.norm(np.cross(p.T - a, k)) for p in poses])
        cols["centre_mm"] = np.hypot(cols["centre_mm"], e * dist)
        for name, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
            sin = np.array([np.linalg.norm(np.cross(p.R[:, col], k)) for p in poses])
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
        from .turntable import RIGID_FORMULA

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
                   if self.angle_corrections else {})}

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
                           for r in jit.get("positions", [])})


def _pose_sigmas(base: _Base, cov: np.ndarray, t: np.ndarray, null: np.ndarray
                 ) -> dict[str, np.ndarray]:
    """Propagate ``cov`` (10, 10) to centre, z, x sigmas at angles ``t`` (finite differences)."""
    x0 = np.zeros(N_RIG)
    R0, _ = _poses(*_rig(x0, base), t)
    h = _STEPS[:N_RIG]
    GT = np.zeros((len(t), 3, N_RIG))
    Gw = np.zeros((len(t), 3, N_RIG))
    for j in range(N_RIG):
        dx = np.zeros(N_RIG)
        dx[j] = h[j]
        Rp, Tp = _poses(*_rig(dx, base), t)
        Rm, Tm = _poses(*_rig(-dx, base), t)
        GT[:, :, j] = (Tp - Tm) / (2 * h[j])
        Gw[:, :, j] = (Rotation.from_matrix(Rp @ np.transpose(R0, (0, 2, 1))).as_rotvec()
                       - Rotation.from_matrix(Rm @ np.transpose(R0, (0, 2, 1))).as_rotvec()) / (2 * h[j])
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
    Gf = np.zeros((3, N_RIG))
    for j in range(N_RIG):
        dx = np.zeros(N_RIG)
        dx[j] = h[j]
        fp = _foot(_rig(dx, base), base.T)
        fm = _foot(_rig(-dx, base), base.T)
        Gf[:, j] = (fp - fm) / (2 * h[j])
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


def _foot(rig: tuple, p: np.ndarray) -> np.ndarray:
    k, a, _, _ = rig
    return a + k * ((p - a) @ k)


# ----------------------------------------------------------------------------- fitting


def _start_bases(result_or_models, data: JointData, psi_ref: float) -> list[_Base]:
    bases = []
    for m in result_or_models:
        if m is None:
            continue
        p = m.pose(psi_ref)
        bases.append(_Base.make(m.axis.direction, m.axis.point, p.R, p.T, data.board_R, data.board_T))
    if not bases:
        raise ValueError("fit_joint needs a start model (rigid or paper)")
    return bases


def fit_joint_data(data: JointData, starts: list, *, fit_planes: bool = False,
                   loss: str = "soft_l1", psi_ref_deg: float | None = None,
                   f_scale: float = F_SCALE, solver: str = "lm",
                   correlated: bool = True,
                   corner_floor_px: float = CORNER_FLOOR_PX, jitter: bool = True) -> JointModel:
    """Joint fit on prepared observations; ``starts`` are pose functions (axis + ``pose``).

    See :func:`fit_joint`. Every start is refined once with the start's noise
    scales and the lowest robust cost wins; then the noise scales are
    re-estimated from the residuals, the stripe scale factors recomputed, and
    the fit repeated (twice).
    """
    if data.n_positions < 2:
        raise ValueError(f"the joint fit needs at least 2 positions, got {data.n_positions}")
    if len(data.scan_xy) == 0:
        raise ValueError("no scan points: the joint fit needs the board returns of the scans")
    use_corners = fit_planes and data.corners_px is not None
    if fit_planes and not use_corners:
        raise ValueError("fit_planes=True needs the board corners and object points (v_board)")
    psi_ref = float(np.mean(data.psi_deg)) if psi_ref_deg is None else float(psi_ref_deg)
    bases = _start_bases(starts, data, psi_ref)
    n_par = N_RIG + (2 * N_BOARD if fit_planes else 0)
    x0 = np.zeros(n_par)

    def _full(x):
        return x if len(x) > N_RIG else np.concatenate([x, np.zeros(2 * N_BOARD)])

    def solve(prob: _Problem, x: np.ndarray):
        if solver == "scipy":
            return least_squares(prob.normalised, x, jac=prob.jacobian, args=(use_corners,),
                                 loss=loss, f_scale=f_scale, x_scale="jac", method="trf",
                                 xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
        return irls_lm(lambda v: prob.normalised(v, use_corners),
                       lambda v: prob.jacobian(v, use_corners), x, loss, f_scale)

    sols = []
    for base in bases:
        prob = _Problem(data, base, psi_ref)
        prob.set_stripe_scale(_full(x0))
        prob.estimate_noise(x0, correlated=False)
        sols.append((prob, solve(prob, x0)))
    # costs are comparable only with the same noise model: rescore with the first start's
    scores = []
    for prob, sol in sols:
        prob.scan, prob.stripe = sols[0][0].scan, sols[0][0].stripe
        prob.sigma_corner = sols[0][0].sigma_corner
        r = prob.normalised(_full(sol.x), use_corners)
        scores.append(np.sum(_rho(r / f_scale, loss)))
    best = int(np.argmin(scores))
    prob, sol = sols[best]
    x = sol.x

    def refine(prob: _Problem, x: np.ndarray):
        """Noise re-estimated at ``x``, outliers dropped, solved again."""
        prob.set_stripe_scale(_full(x))
        prob.estimate_noise(x, correlated)
        prob.reject(_full(x))
        return solve(prob, x)

    for _ in range(2):
        sol = refine(prob, x)
        x = sol.x
    # encoder jitter (beyond the paper): per-position angle corrections, then the rig again
    t_reported = prob.t.copy()
    jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated) if jitter else None
    if jit is not None and jit["lr"] > JITTER_LR:
        prob.t = t_reported + np.radians(jit["correction_deg"])
        sol = refine(prob, x)
        x = sol.x
        jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated)
    applied = jit is not None and jit["lr"] > JITTER_LR
    t_final = t_reported + np.radians(jit["correction_deg"]) if applied else t_reported
    # re-base at the solution so the covariance is about it (x = 0)
    k, a, R_ref, T_ref = _rig(x, prob.base)
    bR, bT = _boards(_full(x), prob.base)
    base = _Base.make(k, a, R_ref, T_ref, bR, bT)
    old = prob
    prob = _Problem(data, base, psi_ref)
    prob.t = t_final
    prob.scale_px, prob.scan, prob.stripe = old.scale_px, old.scan, old.stripe
    prob.sigma_corner = old.sigma_corner
    prob.corner_floor_px = float(corner_floor_px)
    cov, null, s2 = _covariance(prob, fit_planes, loss, f_scale)
    axis = Axis.from_point_direction(base.a, base.k)
    rs, rp, rc = prob.blocks(np.zeros(N_RIG + 2 * N_BOARD))
    noise = {}
    for name, grp, unit_ in (("scan", prob.scan, "mm"), ("stripe", prob.stripe, "px")):
        for b in range(2):
            noise[f"{name}{b}_{unit_}"] = float(grp.sigma[b])
            noise[f"{name}{b}_offset_{unit_}"] = float(np.sqrt(grp.var0[b]))
            noise[f"{name}{b}_tilt_{unit_}_per_{unit_}"] = float(np.sqrt(grp.var1[b]))
    if data.corners_px is not None:
        noise["corner_px"] = float(prob.sigma_corner)
    corrections = {int(i): (float(c), float(e)) for i, c, e in
                   zip(data.indices, jit["correction_deg"], jit["correction_sigma_deg"])} if applied else {}
    jitter_deg = float(jit["sigma_deg"]) if applied else 0.0
    model = JointModel(axis, psi_ref, base.R, base.T, cov, noise)
    warn = joint_warnings(data, model, null)
    info = {"null": null, "residual_variance": s2, "cost": float(sol.cost), "nfev": int(sol.nfev),
            "status": int(sol.status), "start": best, "fit_planes": fit_planes,
            "residuals": {"scan_mm": rs, "stripe_px": rp, "corner_px": rc},
            "board_planes": tuple(Plane.from_normal_point(bR[j][:, 2], bT[j]) for j in range(2)),
            "n_scan": len(rs), "n_stripe": len(rp), "stripes": len(data.stripe_px) > 0,
            "rejected_scan": int((prob.scan.w == 0).sum()),
            "rejected_stripe": int((prob.stripe.w == 0).sum()), "jitter": jit}
    return JointModel(axis, psi_ref, base.R, base.T, cov, noise, tuple(warn), info,
                      jitter_deg, corrections)


def _angle_steps(prob: _Problem, x: np.ndarray, loss: str, f_scale: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Generalised least-squares step of each position's own turntable angle, rig held at ``x``.

    The residuals of position ``i`` depend on its angle ``t_i`` only: one central
    difference of all angles at once gives every ``dr/dt_i``. With robust weights
    ``w``: ``H_i = sum w J^2``, ``g_i = sum w J r``; step ``-g_i / H_i`` (rad) and its
    variance ``s^2 / H_i`` (``s^2 >= 1`` the weighted residual variance).
    """
    d = prob.data
    t0 = prob.t
    h = 1e-5
    r0 = prob.normalised(x, False)
    prob.t = t0 + h
    rp = prob.normalised(x, False)
    prob.t = t0 - h
    rm = prob.normalised(x, False)
    prob.t = t0
    J = (rp - rm) / (2 * h)
    pos = np.concatenate([d.scan_pos, d.stripe_pos])
    w = _irls_weights(r0 / f_scale, loss)
    n = d.n_positions
    s2 = max(float(np.sum(w * r0 * r0)) / max(len(r0) - N_RIG - n, 1), 1.0)
    H = np.bincount(pos, w * J * J, minlength=n)
    g = np.bincount(pos, w * J * r0, minlength=n)
    ok = H > 1e-300
    step = np.where(ok, -g / np.where(ok, H, 1.0), 0.0)
    return step, np.where(ok, s2 / np.where(ok, H, 1.0), np.inf)


def angle_jitter(prob: _Problem, x: np.ndarray, t_reported: np.ndarray, loss: str,
                 f_scale: float, correlated: bool = True) -> dict:
    """Turntable angle error of every position (encoder jitter) as a random effect (beyond the paper).

    The encoder reports ``psi_i``; the turntable stood at ``psi_i + delta_i`` with
    ``delta_i ~ N(0, tau^2)``. A jitter moves all of a position's stripe centres and
    scan points coherently, which the correlated-noise model otherwise takes for
    stripe offsets (and then trusts the stripes less). With the rig held:

    1. each position's angle step ``d_i`` (:func:`_angle_steps`);
    2. the noise components re-estimated with those steps applied (the offsets
       are then the stripes' own), and the steps refined, with variances ``v_i``;
    3. ``tau^2`` maximises the marginal likelihood ``d_i ~ N(0, tau^2 + v_i)``;
       posterior ``delta_i = tau^2 / (tau^2 + v_i) d_i``, variance
       ``tau^2 v_i / (tau^2 + v_i)``. ``lr`` is the likelihood-ratio statistic of
       ``tau > 0`` against no jitter.

    ``prob.t`` may already hold corrections (``t_reported`` are the encoder's
    angles); ``prob`` is not changed (step 2 works on a copy). Angles in the
    returned dict are degrees.
    """
    import copy

    from scipy.optimize import minimize_scalar

    d1, _ = _angle_steps(prob, x, loss, f_scale)
    work = copy.copy(prob)
    work.scan, work.stripe = copy.deepcopy(prob.scan), copy.deepcopy(prob.stripe)
    work.t = prob.t + d1
    work.estimate_noise(x, correlated)
    d2, v = _angle_steps(work, x, loss, f_scale)
    dhat = (prob.t - t_reported) + d1 + d2
    ok = np.isfinite(v)
    if ok.sum() < 3:
        z = np.zeros(len(dhat))
        return {"sigma_deg": 0.0, "lr": 0.0, "correction_deg": z, "correction_sigma_deg": z}

    def nll(log_tau2: float) -> float:
        tot = np.exp(log_tau2) + v[ok]
        return 0.5 * float(np.sum(np.log(tot) + dhat[ok] ** 2 / tot))

    lo = float(np.log(max(np.median(v[ok]) * 1e-6, 1e-30)))
    hi = float(np.log(max(np.max(dhat[ok] ** 2) * 10.0, np.exp(lo) * 10.0)))
    opt = minimize_scalar(nll, bounds=(lo, hi), method="bounded")
    tau2 = float(np.exp(opt.x))
    lr = max(2.0 * (0.5 * float(np.sum(np.log(v[ok]) + dhat[ok] ** 2 / v[ok])) - float(opt.fun)), 0.0)
    shrink = np.where(ok, tau2 / (tau2 + np.where(ok, v, 1.0)), 0.0)
    return {"sigma_deg": float(np.degrees(np.sqrt(tau2))), "lr": float(lr),
            "correction_deg": np.degrees(shrink * dhat),
            "correction_sigma_deg": np.degrees(np.sqrt(np.where(ok, shrink * v, tau2)))}


@dataclass
class LMResult:
    """Outcome of :func:`irls_lm` (the fields of scipy's ``OptimizeResult`` used here)."""

    x: np.ndarray
    cost: float
    nfev: int
    status: int  # 1 converged, 0 iteration limit, -1 no decrease possible


def irls_lm(fun, jac, x0: np.ndarray, loss: str = "soft_l1", f_scale: float = 1.0,
            max_iter: int = 60, ftol: float = 1e-12) -> LMResult:
    """Robust Levenberg-Marquardt on the normal equations (iteratively reweighted).

    Minimises ``sum f_scale^2 rho((r / f_scale)^2)`` (scipy's loss definitions):
    each iteration solves ``(J^T W J + lam diag(J^T W J)) dx = -J^T W r`` with
    ``W = rho'`` at the current residuals and accepts the step when the robust
    cost drops. Equivalent to ``least_squares(..., loss=...)`` at the optimum,
    but works on the small (n, n) system: with ~1e5 residuals and ~10
    parameters it avoids the dense SVD of the Jacobian that ``method="trf"``
    repeats every iteration.
    """
    x = np.asarray(x0, dtype=float).copy()
    r = fun(x)
    cost = 0.5 * f_scale**2 * float(np.sum(_rho(r / f_scale, loss)))
    lam, nfev, status = 1e-4, 1, 0
    for _ in range(max_iter):
        J = jac(x)
        w = _irls_weights(r / f_scale, loss)
        Jw = J * w[:, None]
        H = _mm(Jw.T, J)
        g = _mm(Jw.T, r[:, None])[:, 0]
        D = np.maximum(np.diag(H), 1e-12 * max(np.diag(H).max(), 1e-300))
        while True:
            try:
                step = -np.linalg.solve(H + lam * np.diag(D), g)
            except np.linalg.LinAlgError:
                step = -np.linalg.lstsq(H + lam * np.diag(D), g, rcond=None)[0]
            rn = fun(x + step)
            nfev += 1
            cn = 0.5 * f_scale**2 * float(np.sum(_rho(rn / f_scale, loss)))
            if np.isfinite(cn) and cn <= cost:
                break
            lam *= 10.0
            if lam > 1e10:
                return LMResult(x, cost, nfev, -1 if status == 0 else status)
        x = x + step
        r = rn
        done = cost - cn <= ftol * max(cost, 1e-300)
        cost = cn
        lam = max(lam / 10.0, 1e-9)
        if done:
            status = 1
            break
    return LMResult(x, cost, nfev, status)


def _rho(z: np.ndarray, loss: str) -> np.ndarray:
    """Robust loss of normalised residuals ``z`` (scipy's definitions, per unit f_scale)."""
    s = z * z
    if loss == "linear":
        return s
    if loss == "soft_l1":
        return 2 * (np.sqrt(1 + s) - 1)
    if loss == "huber":
        return np.where(s <= 1, s, 2 * np.sqrt(s) - 1)
    if loss == "cauchy":
        return np.log1p(s)
    if loss == "arctan":
        return np.arctan(s)
    raise ValueError(f"unknown loss {loss!r}")


def _irls_weights(z: np.ndarray, loss: str) -> np.ndarray:
    """rho'(s) at ``s = z^2``: the IRLS weight of each normalised residual."""
    s = z * z
    if loss == "linear":
        return np.ones_like(s)
    if loss == "soft_l1":
        return 1 / np.sqrt(1 + s)
    if loss == "huber":
        return np.where(s <= 1, 1.0, 1 / np.sqrt(np.maximum(s, 1e-300)))
    if loss == "cauchy":
        return 1 / (1 + s)
    if loss == "arctan":
        return 1 / (1 + s * s)
    raise ValueError(f"unknown loss {loss!r}")


def _jacobian(prob: _Problem, n_board: bool) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference Jacobian of the normalised residuals (scan, stripe, corners) wrt
    rig (10) and board (12) parameters, at x = 0. Returns (residuals, J)."""
    n = N_RIG + 2 * N_BOARD
    x0 = np.zeros(n)
    return prob.normalised(x0, True), prob.jacobian(x0, True)


def _covariance(prob: _Problem, fit_planes: bool, loss: str, f_scale: float
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Covariance (10, 10) of the rig parameters, the unobservable directions (10, q), s^2."""
    r, J = _jacobian(prob, True)
    n_main = len(r) - len(prob.corner_residuals(prob.base.board_R, prob.base.board_T))
    w = _irls_weights(r / f_scale, loss)
    Jw = J * np.sqrt(w)[:, None]
    has_corners = prob.data.corners_px is not None and prob.data.object_points is not None
    m_used = len(r) if (fit_planes or has_corners) else n_main
    n_used = N_RIG + (2 * N_BOARD if fit_planes else 0)
    s2 = float(np.sum(w * r * r) / max(m_used - n_used, 1))
    s2 = max(s2, 1.0)  # the noise scales are estimated: never shrink below them
    # corner errors of chessboard detectors are correlated over the board: the pose absorbs
    # their low-order part, so the residual scale understates the plane error; the planes'
    # information uses at least ``corner_floor_px`` per coordinate
    Jw[n_main:] *= prob.sigma_corner / max(prob.sigma_corner, prob.corner_floor_px)
    if fit_planes:
        H = _mm(Jw.T, Jw)
        C, null = _inverse(H)
        return s2 * C[:N_RIG, :N_RIG], null[:N_RIG], s2
    # planes held fixed: rig covariance from scans + stripes, plus the planes' own
    # uncertainty from the corners propagated ("consider" covariance)
    Jx, Jb = Jw[:n_main, :N_RIG], Jw[:n_main, N_RIG:]
    Hx_inv, null = _inverse(_mm(Jx.T, Jx))
    C = Hx_inv
    if has_corners:
        Jc = Jw[n_main:, N_RIG:]
        Pb, _ = _inverse(_mm(Jc.T, Jc))
        A = Hx_inv @ _mm(Jx.T, Jb)
        C = C + A @ Pb @ A.T
    return s2 * C, null, s2


def _inverse(H: np.ndarray, rcond: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-inverse of a symmetric information matrix, column-scaled, and its null directions."""
    d = np.sqrt(np.maximum(np.diag(H), 1e-300))
    Hs = H / np.outer(d, d)
    w, V = np.linalg.eigh(Hs)
    small = w < rcond * w.max()
    inv = np.where(small, 0.0, 1 / np.where(small, 1.0, w))
    C = (V * inv) @ V.T / np.outer(d, d)
    null = V[:, small] / d[:, None]
    if null.shape[1]:
        null = null / np.linalg.norm(null, axis=0)
    return C, null


def joint_warnings(data: JointData, model: JointModel, null: np.ndarray | None = None) -> list[str]:
    """Warnings for weak setups (few positions, short sweep, axis ~ scan-plane normal, ...)."""
    out = []
    n = data.n_positions
    span = float(np.ptp(data.psi_deg))
    if n < 5:
        out.append(f"only {n} positions: the joint fit has little redundancy; capture at least 5")
    if span < 5.0:
        out.append(f"turntable positions span only {span:.2f} deg: the axis is poorly determined; "
                   "sweep at least ~5-10 deg")
    z = model.R_ref[:, 2]
    ang = np.degrees(np.arccos(min(abs(float(z @ model.axis.direction)), 1.0)))
    if ang < 10.0:
        out.append(f"the turntable axis is only {ang:.1f} deg from the scan-plane normal: turning "
                   "barely moves the scan plane, the axis is weakly determined")
    for b in range(2):
        cnt = np.bincount(data.scan_pos[data.scan_board == b], minlength=n)
        bad = np.flatnonzero(cnt < MIN_POINTS_PER_BOARD)
        if len(bad):
            out.append(f"board {b} has fewer than {MIN_POINTS_PER_BOARD} scan returns at "
                       f"{len(bad)} position(s) (indices {data.indices[bad].tolist()[:10]}): "
                       "only one board hit there")
        if len(data.stripe_px):
            cs = np.bincount(data.stripe_pos[data.stripe_board == b], minlength=n)
            bad = np.flatnonzero(cs < MIN_POINTS_PER_BOARD)
            if len(bad):
                out.append(f"board {b} shows fewer than {MIN_POINTS_PER_BOARD} stripe centres at "
                           f"{len(bad)} position(s) (indices {data.indices[bad].tolist()[:10]})")
    if null is not None and null.shape[1]:
        out.append(f"{null.shape[1]} combination(s) of the rig parameters are not determined by the "
                   "data (rank-deficient Jacobian); their sigmas are reported as inf")
    return out


def fit_joint(result, *, fit_planes: bool = False, loss: str = "soft_l1", stripes: bool = True,
              correlated: bool = True, board_poses: str = "pnp", psi_ref_deg: float | None = None,
              corner_floor_px: float = CORNER_FLOOR_PX, jitter: bool = True) -> JointModel:
    """Joint maximum-likelihood fit of the rig to all stripe pixels and scan points (beyond the paper).

    Parameters
    ----------
    result : lidarcal.pipeline.CalibrationResult
        Section 1 at every position (stripe centres, scan segments, single-shot
        poses with their segment <-> board assignment) and the section-2 models
        (``rigid_model``, ``paper_model``), used as starting points.
    fit_planes : bool
        Also refine both board poses (started from ``board_poses``); the
        chessboard corners' reprojection residuals then enter the fit.
    loss : str
        Robust loss (scipy's names: "soft_l1", "huber", "cauchy", "arctan",
        "linear"); residuals are in noise sigmas, the loss scale is ``F_SCALE``.
    stripes : bool
        False: scan points only (the Zhang-Pless style point-on-plane
        calibration with the turntable model). With one V-board the scan alone
        cannot see the LiDAR slide along the hinge: that direction stays at the
        start and is reported with infinite sigma (and a warning).
    correlated : bool
        Model per-segment / per-stripe correlated errors (see the module doc);
        False: white noise only (optimistic covariance on real stripe data).
    board_poses : {"pnp", "homography"}
        Which board poses (planes) to hold, or to start from with ``fit_planes``:
        ``cv2.solvePnP`` (the corners' maximum-likelihood pose, default) or the
        paper's homography (eqs. 2-3).
    psi_ref_deg : float, optional
        Reference angle of ``pose_ref`` (default: the mean psi).
    corner_floor_px : float
        Least per-coordinate corner error assumed for the planes' uncertainty.
    jitter : bool
        Estimate the turntable's angle jitter and correct each position's angle
        when the data show one (:func:`angle_jitter`).

    Returns
    -------
    JointModel
        ``sigma(psi)`` gives 1-sigma uncertainties, ``warnings`` weak-setup warnings,
        ``noise`` the estimated noise scales, ``info`` residuals and solver details.
    """
    data = joint_data(result, board_poses)
    if not stripes:
        data = data.without_stripes()
    return fit_joint_data(data, [result.rigid_model, result.paper_model], fit_planes=fit_planes,
                          loss=loss, psi_ref_deg=psi_ref_deg, correlated=correlated,
                          corner_floor_px=corner_floor_px, jitter=jitter)
