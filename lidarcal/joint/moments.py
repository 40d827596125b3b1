"""The joint fit on per-segment second moments: O(positions) per iteration (issue 15).

Every residual of the joint fit is linear in a short homogeneous vector of its
observation, with coefficients that depend on the parameters only through its
position and board:

* scan return (eq. 28 against eq. 3), ``h = [x, y, u_x, u_y, dark u_x, dark u_y, 1]``,
  ``c = [a, b, -offset a, -offset b, -extra a, -extra b, n.T - d]`` with
  ``a = n . R_x``, ``b = n . R_y`` (``n``, ``d``: the board's plane; ``R``, ``T``:
  the LiDAR pose at that position; ``u`` the beam direction; ranging terms of
  :mod:`lidarcal.ranging`);
* stripe centre back-projected onto its board (eq. 5) against the laser plane,
  ``h = [s P, s]``, ``c = [z, -T . z]`` (``P`` the point on the board, fixed while the
  planes are held; ``s`` the pixel scale; ``z`` the LiDAR's z axis).

The generalised-least-squares whitening of :class:`lidarcal.joint.noise._Groups`
(per-group offset and tilt) is linear too, so it acts on ``h``. With the robust
IRLS weights ``W`` held, the weighted sum of squares of a group is exactly
``c^T Q c`` with ``Q = sum W h~ h~^T`` (``h~`` the whitened ``h``): a
Gauss-Newton/Levenberg-Marquardt step needs only the (k, k) ``Q`` of each group
and the derivatives of ``c``, never the ~1e5-row Jacobian. The robust weights are
recomputed between these inner solves (iteratively reweighted least squares); at
convergence the stationarity condition is that of the robust cost, the same
optimum as :func:`lidarcal.joint.solver.irls_lm`.
"""

from __future__ import annotations

import weakref

import numpy as np

from .noise import _Groups, padded_rows_dot, whiten_padded
from .params import N_BOARD, N_RIG, _poses, _rig
from .problem import _Problem, _stripe_points
from .solver import (
    LMResult,
    _curvature_weights,
    _irls_weights,
    _lm_scaling,
    _lm_step,
    _rho_and_weights,
)

_OBS_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
MOMENT_GROUPS = 16  # groups per batched product of :meth:`_MomentProblem.moments`


def _noise_state(prob: _Problem) -> list:
    """What the whitened observations depend on besides the data and the held planes: the
    noise model and masks of both groupings, the stripe scales and the dark shares (arrays
    that are replaced, never changed in place, when they change: compared by identity),
    and the planes (by value)."""
    arrays = [a for g in (prob.scan, prob.stripe) for a in (g.w, g.g0, g.g1, g.sig_g, g.sc)]
    return arrays + [prob.scale_px, prob.dark,
                     prob.base.board_R.tobytes() + prob.base.board_T.tobytes()]


def raw_observations(prob: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """Homogeneous observations ``h`` of scans (M, 7) and stripes (S, 4) (module docstring),
    neither whitened nor masked."""
    d = prob.data
    u, dark = prob.scan_u, prob.dark
    hs = np.column_stack([d.scan_xy, u, dark[:, None] * u, np.ones(len(u))])
    P = _stripe_points(d, prob.base.board_R, prob.base.board_T)["P"]
    s = prob.scale_px[:, None]
    hp = np.column_stack([s * P, s]) if len(P) else np.zeros((0, 4))
    return hs, hp


_GRID_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def raw_observations_grid(prob: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """:func:`raw_observations` on the groupings' grids (:meth:`lidarcal.joint.noise._Groups.pad_columns`),
    (G, 7, n_max) and (G, 4, n_max): the parts that do not change during a fit (scan points,
    beam directions, stripe points on the held planes) are laid out once per data and planes;
    the dark shares and the stripe scales are laid out as they are."""
    d, scan, stripe = prob.data, prob.scan, prob.stripe
    key = prob.base.board_R.tobytes() + prob.base.board_T.tobytes()
    const = _GRID_CACHE.get(d)
    if const is None or const["planes"] != key:
        P = _stripe_points(d, prob.base.board_R, prob.base.board_T)["P"]
        const = _GRID_CACHE[d] = {
            "planes": key, "P": stripe.pad_columns(P),
            "xyu1": scan.pad_columns(np.column_stack([d.scan_xy, prob.scan_u,
                                                      np.ones(len(d.scan_xy))])),
            "one_p": stripe.pad(np.ones(len(P)))}
    xyu1, P = const["xyu1"], const["P"]
    hs = np.empty((xyu1.shape[0], 7, xyu1.shape[2]))
    hs[:, :4], hs[:, 6] = xyu1[:, :4], xyu1[:, 4]
    np.multiply(scan.pad(prob.dark)[:, None, :], xyu1[:, 2:4], out=hs[:, 4:6])
    hp = np.empty((P.shape[0], 4, P.shape[2]))
    hp[:, 3] = stripe.pad(prob.scale_px)
    np.multiply(hp[:, 3:], P, out=hp[:, :3])
    return hs, hp


def whitened_observations(prob: _Problem, build: bool = True, store: bool = True) -> dict | None:
    """Whitened, masked homogeneous observations ``h~`` of scans (M, 7) and stripes (S, 4)
    (module docstring), as ``{"hs": .., "hp": ..}``, each on its grouping's grid
    (:meth:`lidarcal.joint.noise._Groups.pad_columns`: (G, k, n_max), zero where dropped or
    padded).
    They do not depend on the rig parameters: computed once per noise state and reused by
    every solve, the covariance and the jitter test on it (``store`` False: built, when not
    at hand, without replacing the ones kept, e.g. for a trial noise model)."""
    state = _noise_state(prob)
    hit = _OBS_CACHE.get(prob.data)
    if hit is not None and all(a is b for a, b in zip(hit[0][:-1], state[:-1])) \
            and hit[0][-1] == state[-1]:
        return hit[1]
    if not build:
        return None
    hs, hp = raw_observations_grid(prob)
    obs = {"hs": whiten_padded(prob.scan, hs), "hp": whiten_padded(prob.stripe, hp)}
    if store:
        _OBS_CACHE[prob.data] = (state, obs)
    return obs


class _MomentProblem:
    """The scan and stripe blocks of a :class:`_Problem` as per-group homogeneous observations
    (planes held, the noise model and the masks as they are in ``prob``)."""

    def __init__(self, prob: _Problem, observations: bool = True):
        """``observations`` False: the coefficients only (no whitened observations)."""
        self.prob = prob
        self.n_par = N_RIG + prob.n_ranging
        bR, bT = prob.base.board_R, prob.base.board_T
        self.nb = bR[:, :, 2]
        self.db = np.einsum("ij,ij->i", self.nb, bT)
        if observations:
            self.obs = whitened_observations(prob)
            self.hs, self.hp = self.obs["hs"], self.obs["hp"]
        self.gs, self.gp = prob.scan.gid, prob.stripe.gid
        self._coef_memo: dict = {}
        self._memo_base = prob.base
        self.n_groups = prob.scan.n_groups
        self.cuts_s = np.searchsorted(self.gs, np.arange(self.n_groups + 1))
        self.cuts_p = np.searchsorted(self.gp, np.arange(self.n_groups + 1))

    def coefficients(self, x: np.ndarray, derivatives: bool = True
                     ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None]:
        """Per group ``c`` and ``dc/dx`` for scans (G, 7), (G, 7, n) and stripes (G, 4), (G, 4, n)
        (without ``derivatives``: ``c`` only, None for the derivatives). The last few are
        kept: the solver asks again at the point it has just stepped to."""
        key = (np.asarray(x, float).tobytes(), derivatives, self.prob.t.tobytes(),
               self.prob.frozen)
        if self._memo_base is not self.prob.base:
            self._coef_memo, self._memo_base = {}, self.prob.base
        hit = self._coef_memo.get(key)
        if hit is None:
            if len(self._coef_memo) >= 4:
                self._coef_memo.pop(next(iter(self._coef_memo)))
            hit = self._coef_memo[key] = self._coefficients(x, derivatives)
        return hit

    def _coefficients(self, x: np.ndarray, derivatives: bool
                      ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray | None]:
        """:meth:`coefficients`, computed per position and laid out per group ``2 i + b``
        (a position's two groups share its pose, each with its board's plane)."""
        prob = self.prob
        xr, rv = prob.split(x)
        if derivatives:
            R, T, G = prob.pose_derivatives(xr)
        else:
            R, T = _poses(*_rig(xr, prob.base), prob.t)
        n_grp = 2 * len(R)
        nb = self.nb  # (2, 3): per position, both boards at once, (N, 2) -> groups 2 i + b
        a = (R[:, :, 0] @ nb.T).ravel()
        b = (R[:, :, 1] @ nb.T).ravel()
        gam = (T @ nb.T - self.db).ravel()
        off, ex = rv[0], rv[1]
        cs = np.column_stack([a, b, -off * a, -off * b, -ex * a, -ex * b, gam])
        z = R[:, :, 2]
        tz = np.einsum("ij,ij->i", T, z)
        cp = np.repeat(np.column_stack([z, -tz]), 2, axis=0)
        if not derivatives:
            return cs, None, cp, None
        da = (nb @ G[:, 0:3]).reshape(n_grp, N_RIG)
        db = (nb @ G[:, 3:6]).reshape(n_grp, N_RIG)
        dg = (nb @ G[:, 9:12]).reshape(n_grp, N_RIG)
        Js = np.zeros((n_grp, 7, self.n_par))
        Js[:, 0, :N_RIG], Js[:, 1, :N_RIG] = da, db
        Js[:, 2, :N_RIG], Js[:, 3, :N_RIG] = -off * da, -off * db
        Js[:, 4, :N_RIG], Js[:, 5, :N_RIG] = -ex * da, -ex * db
        Js[:, 6, :N_RIG] = dg
        if prob.n_ranging >= 1:
            Js[:, 2, N_RIG], Js[:, 3, N_RIG] = -a, -b
        if prob.n_ranging >= 2:
            Js[:, 4, N_RIG + 1], Js[:, 5, N_RIG + 1] = -a, -b
        for j in prob.frozen:  # held ranging terms: no column
            Js[:, :, N_RIG + j] = 0.0
        dz = G[:, 6:9]
        Jp = np.zeros((len(R), 4, self.n_par))
        Jp[:, :3, :N_RIG] = dz
        Jp[:, 3, :N_RIG] = -(np.einsum("ni,nij->nj", T, dz) + np.einsum("ni,nij->nj", z, G[:, 9:12]))
        return cs, Js, cp, np.repeat(Jp, 2, axis=0)

    def angle_coefficients(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per group ``c`` and ``dc/dt`` wrt the group's own turntable angle: scans (G, 7) x 2,
        stripes (G, 4) x 2. ``dR/dt = [k]x R`` and ``dT/dt = [k]x (T - a)`` (the rigid model,
        :func:`lidarcal.joint.params._poses`)."""
        prob = self.prob
        xr, rv = prob.split(x)
        k, a_pt, R_ref, T_ref = _rig(xr, prob.base)
        R, T = _poses(k, a_pt, R_ref, T_ref, prob.t)
        n_pos = len(prob.t)
        pos = np.repeat(np.arange(n_pos), 2)
        brd = np.tile([0, 1], n_pos)
        n = self.nb[brd]
        Rg, Tg = R[pos], T[pos]
        dRg = np.cross(k, Rg.transpose(0, 2, 1)).transpose(0, 2, 1)  # [k]x R, column by column
        dTg = np.cross(k, Tg - a_pt)
        off, ex = rv[0], rv[1]

        def scan(Rc, Tc, shift):
            a = np.einsum("gi,gi->g", n, Rc[:, :, 0])
            b = np.einsum("gi,gi->g", n, Rc[:, :, 1])
            gam = np.einsum("gi,gi->g", n, Tc) - shift
            return np.column_stack([a, b, -off * a, -off * b, -ex * a, -ex * b, gam])

        z, dz = Rg[:, :, 2], dRg[:, :, 2]
        cp = np.column_stack([z, -np.einsum("gi,gi->g", Tg, z)])
        dcp = np.column_stack([dz, -np.einsum("gi,gi->g", dTg, z) - np.einsum("gi,gi->g", Tg, dz)])
        return scan(Rg, Tg, self.db[brd]), scan(dRg, dTg, 0.0), cp, dcp

    def residuals(self, cs: np.ndarray, cp: np.ndarray, grid: bool = False
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Normalised (whitened, masked) scan and stripe residuals for coefficients ``cs``, ``cp``:
        per row (M,), (S,), or with ``grid`` on the groupings' grids, flattened (G n_max,) (zero
        on padding and on dropped rows, as on those rows)."""
        out = []
        for h, c, grp in ((self.hs, cs, self.prob.scan), (self.hp, cp, self.prob.stripe)):
            out.append(padded_rows_dot(grp, h, c) if not grid
                       else np.matmul(c[:, None, :], h).reshape(-1))
        return out[0], out[1]

    def _on_grid(self, grp: _Groups, v: np.ndarray, grid: bool) -> np.ndarray:
        """A value per row (or already on the grid, flattened, with ``grid``) as (G, n_max)."""
        return v.reshape(grp.n_groups, grp.n_max) if grid else grp.pad(v)

    def first_moments(self, vs: np.ndarray, vp: np.ndarray, grid: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
        """``sum v h~`` of every group (G, 7) and (G, 4): with ``v = W r`` the gradient moments
        ``Q c`` of the robust cost (one batched product over the groups' grids). ``grid``: ``v``
        on the grids (:meth:`residuals`)."""
        return tuple(np.matmul(h, self._on_grid(grp, v, grid)[:, :, None])[:, :, 0]
                     for h, v, grp in ((self.hs, vs, self.prob.scan),
                                       (self.hp, vp, self.prob.stripe)))

    def moments(self, Ws: np.ndarray, Wp: np.ndarray, grid: bool = False
                ) -> tuple[np.ndarray, np.ndarray]:
        """``Q`` of every group: ``sum W h~ h~^T`` (G, 7, 7) and (G, 4, 4). ``grid``: the weights
        on the grids (:meth:`residuals`).

        A batched product ``(W h~)^T h~`` over the groups' grids, :data:`MOMENT_GROUPS` groups
        at a time (each group's product on its own: the same numbers): the work array ``W h~``
        stays small (memory the allocator reuses, not a fresh copy of the grids: page faults);
        no per-row products stored, nothing to rebuild when the noise model changes."""
        out = []
        for h, W, grp in ((self.hs, Ws, self.prob.scan), (self.hp, Wp, self.prob.stripe)):
            Wg = self._on_grid(grp, W, grid)
            Q = np.empty((h.shape[0], h.shape[1], h.shape[1]))
            for i in range(0, len(h), MOMENT_GROUPS):
                hb = h[i:i + MOMENT_GROUPS]
                np.matmul(hb * Wg[i:i + MOMENT_GROUPS, None, :], hb.transpose(0, 2, 1),
                          out=Q[i:i + MOMENT_GROUPS])
            out.append(Q)
        return out[0], out[1]


def moments_usable(prob: _Problem, use_corners: bool) -> bool:
    """The moment form applies with the planes held and rows grouped (as built)."""
    return (not use_corners and prob.scan._sorted and prob.stripe._sorted)


NEAR_D2 = 36.0  # a second start within this d^2 of the first's optimum, on its quadratic: tie


def irls_moments(prob: _Problem, x0: np.ndarray, loss: str = "soft_l1", f_scale: float = 1.0,
                 max_outer: int = 50, max_inner: int = 30, tol: float = 1e-12,
                 inner_tol: float = 1e-12, near: LMResult | None = None) -> LMResult:
    """Robust fit of ``prob`` (planes held) on per-group moments (module docstring).

    Outer loop: residuals ``r`` at ``x``, their robust weights ``W = rho'`` and second-order
    weights ``W2 = rho' + 2 z^2 rho''`` (:func:`lidarcal.joint.solver._curvature_weights`),
    each group's gradient moment ``b = sum W r h~`` (``= Q c0``, ``Q = sum W h~ h~^T``) and
    curvature moment ``Q2 = sum W2 h~ h~^T``. Inner loop: Levenberg-Marquardt on the
    second-order model of the robust cost, ``sum b . (c - c0) + 1/2 (c - c0)^T Q2 (c - c0)``
    (+ the ranging prior's): Newton steps on the robust cost, converging in a few passes.
    When that pass does not lower the robust cost, the IRLS pass (``Q2 = Q``: a majoriser of
    the cost, it never raises it) is taken instead. Stops when an outer pass moves the
    robust cost by less than ``tol`` (relative), or when the next pass would take no step:
    its first predicted decrease (gradient ``g`` at the new ``x`` from its ``b``, ``H`` the
    last pass's information) below ``inner_tol`` of ``sum W r^2``. Returns
    the robust cost at the end (scipy's definition, as :func:`lidarcal.joint.solver.irls_lm`)
    and the Gauss-Newton information ``sum J^T Q2 J`` of the last inner step.

    ``near`` (another start's result on the same problem, with its information): stop
    (status 2) once an outer pass ends within six sigma of it, ``d^2 = dx^T I dx <=
    NEAR_D2``, at a robust cost above its by ``d^2 / 2`` (to a quarter of ``d^2``: the cost's
    quadratic model about it holds): the solution is in the same basin and converges to the
    same optimum (the starts tie). Measured on the paper and simulated rigs: a second start
    that passes there ends on the quadratic to 1 % of ``d^2 / 2``.
    """
    mp = _MomentProblem(prob)
    x = np.asarray(x0, dtype=float).copy()
    nfev, status = 0, 0
    H = None

    def robust_cost(x: np.ndarray):
        """Robust cost at ``x``, its residuals' IRLS weights ``rho'`` and second-order weights
        ``rho' + 2 z^2 rho''`` (scan, stripe, prior), and the residuals."""
        cs, _, cp, _ = mp.coefficients(x, derivatives=False)
        # on the grids: padding and dropped rows have r = 0, rho = 0 and h~ = 0
        res = (*mp.residuals(cs, cp, grid=True), prob.prior_residuals(x))
        total, weights, curv = 0.0, [], []
        for r in res:
            z = r / f_scale
            rho, w = _rho_and_weights(z, loss)
            total += rho
            weights.append(w)
            curv.append(_curvature_weights(z, w, loss))
        return 0.5 * f_scale**2 * total, weights, curv, res

    def gradient_moments(res: tuple, weights: list) -> tuple[tuple, float]:
        """The gradient moments ``b = sum W r h~`` (scan, stripe) and ``q = sum W r^2``."""
        (rs, rp, rr), (ws, wp, wr) = res, weights
        Wr_s, Wr_p = ws * rs, wp * rp
        # einsum, not BLAS: a threaded dot of ~1e5 entries stalls on a busy machine
        q = float(np.einsum("i,i->", Wr_s, rs) + np.einsum("i,i->", Wr_p, rp)
                  + np.sum(wr * rr * rr))
        return mp.first_moments(Wr_s, Wr_p, grid=True), q

    Jr = np.zeros((prob.n_ranging, mp.n_par))
    if prob.n_ranging:
        Jr[:, N_RIG:] = np.diag(1 / prob.prior_sigma[:prob.n_ranging])
        for j in prob.frozen:
            Jr[:, N_RIG + j] = 0.0

    def gradient(x: np.ndarray, b: tuple, Wr: np.ndarray) -> np.ndarray:
        """Gradient of the robust cost at ``x`` from its gradient moments ``b``:
        ``sum_g (dc_g/dx)^T b_g`` (+ the prior's)."""
        _, Js, _, Jp = mp.coefficients(x)
        return (np.einsum("gki,gk->i", Js, b[0]) + np.einsum("gki,gk->i", Jp, b[1])
                + Jr.T @ (Wr * prob.prior_residuals(x)))

    def inner(x: np.ndarray, b: tuple, q_ref: float, C: tuple, Wr: np.ndarray,
              Wr2: np.ndarray):
        """Levenberg-Marquardt on the model ``sum b . (c - c0) + 1/2 (c - c0)^T C (c - c0)``
        (+ the prior's) of the robust cost about ``x`` (``c0 = c(x)``; ``C = Q``: the IRLS
        quadratic). Returns the new ``x`` and the Gauss-Newton information."""
        (gs0, gp0), (Cs, Cp) = b, C
        cs0, _, cp0, _ = mp.coefficients(x, derivatives=False)
        rr0 = prob.prior_residuals(x)

        def model(cs, cp, rr_):
            ds, dp, dr = cs - cs0, cp - cp0, rr_ - rr0
            return (float(np.sum(gs0 * ds) + np.sum(gp0 * dp) + np.sum(Wr * rr0 * dr))
                    + 0.5 * (float(np.einsum("gi,gij,gj->", ds, Cs, ds))
                             + float(np.einsum("gi,gij,gj->", dp, Cp, dp))
                             + float(np.sum(Wr2 * dr * dr))))

        xi, m, lam, H = x.copy(), 0.0, 1e-4, None
        for it in range(max_inner):
            cs, Js, cp, Jp = mp.coefficients(xi)
            rri = prob.prior_residuals(xi)
            CJs, CJp = Cs @ Js, Cp @ Jp
            H = (Js.reshape(-1, mp.n_par).T @ CJs.reshape(-1, mp.n_par)
                 + Jp.reshape(-1, mp.n_par).T @ CJp.reshape(-1, mp.n_par) + (Jr.T * Wr2) @ Jr)
            g = (np.einsum("gki,gk->i", Js, gs0 + np.einsum("gij,gj->gi", Cs, cs - cs0))
                 + np.einsum("gki,gk->i", Jp, gp0 + np.einsum("gij,gj->gi", Cp, cp - cp0))
                 + Jr.T @ (Wr * rr0 + Wr2 * (rri - rr0)))
            D = _lm_scaling(H)
            while True:
                step = _lm_step(H, g, lam, D)
                pred = abs(float(g @ step))
                if it == 0:
                    first = pred
                # converged: the predicted decrease is below rounding, or a millionth of this
                # pass's first (the weights change before that matters)
                if pred <= max(inner_tol * max(q_ref, 1e-300), 1e-6 * first):
                    step = None
                    break
                c2 = mp.coefficients(xi + step, derivatives=False)
                m2 = model(c2[0], c2[2], prob.prior_residuals(xi + step))
                if np.isfinite(m2) and m2 <= m:
                    break
                lam *= 10.0
                if lam > 1e10:
                    step = None
                    break
            if step is None:
                break
            xi = xi + step
            done = m - m2 <= 0.5 * inner_tol * max(q_ref, 1e-300)
            m = m2
            lam = max(lam / 10.0, 1e-9)
            if done:
                break
        return xi, H

    def settled(x: np.ndarray, b: tuple, q: float, Wr: np.ndarray, H: np.ndarray | None
                ) -> bool:
        """Whether another pass from ``x`` would take no step: the inner loop's first predicted
        decrease (its first step with ``H``, the last pass's information) is below
        ``inner_tol`` of ``sum W r^2``. (Not the outer ``tol``: a start solve stopped that
        early moves the noise estimate of the passes after it.)"""
        if H is None:
            return False
        g = gradient(x, b, Wr)
        step = _lm_step(H, g, 1e-4, _lm_scaling(H))  # the inner loop's first step
        return abs(float(g @ step)) <= inner_tol * max(q, 1e-300)

    cost, (Ws, Wp, Wr), (Ws2, Wp2, Wr2), res = robust_cost(x)
    b, q = gradient_moments(res, [Ws, Wp, Wr])
    nfev += 1
    for _ in range(max_outer):
        # Newton on the robust cost first (second-order weights); the IRLS step (a
        # majoriser: never increases the cost) when that does not decrease it
        xi, H = inner(x, b, q, mp.moments(Ws2, Wp2, grid=True), Wr, Wr2)
        cn, W2, C2, res = robust_cost(xi)
        nfev += 1
        if not (np.isfinite(cn) and cn <= cost):
            xi, H = inner(x, b, q, mp.moments(Ws, Wp, grid=True), Wr, Wr)
            cn, W2, C2, res = robust_cost(xi)
            nfev += 1
        if not (np.isfinite(cn) and cn <= cost * (1 + 1e-12)):
            status = -1 if status == 0 else status
            break
        done = cost - cn <= tol * max(cost, 1e-300)
        x, cost, (Ws, Wp, Wr), (Ws2, Wp2, Wr2) = xi, cn, W2, C2
        if done:
            status = 1
            break
        if near is not None and near.information is not None and cost >= near.cost:
            dx = x - near.x
            d2 = float(dx @ near.information @ dx)
            # within six sigma, where the cost rises as its quadratic model says
            if d2 <= NEAR_D2 and abs((cost - near.cost) - 0.5 * d2) <= 0.25 * d2 + 1e-9 * cost:
                status = 2
                break
        b, q = gradient_moments(res, [Ws, Wp, Wr])
        if settled(x, b, q, Wr, H):
            status = 1
            break
    return LMResult(x, cost, nfev, status, H)


def _group_cross(A: np.ndarray, B: np.ndarray, W: np.ndarray, cuts: np.ndarray) -> np.ndarray:
    """``sum W a b^T`` over the rows of every group (rows sorted by group): (G, k, q)."""
    out = np.zeros((len(cuts) - 1, A.shape[1], B.shape[1]))
    Aw = A * W[:, None]
    for g in range(len(cuts) - 1):
        a, b = cuts[g], cuts[g + 1]
        if b > a:
            out[g] = Aw[a:b].T @ B[a:b]
    return out


def _scan_plane_cross(prob: _Problem, Qs: np.ndarray) -> np.ndarray:
    """``sum W h~ db~^T`` of every scan group (G, 7, 4) at ``x = 0``: a return's derivative
    wrt its board's (normal, d) is ``[X, -1]`` with ``X = R_x x' + R_y y' + T`` (eq. 28, the
    range-corrected point ``(x', y') = (x, y) - (offset + extra dark) u``), i.e. ``B_g h``
    with ``B_g = [[R_x, R_y, -o R_x, -o R_y, -e R_x, -e R_y, T], [0 .. 0, -1]]`` (4, 7); the
    whitening acts on the rows, so ``sum W h~ (B h~)^T = Q_g B_g^T``."""
    R, T = _poses(*_rig(np.zeros(N_RIG), prob.base), prob.t)
    off, ex = prob.base.ranging[0], prob.base.ranging[1]
    Rg, Tg = np.repeat(R, 2, axis=0), np.repeat(T, 2, axis=0)  # group 2 i + b
    B = np.zeros((len(Rg), 4, 7))
    for j, (col, f) in enumerate(((0, 1.0), (1, 1.0), (0, -off), (1, -off), (0, -ex), (1, -ex))):
        B[:, :3, j] = f * Rg[:, :, col]
    B[:, :3, 6] = Tg
    B[:, 3, 6] = -1.0
    return Qs @ B.transpose(0, 2, 1)


def _stripe_plane_cross(prob: _Problem, mp: _MomentProblem, Qp: np.ndarray, Wp: np.ndarray
                        ) -> np.ndarray:
    """``sum W h~ db~^T`` of every stripe group (G, 4, 4) at ``x = 0``: with the pixel scale
    going as 1 / depth (:meth:`_Problem.stripe_scale`, set by :meth:`_Problem.set_stripe_scale`)
    a centre's derivative wrt its board's (normal, d) is ``-(T . z / d) [s P, -s]``
    (:meth:`_Problem.stripe_plane_rows`, with ``P = ray d / (ray . n)``), linear in its
    ``h = [s P, s]``: ``Q_g C_g^T``, ``C_g = -(T . z / d) diag(1, 1, 1, -1)``. With the
    scale held, the rows are whitened and summed."""
    d = prob.data
    bR, bT = prob.base.board_R, prob.base.board_T
    nb = bR[:, :, 2]
    db = np.einsum("ij,ij->i", nb, bT)
    R, T = _poses(*_rig(np.zeros(N_RIG), prob.base), prob.t)
    if prob.scale_depth is not None:
        tz = np.repeat(np.einsum("ij,ij->i", T, R[:, :, 2]), 2) / np.tile(db, len(T))  # (G,)
        return -tz[:, None, None] * (Qp * np.array([1.0, 1.0, 1.0, -1.0]))
    p, b = d.stripe_pos, d.stripe_board
    rn = np.einsum("ij,ij->i", d.stripe_rays, nb[b])[:, None]
    Dp = (prob.stripe_plane_rows(rn, db[b][:, None], R[p, :, 2], T[p]) if len(p)
          else np.zeros((0, 4)))
    Dp = prob.stripe.whiten_columns(Dp) * prob.stripe.w[:, None]
    hp = mp.hp.transpose(0, 2, 1).reshape(-1, mp.hp.shape[1])[prob.stripe._grid]  # rows
    return _group_cross(hp, Dp, Wp, mp.cuts_p)


def moments_covariance(prob: _Problem, loss: str, f_scale: float
                       ) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`lidarcal.joint.solver._covariance` (planes held) from the group moments: exact,
    O(positions) products instead of the ~1e5-row Jacobian.

    At ``x = 0`` (the problem re-based at the solution) the robust weights ``W`` of the
    whitened residuals give the group moments ``Q``; the information of the rig and
    ranging terms is ``sum_g J_g^T Q_g J_g`` (+ the ranging prior's), with ``J_g = dc/dx``
    of the group. The consider term needs the cross information with the board planes:
    each residual's derivative wrt its board's (normal, d) is a row (scan: ``[X, -1]``,
    ``X`` the point, eq. 28; stripe: ``s (z . P) / d [-P, 1]``, eq. 5), whitened like the
    residuals, so ``J_x^T W J_b = sum_g J_g^T (sum W h~ db~^T) G_b`` (``G_b``: d(normal, d) /
    d board pose); those rows are linear in the observation ``h`` of their group
    (:func:`_scan_plane_cross`, :func:`_stripe_plane_cross`), so the cross moments are
    ``Q_g B_g^T``. The cluster-robust scores of a position are ``sum_g J_g^T Q_g c_g``.
    """
    from .solver import _inverse

    d = prob.data
    n_rng = prob.n_ranging
    x0 = np.zeros(N_RIG + n_rng)
    mp = _MomentProblem(prob)
    cs, Js, cp, Jp = mp.coefficients(x0)
    rs, rp = mp.residuals(cs, cp)
    rr = prob.prior_residuals(x0)
    Ws, Wp, Wr = (_irls_weights(r / f_scale, loss) for r in (rs, rp, rr))
    Qs, Qp = mp.moments(Ws, Wp)
    Jr = np.zeros((n_rng, mp.n_par))
    if n_rng:
        Jr[:, N_RIG:] = np.diag(1 / prob.prior_sigma[:n_rng])
        for j in prob.frozen:
            Jr[:, N_RIG + j] = 0.0
    # sum_g J_g^T (Q_g J_g): two two-operand products (einsum's three-operand loop is ~20x slower)
    Hx = (np.einsum("gki,gkj->ij", Js, Qs @ Js) + np.einsum("gki,gkj->ij", Jp, Qp @ Jp)
          + (Jr.T * Wr) @ Jr)
    # cross information with the board planes (consider term)
    Kx = (np.einsum("gki,gkj->gij", Js, _scan_plane_cross(prob, Qs))
          + np.einsum("gki,gkj->gij", Jp, _stripe_plane_cross(prob, mp, Qp, Wp)))  # (G, n, 4)
    Gb = prob.plane_derivatives(np.zeros(N_RIG + 2 * N_BOARD))
    brd = np.arange(mp.n_groups) % 2
    Hxb = np.concatenate([np.einsum("gij,jk->ik", Kx[brd == k], Gb[k]) for k in range(2)], 1)
    # residual variance over every row (scan, stripe, prior and, when present, corners)
    ss = (float(np.einsum("gi,gij,gj->", cs, Qs, cs)) + float(np.einsum("gi,gij,gj->", cp, Qp, cp))
          + float(np.sum(Wr * rr * rr)))
    m_used = len(rs) + len(rp) + n_rng
    has_corners = d.corners_px is not None and d.object_points is not None
    if has_corners:
        rc = prob.corner_residuals(prob.base.board_R, prob.base.board_T) / prob.sigma_corner
        wc = _irls_weights(rc / f_scale, loss)
        ss += float(np.sum(wc * rc * rc))
        m_used += len(rc)
    s2 = max(ss / max(m_used - mp.n_par, 1), 1.0)
    Hx_inv, null = _inverse(Hx)
    # cluster-robust covariance: the scores of each position (its groups)
    S = (np.einsum("gki,gk->gi", Js, np.einsum("gkl,gl->gk", Qs, cs))
         + np.einsum("gki,gk->gi", Jp, np.einsum("gkl,gl->gk", Qp, cp)))
    S = S.reshape(-1, 2, mp.n_par).sum(1)
    G = int(np.count_nonzero(np.any(S != 0, axis=1)))
    meat = S.T @ S * (G / max(G - 1, 1))
    prob.sandwich = Hx_inv @ meat @ Hx_inv
    C = Hx_inv
    if prob.board_cov is not None:  # the held planes' covariance given (intrinsics included)
        A = Hx_inv @ Hxb
        C = C + A @ prob.board_cov @ A.T
    elif has_corners:
        Jc = prob.corner_jacobian(np.zeros(N_RIG + 2 * N_BOARD)) / prob.sigma_corner
        Jc *= np.sqrt(wc)[:, None] * prob.sigma_corner / max(prob.sigma_corner, prob.corner_floor_px)
        Pb, _ = _inverse(Jc.T @ Jc)
        A = Hx_inv @ Hxb
        C = C + A @ Pb @ A.T
    return s2 * C, null, s2
