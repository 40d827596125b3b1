"""The joint fit itself: starts, robust passes, noise re-estimation, jitter, covariance."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from ..geometry import Plane
from ..ranging import DATA_SHARE, PRIOR_CONFLICT, RANGING_SIGNIFICANCE, RangingModel, RangingPrior
from ..ranging import ranging_prior as _ranging_prior
from ..turntable import Axis
from .data import JointData, joint_data
from .jitter import COHERENT_JITTER_P, angle_jitter, board_steps, coherent_jitter
from .model import JointModel
from .moments import irls_moments, moments_usable
from .params import (
    CORNER_FLOOR_PX,
    F_SCALE,
    JITTER_LR,
    JITTER_OFFSET_RATIO,
    MIN_POINTS_PER_BOARD,
    N_BOARD,
    N_RIG,
    _Base,
    _boards,
    _rig,
)
from .problem import _Problem, _stripe_points, start_step
from .solver import _covariance, _inverse, _robust_cost, irls_lm

if TYPE_CHECKING:
    from .planes_prior import PlanePrior

START_TIE = 1e-6  # relative robust-cost difference below which two starts tie


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
                   f_scale: float = F_SCALE, solver: str = "moments",
                   correlated: bool = True,
                   corner_floor_px: float = CORNER_FLOOR_PX, jitter: bool = True,
                   ranging: bool = True, ranging_prior: RangingPrior | None = None,
                   plane_prior: PlanePrior | None = None,
                   board_cov: np.ndarray | None = None) -> JointModel:
    """Joint fit on prepared observations; ``starts`` are pose functions (axis + ``pose``).

    See :func:`fit_joint`. Every start is refined once with the start's noise
    scales and the lowest robust cost wins; then the noise scales are
    re-estimated from the residuals, the stripe scale factors recomputed, and
    the fit repeated (twice). With ``ranging`` the range offset (and, when the
    data tell the returns from black squares, the dark-square extra) are
    estimated with the rig (:mod:`lidarcal.ranging`), under ``ranging_prior``
    (default: the wide :class:`lidarcal.ranging.RangingPrior`). With ``plane_prior``
    (:mod:`lidarcal.joint.planes_prior`) the board poses are parameters under that prior
    instead of the corners' residuals (``fit_planes`` is implied). ``board_cov`` (12, 12):
    the held board poses' covariance for the consider term of the rig covariance (default:
    the corners' own, :mod:`lidarcal.joint`); the estimate does not depend on it.
    """
    if plane_prior is not None:  # the prior stands for the corners (their information in it)
        fit_planes = True
        data = replace(data, corners_px=None, object_points=None)
    if data.n_positions < 2:
        raise ValueError(f"the joint fit needs at least 2 positions, got {data.n_positions}")
    if len(data.scan_xy) == 0:
        raise ValueError("no scan points: the joint fit needs the board returns of the scans")
    use_corners = fit_planes and data.corners_px is not None
    if fit_planes and not use_corners and plane_prior is None:
        raise ValueError("fit_planes=True needs the board corners and object points (v_board)")
    psi_ref = float(np.mean(data.psi_deg)) if psi_ref_deg is None else float(psi_ref_deg)
    bases = _start_bases(starts, data, psi_ref)
    prior = ranging_prior or RangingPrior()
    n_rng = (2 if data.can_see_dark else 1) if ranging else 0
    prior_arrays = (np.array([prior.offset_mm, prior.dark_extra_mm]),
                    np.array([prior.offset_sigma_mm, prior.dark_extra_sigma_mm]))
    n_par = N_RIG + (2 * N_BOARD if fit_planes else 0) + n_rng
    x0 = np.zeros(n_par)

    def _full(x):
        """[rig | boards | ranging] with zero board steps when the boards are held."""
        if fit_planes:
            return x
        return np.concatenate([x[:N_RIG], np.zeros(2 * N_BOARD), x[N_RIG:]])

    def solve(prob: _Problem, x: np.ndarray, tol: float = 1e-12, near=None):
        if solver == "moments" and not fit_planes and moments_usable(prob, use_corners):
            return irls_moments(prob, x, loss, f_scale, tol=tol, near=near)
        if solver == "scipy":
            from scipy.optimize import least_squares

            return least_squares(prob.normalised, x, jac=prob.jacobian, args=(use_corners,),
                                 loss=loss, f_scale=f_scale, x_scale="jac", method="trf",
                                 xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=100)
        return irls_lm(lambda v: prob.normalised(v, use_corners),
                       lambda v: prob.jacobian(v, use_corners), x, loss, f_scale,
                       n_plain=0 if use_corners else len(prob.board_prior_residuals(x)))

    sols = []
    for base in bases:
        # later starts as steps in the first start's problem (same noise model and scales)
        step = start_step(sols[0][0].base, base) if sols else None
        if step is None:
            prob, xs = _Problem(data, base, psi_ref, n_rng, prior_arrays), x0
            prob.board_prior = plane_prior
            prob.board_cov = board_cov
            prob.classify(_full(x0))
            prob.set_stripe_scale(_full(x0))
            prob.estimate_noise(x0, correlated=False)
        else:
            prob, xs = sols[0][0], np.concatenate([step, x0[N_RIG:]])
        near = sols[0][1] if sols and prob is sols[0][0] else None  # same basin: stop, tie
        sols.append((prob, solve(prob, xs, 1e-8, near)))  # to pick a start; the passes below finish
    # costs are comparable only with the same noise model: rescore with the first start's
    scores = []
    for prob, sol in sols:
        if prob is sols[0][0]:  # the solver's robust cost (scipy's definition)
            scores.append(2 * sol.cost / f_scale**2)
            continue
        prob.scan, prob.stripe = sols[0][0].scan, sols[0][0].stripe
        prob.sigma_corner = sols[0][0].sigma_corner
        r = prob.normalised(_full(sol.x), use_corners)
        n_plain = len(prob.board_prior_residuals(_full(sol.x)))
        scores.append(2 * _robust_cost(r, loss, f_scale, n_plain) / f_scale**2)
    # the first start unless another is lower by more than the start solves' tolerance
    # (solved to 1e-8: starts that reach the same optimum tie)
    best = int(np.argmin(scores))
    if scores[0] <= scores[best] + START_TIE * abs(scores[0]):
        best = 0
    prob, sol = sols[best]
    x = sol.x

    def refine(prob: _Problem, x: np.ndarray):
        """Noise re-estimated at ``x``, outliers dropped, solved again."""
        prob.classify(_full(x))
        prob.set_stripe_scale(_full(x))
        prob.estimate_noise(x, correlated)
        prob.reject(_full(x))
        return solve(prob, x)

    # encoder jitter shows as both boards' stripes shifting together at a position; the
    # boards' agreement is tested here, under white noise, before the correlated noise model
    # can take those shifts for stripe offsets (then used below if the jitter test misses it)
    t_reported = prob.t.copy()
    t_early = _coherent_start(prob, x, t_reported, loss, f_scale) if jitter else None
    x_white = x
    for _ in range(2):
        sol = refine(prob, x)
        x = sol.x

    def rebased(prob: _Problem, x: np.ndarray, t: np.ndarray) -> _Problem:
        """The problem re-based at ``x`` (so x = 0 there), with the given prior: its
        covariance is about the solution."""
        xr, rv = prob.split(_full(x))
        k, a, R_ref, T_ref = _rig(xr, prob.base)
        bR, bT = _boards(xr, prob.base)
        out = _Problem(data, _Base.make(k, a, R_ref, T_ref, bR, bT, rv), psi_ref, n_rng,
                       prior_arrays)
        out.t = t
        out.board_prior = prob.board_prior
        out.board_cov = prob.board_cov
        out.scale_px, out.scan, out.stripe, out.dark = prob.scale_px, prob.scan, prob.stripe, prob.dark
        out.scale_depth = prob.scale_depth
        out.sigma_corner = prob.sigma_corner
        out.corner_floor_px = float(corner_floor_px)
        return out

    # ranging terms the data do not move significantly from the prior are held at the
    # prior's mean (the pose stays as with exact ranges); their uncertainty stays in every
    # sigma: the covariance below is the one with the terms free (marginal = conditional +
    # the held terms' posterior variance propagated)
    held: tuple[int, ...] = ()
    decided = None  # (problem, covariance) at the decision: the final ones if nothing moves
    if n_rng:
        p = rebased(prob, x, prob.t)
        decided = (p, _covariance(p, fit_planes, loss, f_scale))
        c_all = decided[1][0]
        _, rv = prob.split(_full(x))
        sig = _ranging_sigmas(c_all, p.sandwich, rv, prob.dark)
        z = np.abs(rv[:n_rng] - prior_arrays[0][:n_rng]) / np.maximum(sig, 1e-300)
        conflict = _prior_conflicts(rv[:n_rng], prior_arrays)
        if conflict.any():
            # the fit went far with the ranging terms (and estimated its noise model there):
            # fitted again from the starts with ranges taken as exact, and said so
            again = fit_joint_data(data, starts, fit_planes=fit_planes, loss=loss,
                                   psi_ref_deg=psi_ref_deg, f_scale=f_scale, solver=solver,
                                   correlated=correlated, corner_floor_px=corner_floor_px,
                                   jitter=jitter, ranging=False, plane_prior=plane_prior,
                                   board_cov=board_cov)
            return replace(again, warnings=tuple(_conflict_warnings(rv[:n_rng], conflict, prior))
                           + again.warnings)
        held = tuple(int(j) for j in np.flatnonzero(z <= RANGING_SIGNIFICANCE))
        if held:
            rng0 = prob.base.ranging.copy()
            cols = [len(x) - n_rng + j for j in held]
            x = x + _conditional_step(getattr(sol, "information", None), len(x), cols,
                                      prior_arrays[0][list(held)] - rv[list(held)])
            for j, c in zip(held, cols):
                rng0[j] = prior_arrays[0][j]
                x[c] = 0.0
            prob.base = replace(prob.base, ranging=rng0)
            prob.frozen = held
            sol = solve(prob, x)  # same noise model and kept residuals, terms held
            x = sol.x
    # encoder jitter (beyond the paper): per-position angle corrections, then the rig again
    jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated) if jitter else None
    if jit is not None and jit["lr"] > JITTER_LR:
        prob.t = t_reported + np.radians(jit["correction_deg"])
        sol = refine(prob, x)
        x = sol.x
        jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated)
    applied = jit is not None and jit["lr"] > JITTER_LR
    if not applied and t_early is not None:
        # the stripes of both boards moved together but the offsets took it (paper rig, 270 deg
        # LiDAR yawed 90 deg, 0.02 deg jitter: offsets 140x the white noise, no jitter found,
        # the axis 22 mm off and the centres 3.5 mm): from the white start and the coherent
        # angles again
        prob.t, x = t_early, x_white.copy()
        x[[len(x) - n_rng + j for j in held]] = 0.0  # ranging terms held at the prior as above
        for _ in range(2):
            sol = refine(prob, x)
            x = sol.x
        jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated)
        prob.t = t_reported + np.radians(jit["correction_deg"])
        sol = refine(prob, x)
        x = sol.x
        jit = angle_jitter(prob, x, t_reported, loss, f_scale, correlated)
        applied = True
    t_final = t_reported + np.radians(jit["correction_deg"]) if applied else t_reported
    # re-base at the solution so the covariance is about it (x = 0); ranging terms free
    xr, rv = prob.split(_full(x))
    bR, bT = _boards(xr, prob.base)
    if decided is not None and not applied:
        # same angles and noise model; held terms moved the rig by less than its sigma, so
        # the Jacobian there (the covariance, about the local steps) is the same
        cov_all, null_all, s2 = decided[1]
        sandwich = decided[0].sandwich
        prob = rebased(prob, x, t_final)
        prob.sandwich = sandwich
    else:
        prob = rebased(prob, x, t_final)
        cov_all, null_all, s2 = _covariance(prob, fit_planes, loss, f_scale)
    base = prob.base
    cov, null = cov_all[:N_RIG, :N_RIG], null_all[:N_RIG]
    axis = Axis.from_point_direction(base.a, base.k)
    rs, rp, rc = prob.blocks(np.zeros(N_RIG + 2 * N_BOARD + n_rng))
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
    warn += jitter_offset_warnings(noise, jitter_deg)
    shift_chi2 = None
    if fit_planes:
        shift_chi2, w = _plane_shift(data, plane_prior, bR, bT, corner_floor_px)
        warn += w
    rmodel = None
    if n_rng:
        rmodel, rwarn = _ranging_model(rv, _ranging_sigmas(cov_all, prob.sandwich, rv, prob.dark), n_rng,
                                       prior, prob.dark, held)
        warn += rwarn
    info = {"null": null, "residual_variance": s2, "cost": float(sol.cost), "nfev": int(sol.nfev),
            "status": int(sol.status), "start": best, "fit_planes": fit_planes,
            "plane_prior": plane_prior, "plane_shift_chi2": shift_chi2,
            "residuals": {"scan_mm": rs, "stripe_px": rp, "corner_px": rc},
            "board_planes": tuple(Plane.from_normal_point(bR[j][:, 2], bT[j]) for j in range(2)),
            "n_scan": len(rs), "n_stripe": len(rp), "stripes": len(data.stripe_px) > 0,
            "rejected_scan": int((prob.scan.w == 0).sum()),
            "rejected_stripe": int((prob.stripe.w == 0).sum()), "jitter": jit,
            "scan_dark": prob.dark, "scan_edge_zones": data.edge_zones, "ranging_covariance": cov_all[N_RIG:, N_RIG:],
            "ranging_rig_covariance": cov_all[N_RIG:, :N_RIG]}
    model = JointModel(axis, psi_ref, base.R, base.T, cov, noise, tuple(warn), info,
                       jitter_deg, corrections, rmodel)
    scan_components = any(noise.get(f"scan{b}_{c}", 0.0) > 0 for b in range(2)
                          for c in ("offset_mm", "tilt_mm_per_mm"))
    if rmodel is not None and "offset" not in rmodel.held and correlated and scan_components:
        # an offset found with correlated scan errors in the noise model: those can absorb
        # the pattern that separates the offset from the LiDAR's position (a far solution
        # whose residuals then look correlated); the white-noise model must agree
        white = fit_joint_data(data, starts, fit_planes=fit_planes, loss=loss,
                               psi_ref_deg=psi_ref_deg, f_scale=f_scale, solver=solver,
                               correlated=False, corner_floor_px=corner_floor_px, jitter=jitter,
                               ranging=True, ranging_prior=prior, plane_prior=plane_prior,
                               board_cov=board_cov)
        disagree = _offset_disagreement(rmodel, white.ranging)
        if disagree > RANGING_SIGNIFICANCE:
            msg = (f"the range offset is {rmodel.offset_mm:.4g} +- {rmodel.offset_sigma_mm:.2g} mm "
                   f"with correlated scan errors in the noise model but "
                   f"{white.ranging.offset_mm:.4g} +- {white.ranging.offset_sigma_mm:.2g} mm with "
                   f"white noise ({disagree:.1f} sigma apart): the scans do not separate the "
                   "offset from the LiDAR's position; the white-noise fit is used (its sigmas "
                   "may be optimistic); give lidar.range_offset_mm and range_offset_sigma_mm in "
                   "dataset.json if the datasheet knows the offset")
            return replace(white, warnings=(msg,) + white.warnings)
    return model


def _coherent_start(prob: _Problem, x: np.ndarray, t_reported: np.ndarray, loss: str,
                    f_scale: float) -> np.ndarray | None:
    """Turntable angles corrected for a jitter both boards' stripes agree on (beyond the paper).

    At the white-noise start ``x``: when the boards' angle steps agree beyond chance
    (:func:`lidarcal.joint.jitter.coherent_jitter`, p below ``COHERENT_JITTER_P``), the
    reported angles plus the white-noise jitter corrections (:func:`angle_jitter`) about
    their line in psi (a common shift is the reference pose's, a trend the axis's: the
    white fit took part of the jitter there); else None."""
    _, p = coherent_jitter(board_steps(prob, x, loss, f_scale))
    if p >= COHERENT_JITTER_P:
        return None
    c = np.radians(angle_jitter(prob, x, t_reported, loss, f_scale, False)["correction_deg"])
    A = np.column_stack([np.ones_like(t_reported), t_reported])
    return t_reported + c - A @ np.linalg.lstsq(A, c, rcond=None)[0]


def _offset_disagreement(a: RangingModel, b: RangingModel | None) -> float:
    """How many combined sigmas two fits' range offsets are apart (0 without the second)."""
    if b is None:
        return 0.0
    s = float(np.hypot(a.offset_sigma_mm, b.offset_sigma_mm))
    return abs(a.offset_mm - b.offset_mm) / s if s > 0 else 0.0


def _conditional_step(H: np.ndarray | None, n: int, cols: list[int], delta: np.ndarray
                      ) -> np.ndarray:
    """Step of the other parameters that keeps the cost's quadratic model (information ``H``
    at the optimum) at its minimum when parameters ``cols`` move by ``delta``:
    ``-H_ff^-1 H_fc delta`` (the conditional mean of a Gaussian), as a full-length step
    (zero at ``cols``) of the ``n`` parameters. A warm start for the solve with those terms
    held. Zero without ``H`` (of ``n`` parameters) or when ``H_ff`` is rank-deficient
    (:func:`lidarcal.joint.solver._inverse`): where the data leave a direction undetermined
    the solve keeps it where it would have without the warm start."""
    step = np.zeros(n)
    if H is None or H.shape != (n, n):
        return step
    free = np.setdiff1d(np.arange(n), cols)
    C, null = _inverse(H[np.ix_(free, free)])
    if null.shape[1]:
        return step
    step[free] = -C @ (H[np.ix_(free, cols)] @ delta)
    return step if np.all(np.isfinite(step)) else np.zeros(n)


def _plane_shift(data: JointData, plane_prior: PlanePrior | None, bR: np.ndarray,
                 bT: np.ndarray, floor_px: float) -> tuple[float | None, list[str]]:
    """How far the fit moved the board poses from the camera's estimate: ``|L (p - p0)|^2``
    under the plane prior (:mod:`lidarcal.joint.planes_prior`; the corners' floored covariance
    when the corners entered instead), chi-square with 12 dof; a warning beyond
    ``PLANE_SHIFT_CHI2`` (the scans and stripes disagree with the board image or the
    camera)."""
    from .planes_prior import PLANE_SHIFT_CHI2, plane_prior_of

    if plane_prior is None:
        if data.corners_px is None or data.object_points is None:
            return None, []
        plane_prior = plane_prior_of(data, None, floor_px)
    chi2 = float(np.sum(plane_prior.residuals(bR, bT) ** 2))
    if chi2 <= PLANE_SHIFT_CHI2:
        return chi2, []
    sig = plane_prior.sigmas()
    return chi2, [(f"the fit moved the board planes far from the camera's estimate (chi-square "
                  f"{chi2:.0f} on 12 dof, expected below {PLANE_SHIFT_CHI2:.0f}; prior 1-sigma "
                  f"normal {sig['normal_deg'][0]:.3f}/{sig['normal_deg'][1]:.3f} deg, offset "
                  f"{sig['offset_mm'][0]:.2f}/{sig['offset_mm'][1]:.2f} mm): board.png or the "
                  "camera's intrinsics disagree with the scans and stripes; check the board "
                  "detection and the camera, or fit with fit_planes=False")]


def _ranging_sigmas(cov_all: np.ndarray, sandwich: np.ndarray | None, rv: np.ndarray,
                    dark: np.ndarray) -> np.ndarray:
    """1-sigma of the ranging terms: the larger of the model's and the cluster-robust one
    (positions as clusters, :func:`lidarcal.joint.solver._cluster_covariance`); the dark
    extra adds, in quadrature, the error of the returns near a square edge (partly dark,
    :data:`lidarcal.ranging.EDGE_BLEND_MM`): up to half the extra on that share of the
    returns, uniform, ``0.5 |extra| share / sqrt(3)``."""
    v = np.clip(np.diag(cov_all)[N_RIG:], 0, None)
    if sandwich is not None:
        v = np.maximum(v, np.clip(np.diag(sandwich)[N_RIG:], 0, None))
    if len(v) > 1 and len(dark):
        share = float(np.mean((dark > 0) & (dark < 1)))
        v[1] += (0.5 * abs(rv[1]) * share) ** 2 / 3.0
    return np.sqrt(v)


def _prior_conflicts(rv: np.ndarray, prior_arrays: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Ranging terms the fit put more than ``PRIOR_CONFLICT`` prior sigmas from the prior's
    mean (:data:`lidarcal.ranging.PRIOR_CONFLICT`): the data contradict the prior."""
    mu, sd = prior_arrays[0][:len(rv)], prior_arrays[1][:len(rv)]
    return np.abs(rv - mu) > PRIOR_CONFLICT * sd


def _conflict_warnings(rv: np.ndarray, conflict: np.ndarray, prior: RangingPrior) -> list[str]:
    """The warning for each term held because it contradicted its prior."""
    out = []
    sds = (prior.offset_sigma_mm, prior.dark_extra_sigma_mm)
    mus = (prior.offset_mm, prior.dark_extra_mm)
    for j in np.flatnonzero(conflict):
        what = "range offset" if j == 0 else "extra range of dark squares"
        out.append(f"the fit put the {what} at {rv[j]:.4g} mm, {abs(rv[j] - mus[j]) / sds[j]:.0f} "
                   f"sigmas of its prior ({mus[j]:g} +- {sds[j]:g} mm, {prior.source}) from the "
                   "prior's mean: the scans do not separate it from the LiDAR's position (noisy or "
                   "biased ranges?); the rig is fitted again with ranges taken as exact (no ranging "
                   "model; its sigmas do not include a range offset); if the LiDAR really reads "
                   "that far off, give lidar.range_offset_mm and lidar.range_offset_sigma_mm in "
                   "dataset.json")
    return out


def _ranging_model(rv: np.ndarray, sig: np.ndarray, n_rng: int, prior: RangingPrior,
                   dark: np.ndarray, held: tuple[int, ...] = ()) -> tuple[RangingModel, list[str]]:
    """The fitted ranging terms with their 1-sigma, and a warning for each term the data do
    not determine (posterior sigma above ``DATA_SHARE`` of the prior's: the prior decides).
    ``held``: terms held at the prior's mean (not significant)."""
    prior_sig = (prior.offset_sigma_mm, prior.dark_extra_sigma_mm)
    names = ("offset", "dark_extra")[:n_rng]
    determined, warn = [], []
    if prior.source == "dataset.json":
        src = (f"dataset.json lidar.range_offset_mm = {prior.offset_mm:g} +- "
               f"{prior.offset_sigma_mm:g} mm")
    elif prior.source == "default":
        src = (f"a wide default prior of 0 +- {prior.offset_sigma_mm:g} mm (dataset.json gives no "
               "lidar.range_offset_mm / range_offset_sigma_mm: give the datasheet's systematic error)")
    else:
        src = f"the {prior.source} prior {prior.offset_mm:g} +- {prior.offset_sigma_mm:g} mm"
    for j, name in enumerate(names):
        if not np.isfinite(sig[j]) or sig[j] > DATA_SHARE * prior_sig[j]:
            what = ("the range offset" if j == 0 else
                    f"the extra range of dark squares ({int(np.sum(dark > 0))} returns on black "
                    "squares)")
            warn.append(f"the data do not separate {what} from the rig (posterior sigma "
                        f"{sig[j]:.3g} mm against the prior's {prior_sig[j]:g} mm): "
                        + (f"{src} decides it, and its sigma is in every rig sigma" if j == 0 else
                           f"a wide prior of 0 +- {prior_sig[j]:g} mm decides it"))
        else:
            determined.append(name)
    rm = RangingModel(float(rv[0]), float(sig[0]), float(rv[1]) if n_rng > 1 else 0.0,
                      float(sig[1]) if n_rng > 1 else 0.0, prior=prior, estimated=names,
                      determined=tuple(determined), held=tuple(names[j] for j in held))
    return rm, warn



MIN_COVERAGE = 0.7  # scan span / stripe span below this: fragments of a board


def jitter_offset_warnings(noise: dict, jitter_deg: float) -> list[str]:
    """A warning when the encoder jitter found is not told apart from the stripes' offsets (beyond the paper).

    A turntable angle error shifts a position's whole stripe, as a stripe offset
    (:class:`lidarcal.joint.noise._Groups`) does. When the angle corrections
    (:func:`lidarcal.joint.angle_jitter`) are right, the offsets left are the stripes' own
    (on rendered rigs below the white noise); offsets still above ``JITTER_OFFSET_RATIO``
    times the stripes' white noise (``noise`` as :attr:`JointModel.noise`) mean the two
    share the signal and the corrected angles, so the poses' axis sigmas, are doubtful
    (wide rig, 0.02 deg jitter, 270-deg LiDAR yawed 90 deg: offsets 18x the white noise, a
    correction 0.07 deg the wrong way, a z axis 5 sigma off, and no warning before).
    """
    if jitter_deg <= 0.0:
        return []
    ratio = max(noise.get(f"stripe{b}_offset_px", 0.0) / max(noise.get(f"stripe{b}_px", 0.0), 1e-12)
                for b in range(2))
    if ratio <= JITTER_OFFSET_RATIO:
        return []
    return [(f"the turntable's encoder jitter ({jitter_deg:.4f} deg) is not told apart from the "
             f"stripes' offsets (still {ratio:.0f}x the stripes' pixel noise after the angle "
             "corrections): each position's corrected angle, so its pose's z/x axes, may be off by "
             "several sigma; use a turntable with a repeatable encoder, or more positions")]


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
    cover = np.min(np.where(np.isfinite(c := scan_coverage(data, model)), c, np.inf), axis=1)
    short = np.flatnonzero(cover < MIN_COVERAGE)  # positions without stripes: inf, never short
    if len(short) > 0.1 * n:
        out.append(f"at {len(short)} of {n} positions (indices {data.indices[short].tolist()[:10]}) "
                   f"the kept scan returns span less than {MIN_COVERAGE:.0%} of the board the laser "
                   f"stripe crosses (median {float(np.median(cover[short])):.0%}): the V split kept fragments "
                   "of the boards (ranges in steps, e.g. dark squares read farther?); the fit, and "
                   "its ranging terms, rest on those fragments")
    return out


def scan_coverage(data: JointData, model) -> np.ndarray:
    """Per position and board (N, 2): the span of the kept scan returns along the board's
    laser line over the span of its stripe centres (1: the scan covers what the camera sees
    of the line; NaN: too few points). Returns in the camera frame by ``model.pose_arrays``."""
    n_pos = data.n_positions
    R, T = model.pose_arrays(np.asarray(data.psi_deg, float))
    R, T = R.reshape(n_pos, 3, 3), T.reshape(n_pos, 3)
    nb = data.board_R[:, :, 2]
    line = np.cross(np.tile(nb, (n_pos, 1)), np.repeat(R[:, :, 2], 2, axis=0))  # group 2 i + b
    line /= np.maximum(np.linalg.norm(line, axis=1), 1e-12)[:, None]
    P = data.stripe_rays
    if len(P):  # the centres on their boards (eq. 5), as the fit has them
        P = _stripe_points(data, data.board_R, data.board_T)["P"]
    p, xy = data.scan_pos, data.scan_xy
    X = xy[:, :1] * R[p, :, 0] + xy[:, 1:] * R[p, :, 1] + T[p]
    spans = []
    for pts, pos, brd in ((P, data.stripe_pos, data.stripe_board), (X, p, data.scan_board)):
        g = 2 * np.asarray(pos) + np.asarray(brd)
        cnt = np.bincount(g, minlength=2 * n_pos)
        if np.all(g[1:] >= g[:-1]):  # grouped as built: each group's line spread over its rows
            proj = np.einsum("ij,ij->i", pts, np.repeat(line, cnt, axis=0))
        else:
            order = np.argsort(g, kind="stable")
            g = g[order]
            proj = np.einsum("ij,ij->i", pts[order], line[g]) if len(g) else np.zeros(0)
        span = np.zeros(2 * n_pos)
        ne = np.flatnonzero(cnt)
        if len(ne):
            starts = np.searchsorted(g, ne)
            span[ne] = np.maximum.reduceat(proj, starts) - np.minimum.reduceat(proj, starts)
        spans.append((span, cnt))
    (sp, cp), (ss, cs) = spans
    out = ss / np.maximum(sp, 1e-9)
    out[(cp < 5) | (cs < 2)] = np.nan
    return out.reshape(n_pos, 2)


def fit_joint(result, *, fit_planes: bool = False, loss: str = "soft_l1", stripes: bool = True,
              correlated: bool = True, board_poses: str = "pnp", psi_ref_deg: float | None = None,
              corner_floor_px: float = CORNER_FLOOR_PX, jitter: bool = True,
              ranging: bool = True, ranging_prior: RangingPrior | None = None,
              plane_prior: bool = False) -> JointModel:
    """Joint maximum-likelihood fit of the rig to all stripe pixels and scan points (beyond the paper).

    Parameters
    ----------
    result : lidarcal.pipeline.CalibrationResult
        Section 1 at every position (stripe centres, scan segments, single-shot
        poses with their segment <-> board assignment) and the section-2 models
        (``rigid_model``, ``paper_model``), used as starting points.
    fit_planes : bool
        Also refine both board poses (started from ``board_poses``); the
        chessboard corners' reprojection residuals then enter the fit. Measured on the
        rendered wide rigs (one board image, a camera calibrated from photos): the scans
        and stripes correct the planes (pose function's mean centre error over 5 seeds
        0.245 -> 0.217 mm); on the paper rigs it changes the errors by less than their
        spread; it runs the row-wise solver (several times slower). Default False: the
        planes held, their uncertainty propagated (:mod:`lidarcal.joint`).
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
    ranging : bool
        Estimate the LiDAR's range offset and the extra range of returns from
        black squares with the rig (:mod:`lidarcal.ranging`); False: ranges exact.
    ranging_prior : RangingPrior, optional
        Prior of the ranging terms; default from the dataset's ``lidar``
        (``range_offset_mm``, ``range_offset_sigma_mm``) or the wide default.
    plane_prior : bool
        Fit the board poses under the camera's estimate as a prior (its covariance from
        the corners, floored at ``corner_floor_px``, plus the intrinsics' uncertainty when
        the camera was calibrated from photos; :mod:`lidarcal.joint.planes_prior`)
        instead of holding them (or, with ``fit_planes``, of the raw corner residuals).

    Returns
    -------
    JointModel
        ``sigma(psi)`` gives 1-sigma uncertainties, ``warnings`` weak-setup warnings,
        ``noise`` the estimated noise scales, ``info`` residuals and solver details.
    """
    data = joint_data(result, board_poses)
    if not stripes:
        data = data.without_stripes()
    ds = getattr(result, "dataset", None)
    if ranging_prior is None and getattr(ds, "raw", None) is not None:
        ranging_prior = _ranging_prior(ds.raw, ds.dataset_json)
    prior, board_cov = None, None
    intrinsics = getattr(result, "intrinsics", None)
    if plane_prior:
        from .planes_prior import plane_prior_of

        prior = plane_prior_of(data, intrinsics, corner_floor_px)
    elif not fit_planes and intrinsics is not None and data.corners_px is not None:
        # planes held, camera from photos: the intrinsics' error moves both board poses (and
        # with them the rig) coherently; their covariance carries it into every sigma
        from .planes_prior import plane_prior_of

        board_cov = plane_prior_of(data, intrinsics, corner_floor_px).cov
    return fit_joint_data(data, [result.rigid_model, result.paper_model], fit_planes=fit_planes,
                          loss=loss, psi_ref_deg=psi_ref_deg, correlated=correlated,
                          corner_floor_px=corner_floor_px, jitter=jitter, ranging=ranging,
                          ranging_prior=ranging_prior, plane_prior=prior, board_cov=board_cov)
