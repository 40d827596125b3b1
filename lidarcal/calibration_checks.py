"""The calibration's self-checks after the fits (the pipeline's "never silently wrong"):
the joint fit against the rigid fit (section 2) and the range offset that may explain
their distance, the z-axis hint that picks the mirror assignment (section 1.5), the
reported turntable angles against the samples' turn, the capture plan; and the pose
function evaluated at the positions (``pose_rows``), which the checks and
``calibration.json`` share. Split from :mod:`lidarcal.pipeline`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .geometry import Line3D, Pose, line_difference
from .io.dataset import Dataset, DatasetError
from .turntable import angle_scale

if TYPE_CHECKING:
    from .pipeline import CalibrationResult


def pose_rows(model, psi: dict[int, float]) -> list[dict]:
    """The pose function ``model`` at every position, as :meth:`CalibrationResult.fitted`
    (evaluated at all angles in one ``pose_arrays`` call); with a model that corrects the
    encoder's angles, each row also gives ``psi_corrected_deg``, the angle it was evaluated at."""
    at = model.position_psi if getattr(model, "angle_corrections", None) else None
    idx = sorted(psi)
    psi_at = [at(i, psi[i]) for i in idx] if at else [psi[i] for i in idx]
    R, T = model.pose_arrays(np.asarray(psi_at, dtype=float))
    return [{"index": i, "psi_deg": psi[i], **({"psi_corrected_deg": a} if at else {}),
             "R": r.tolist(), "T_mm": t.tolist()} for i, a, r, t in zip(idx, psi_at, R, T)]


#: the joint and the rigid pose functions fit the same observations: their centres differ by a
#: small share of the joint fit's own 1-sigma (at most 0.18 sigma over 45 rendered camera and
#: board variants of scripts/rig_sweep.py); 3.6 sigma was a joint fit 57 mm off (6 px squares,
#: 2-deg sweep), the rigid one 5.5 mm
JOINT_RIGID_SIGMAS = 1.0
#: a range offset explains the joint fit's distance from the rigid fit only when this many of
#: its sigmas from zero (combo r29, a true -30 mm offset: found -30.0 +- 0.6 mm; combo r17,
#: 1 % range noise, no offset: a spurious 19 +- 6.1 mm with the joint fit 20 mm off)
OFFSET_EXPLAINS_SIGMAS = 5.0


def joint_rigid_warnings(res: CalibrationResult) -> list[str]:
    """A warning when the joint fit's LiDAR centres (:mod:`lidarcal.joint`) leave the rigid
    fit's (section 2, a rigid rotation about the axis fitted to the single-shot poses) by more
    than ``JOINT_RIGID_SIGMAS`` of the joint fit's own 1-sigma at some position: then the
    joint fit's linearised sigmas do not describe its error (a nearly degenerate setup, a
    noise model that took a systematic error for noise).

    Neither fit is then known to be the right one (measured: the joint fit was 3.5 / 57 /
    1.1 mm off where the rigid one was 0.26 / 5.5 / 0.03 mm, and 0.02 mm where the rigid one
    was 32 mm off, a range offset): ``poses`` stays the joint fit's and its ``sigma`` is
    widened to cover both fits (:func:`rigid_spread`, stored in the joint model's
    ``info["rigid_spread"]``, applied by :func:`sigma_block`). A disagreement that the range
    offset the joint fit found explains (the single-shot poses use raw ranges; a range offset
    ``o`` moves the V's hinge, so the LiDAR, by up to ``o / sin(alpha / 2)``; the offset
    ``OFFSET_EXPLAINS_SIGMAS`` of its sigmas from zero) is reported as such. Its sigmas stay
    as they are only when dataset.json's own prior confirms that offset
    (:func:`offset_confirmed_by_prior`): scans of planes do not tell a range offset from a
    range bias growing with the incidence angle, which leaves the LiDAR near the rigid fit
    (combo3, a 10 mm incidence bias ``k (1/cos - 1)``: the joint fit found a -9.2 +- 0.8 mm
    offset and sat 10.3 mm from the truth at 12.7 sigma, the rigid fit 0.66 mm; 30 mm on
    the wide rig: 35.4 and 3.1 mm), so otherwise the sigmas are widened to cover both fits."""
    spread = rigid_spread(res)
    if spread is None:
        return []
    ratio, d, sig = spread["ratio"], spread["centre_mm"], spread["sigma_mm"]
    worst = max(ratio, key=ratio.get)
    if ratio[worst] <= JOINT_RIGID_SIGMAS:
        return []
    rng = getattr(res.joint_model, "ranging", None)
    confirmed = rng is not None and offset_confirmed_by_prior(rng)  # held at that prior: applied
    if (rng is not None and ("offset" not in rng.held or confirmed)
            and abs(rng.offset_mm) > OFFSET_EXPLAINS_SIGMAS * rng.offset_sigma_mm):
        half = 0.5 * float(np.mean([p.camera_lines.alpha for p in res.positions]))
        bound = (abs(rng.offset_mm) + 3.0 * rng.offset_sigma_mm) / max(np.sin(half), 0.1)
        if all(d[i] <= bound + 3.0 * sig[i] for i in d):
            found = (f"the joint fit's LiDAR centre is {d[worst]:.2f} mm from the rigid fit's at "
                     f"position {worst}, as the range offset it found ({rng.offset_mm:.3g} +- "
                     f"{rng.offset_sigma_mm:.2g} mm) explains: the single-shot poses, "
                     "'poses_rigid' and 'poses_paper' use the raw ranges")
            if confirmed:
                return [found + f" (the offset agrees with dataset.json's prior {rng.prior.offset_mm:g} "
                                f"+- {rng.prior.offset_sigma_mm:g} mm)"]
            res.joint_model.info["rigid_spread"] = spread
            return [found + (". But scans of the two boards' planes do not tell a range offset from "
                             "a range bias growing with the incidence angle (k (1/cos - 1) reads as an "
                             "offset -k and a shift of the LiDAR by about k / sin(alpha/2)), which "
                             "would leave the LiDAR where the rigid fit puts it: 'sigma' is widened "
                             "to cover both fits; if the LiDAR's zero offset is known (datasheet, a "
                             "range to a measured distance), give lidar.range_offset_mm and "
                             "lidar.range_offset_sigma_mm in dataset.json")]
    res.joint_model.info["rigid_spread"] = spread
    return [(f"the joint fit's LiDAR centre is {d[worst]:.2f} mm ({ratio[worst]:.1f} sigma) from the "
             f"rigid fit's at position {worst}: the joint sigmas understate its error here; "
             "'sigma' is widened to cover both fits; compare 'poses_rigid', check the warnings "
             "above (sweep span, board squares, jitter) or calibrate with --method rigid")]


def offset_confirmed_by_prior(rng) -> bool:
    """Whether dataset.json's own range-offset prior (:class:`lidarcal.ranging.RangingPrior`)
    already says the LiDAR reads ``OFFSET_EXPLAINS_SIGMAS`` of its sigmas off zero and agrees
    with the offset the joint fit found (within 3 sigma of both): then the offset is the
    LiDAR's, not a range bias growing with the incidence angle, which plane scans cannot tell
    from it (``k (1/cos(theta) - 1) = -k + k``, the constant ``k`` along both board normals
    being a shift of the LiDAR)."""
    pr = getattr(rng, "prior", None)
    if pr is None or pr.source != "dataset.json":
        return False
    return bool(abs(pr.offset_mm) > OFFSET_EXPLAINS_SIGMAS * pr.offset_sigma_mm
                and abs(rng.offset_mm - pr.offset_mm) <= 3.0 * np.hypot(pr.offset_sigma_mm,
                                                                        rng.offset_sigma_mm))


def rigid_spread(res: CalibrationResult) -> dict | None:
    """Per position, how far the joint fit's pose is from the rigid fit's (centre mm, z and x
    axes deg), its centre in the joint 1-sigma (``ratio``, ``sigma_mm``), and the two axes'
    direction angle (deg) and distance near the LiDAR (mm); None without positions."""
    pos = res.positions
    if not pos:
        return None
    psi = {p.index: p.psi_deg for p in pos}
    sig = res.joint_model.position_sigma_columns([p.index for p in pos],
                                                 [p.psi_deg for p in pos])["centre_mm"]
    sig = dict(zip([p.index for p in pos], sig))
    joint = {r["index"]: r for r in pose_rows(res.joint_model, psi)}
    rigid = {r["index"]: r for r in pose_rows(res.rigid_model, psi)}

    def angle(a, b, col):
        u, v = np.asarray(a["R"])[:, col], np.asarray(b["R"])[:, col]
        return float(np.degrees(np.arccos(np.clip(u @ v, -1.0, 1.0))))

    d = {i: float(np.linalg.norm(np.subtract(joint[i]["T_mm"], rigid[i]["T_mm"]))) for i in psi}
    ratio = {i: d[i] / sig[i] for i in psi if np.isfinite(sig[i]) and sig[i] > 0}
    if not ratio:
        return None
    ja, ra = res.joint_model.axis, res.rigid_model.axis
    direction_deg, point_mm = line_difference(Line3D(ra.point, ra.direction), Line3D(ja.point, ja.direction),
                                              res.joint_model.T_ref)
    return {"ratio": ratio, "centre_mm": d, "sigma_mm": sig,
            "z_axis_deg": {i: angle(joint[i], rigid[i], 2) for i in psi},
            "x_axis_deg": {i: angle(joint[i], rigid[i], 0) for i in psi},
            "axis_direction_deg": direction_deg, "axis_point_mm": point_mm}


def check_z_axis_hint(ds: Dataset, samples: list[Pose]) -> list[str]:
    """The hint must pick the mirror assignment (section 1.5, :func:`lidarcal.pose.single_shot_pose`):
    within ~6 deg of perpendicular to the samples' z axis (median ``|cos| < 0.1``) the choice is
    a coin toss, so stop, naming dataset.json and the z axis found; more than 60 deg away
    (``|cos| < 0.5``, a hint meant for another mounting?) a warning."""
    dots = np.array([q.info.get("hint_dot", 1.0) for q in samples])
    hint = np.asarray(ds.lidar.z_axis_hint, float)
    z = np.median([q.z_axis for q in samples], axis=0)
    z = np.round(z / np.linalg.norm(z), 2) + 0.0
    cos = float(np.median(np.abs(dots)))
    if cos >= 0.5:
        return []
    if cos >= 0.1:
        return [(f"{ds.dataset_json}: lidar.z_axis_hint {hint.tolist()} is "
                 f"{np.degrees(np.arccos(cos)):.0f} deg from the LiDAR's z axis found ({z.tolist()}); "
                 "if the LiDAR is mounted otherwise, the pose is its mirror image: check the hint")]
    raise DatasetError(ds.dataset_json,
                       f"lidar.z_axis_hint {hint.tolist()} is almost perpendicular to the LiDAR's z axis "
                       f"(+-{z.tolist()} in the camera frame): it cannot tell the pose from its mirror "
                       "image; set lidar.z_axis_hint to the LiDAR's z direction (the scan plane's "
                       f"normal, x cross y of the scanner), {z.tolist()} or {(-z + 0.0).tolist()}")


def check_angle_scale(ds: Dataset, psi: np.ndarray, samples: list[Pose]) -> list[str]:
    """The reported angles must measure the samples' turn (:func:`lidarcal.turntable.angle_scale`):
    off by more than 10 % (and 0.2 deg, 4x the worst sample noise seen) is fatal, naming
    positions.csv; by 3-10 % a warning."""
    sc = angle_scale(psi, samples)
    off = abs(sc.turned_deg - sc.reported_deg)
    text = (f"the single-shot poses turn {sc.turned_deg:.4g} deg between positions whose psi_deg "
            f"differ by {sc.reported_deg:.4g} deg (median of {sc.pairs} pairs, ratio {sc.ratio:.3g})")
    if off > 0.2 and abs(sc.ratio - 1.0) > 0.10:
        raise DatasetError(ds.root / "positions.csv",
                           f"{text}; psi_deg must be the turntable angle in degrees (radians? encoder "
                           "counts? a gear ratio?)")
    if off > 0.2 and abs(sc.ratio - 1.0) > 0.03:
        return [f"{ds.root / 'positions.csv'}: {text}; is psi_deg the turntable angle in degrees?"]
    return []


def setup_warnings(psi: np.ndarray, results: list) -> list[str]:
    """Warnings on the capture plan: a short sweep span (the axis poorly determined) or few
    positions (little redundancy for the pose function)."""
    out = []
    span = float(np.ptp(psi))
    if span < 5.0:
        out.append(f"turntable positions span only {span:.2f} deg: the axis is poorly "
                   "determined; sweep at least ~10 deg")
    if len(results) < 10:
        out.append(f"only {len(results)} positions: the pose function has little redundancy")
    return out
