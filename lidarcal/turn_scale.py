"""Does the turntable turn by the reported angles? The encoder's scale from the single-shot poses.

Eq. (15) of the paper (and every pose function here: the paper's chain, the rigid fit, the
joint fit) takes the reported angles as exact: the LiDAR turns by ``psi_j - psi_i`` between
two positions. An encoder read through a wrong gear ratio or counts-per-degree reports
``(1 + e)`` times the turn; :func:`lidarcal.turntable.angle_scale` refuses a ratio off by
more than 10 % and warns from 3 %, but 1 % over a 21.5 deg sweep already turns the poses at
the sweep's ends 0.1 deg from the fitted model (combo3 ``paper_psiscale1pct``: the joint
fit's z axes 0.06 deg, centres up to 2.2 mm from the truth, at 5.8 sigma).

:func:`turn_scale` measures the turn per reported degree from the samples: each sample's
rotation angle about the axis, relative to the sample nearest the middle of the sweep, is
regressed on ``psi`` with Theil-Sen (:func:`scipy.stats.theilslopes`, robust to a minority
of wrong samples) and its 95 % interval gives the slope's sigma (bundled paper rig:
0.999997 +- 0.00002; 1 % off: 0.9900 +- 0.00007). :func:`turn_scale_spread` is what the
scale does to the poses: the rigid fit (eq. 15 rigidly about one axis) with the angles as
reported against the one with the turns the samples show, per position.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import theilslopes

from .geometry import Line3D, Pose, line_difference, unit
from .turntable import fit_rigid

#: a slope this many of its sigmas from 1 is the encoder's scale, not the samples' noise
SCALE_SIGNIFICANCE = 5.0
_Z95 = 1.959963984540054  # half width of a 95 % interval in sigmas


@dataclass(frozen=True)
class TurnScale:
    """Turn of the samples per reported degree (``slope``, 1 = exact) and its 1-sigma."""

    slope: float
    sigma: float
    n: int

    @property
    def significant(self) -> bool:
        return bool(np.isfinite(self.sigma) and abs(self.slope - 1.0) > SCALE_SIGNIFICANCE * self.sigma)


def turn_scale(psi_deg, samples: Sequence[Pose]) -> TurnScale:
    """The samples' turn per reported degree (eq. 15's premise, slope 1), by Theil-Sen.

    Angles ``theta_i`` of ``R_i R_ref^T`` about the axis ``k`` (the median of the rotation
    vectors per reported degree; ``ref`` the sample nearest the median angle) regressed on
    ``psi_i - psi_ref``; sigma from the slope's 95 % interval. Fewer than 4 samples: NaN sigma.
    """
    psi = np.asarray(psi_deg, dtype=float).ravel()
    if len(psi) < 4 or np.ptp(psi) <= 0:
        return TurnScale(1.0, float("nan"), len(psi))
    R = np.stack([np.asarray(q.R, float) for q in samples])
    ref = int(np.argmin(np.abs(psi - np.median(psi))))
    x = psi - psi[ref]
    rv = Rotation.from_matrix(R @ R[ref].T).as_rotvec()
    m = x != 0
    k = unit(np.median(rv[m] / x[m, None], axis=0))
    theta = np.degrees(rv @ k)
    slope, _, lo, hi = theilslopes(theta, x, alpha=0.95)
    return TurnScale(float(slope), float((hi - lo) / (2.0 * _Z95)), len(psi))


def turn_scale_spread(psi_deg, samples: Sequence[Pose], rigid, scale: TurnScale) -> dict:
    """Per position how far the rigid fit with the reported angles (``rigid``) is from the
    rigid fit with the turns the samples show (``psi_mid + slope (psi - psi_mid)``): centre
    (mm), z and x axes (deg) keyed by position order, and the axes' direction (deg) and
    distance near the LiDAR (mm)."""
    psi = np.asarray(psi_deg, dtype=float)
    mid = float(np.median(psi))
    turned = mid + scale.slope * (psi - mid)
    other = fit_rigid(turned, samples, init=rigid)
    Ra, Ta = rigid.pose_arrays(psi)
    Rb, Tb = other.pose_arrays(turned)

    def angle(col: int) -> np.ndarray:
        c = np.einsum("ni,ni->n", Ra[:, :, col], Rb[:, :, col])
        return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))

    direction_deg, point_mm = line_difference(Line3D(rigid.axis.point, rigid.axis.direction),
                                              Line3D(other.axis.point, other.axis.direction), Ta.mean(0))
    return {"centre_mm": np.linalg.norm(Ta - Tb, axis=1), "z_axis_deg": angle(2),
            "x_axis_deg": angle(0), "axis_direction_deg": direction_deg, "axis_point_mm": point_mm}


def turn_scale_warnings(res, psi: np.ndarray, samples: Sequence[Pose], limit_sigmas: float) -> list[str]:
    """A warning naming positions.csv when the single-shot poses turn by a significantly
    different angle than the reported one (an encoder's scale error below the 3 % that
    :func:`lidarcal.calibration_checks.check_angle_scale` names) and that moves some position by more
    than ``limit_sigmas`` of the joint fit's 1-sigma (``res`` a
    :class:`lidarcal.pipeline.CalibrationResult` with its joint model); 'sigma' is then
    widened by what the scale does to the rigid fit (stored as the joint model's
    ``info["turn_scale_spread"]``, applied by :func:`lidarcal.pipeline.sigma_block`)."""
    sc = turn_scale(psi, samples)
    if not sc.significant:
        return []
    spread = turn_scale_spread(psi, samples, res.rigid_model, sc)
    cols = res.joint_model.position_sigma_columns([p.index for p in res.positions], psi)
    ratio = max(float(np.max(spread[q] / cols[q])) for q in ("centre_mm", "z_axis_deg", "x_axis_deg"))
    if not ratio > limit_sigmas:
        return []
    idx = [p.index for p in res.positions]
    res.joint_model.info["turn_scale_spread"] = {
        **{q: dict(zip(idx, map(float, spread[q]))) for q in ("centre_mm", "z_axis_deg", "x_axis_deg")},
        **{q: spread[q] for q in ("axis_direction_deg", "axis_point_mm")}}
    return [(f"{res.dataset.root / 'positions.csv'}: the single-shot poses turn {sc.slope:.5f} +- "
             f"{sc.sigma:.1g} deg per reported degree ({100 * (sc.slope - 1):+.2f} %), not 1: the pose "
             "functions take psi_deg as exact, which moves the rigid fit's poses by up to "
             f"{float(np.max(spread['centre_mm'])):.2g} mm and {float(np.max(spread['z_axis_deg'])):.2g} "
             f"deg ({ratio:.1f} sigma); 'sigma' is widened to cover it; check the encoder's counts per "
             "degree or gear ratio and write the turntable's true angles in psi_deg")]
