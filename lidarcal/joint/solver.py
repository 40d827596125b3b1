"""Robust Levenberg-Marquardt (IRLS) and the covariance of the joint fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .params import N_BOARD, N_RIG, _mm
from .problem import _Problem


@dataclass
class LMResult:
    """Outcome of :func:`irls_lm` (the fields of scipy's ``OptimizeResult`` used here)."""

    x: np.ndarray
    cost: float
    nfev: int
    status: int  # 1 converged, 0 iteration limit, -1 no decrease possible, 2 joined ``near``
    information: np.ndarray | None = None  # Gauss-Newton information at x (moment solver)


def irls_lm(fun, jac, x0: np.ndarray, loss: str = "soft_l1", f_scale: float = 1.0,
            max_iter: int = 60, ftol: float = 1e-12, n_plain: int = 0) -> LMResult:
    """Robust Levenberg-Marquardt on the normal equations (iteratively reweighted).

    Minimises ``sum f_scale^2 rho((r / f_scale)^2)`` (scipy's loss definitions):
    each iteration solves ``(J^T W J + lam diag(J^T W J)) dx = -J^T W r`` with
    ``W = rho'`` at the current residuals and accepts the step when the robust
    cost drops. Equivalent to ``least_squares(..., loss=...)`` at the optimum,
    but works on the small (n, n) system: with ~1e5 residuals and ~10
    parameters it avoids the dense SVD of the Jacobian that ``method="trf"``
    repeats every iteration. The last ``n_plain`` residuals are Gaussian prior
    terms: plain squares, never down-weighted (a robust loss would let the data
    override a prior by any number of its sigmas).
    """
    x = np.asarray(x0, dtype=float).copy()
    r = fun(x)
    cost = _robust_cost(r, loss, f_scale, n_plain)
    lam, nfev, status = 1e-4, 1, 0
    for _ in range(max_iter):
        J = jac(x)
        w = _irls_weights(r / f_scale, loss)
        if n_plain:
            w[len(w) - n_plain:] = 1.0
        Jw = J * w[:, None]
        H = _mm(Jw.T, J)
        g = _mm(Jw.T, r[:, None])[:, 0]
        D = _lm_scaling(H)
        while True:
            step = _lm_step(H, g, lam, D)
            rn = fun(x + step)
            nfev += 1
            cn = _robust_cost(rn, loss, f_scale, n_plain)
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


def _robust_cost(r: np.ndarray, loss: str, f_scale: float, n_plain: int = 0) -> float:
    """scipy's robust cost ``0.5 f^2 sum rho((r/f)^2)``, the last ``n_plain`` terms plain squares."""
    m = len(r) - n_plain
    return (0.5 * f_scale**2 * float(np.sum(_rho(r[:m] / f_scale, loss)))
            + 0.5 * float(np.sum(r[m:] ** 2)))


def _lm_scaling(H: np.ndarray) -> np.ndarray:
    """Marquardt's diagonal scaling ``diag(H)``, floored at 1e-12 of its largest entry."""
    return np.maximum(np.diag(H), 1e-12 * max(np.diag(H).max(), 1e-300))


def _lm_step(H: np.ndarray, g: np.ndarray, lam: float, D: np.ndarray) -> np.ndarray:
    """The Levenberg-Marquardt step ``dx = -(H + lam diag(D))^-1 g`` (least squares when
    the damped system is singular)."""
    A = H + lam * np.diag(D)
    try:
        return -np.linalg.solve(A, g)
    except np.linalg.LinAlgError:
        return -np.linalg.lstsq(A, g, rcond=None)[0]


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


def _rho_and_weights(z: np.ndarray, loss: str) -> tuple[float, np.ndarray]:
    """``sum rho`` and the IRLS weights ``rho'`` of normalised residuals ``z`` in one go."""
    if loss == "soft_l1":
        t = z * z
        t += 1
        np.sqrt(t, out=t)
        total = 2 * float(np.sum(t)) - 2 * len(z)
        return total, np.reciprocal(t, out=t)
    return float(np.sum(_rho(z, loss))), _irls_weights(z, loss)


def _curvature_weights(z: np.ndarray, w: np.ndarray, loss: str) -> np.ndarray:
    """``rho'(s) + 2 s rho''(s)`` at ``s = z^2`` (``w = rho'``): the second derivative of the
    robust cost along a residual (Triggs et al. 2000, "Bundle adjustment", section 4.3),
    floored at 0 (where the loss bends down, Gauss-Newton takes no curvature)."""
    if loss == "soft_l1":
        return w * w * w  # (1 + s)^(-3/2)
    s = z * z
    if loss == "linear":
        return np.ones_like(s)
    if loss == "huber":
        return (s <= 1).astype(float)
    if loss == "cauchy":
        return np.maximum(1 - s, 0.0) * w * w
    if loss == "arctan":
        return np.maximum(1 - 3 * s * s, 0.0) * w * w
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


def _jacobian(prob: _Problem) -> tuple[np.ndarray, np.ndarray]:
    """Jacobian of the normalised residuals (scan, stripe, ranging prior, corners) wrt rig
    (10), board (12) and ranging (``prob.n_ranging``) parameters, at x = 0. Returns (residuals, J)."""
    n = N_RIG + 2 * N_BOARD + prob.n_ranging
    x0 = np.zeros(n)
    return prob.normalised(x0, True), prob.jacobian(x0, True)


def _covariance(prob: _Problem, fit_planes: bool, loss: str, f_scale: float
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Covariance (10 + n_ranging, 10 + n_ranging) of the rig and ranging parameters, the
    unobservable directions (10 + n_ranging, q), s^2. The rig block is marginal over the
    ranging terms: estimating them shows as larger rig sigmas. Planes held: from the
    group moments (:func:`lidarcal.joint.moments.moments_covariance`)."""
    if not fit_planes and prob.scan._sorted and prob.stripe._sorted:
        from .moments import moments_covariance  # moments builds on this module

        return moments_covariance(prob, loss, f_scale)
    return _covariance_rows(prob, fit_planes, loss, f_scale)


def _covariance_rows(prob: _Problem, fit_planes: bool, loss: str, f_scale: float
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """:func:`_covariance` from the row-by-row Jacobian (with ``fit_planes``, or rows not
    grouped; :func:`lidarcal.joint.moments.moments_covariance` is the same, faster)."""
    r, J = _jacobian(prob)
    n_main = len(r) - len(prob.corner_residuals(prob.base.board_R, prob.base.board_T))
    w = _irls_weights(r / f_scale, loss)
    n_plain = len(prob.board_prior_residuals(np.zeros(J.shape[1])))  # Gaussian prior rows
    w[n_main - n_plain:n_main] = 1.0
    Jw = J * np.sqrt(w)[:, None]
    has_corners = prob.data.corners_px is not None and prob.data.object_points is not None
    m_used = len(r) if (fit_planes or has_corners) else n_main
    n_used = N_RIG + (2 * N_BOARD if fit_planes else 0) + prob.n_ranging
    s2 = float(np.sum(w * r * r) / max(m_used - n_used, 1))
    s2 = max(s2, 1.0)  # the noise scales are estimated: never shrink below them
    # corner errors of chessboard detectors are correlated over the board: the pose absorbs
    # their low-order part, so the residual scale understates the plane error; the planes'
    # information uses at least ``corner_floor_px`` per coordinate
    Jw[n_main:] *= prob.sigma_corner / max(prob.sigma_corner, prob.corner_floor_px)
    xi = np.r_[0:N_RIG, N_RIG + 2 * N_BOARD:J.shape[1]]  # rig + ranging columns
    bi = np.arange(N_RIG, N_RIG + 2 * N_BOARD)
    Jx, Jb = Jw[:n_main][:, xi], Jw[:n_main][:, bi]
    Hx_inv, null = _inverse(_mm(Jx.T, Jx))
    prob.sandwich = _cluster_covariance(prob, Jx, r[:n_main] * np.sqrt(w[:n_main]), Hx_inv)
    if fit_planes:
        H = _mm(Jw.T, Jw)
        C, null = _inverse(H)
        return s2 * C[np.ix_(xi, xi)], null[xi], s2
    # planes held fixed: rig covariance from scans + stripes, plus the planes' own
    # uncertainty from the corners propagated ("consider" covariance)
    C = Hx_inv
    if prob.board_cov is not None:  # the held planes' covariance given (intrinsics included)
        A = Hx_inv @ _mm(Jx.T, Jb)
        C = C + A @ prob.board_cov @ A.T
    elif has_corners:
        Jc = Jw[n_main:][:, bi]
        Pb, _ = _inverse(_mm(Jc.T, Jc))
        A = Hx_inv @ _mm(Jx.T, Jb)
        C = C + A @ Pb @ A.T
    return s2 * C, null, s2


def _cluster_covariance(prob: _Problem, Jx: np.ndarray, rw: np.ndarray, H_inv: np.ndarray
                        ) -> np.ndarray:
    """Cluster-robust ("sandwich") covariance ``H^-1 (sum_i g_i g_i^T) H^-1 G / (G - 1)`` with
    ``g_i`` the score of position ``i`` (its rows of ``Jx^T r``, whitened, robust-weighted).

    It does not trust the noise model: a systematic error the model lacks (e.g. a
    dark-square bias that is not one constant) shows as scores that disagree between
    positions. Used as a floor for the ranging terms' sigmas.
    """
    d = prob.data
    pos = np.concatenate([d.scan_pos, d.stripe_pos])
    m = len(pos)
    n = d.n_positions
    S = np.zeros((n, Jx.shape[1]))
    np.add.at(S, pos, Jx[:m] * rw[:m, None])
    G = int(np.count_nonzero(np.any(S != 0, axis=1)))
    meat = _mm(S.T, S) * (G / max(G - 1, 1))
    return H_inv @ meat @ H_inv


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
