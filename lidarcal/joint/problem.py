"""Residuals and Jacobians of the joint fit (scan points and stripe centres against the planes)."""

from __future__ import annotations

import copy
import weakref

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import skew, so3_left_jacobian, unit
from ..pixel_jacobian import pixel_jacobian_forms, quadratic_form_coefficients
from .data import JointData
from .noise import _Groups, _rows_dot
from .params import (
    _STEPS,
    N_BOARD,
    N_RANGING,
    N_RIG,
    REJECT_SIGMAS,
    _Base,
    _boards,
    _mm,
    _poses,
    _rig,
    _robust_sigma,
)


class _Problem:
    """Residual blocks of the joint fit.

    Parameter vectors are ``[rig 10 | boards 12 (optional) | ranging n_ranging]``:
    the last ``n_ranging`` entries (0, 1: range offset, 2: and the dark-square
    extra, mm, :mod:`lidarcal.ranging`) are steps from ``base.ranging``. The
    ranging prior enters as ``n_ranging`` pseudo-residuals after the stripes.
    """

    def __init__(self, data: JointData, base: _Base, psi_ref_deg: float, n_ranging: int = 0,
                 prior: tuple[np.ndarray, np.ndarray] | None = None):
        self.data = data
        self.base = base
        self.n_ranging = int(n_ranging)
        mean, sig = prior if prior is not None else (np.zeros(N_RANGING), np.full(N_RANGING, np.inf))
        self.prior_mean, self.prior_sigma = np.asarray(mean, float), np.asarray(sig, float)
        rho = np.linalg.norm(data.scan_xy, axis=1)
        self.scan_u = data.scan_xy / np.where(rho > 0, rho, 1.0)[:, None]  # beam directions
        self.dark = (np.zeros(len(data.scan_xy)) if data.scan_dark is None
                     else np.asarray(data.scan_dark, float))
        self.t = np.radians(data.psi_deg - psi_ref_deg)
        self.scale_px = np.ones(len(data.stripe_px))
        self.scale_depth: np.ndarray | None = None  # depths (mm) scale_px holds at
        self.scan, self.stripe = _groups(data)
        self.sigma_corner = 1.0
        self.corner_floor_px = 0.0
        self.sandwich: np.ndarray | None = None  # cluster-robust covariance (solver._covariance)
        self.frozen: tuple[int, ...] = ()  # ranging terms held at base.ranging (zero columns)
        self._blocks_memo: tuple | None = None  # (key, (scan, stripe residuals)) of blocks()
        # the board poses' prior (lidarcal.joint.planes_prior.PlanePrior): 12 pseudo-residuals
        # after the ranging prior when the boards are parameters; None: no such rows
        self.board_prior = None
        # planes held: the board poses' covariance (12, 12) for the consider term when it is
        # more than the corners' (the intrinsics' uncertainty of a camera from photos,
        # lidarcal.joint.planes_prior); None: from the corner rows
        self.board_cov: np.ndarray | None = None

    def split(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rig + boards part of ``x``, ranging terms (2,) in mm)."""
        m = len(x) - self.n_ranging
        rv = self.base.ranging.copy()
        rv[:self.n_ranging] += x[m:]
        return x[:m], rv

    def classify(self, x: np.ndarray) -> None:
        """Which returns hit a black square (:func:`lidarcal.ranging.dark_returns`), with the
        LiDAR poses and board poses at ``x``; held when the data give ``scan_dark``."""
        d = self.data
        if d.scan_dark is not None or not d.can_see_dark:
            return
        from ..ranging import dark_share

        xr, _ = self.split(x)
        R, T = _poses(*_rig(xr, self.base), self.t)
        bR, bT = _boards(xr, self.base)
        # per group (position i, board b): a return along u = (u_x, u_y) in the LiDAR plane
        # leaves T_i along D u (D = [R_x R_y]) and cuts the board's plane (eq. 3) at
        # t = e / (a . u), a = D^T n_b, e = n_b . (T_b - T_i); in board coordinates (the board
        # frame's x, y) the hit is c + t (A u), A = R_b[:, :2]^T D, c = R_b[:, :2]^T (T_i - T_b)
        brd = np.tile([0, 1], len(R))
        Rg, Tg = np.repeat(R, 2, axis=0), np.repeat(T, 2, axis=0)
        D, Bxy, n = Rg[:, :, :2], bR[brd][:, :, :2], bR[brd][:, :, 2]
        a = np.einsum("gk,gkj->gj", n, D)  # (G, 2)
        e = np.einsum("gk,gk->g", n, bT[brd] - Tg)
        A = np.einsum("gki,gkj->gij", Bxy, D)  # (G, 2, 2)
        c = np.einsum("gki,gk->gi", Bxy, Tg - bT[brd])  # (G, 2)
        sp, ux, uy = self.scan.spread, self.scan_u[:, 0], self.scan_u[:, 1]
        den = sp(a[:, 0]) * ux + sp(a[:, 1]) * uy
        ok = np.abs(den) > 1e-12
        t = sp(e) / np.where(ok, den, 1.0)
        bx = sp(c[:, 0]) + t * (sp(A[:, 0, 0]) * ux + sp(A[:, 0, 1]) * uy)
        by = sp(c[:, 1]) + t * (sp(A[:, 1, 0]) * ux + sp(A[:, 1, 1]) * uy)
        dark = np.zeros(len(ux))
        for b in range(2):
            m = (d.scan_board == b) & ok
            dark[m] = dark_share(bx[m], by[m], d.board_spec, d.black_parity[b])
        self.dark = dark

    def prior_residuals(self, x: np.ndarray) -> np.ndarray:
        """``(term - prior mean) / prior sigma`` of the estimated ranging terms."""
        if self.n_ranging == 0:
            return np.zeros(0)
        _, rv = self.split(x)
        k = self.n_ranging
        return (rv[:k] - self.prior_mean[:k]) / self.prior_sigma[:k]

    def estimate_noise(self, x: np.ndarray, correlated: bool) -> None:
        """Noise scales of every residual kind from the residuals at ``x`` (:meth:`_Groups.estimate`);
        without ``correlated`` the per-segment / per-stripe components are zero."""
        rs, rp, rc = self.blocks(x)
        self.scan.estimate(rs, 1e-9 * max(float(np.abs(self.data.board_T).max()), 1.0),
                           correlated)
        self.stripe.estimate(rp, 1e-6, correlated)
        self.sigma_corner = _robust_sigma(rc, 1e-6)

    def reject(self, x: np.ndarray) -> None:
        """Drop residuals beyond ``REJECT_SIGMAS`` (whitened) from the fit: a bounded loss
        still lets gross outliers pull with constant force; cutting them restores the
        Gaussian-noise optimum (for Gaussian data nothing is cut: P(|z| > 5) ~ 6e-7)."""
        rs, rp, _ = self.blocks(x, corners=False)
        for grp, r in ((self.scan, rs), (self.stripe, rp)):
            keep = np.ones(len(r), bool)
            grp.set_mask(keep)
            for _ in range(2):  # the kept set changes the group moments: settle it
                new = np.abs(grp.whiten(r)) <= REJECT_SIGMAS
                if np.array_equal(new, keep):  # settled: another pass would repeat this one
                    break
                keep = new
                grp.set_mask(keep)

    def blocks(self, x: np.ndarray, corners: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Raw residuals: scan (mm), stripe (px), corners (px, x and y interleaved).

        The scan and stripe residuals of the last call are kept: the noise estimate and the
        rejection ask for the same ``x`` one after the other."""
        d = self.data
        key = (np.asarray(x, float).tobytes(), self.t.tobytes(), self.base, self.scale_px,
               self.dark)
        x, rv = self.split(x)
        bR, bT = _boards(x, self.base)
        memo = self._blocks_memo
        if memo is not None and memo[0][:2] == key[:2] and all(
                a is b for a, b in zip(memo[0][2:], key[2:])):
            r_corner = self.corner_residuals(bR, bT) if corners else np.zeros(0)
            return memo[1][0], memo[1][1], r_corner
        k, a, R_ref, T_ref = _rig(x, self.base)
        R, T = _poses(k, a, R_ref, T_ref, self.t)
        n = bR[:, :, 2]
        dd = np.einsum("ij,ij->i", n, bT)
        # per (position i, board b), group 2 i + b: the board's plane in the LiDAR frame
        pos, brd = np.repeat(np.arange(len(R)), 2), np.tile([0, 1], len(R))
        nR = np.einsum("gi,gij->gj", n[brd], R[pos])  # n . R_x, n . R_y, n . R_z
        # scan points (ranges corrected by the ranging model) in the camera frame, eq. (28),
        # against their board's plane, eq. (3): x (n . R_x) + y (n . R_y) + n . T - d
        xy = self.scan_xy(rv)
        sp = self.scan.spread
        r_scan = (xy[:, 0] * sp(nR[:, 0]) + xy[:, 1] * sp(nR[:, 1])
                  + sp(np.einsum("gi,gi->g", n[brd], T[pos]) - dd[brd]))
        # stripe centres back-projected onto their board (eq. 5), against the laser plane:
        # (P - T) . z
        P = _stripe_points(d, bR, bT, cache=not np.any(x[N_RIG:]))["P"]
        z = R[:, :, 2][pos]
        sp = self.stripe.spread
        r_stripe = ((np.einsum("ij,ij->i", P, sp(z)) - sp(np.einsum("gi,gi->g", T[pos], z)))
                    * self.stripe_scale(P))
        r_corner = self.corner_residuals(bR, bT) if corners else np.zeros(0)
        self._blocks_memo = (key, (r_scan, r_stripe))
        return r_scan, r_stripe, r_corner

    def scan_xy(self, rv: np.ndarray) -> np.ndarray:
        """Scan points with ranges corrected: ``(rho - offset - dark_extra * dark) u``."""
        if not np.any(rv):
            return self.data.scan_xy
        return self.data.scan_xy - (rv[0] + rv[1] * self.dark)[:, None] * self.scan_u

    def pose_derivatives(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """R (N, 3, 3), T (N, 3) at the rig parameters ``x[:10]`` and d[R_x, R_y, R_z, T] /
        d rig (N, 12, 10): the pose columns at every position (:func:`pose_jacobian`)."""
        return pose_jacobian(x[:N_RIG], self.base, self.t)

    def jacobian(self, x: np.ndarray, use_corners: bool) -> np.ndarray:
        """Jacobian of :meth:`normalised` wrt the full parameters (rig 10 + boards 12).

        Chain rule: the residuals are linear in each position's pose columns and
        in each board's plane (normal, d), which depend on the parameters through
        small functions differentiated numerically (central differences).
        Corners: central differences.
        """
        d = self.data
        n_par = len(x)
        x, rv = self.split(x)
        n_main = len(x)  # rig (+ boards); the ranging columns follow
        R, T, G = self.pose_derivatives(x)
        bR, bT = _boards(x, self.base)
        nb = bR[:, :, 2]
        db = np.einsum("ij,ij->i", nb, bT)
        Gb = self.plane_derivatives(x) if n_main > N_RIG else np.zeros((2, 4, N_BOARD))
        blocks = []
        # scan: r = n_b . (R_x x + R_y y + T) - d_b, (x, y) = (rho - offset - extra dark) u
        p, b = d.scan_pos, d.scan_board
        xy = self.scan_xy(rv)
        xs, ys = xy[:, :1], xy[:, 1:]
        n = nb[b]
        dr = np.concatenate([n * xs, n * ys, np.zeros((len(p), 3)), n], 1)  # wrt [Rx Ry Rz T]
        Js = np.zeros((len(p), n_par))
        Js[:, :N_RIG] = _rows_times(dr, G, p)
        if self.n_ranging:
            u = self.scan_u
            du = -np.einsum("ij,ij->i", n, R[p, :, 0] * u[:, :1] + R[p, :, 1] * u[:, 1:])
            Js[:, n_main] = du
            if self.n_ranging > 1:
                Js[:, n_main + 1] = du * self.dark
        if n_main > N_RIG:
            X = R[p, :, 0] * xs + R[p, :, 1] * ys + T[p]
            drb = np.concatenate([X, -np.ones((len(p), 1))], 1)  # wrt [n, d]
            for bb in range(2):
                m = b == bb
                c = N_RIG + bb * N_BOARD
                Js[m, c:c + N_BOARD] = _mm(drb[m], Gb[bb])
        blocks.append(self.scan.whiten_columns(Js) * self.scan.w[:, None])
        # stripe: r = s (P - T) . z,  P = ray d_b / (ray . n_b)
        p, b = d.stripe_pos, d.stripe_board
        ray = d.stripe_rays
        rn = np.einsum("ij,ij->i", ray, nb[b])[:, None]
        P = ray * (db[b][:, None] / rn)
        s = self.stripe_scale(P)[:, None]
        z = R[p, :, 2]
        dr = np.concatenate([np.zeros((len(p), 6)), (P - T[p]) * s, -z * s], 1)
        Jp = np.zeros((len(p), n_par))
        Jp[:, :N_RIG] = _rows_times(dr, G, p)
        if n_main > N_RIG:
            drb = self.stripe_plane_rows(rn, db[b][:, None], z, T[p])
            for bb in range(2):
                m = b == bb
                c = N_RIG + bb * N_BOARD
                Jp[m, c:c + N_BOARD] = _mm(drb[m], Gb[bb])
        blocks.append(self.stripe.whiten_columns(Jp) * self.stripe.w[:, None])
        if self.n_ranging:  # prior pseudo-residuals
            Jr = np.zeros((self.n_ranging, n_par))
            Jr[:, n_main:] = np.diag(1 / self.prior_sigma[:self.n_ranging])
            blocks.append(Jr)
        for j in self.frozen:  # held terms: no column (the step leaves them)
            for blk in blocks:
                blk[:, n_main + j] = 0.0
        if self.board_prior is not None and n_main > N_RIG:
            blocks.append(self._board_prior_jacobian(x, n_par))
        if use_corners:
            Jc = np.zeros((len(self.corner_residuals(bR, bT)), n_par))
            if n_main > N_RIG:
                Jc[:, N_RIG:n_main] = self.corner_jacobian(x)
            blocks.append(Jc / self.sigma_corner)
        return np.vstack(blocks)

    def plane_derivatives(self, x: np.ndarray) -> np.ndarray:
        """d (normal, d) of both boards / d board parameters ``x[10:22]`` (2, 4, 6), analytic:
        with ``R = Exp(w) R0`` (:func:`lidarcal.joint.params._boards`) the normal ``n = R e_z``
        turns as ``dn/dw = -[n]x J_l(w)`` (SO(3)'s left Jacobian,
        :func:`lidarcal.geometry.so3_left_jacobian`) and ``d = n . T`` (eq. 3) gives
        ``dd/dw = T^T dn/dw``, ``dd/dT = n``."""
        x = np.asarray(x[:N_RIG + 2 * N_BOARD], float)
        bR, bT = _boards(x, self.base)
        Gb = np.zeros((2, 4, N_BOARD))
        for b in range(2):
            w = x[N_RIG + b * N_BOARD:N_RIG + b * N_BOARD + 3] if len(x) > N_RIG else np.zeros(3)
            dn = -skew(bR[b][:, 2]) @ so3_left_jacobian(w)
            Gb[b, :3, :3] = dn
            Gb[b, 3, :3] = bT[b] @ dn
            Gb[b, 3, 3:] = bR[b][:, 2]
        return Gb

    def corner_jacobian(self, x: np.ndarray) -> np.ndarray:
        """Corner reprojection residuals (px) / d board parameters ``x[10:22]`` (m, 12),
        analytic: ``cv2.projectPoints``' Jacobian wrt its translation is d pixel / d X of the
        corner ``X = R p + T`` (eq. 1), so d pixel / d T is that and, with ``R = Exp(w) R0``,
        ``dX/dw = -[R p]x J_l(w)`` (SO(3)'s left Jacobian)."""
        d = self.data
        x = np.asarray(x[:N_RIG + 2 * N_BOARD], float)
        bR, bT = _boards(x, self.base)
        if d.corners_px is None or d.object_points is None:
            return np.zeros((0, 2 * N_BOARD))
        K, dist = np.asarray(d.camera.K, float), np.asarray(d.camera.dist, float)
        p = d.object_points.reshape(-1, 3)
        out = []
        for b in range(2):
            w = x[N_RIG + b * N_BOARD:N_RIG + b * N_BOARD + 3] if len(x) > N_RIG else np.zeros(3)
            _, J = cv2.projectPoints(p.reshape(-1, 1, 3), cv2.Rodrigues(bR[b])[0], bT[b], K, dist)
            Jt = J[:, 3:6].reshape(-1, 2, 3)  # d pixel / d X, per corner
            dXdw = -skew(p @ bR[b].T) @ so3_left_jacobian(w)  # (m, 3, 3)
            blk = np.zeros((len(p), 2, 2 * N_BOARD))
            blk[:, :, b * N_BOARD:b * N_BOARD + 3] = Jt @ dXdw
            blk[:, :, b * N_BOARD + 3:(b + 1) * N_BOARD] = Jt
            out.append(blk.reshape(-1, 2 * N_BOARD))
        return np.concatenate(out)

    def corner_residuals(self, bR: np.ndarray, bT: np.ndarray, boards: tuple[int, ...] = (0, 1)
                         ) -> np.ndarray:
        """Reprojection residuals (px, x and y interleaved) of the corners of ``boards`` with
        the board poses ``bR``, ``bT`` (eq. 1, ``cv2.projectPoints``)."""
        d = self.data
        if d.corners_px is None or d.object_points is None:
            return np.zeros(0)
        out = []
        K, dist = np.asarray(d.camera.K, float), np.asarray(d.camera.dist, float)
        for j in boards:
            rvec = cv2.Rodrigues(bR[j])[0]
            proj, _ = cv2.projectPoints(d.object_points.reshape(-1, 1, 3), rvec, bT[j], K, dist)
            out.append((proj.reshape(-1, 2) - d.corners_px[j]).ravel())
        return np.concatenate(out)

    def normalised(self, x: np.ndarray, use_corners: bool) -> np.ndarray:
        r = self.blocks(x, corners=use_corners)
        parts = [self.scan.whiten(r[0]) * self.scan.w, self.stripe.whiten(r[1]) * self.stripe.w,
                 self.prior_residuals(x), self.board_prior_residuals(x)]
        if use_corners:
            parts.append(r[2] / self.sigma_corner)
        return np.concatenate(parts)

    def board_prior_residuals(self, x: np.ndarray) -> np.ndarray:
        """The board poses' whitened prior residuals (12,) when the boards are parameters and
        ``board_prior`` is set (:mod:`lidarcal.joint.planes_prior`), else none."""
        xm, _ = self.split(x)
        if self.board_prior is None or len(xm) <= N_RIG:
            return np.zeros(0)
        return self.board_prior.residuals(*_boards(xm, self.base))

    def _board_prior_jacobian(self, xm: np.ndarray, n_par: int) -> np.ndarray:
        """Rows (12, n_par) of :meth:`board_prior_residuals` (central differences)."""
        J = np.zeros((2 * N_BOARD, n_par))
        for i in range(N_RIG, N_RIG + 2 * N_BOARD):
            dx = np.zeros(len(xm))
            dx[i] = _STEPS[i]
            J[:, i] = (self.board_prior.residuals(*_boards(xm + dx, self.base))
                       - self.board_prior.residuals(*_boards(xm - dx, self.base))) / (2 * _STEPS[i])
        return J

    def stripe_plane_rows(self, rn: np.ndarray, db: np.ndarray, z: np.ndarray, Tp: np.ndarray
                          ) -> np.ndarray:
        """d stripe residual / d (normal, d) of its board (S, 4), eq. (5) back-projection:
        ``rn`` = ray . n and ``db`` = d of the board (S, 1), ``z`` the LiDAR's z axis and
        ``Tp`` its centre at each centre's position (S, 3).

        With the scale held (``scale_depth`` None) ``r = s (ray d / rn - T) . z``; with it
        going as 1 / depth (:meth:`stripe_scale`) ``r = (s0 Z0 / ray_z) (ray . z - (T . z)
        rn / d)``, in pixels."""
        ray = self.data.stripe_rays
        if self.scale_depth is None:
            s = self.scale_px[:, None]
            zr = np.einsum("ij,ij->i", z, ray)[:, None]
            return np.concatenate([-s * zr * db * ray / rn**2, s * zr / rn], 1)
        s0 = (self.scale_px * self.scale_depth / ray[:, 2])[:, None]
        tz = np.einsum("ij,ij->i", Tp, z)[:, None]
        return np.concatenate([-s0 * tz * ray / db, s0 * tz * rn / db**2], 1)

    def stripe_scale(self, P: np.ndarray) -> np.ndarray:
        """Pixels per mm of each stripe centre's laser offset with its board point at ``P``:
        ``scale_px`` scaled by the depth it was computed at over ``P``'s (an image scale goes as
        1 / depth), so a stripe residual stays in pixels when the planes move (scaling the
        whole scene about the camera centre leaves every stripe residual as it is)."""
        if self.scale_depth is None:
            return self.scale_px
        return self.scale_px * self.scale_depth / P[:, 2]

    def set_stripe_scale(self, x: np.ndarray) -> None:
        """Pixels of stripe displacement (perpendicular to the imaged stripe) per mm of laser offset."""
        d = self.data
        if len(d.stripe_px) == 0:
            return
        x, _ = self.split(x)
        k, a, R_ref, T_ref = _rig(x, self.base)
        R, _ = _poses(k, a, R_ref, T_ref, self.t)
        bR, bT = _boards(x, self.base)
        ent = _stripe_points(d, bR, bT, jacobian=True, cache=not np.any(x[N_RIG:]))
        # per (position, board): the stripe's direction on the board and the direction
        # perpendicular to it in the board
        nb = bR[:, :, 2]
        n = nb[np.tile([0, 1], len(self.t))]
        zL = R[np.repeat(np.arange(len(self.t)), 2), :, 2]
        line = unit(np.cross(n, zL))  # stripe direction on the board
        u = unit(np.cross(n, line))  # in the board, perpendicular to the stripe
        # px per mm along u: the image of u (pu = J u, J = d pixel / d P) perpendicular to
        # the imaged stripe (pl = J line), |pu x pl| / |pl|, by the Binet-Cauchy identity from
        # each centre's forms and per-group coefficients (:mod:`lidarcal.pixel_jacobian`)
        coef = np.zeros((len(n), 9, 2))
        coef[:, :3, 0] = np.cross(u, line)
        coef[:, 3:, 1] = quadratic_form_coefficients(line)
        cross, pl2 = _rows_dot(ent["forms"], coef, self.stripe).T
        if np.any(pl2 <= 0):
            raise ValueError("a stripe images to a point: no stripe direction in the image")
        perp = np.abs(cross) / np.sqrt(pl2)
        du = np.abs(np.einsum("ij,ij->i", zL, u))  # mm of laser offset per mm along u
        self.scale_px = perp / self.stripe.spread(np.maximum(du, 1e-9))
        self.scale_depth = ent["P"][:, 2].copy()  # the depths it holds at (stripe_scale)


_STRIPE_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_GROUPS_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _groups(data: JointData) -> tuple[_Groups, _Groups]:
    """Fresh noise models of the scan and the stripe residuals (:class:`_Groups`, white unit
    noise, all kept): shallow copies of ones built once per :class:`JointData` (a
    :class:`_Groups` replaces its arrays, never changes them in place)."""
    proto = _GROUPS_CACHE.get(data)
    if proto is None:
        n = data.n_positions
        proto = _GROUPS_CACHE[data] = (
            _Groups(data.scan_pos, data.scan_board, data.scan_xy, n),
            _Groups(data.stripe_pos, data.stripe_board, data.stripe_px, n))
    return copy.copy(proto[0]), copy.copy(proto[1])


def _stripe_points(data: JointData, bR: np.ndarray, bT: np.ndarray, jacobian: bool = False,
                   cache: bool = True) -> dict:
    """Stripe centres back-projected onto their boards (eq. 5), ``P`` (S, 3), and with
    ``jacobian`` the forms of d pixel / d P through the lens model, ``forms`` (S, 9)
    (:func:`lidarcal.pixel_jacobian.pixel_jacobian_forms`).

    Both depend on the board planes only: with the planes held (``cache``) they are
    computed once per :class:`JointData` and board poses.
    """
    key = (bR.tobytes(), bT.tobytes())
    per = _STRIPE_CACHE.setdefault(data, {}) if cache else {}
    ent = per.get(key)
    if ent is None:
        if len(per) >= 4:
            per.clear()
        b, ray = data.stripe_board, data.stripe_rays
        n = bR[:, :, 2]
        dd = np.einsum("ij,ij->i", n, bT)
        ent = per[key] = {"P": ray * (dd[b] / np.einsum("ij,ij->i", ray, n[b]))[:, None]}
    if jacobian and "forms" not in ent:
        ent["forms"] = pixel_jacobian_forms(data.camera, ent["P"])
    return ent


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


def pose_jacobian(x: np.ndarray, base: _Base, t: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rigid model's poses at angles ``t`` and their derivatives wrt the rig parameters
    (analytic): R (N, 3, 3), T (N, 3), G (N, 12, 10) with rows ``[R_x, R_y, R_z, T]``.

    ``R = Q(t, k) R_ref``, ``T = a + Q (T_ref - a)`` with Rodrigues'
    ``Q = cos t I + sin t [k]x + (1 - cos t) k k^T`` (:func:`lidarcal.joint.params._poses`):

    * direction steps ``x[0:2]``: ``k = unit(k0 + x B)``, ``dk = (I - k k^T) B_i / |k0 + x B|``,
      ``dQ = sin t [dk]x + (1 - cos t)(dk k^T + k dk^T)``; ``dR = dQ R_ref``,
      ``dT = dQ (T_ref - a)``;
    * axis point steps ``x[2:4]``: ``dT = (I - Q) B_i``;
    * reference rotation vector ``w = x[4:7]`` (``R_ref = Exp(w) R0``):
      ``dExp(w)/dw_j = [J_l(w) e_j]x Exp(w)`` with the left Jacobian of SO(3)
      ``J_l = I + (1 - cos th)/th^2 [w]x + (th - sin th)/th^3 [w]x^2``;
      ``dR = Q [J_l e_j]x R_ref``;
    * reference centre steps ``x[7:10]``: ``dT = Q e_j``.
    """
    x = np.asarray(x, float)
    k, a, R_ref, T_ref = _rig(x, base)
    R, T = _poses(k, a, R_ref, T_ref, t)
    n = len(t)
    c, s = np.cos(t)[:, None, None], np.sin(t)[:, None, None]
    kx = skew(k)
    Q = c * np.eye(3) + s * kx + (1 - c) * np.outer(k, k)
    dR = np.zeros((n, N_RIG, 3, 3))
    dT = np.zeros((n, N_RIG, 3))
    # axis direction
    k_raw = base.k + x[0:2] @ base.B
    dk = (base.B - np.outer(base.B @ k, k)) / np.linalg.norm(k_raw)  # (2, 3)
    dQ = (s[:, None] * skew(dk)[None]
          + (1 - c)[:, None] * (dk[:, :, None] * k[None, None, :] + k[None, :, None] * dk[:, None, :])[None])
    dR[:, 0:2] = dQ @ R_ref
    dT[:, 0:2] = dQ @ (T_ref - a)
    # axis point
    dT[:, 2:4] = np.einsum("ij,nkj->nik", base.B, np.eye(3) - Q)
    # reference rotation
    w = x[4:7]
    Jl = so3_left_jacobian(w)
    dR[:, 4:7] = Q[:, None] @ (skew(Jl.T) @ R_ref)[None]
    # reference centre
    dT[:, 7:10] = Q.transpose(0, 2, 1)[:, :, :]
    G = np.concatenate([dR.transpose(0, 1, 3, 2).reshape(n, N_RIG, 9), dT], 2).transpose(0, 2, 1)
    return R, T, np.ascontiguousarray(G)


def start_step(base: _Base, start: _Base) -> np.ndarray | None:
    """Rig parameters (10) at which ``base``'s parametrisation gives the rig of ``start``
    (another start of the fit), or None when its axis direction is more than 60 deg off
    (``k = unit(k0 + x B)`` cannot reach it well).

    Direction: ``k0 + x B`` parallel to ``k``; axis point: where ``start``'s axis meets the
    plane through ``base.a`` perpendicular to ``k0``; rotation vector of ``R R0^T``; centre
    step ``T - T0``.
    """
    c = float(start.k @ base.k)
    if c < 0.5:
        return None
    foot = start.a + start.k * float((base.a - start.a) @ base.k) / c
    w = Rotation.from_matrix(start.R @ base.R.T).as_rotvec()
    return np.concatenate([(start.k / c) @ base.B.T, (foot - base.a) @ base.B.T, w,
                           start.T - base.T])
