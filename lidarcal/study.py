"""Accuracy study: Monte Carlo comparison of the paper's chain, the joint fit and a scan-only fit.

Every simulated rig is solved by all methods on the SAME observations, and the
estimates are compared with the simulator's truth:

* ``samples``: the single-shot poses of section 1 (eqs. 13-14), no turntable model;
* ``paper``: the paper's chain, section 2 (eqs. 15-27, :func:`lidarcal.turntable.fit_paper`);
* ``rigid``: the rigid rotation model fitted to the samples (:func:`~lidarcal.turntable.fit_rigid`);
* ``joint``: the joint fit of :mod:`lidarcal.joint` (scan points + stripe centres);
* ``joint_exact``: the joint fit with the ranges taken as exact (``ranging=False``:
  no range offset or dark-square terms, :mod:`lidarcal.ranging`);
* ``joint_planes``: the same, also refining both board poses with their corners;
* ``scan_only``: the Zhang-Pless style point-on-plane calibration: scan points
  must lie on the camera's board planes; with the turntable's rigid model it is
  the joint fit without stripe residuals. With a single V-board the scan alone
  cannot see the LiDAR slide along the hinge (and sees one tilt only weakly):
  the slide stays at the start (the rigid model), and the study shows what the
  stripes add.

What is simulated (no images are rendered: rendering is slow)
--------------------------------------------------------------
Geometry: :func:`lidarcal.synthetic.make_truth` for the rig preset (camera,
V-board, wall, posts, LiDAR on the turntable), with the setting's number of
positions and angle step; reported angles are exact unless the rig has
encoder noise.

Scans: :func:`lidarcal.synthetic.simulate_scans`, the full ray-cast LiDAR
model (beam footprint, mixed pixels at depth edges, Gaussian range noise of
``range_noise_mm``, spurious/dropped returns as the preset says). The
pipeline's own segmentation (:func:`lidarcal.scan.split_v`) and constrained
line fit (:func:`lidarcal.scan.fit_v_lines`) run on them. The setting's
ranging errors (``range_offset_mm``, ``dark_extra_mm``, ``range_quantum_mm``,
the simulator's :class:`~lidarcal.synthetic.RigConfig` fields) enter there,
in the scan model itself; the joint fit tells the returns from black squares by
the boards' ``blackness`` (here from the truth, :func:`board_blackness_truth`).

Ranging sweep (:func:`ranging_settings`, ``python -m lidarcal.study --ranging
OUT.csv``): range offset x dark-square extra, solved by :data:`RANGING_METHODS`
(the joint fit without the ranging model is ``joint_exact``);
:func:`summarise_ranging` adds what the ranging model recovered (estimates,
spread, reported sigma, 2-sigma coverage), :func:`plot_ranging` draws it.

Board corners: the true inner corners, moved as a whole by a small random
tilt (``corner_tilt_deg`` per in-plane axis, about the corners' centre) and
shift along the normal (``corner_offset_mm``), projected through the lens
(distortion included), plus isotropic Gaussian pixel noise
``corner_noise_px``. The rigid part stands for the correlated corner-detector
errors that a pose absorbs (on rendered paper-rig data the solvePnP planes
are off by 0.001-0.012 deg, rms ~0.004 deg, while the reprojection residuals
are only ~0.02-0.03 px). Both planes by :func:`lidarcal.board.board_view`
(homography, eqs. 2-3, and solvePnP) exactly as in the pipeline.

Stripe centres: the true stripe on each board (the scan plane cut with the
board plane) where it is lit (inside the chessboard area and the LiDAR's
aperture) is projected through the lens; one centre per image column (per
row for steep stripes), as the stripe extractor returns, with Gaussian noise
of ``stripe_noise_px`` across the stripe plus, per stripe, a random offset of
``stripe_offset_px`` (the correlated error measured on rendered images: the
sub-pixel centre estimator's bias changes slowly along a stripe and between
positions). Defaults are the values measured on rendered paper-rig datasets
(white ~0.03 px, offset ~0.004 px). Then the camera side of section 1.3
(laser plane, E, l1, l2, alpha) and the pose (eqs. 13-14) as in the pipeline.

Errors: centre (mm), z and x axes (deg) of every method's pose at every
position against the true pose; axis direction (deg) and axis offset near
the LiDAR (mm). Coverage: fraction of (position, quantity) pairs whose true
error is within twice the reported 1-sigma (:meth:`JointModel.sigma`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from .board import board_view
from .camera import project_points
from .evaluate import axis_direction_error_deg, pose_error
from .geometry import Plane, unit
from .io.dataset import BoardSpec, CameraModel
from .joint import JointModel, fit_joint
from .pipeline import CalibrationResult, PositionResult
from .pose import single_shot_pose
from .scan import fit_v_lines, scan_points, split_v
from .stripe import camera_lines_from_centres
from .turntable import axis_distance_mm, fit_paper, fit_rigid

METHODS = ("samples", "paper", "rigid", "joint", "joint_planes", "scan_only")
#: the ranging sweep's methods: ``joint_exact`` is the joint fit without the ranging model
RANGING_METHODS = ("samples", "paper", "rigid", "joint_exact", "joint")
QUANTITIES = ("centre_mm", "z_axis_deg", "x_axis_deg")
SWEPT = ("range_noise_mm", "stripe_noise_px", "n_positions")
PAPER_SPAN_DEG = 21.5  # the paper: 87 positions 0.25 deg apart


@dataclass(frozen=True)
class StudySetting:
    """One cell of the study: rig preset, sweep layout and noise levels.

    ``range_noise_mm`` None keeps the preset's. The sweep spans ``span_deg``
    with ``n_positions`` evenly spaced positions. ``range_offset_mm``,
    ``dark_extra_mm``, ``range_quantum_mm``: the LiDAR's systematic ranging
    errors, as the simulator's :class:`~lidarcal.synthetic.RigConfig` fields
    (0: exact ranges).
    """

    name: str = "paper-like"
    rig: str = "paper"
    n_positions: int = 22
    span_deg: float = PAPER_SPAN_DEG
    range_noise_mm: float | None = None
    stripe_noise_px: float = 0.03
    stripe_offset_px: float = 0.004
    corner_noise_px: float = 0.03
    corner_tilt_deg: float = 0.003
    corner_offset_mm: float = 0.01
    range_offset_mm: float = 0.0
    dark_extra_mm: float = 0.0
    range_quantum_mm: float = 0.0
    methods: tuple[str, ...] = METHODS

    @property
    def psi_step_deg(self) -> float:
        return self.span_deg / max(self.n_positions - 1, 1)


# ------------------------------------------------------------------- observations


def stripe_centres_truth(camera: CameraModel, board, laser: Plane, lidar_pose, rig,
                         samples: int = 4000) -> np.ndarray:
    """Noise-free stripe centres (N, 2) on one board: one per image column (or row).

    The line ``laser ^ board`` inside the chessboard area (the rect minus its
    white margin) and inside the LiDAR's aperture, projected with distortion,
    resampled at integer columns (rows when the stripe is steeper than 45 deg).
    """
    r = board.rect
    m = board.margin_mm
    n = laser.normal
    den = n @ r.e_v
    u = np.linspace(m, r.width - m, samples)
    v = (laser.d - n @ r.origin - u * (n @ r.e_u)) / den
    ok = (v >= m) & (v <= r.height - m)
    X = r.point(u[ok], v[ok])
    q = lidar_pose.inverse_apply(X)
    ang = np.degrees(np.arctan2(q[:, 1], q[:, 0]))
    lit = (q[:, 0] > 0) & (ang >= rig.lidar_angle_min_deg) & (ang <= rig.lidar_angle_max_deg)
    X = X[lit]
    if len(X) < 2:
        return np.zeros((0, 2))
    px = project_points(camera, X)
    d = px[-1] - px[0]
    axis = 0 if abs(d[0]) >= abs(d[1]) else 1
    order = np.argsort(px[:, axis])
    px = px[order]
    t = np.arange(np.ceil(px[0, axis]), np.floor(px[-1, axis]) + 1)
    other = np.interp(t, px[:, axis], px[:, 1 - axis])
    return np.column_stack([t, other]) if axis == 0 else np.column_stack([other, t])


def board_blackness_truth(camera: CameraModel, rect, pad_px: int = 2) -> dict:
    """A noise-free ``blackness`` crop of one board (1 on black squares, 0 elsewhere).

    What :func:`lidarcal.board.board_blackness` reads from the bright image,
    here from the truth: every pixel of the board's bounding box is cut with
    the board plane (eq. 5) and the square it lands on is looked up. Lets the
    joint fit tell the returns from black squares (:func:`lidarcal.ranging.black_parity`).
    Returns the :class:`~lidarcal.board.BoardView` fields ``blackness`` and
    ``blackness_origin``.
    """
    from .camera import backproject_to_plane
    from .synthetic.scene import BLACK

    px = project_points(camera, rect.corners())
    w, h = camera.image_size
    x0, y0 = np.clip(np.floor(px.min(0)).astype(int) - pad_px, 0, [w - 1, h - 1])
    x1, y1 = np.clip(np.ceil(px.max(0)).astype(int) + pad_px, 0, [w - 1, h - 1])
    xx, yy = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
    grid = np.column_stack([xx.ravel(), yy.ravel()]).astype(float)
    X = backproject_to_plane(camera, grid, Plane.from_normal_point(rect.normal, rect.origin))
    black = (rect.material(X) == BLACK).astype(float).reshape(xx.shape)
    return {"blackness": black, "blackness_origin": (int(x0), int(y0))}


@dataclass
class SimulatedRig:
    """A rig's truth and the section-1/2 result built from simulated observations."""

    truth: object  # lidarcal.synthetic.RigTruth
    result: CalibrationResult
    true_poses: dict = field(default_factory=dict)  # index -> Pose


def simulate_rig(seed: int, setting: StudySetting) -> SimulatedRig:
    """Simulate one rig's observations (see the module docstring) and run sections 1-2 on them."""
    from .synthetic import beam_angles_deg, get_rig, make_truth, simulate_scans

    rig = get_rig(setting.rig).with_(n_positions=int(setting.n_positions),
                                     psi_step_deg=float(setting.psi_step_deg))
    if setting.range_noise_mm is not None:
        rig = rig.with_(range_noise_mm=float(setting.range_noise_mm))
    rig = rig.with_(range_offset_mm=float(setting.range_offset_mm),
                    dark_extra_mm=float(setting.dark_extra_mm),
                    range_quantum_mm=float(setting.range_quantum_mm))
    truth = make_truth(seed, rig, with_discs=False, with_intrinsics=False)
    rng = np.random.default_rng([seed, 7919])
    camera = CameraModel(np.asarray(truth.K, float), np.asarray(truth.dist, float), rig.image_size,
                         source="simulated")
    spec = BoardSpec(tuple(rig.v_inner_corners), rig.v_square_mm)
    views = []
    for b in truth.boards:
        X = b.inner_corners_mm()
        c = X.mean(0)
        tilt = np.radians(rng.normal(0, setting.corner_tilt_deg, 2))
        rot = Rotation.from_rotvec(tilt[0] * b.rect.e_u + tilt[1] * unit(b.rect.e_v)).as_matrix()
        X = c + (X - c) @ rot.T + rng.normal(0, setting.corner_offset_mm) * b.rect.normal
        px = project_points(camera, X)
        view = board_view(camera, px + rng.normal(0, setting.corner_noise_px, px.shape), spec)
        views.append(replace(view, **board_blackness_truth(camera, b.rect)))
    order = np.argsort([v.centroid_px[0] for v in views])  # as find_v_boards: left to right
    views = [views[i] for i in order]
    tboards = [truth.boards[i] for i in order]

    R, T = truth.poses_at(truth.psi_true_deg)
    ranges = simulate_scans(truth.surfaces, R, T, rig, rng)
    angles = beam_angles_deg(rig)
    hint = np.array([0.0, -1.0, 0.0])
    positions, true_poses = [], {}
    for i, psi in enumerate(truth.psi_deg):
        pose_t = truth.pose_at(truth.psi_true_deg[i])
        laser = Plane.from_normal_point(pose_t.z_axis, pose_t.T)
        centres = []
        for b in tboards:
            c = stripe_centres_truth(camera, b, laser, pose_t, rig)
            across = 1 if (len(c) > 1 and np.ptp(c[:, 0]) >= np.ptp(c[:, 1])) else 0
            c[:, across] += rng.normal(0, setting.stripe_noise_px, len(c)) \
                + rng.normal(0, setting.stripe_offset_px)
            centres.append(c)
        try:
            if min(len(c) for c in centres) < 10:
                raise ValueError("stripe too short")
            cl = camera_lines_from_centres(camera, centres, [v.plane for v in views])
            rho = np.where(ranges[i] > 0, ranges[i], np.nan)
            seg = split_v(angles, rho, alpha=cl.alpha)
            pts = scan_points(angles, rho)
            ll = fit_v_lines(pts[seg.first], pts[seg.second], cl.alpha)
            pose = single_shot_pose(cl.l, cl.E, cl.alpha, ll, hint)
        except ValueError:
            continue  # as the pipeline's skip_failed
        positions.append(PositionResult(i, float(psi), cl, seg, ll, pose))
        true_poses[i] = pose_t
    if len(positions) < 3:
        raise ValueError(f"seed {seed}: only {len(positions)} positions could be solved")
    psi = np.array([p.psi_deg for p in positions])
    samples = [p.pose for p in positions]
    paper = fit_paper(psi, samples)
    rigid = fit_rigid(psi, samples, init=paper)
    ds = SimpleNamespace(v_board=spec, root=None)
    result = CalibrationResult(ds, camera, None, (views[0], views[1]), positions, [], paper, rigid,
                               "rigid")
    return SimulatedRig(truth, result, true_poses)


# ------------------------------------------------------------------------ evaluation


def _fit(method: str, result: CalibrationResult):
    if method == "samples":
        return None
    if method == "paper":
        return result.paper_model
    if method == "rigid":
        return result.rigid_model
    if method == "joint":
        return fit_joint(result)
    if method == "joint_exact":
        return fit_joint(result, ranging=False)
    if method == "joint_planes":
        return fit_joint(result, fit_planes=True)
    if method == "scan_only":  # the classic point-on-plane calibration: no jitter model
        return fit_joint(result, stripes=False, jitter=False)
    raise ValueError(f"unknown method {method!r}; expected one of {METHODS}")


def evaluate_rig(sim: SimulatedRig, methods: Sequence[str] = METHODS) -> pd.DataFrame:
    """One row per (method, position): true errors and, for joint fits, the reported sigmas."""
    res = sim.result
    truth = sim.truth
    psi = res.psi_deg
    idx = [p.index for p in res.positions]
    true = [sim.true_poses[i] for i in idx]
    near = np.mean([p.T for p in true], axis=0)
    rows = []
    for method in methods:
        t0 = time.perf_counter()
        m = _fit(method, res)
        dt = time.perf_counter() - t0
        joint = isinstance(m, JointModel)
        if m is None:
            est = [p.pose for p in res.positions]
        elif joint:  # at its jitter-corrected angles
            est = [m.pose(m.position_psi(i, a)) for i, a in zip(idx, psi)]
        else:
            est = m.pose(psi)
        sig = pd.DataFrame(m.position_sigma_columns(idx, psi)) if joint else None
        common = {"method": method, "fit_s": dt}
        if m is not None:
            common["axis_direction_deg"] = axis_direction_error_deg(m.axis.direction,
                                                                    truth.axis_direction)
            from .turntable import Axis

            common["axis_offset_mm"] = axis_distance_mm(
                m.axis, Axis.from_point_direction(truth.axis_point, truth.axis_direction), near)
        if sig is not None:
            common["sigma_axis_direction_deg"] = float(sig["axis_direction_deg"].iloc[0])
            common["n_warnings"] = len(m.warnings)
            if m.ranging is not None:  # the estimated ranging terms (mm)
                r = m.ranging
                common.update(est_offset_mm=r.offset_mm, sigma_offset_mm=r.offset_sigma_mm)
                if "dark_extra" in r.estimated:
                    common.update(est_dark_extra_mm=r.dark_extra_mm,
                                  sigma_dark_extra_mm=r.dark_extra_sigma_mm)
        for j, (i, e, t) in enumerate(zip(idx, est, true)):
            row = {**common, "index": i, "psi_deg": float(psi[j]), **pose_error(e, t)}
            if sig is not None:
                for q in QUANTITIES:
                    row[f"sigma_{q}"] = float(sig[q].iloc[j])
            rows.append(row)
    return pd.DataFrame(rows)


def run_rig(seed: int, setting: StudySetting) -> pd.DataFrame:
    """Simulate, solve and evaluate one rig; one row per (method, position)."""
    t0 = time.perf_counter()
    sim = simulate_rig(seed, setting)
    t_sim = time.perf_counter() - t0
    df = evaluate_rig(sim, setting.methods)
    df.insert(0, "seed", seed)
    df.insert(0, "setting", setting.name)
    for k, v in asdict(setting).items():
        if k not in ("name", "methods"):
            df[k] = v
    df["n_used"] = len(sim.result.positions)
    df["simulate_s"] = t_sim
    return df


def _run_rig_safe(args) -> pd.DataFrame:
    seed, setting = args
    try:
        return run_rig(seed, setting)
    except ValueError as e:  # a rig the simulator or section 1 cannot solve: recorded, not fatal
        return pd.DataFrame([{"setting": setting.name, "seed": seed, "method": "failed",
                              "error": str(e)}])


def run_study(settings: StudySetting | Sequence[StudySetting], n_rigs: int, seed: int = 0,
              workers: int = 1, progress: bool = False) -> pd.DataFrame:
    """Monte Carlo over ``n_rigs`` simulated rigs per setting; one row per (setting, rig, method, position).

    Rig ``j`` has seed ``seed * 100003 + j`` in every setting, so settings are
    compared on the same geometries (paired). Columns: ``setting, seed, method,
    fit_s, index, psi_deg, centre_mm, z_axis_deg, x_axis_deg`` (true errors),
    ``axis_direction_deg, axis_offset_mm``, the joint fits' ``sigma_*`` columns,
    the setting's parameters and ``n_used`` (positions solved). Summarise with
    :func:`summarise`.
    """
    settings = [settings] if isinstance(settings, StudySetting) else list(settings)
    jobs = [(seed * 100003 + j, s) for s in settings for j in range(n_rigs)]
    if workers > 1:
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(max_workers=workers) as ex:
            it = ex.map(_run_rig_safe, jobs)
            frames = list(_progress(it, len(jobs), progress))
    else:
        frames = [_run_rig_safe(j) for j in _progress(jobs, len(jobs), progress)]
    return pd.concat(frames, ignore_index=True)


def _progress(it, total: int, enabled: bool):
    if not enabled:
        return it
    from tqdm import tqdm

    return tqdm(it, total=total, desc="rigs", unit="rig")


def coverage(df: pd.DataFrame, k: float = 2.0) -> pd.DataFrame:
    """Fraction of (position, quantity) pairs whose true error is within ``k`` reported sigmas.

    Per (setting, method) for the methods that report sigmas; columns per
    quantity and ``all`` (the three together). Infinite sigmas count as covered.
    """
    have = df.dropna(subset=["sigma_centre_mm"]) if "sigma_centre_mm" in df else df.iloc[:0]
    out = {}
    for q in QUANTITIES:
        have = have.assign(**{f"in_{q}": have[q] <= k * have[f"sigma_{q}"]})
    g = have.groupby(["setting", "method"])
    for q in QUANTITIES:
        out[q] = g[f"in_{q}"].mean()
    res = pd.DataFrame(out)
    res["all"] = res[list(QUANTITIES)].mean(axis=1)
    return res


def summarise(df: pd.DataFrame) -> pd.DataFrame:
    """Mean true errors per (setting, method): centre, z, x, axis direction and offset, coverage.

    Errors are first averaged over the positions of each rig, then over rigs
    (the rigs are the independent samples); ``rigs`` counts them.
    """
    ok = df[df["method"] != "failed"]
    if ok.empty:
        return pd.DataFrame()
    per_rig = ok.groupby(["setting", "method", "seed"]).agg(
        centre_mm=("centre_mm", "mean"), z_axis_deg=("z_axis_deg", "mean"),
        x_axis_deg=("x_axis_deg", "mean"), centre_max_mm=("centre_mm", "max"),
        axis_direction_deg=("axis_direction_deg", "first"), axis_offset_mm=("axis_offset_mm", "first"),
        fit_s=("fit_s", "first"))
    out = per_rig.groupby(["setting", "method"]).mean()
    out["rigs"] = per_rig.groupby(["setting", "method"]).size()
    for col in SWEPT:  # the setting's swept parameters, for plotting against them
        if col in ok:
            out[col] = ok.groupby(["setting", "method"])[col].first().reindex(out.index)
    cov = coverage(ok)
    out["coverage_2sigma"] = cov["all"].reindex(out.index)
    if "sigma_axis_direction_deg" in ok:
        ax = ok.groupby(["setting", "method", "seed"]).first()
        ax = ax.dropna(subset=["sigma_axis_direction_deg"])
        inside = ax["axis_direction_deg"] <= 2 * ax["sigma_axis_direction_deg"]
        out["axis_coverage_2sigma"] = inside.groupby(["setting", "method"]).mean() \
            .reindex(out.index)
    return out


# ------------------------------------------------------------------------- settings


def sweep_settings(base: StudySetting | None = None, *,
                   range_noise_mm: Sequence[float] = (0.5, 1.0, 2.0, 4.0),
                   stripe_noise_px: Sequence[float] = (0.01, 0.03, 0.1, 0.3),
                   n_positions: Sequence[int] = (5, 10, 22, 44, 87),
                   methods: Sequence[str] | None = None) -> list[StudySetting]:
    """The study's sweeps around ``base``: range noise, stripe noise (offset scaled with it),
    number of positions over the same span. Names say what varies; sweep values equal to
    the baseline are left out (the "baseline" row is that point of every sweep)."""
    b = base or StudySetting()
    if b.range_noise_mm is None:  # the preset's value, explicit, so the sweep can match it
        from .synthetic import get_rig

        b = replace(b, range_noise_mm=float(get_rig(b.rig).range_noise_mm))
    if methods is not None:
        b = replace(b, methods=tuple(methods))
    out = [replace(b, name="baseline")]
    out += [replace(b, name=f"range={v:g}mm", range_noise_mm=v) for v in range_noise_mm]
    ratio = b.stripe_offset_px / b.stripe_noise_px if b.stripe_noise_px > 0 else 0.0
    out += [replace(b, name=f"stripe={v:g}px", stripe_noise_px=v, stripe_offset_px=ratio * v)
            for v in stripe_noise_px]
    out += [replace(b, name=f"positions={n}", n_positions=n) for n in n_positions]
    # a sweep value equal to the baseline would repeat it: keep the baseline only
    same = lambda s: replace(s, name=b.name) == b
    return [out[0]] + [s for s in out[1:] if not same(s)]


def small_settings() -> list[StudySetting]:
    """A quick study (< 60 s with 2 rigs): baseline, noisy range, noisy stripe, few positions."""
    b = StudySetting(n_positions=10, methods=("samples", "paper", "rigid", "joint", "scan_only"))
    return [replace(b, name="baseline"), replace(b, name="range=3mm", range_noise_mm=3.0),
            replace(b, name="stripe=0.15px", stripe_noise_px=0.15, stripe_offset_px=0.02),
            replace(b, name="positions=5", n_positions=5)]


def ranging_settings(offsets_mm: Sequence[float] = (0.0, 8.0, 20.0),
                     dark_extras_mm: Sequence[float] = (0.0, 3.0, 6.0),
                     base: StudySetting | None = None) -> list[StudySetting]:
    """The ranging sweep: every (range offset, dark-square extra) pair on the baseline rig
    (22 positions), solved by :data:`RANGING_METHODS`. Named ``offset=8mm dark=6mm``."""
    b = replace(base or StudySetting(), methods=RANGING_METHODS)
    return [replace(b, name=f"offset={o:g}mm dark={d:g}mm", range_offset_mm=float(o),
                    dark_extra_mm=float(d)) for o in offsets_mm for d in dark_extras_mm]


def summarise_ranging(df: pd.DataFrame, k: float = 2.0) -> pd.DataFrame:
    """:func:`summarise` per (setting, method) plus the true ranging terms and what the joint
    fit recovered: mean estimate, its rig-to-rig spread, mean reported 1-sigma and the share
    of rigs whose estimate is within ``k`` sigmas of the truth (``*_coverage``). The dark
    extra's columns are empty where the fit did not estimate it."""
    out = summarise(df)
    if out.empty:
        return out
    ok = df[df["method"] != "failed"]
    g = ok.groupby(["setting", "method"])
    for col in ("range_offset_mm", "dark_extra_mm"):
        out[col] = g[col].first().reindex(out.index)
    per_rig = ok.groupby(["setting", "method", "seed"]).first()
    for est, sig, true, name in (("est_offset_mm", "sigma_offset_mm", "range_offset_mm", "offset"),
                                 ("est_dark_extra_mm", "sigma_dark_extra_mm", "dark_extra_mm",
                                  "dark_extra")):
        if est not in per_rig:
            continue
        r = per_rig.dropna(subset=[est])
        gr = r.groupby(["setting", "method"])
        out[f"{name}_est_mm"] = gr[est].mean().reindex(out.index)
        out[f"{name}_spread_mm"] = gr[est].std().reindex(out.index)
        out[f"{name}_sigma_mm"] = gr[sig].mean().reindex(out.index)
        inside = (r[est] - r[true]).abs() <= k * r[sig]
        out[f"{name}_coverage"] = inside.groupby(["setting", "method"]).mean().reindex(out.index)
    return out


def plot_ranging(summary: pd.DataFrame, methods: Sequence[str] = ("rigid", "joint_exact", "joint")):
    """Mean true centre error of each method against the range offset, one line per dark
    extra (left), and the joint fit's offset and dark-extra estimates against the truth with
    their mean reported 2-sigma (right); the ranging sweep's summary
    (:func:`summarise_ranging`)."""
    import matplotlib.pyplot as plt

    s = summary.reset_index()
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 3.8), constrained_layout=True)
    styles = dict(zip(sorted(s["dark_extra_mm"].unique()), ("-", "--", ":", "-.")))
    for i, m in enumerate(methods):
        for dark, ls in styles.items():
            d = s[(s.method == m) & (s.dark_extra_mm == dark)].sort_values("range_offset_mm")
            if len(d):
                ax.plot(d["range_offset_mm"], d["centre_mm"], "o", ls=ls, color=f"C{i}",
                        label=f"{m}, dark {dark:g} mm")
    ax.set_yscale("log")
    ax.set_xlabel("range offset (mm)")
    ax.set_ylabel("mean true centre error (mm)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=len(methods))
    j = s[s.method == "joint"]
    for col, name, mk in (("range_offset_mm", "offset", "o"), ("dark_extra_mm", "dark_extra", "s")):
        if f"{name}_est_mm" in j:
            d = j.dropna(subset=[f"{name}_est_mm"])
            bx.errorbar(d[col] + (0.3 if name == "dark_extra" else 0.0), d[f"{name}_est_mm"],
                        yerr=2 * d[f"{name}_sigma_mm"], fmt=mk, capsize=3, label=f"{name} (+-2 sigma)")
    lim = [0, max(s["range_offset_mm"].max(), s["dark_extra_mm"].max()) + 1]
    bx.plot(lim, lim, "k-", lw=0.8, label="truth")
    bx.set_xlabel("true term (mm)")
    bx.set_ylabel("joint fit's estimate (mm)")
    bx.grid(True, alpha=0.3)
    bx.legend(fontsize=8)
    return fig


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lidarcal.study", description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", help="CSV file for the per-position rows")
    ap.add_argument("--full", metavar="OUT.csv", help="the full study (all sweeps, --rigs rigs each)")
    ap.add_argument("--ranging", metavar="OUT.csv",
                    help="the ranging sweep (range offset x dark-square extra, --rigs rigs each, "
                         "default 8)")
    ap.add_argument("--offsets", type=float, nargs="+", default=[0.0, 8.0, 20.0], metavar="MM",
                    help="range offsets of the ranging sweep (mm; default 0 8 20)")
    ap.add_argument("--darks", type=float, nargs="+", default=[0.0, 3.0, 6.0], metavar="MM",
                    help="dark-square extras of the ranging sweep (mm; default 0 3 6)")
    ap.add_argument("--rigs", type=int, default=None, help="rigs per setting (default 50 full, 2 small)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    args = ap.parse_args(argv)
    if sum(x is not None for x in (args.full, args.ranging, args.out)) != 1:
        ap.error("give one of OUT.csv (small study), --full OUT.csv, --ranging OUT.csv")
    out = args.full or args.ranging or args.out
    if args.ranging:
        settings, n = ranging_settings(args.offsets, args.darks), args.rigs or 8
    else:
        settings = sweep_settings() if args.full else small_settings()
        n = args.rigs or (50 if args.full else 2)
    df = run_study(settings, n, args.seed, workers=args.workers, progress=sys.stderr.isatty())
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    df.to_csv(out, index=False)
    summary = summarise_ranging(df) if args.ranging else summarise(df)
    summary.to_csv(summary_path(out))
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(summary.to_string(float_format=lambda v: f"{v:.4g}"))
    return 0


def summary_path(out: str | os.PathLike) -> str:
    """Where :func:`main` writes the :func:`summarise` table next to the per-position rows."""
    root, _ = os.path.splitext(os.fspath(out))
    return root + "_summary.csv"


def plot_sweeps(summary: pd.DataFrame, quantity: str = "centre_mm",
                methods: Sequence[str] = ("paper", "rigid", "joint", "scan_only")):
    """Mean true error of each method versus range noise, stripe noise and number of
    positions (one panel each; the baseline setting is a point of every sweep)."""
    import matplotlib.pyplot as plt

    s = summary.reset_index()
    base = s[s.setting == "baseline"]
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), constrained_layout=True)
    for ax, (col, prefix, label) in zip(axes, (("range_noise_mm", "range=", "range noise (mm)"),
                                                ("stripe_noise_px", "stripe=", "stripe noise (px)"),
                                                ("n_positions", "positions=", "positions"))):
        sel = pd.concat([base, s[s.setting.str.startswith(prefix)]])
        for m in methods:
            d = sel[sel.method == m].sort_values(col)
            if len(d):
                ax.plot(d[col], d[quantity], "o-", label=m)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel(f"mean true error, {quantity}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend()
    return fig


if __name__ == "__main__":
    raise SystemExit(main())
