"""Encoder jitter of the turntable as a random effect (beyond the paper)."""

from __future__ import annotations

import numpy as np

from .moments import _MomentProblem, moments_usable, whitened_observations
from .params import N_RIG
from .problem import _Problem
from .solver import _irls_weights


def _angle_steps(prob: _Problem, x: np.ndarray, loss: str, f_scale: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Generalised least-squares step of each position's own turntable angle, rig held at ``x``.

    The residuals of position ``i`` depend on its angle ``t_i`` only. With robust
    weights ``w``: ``H_i = sum w J^2``, ``g_i = sum w J r`` (``J = dr/dt_i``); step
    ``-g_i / H_i`` (rad) and its variance ``s^2 / H_i`` (``s^2 >= 1`` the weighted residual
    variance). Planes held (rows grouped): ``J`` of a row is ``h . dc/dt`` whitened like
    its residual (:meth:`lidarcal.joint.moments._MomentProblem.angle_coefficients`; the
    solver's whitened observations when at hand, else built for ``prob``'s noise model,
    :func:`lidarcal.joint.moments.whitened_observations`); otherwise one central difference of all
    angles at once.
    """
    d = prob.data
    n = d.n_positions
    pos = np.concatenate([d.scan_pos, d.stripe_pos])
    if len(x) == N_RIG + prob.n_ranging and moments_usable(prob, False):
        # on the groupings' grids (zero on padding and dropped rows), sums per group of each
        # position's two (2 i + b)
        cs, dcs, cp, dcp = _MomentProblem(prob, observations=False).angle_coefficients(x)
        obs = whitened_observations(prob, store=False)  # the solver's, when at hand for this noise
        H, g, ss = np.zeros(n), np.zeros(n), 0.0
        for h, c, dc in ((obs["hs"], cs, dcs), (obs["hp"], cp, dcp)):
            r0, J = np.matmul(c[:, None, :], h)[:, 0], np.matmul(dc[:, None, :], h)[:, 0]
            w = _irls_weights(r0 / f_scale, loss)
            wJ = w * J
            H += (wJ * J).sum(1).reshape(n, 2).sum(1)
            g += (wJ * r0).sum(1).reshape(n, 2).sum(1)
            ss += float(np.sum(w * r0 * r0))
    else:
        t0 = prob.t
        h = 1e-5
        r0 = prob.normalised(x, False)
        prob.t = t0 + h
        rp = prob.normalised(x, False)
        prob.t = t0 - h
        rm = prob.normalised(x, False)
        prob.t = t0
        m = len(pos)  # the ranging prior's pseudo-residuals follow: they do not move with t
        r0, rp, rm = r0[:m], rp[:m], rm[:m]
        J = (rp - rm) / (2 * h)
        w = _irls_weights(r0 / f_scale, loss)
        H = np.bincount(pos, w * J * J, minlength=n)
        g = np.bincount(pos, w * J * r0, minlength=n)
        ss = float(np.sum(w * r0 * r0))
    s2 = max(ss / max(len(pos) - N_RIG - n, 1), 1.0)
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
    # a _Groups replaces its arrays when re-estimated, never changes them: shallow copies
    work.scan, work.stripe = copy.copy(prob.scan), copy.copy(prob.stripe)
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


def board_steps(prob: _Problem, x: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """Each position's turntable angle step (rad) from each board's stripe alone, white noise
    (beyond the paper): (2, positions), rig held at ``x``.

    As :func:`_angle_steps` (one central difference of all angles at once), but the noise
    model of a copy of ``prob`` re-estimated without correlated components, and the sums
    ``H``, ``g`` taken over one board's stripe rows at a time. A turntable angle error turns
    the laser plane about the axis and moves both boards' stripes by the same angle step;
    a stripe's own offset (:class:`lidarcal.joint.noise._Groups`) moves one stripe only.
    """
    import copy

    work = copy.copy(prob)
    work.scan, work.stripe = copy.copy(prob.scan), copy.copy(prob.stripe)
    work.estimate_noise(x, False)
    d = prob.data
    n, ns = d.n_positions, len(d.scan_pos)
    m = ns + len(d.stripe_pos)
    t0, h = work.t.copy(), 1e-5
    r0 = work.normalised(x, False)[:m]
    work.t = t0 + h
    rp = work.normalised(x, False)[:m]
    work.t = t0 - h
    rm = work.normalised(x, False)[:m]
    work.t = t0
    J = ((rp - rm) / (2 * h))[ns:]
    r = r0[ns:]
    w = _irls_weights(r / f_scale, loss)
    out = np.full((2, n), np.nan)
    for b in range(2):
        k = d.stripe_board == b
        H = np.bincount(d.stripe_pos[k], (w * J * J)[k], minlength=n)
        g = np.bincount(d.stripe_pos[k], (w * J * r)[k], minlength=n)
        ok = H > 1e-300
        out[b, ok] = -g[ok] / H[ok]
    return out


#: the two boards' angle steps (:func:`coherent_jitter`) agree beyond chance at this p-value:
#: the stripes' per-position shifts are taken as turntable angle errors before the correlated
#: noise model can take them for stripe offsets
COHERENT_JITTER_P = 1e-4


def coherent_jitter(steps: np.ndarray) -> tuple[float, float]:
    """(F, p) of an angle error common to both boards' steps (beyond the paper).

    ``steps`` (2, positions) from :func:`board_steps`, each ``delta_i + e_bi`` with ``e``
    the board's own error (white noise, its stripe's offset), independent between the
    boards. About their means (a common shift of all angles is the reference pose's), the
    half-sum ``delta_i + (e_0i + e_1i) / 2`` and the half-difference ``(e_0i - e_1i) / 2``
    have the same variance without a jitter; ``F`` is the ratio of their mean squares and
    ``p`` its upper tail under ``F(n - 1, n - 1)``.
    """
    from scipy.stats import f as f_dist

    ok = np.all(np.isfinite(steps), axis=0)
    n = int(ok.sum())
    if n < 4:
        return 0.0, 1.0
    s = steps[:, ok] - steps[:, ok].mean(axis=1, keepdims=True)
    ms = float(np.mean((0.5 * (s[0] + s[1])) ** 2))
    md = float(np.mean((0.5 * (s[0] - s[1])) ** 2))
    F = ms / max(md, 1e-300)
    return F, float(f_dist.sf(F, n - 1, n - 1))
