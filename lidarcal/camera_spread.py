"""What the photos' camera's own uncertainty does to the joint fit's poses (never silently wrong).

The joint fit (:mod:`lidarcal.joint`) carries the intrinsics' covariance into the board
planes (``A Sigma_K A^T``, :mod:`lidarcal.joint.planes_prior`) but takes the stripe pixels'
rays (eq. 5, section 1.2) through the calibrated camera as exact. A camera error moves
both coherently: a principal point 0.6 px off turns every ray, and with them the scan
plane the stripes trace, by ~0.03 deg, which the held rays leave out of ``sigma``.
Measured on the clean-room ``sxga_rational`` rig (seed 2, camera from 14 photos: cy 0.67
px off, its 1-sigma 0.63 px): the z axis 0.056 deg off with a reported 1-sigma of 0.020 deg.

Here the uncertainty is propagated by finite differences through the whole fit:
``Sigma_K`` (:func:`spread_covariance`: Gauss-Newton, at least the jackknife) is split into
principal directions of its effect on the rays through the stripe pixels and board corners
(``G Sigma_K G^T``, ``G`` the rays' Jacobian); along the leading ones (``CAMERA_DIRECTIONS``,
together at least ``RAY_SHARE`` of that effect) the camera is moved by its 1-sigma, both
boards are posed again (``cv2.solvePnP``), the rays recomputed and the joint fit repeated.
The poses' changes, summed in quadrature, are :func:`camera_spread` (the format of
:func:`lidarcal.calibration_checks.rigid_spread`), added to the reported sigmas by
:func:`lidarcal.pipeline.sigma_block` (``widened_to_camera``). Conservative: the planes'
share of it is then counted twice.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from .board import pose_pnp
from .camera import pixel_rays
from .geometry import Line3D, line_difference

if TYPE_CHECKING:
    from .pipeline import CalibrationResult

#: at most this many principal directions of the camera's ray uncertainty are refitted
CAMERA_DIRECTIONS = 6
#: ... and no more than needed to cover this share of the rays' variance. Not 0.95: the
#: focal length's direction moves the rays little but the LiDAR's distance much (paper rig,
#: camera from 12 photos, seed 1: the true camera moved the centre by 4.7-5.4 spreads with
#: the 2 directions of 95 %, by 2.0-2.1 with the 4 of 99.99 %; 0.9 s for 4 on 21 positions)
RAY_SHARE = 0.9999
_STEP = np.r_[np.full(4, 1e-3), np.full(5, 1e-7)]  # finite-difference steps (px; unitless)


def _camera_at(camera, v: np.ndarray):
    """``camera`` with ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)`` = ``v``."""
    K = np.array([[v[0], 0.0, v[2]], [0.0, v[1], v[3]], [0.0, 0.0, 1.0]])
    return replace(camera, K=K, dist=np.asarray(v[4:9], float).copy())


def _vector(camera) -> np.ndarray:
    K, d = np.asarray(camera.K, float), np.zeros(5)
    dv = np.asarray(camera.dist, float).ravel()[:5]
    d[:len(dv)] = dv
    return np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2], d]


def ray_directions(camera, cov: np.ndarray, px: np.ndarray, max_dirs: int = CAMERA_DIRECTIONS,
                   share: float = RAY_SHARE) -> np.ndarray:
    """1-sigma steps (k, 9) of the intrinsics along the principal directions of their effect
    on the rays through the pixels ``px`` (N, 2): the eigenvectors ``w`` of
    ``S G^T G S`` (``S = Sigma_K^(1/2)``, ``G`` the (2N, 9) Jacobian of the rays' ``(x, y)``,
    central differences), leading first, as many as cover ``share`` of its trace (at most
    ``max_dirs``); each step is ``S w``, so that the steps' effects sum in quadrature to the
    rays' covariance ``G Sigma_K G^T`` (first order)."""
    ev, U = np.linalg.eigh(0.5 * (cov + cov.T))
    S = (U * np.sqrt(np.clip(ev, 0.0, None))) @ U.T
    v0 = _vector(camera)
    G = np.zeros((2 * len(px), 9))
    for i in range(9):
        if not S[i].any():
            continue
        e = np.zeros(9)
        e[i] = _STEP[i]
        G[:, i] = ((pixel_rays(_camera_at(camera, v0 + e), px)[:, :2]
                    - pixel_rays(_camera_at(camera, v0 - e), px)[:, :2]) / (2 * _STEP[i])).ravel()
    GS = G @ S
    lam, W = np.linalg.eigh(GS.T @ GS)
    order = np.argsort(lam)[::-1]
    lam, W = lam[order], W[:, order]
    total = float(lam.sum())
    if total <= 0:
        return np.zeros((0, 9))
    k = int(np.searchsorted(np.cumsum(lam) / total, share) + 1)
    return (S @ W[:, :min(k, max_dirs)]).T


def spread_covariance(intr) -> np.ndarray:
    """``Sigma_K`` (9, 9) of the photos' camera for :func:`camera_spread`: the Gauss-Newton
    covariance at the photos' own residual scatter
    (:func:`lidarcal.joint.planes_prior.intrinsics_covariance`, unfloored), scaled up so that
    none of fx, fy, cx, cy is below its jackknife 1-sigma (``IntrinsicsResult.sigma_px``, the
    fits' spread over photos left out, which also sees a lens model that misfits: the
    clean-room ``sxga_rational`` rig, a 5-term fit of an 8-term lens, cy 0.63 px by the
    jackknife, 0.17 px by Gauss-Newton, truly 0.67 px off). Without a jackknife (too few
    photos) the floored covariance (``CORNER_FLOOR_PX``) the planes use."""
    from .joint.planes_prior import intrinsics_covariance

    if intr.sigma_px is None:
        return intrinsics_covariance(intr)
    C = intrinsics_covariance(intr, floor_px=0.0)
    gn = np.sqrt(np.clip(np.diag(C)[:4], 0.0, None))
    jk = np.asarray(intr.sigma_px, float)[:4]
    ok = gn > 0
    scale = max(1.0, float(np.max(jk[ok] / gn[ok]))) if ok.any() else 1.0
    return C * scale**2


def _moved(res: CalibrationResult, camera) -> CalibrationResult:
    """``res`` with ``camera`` and both boards posed again through it (solvePnP, started at
    the current poses); the stripes' rays follow in :func:`lidarcal.joint.joint_data`."""
    spec = res.dataset.v_board
    boards = []
    for b in res.boards:
        R, T = pose_pnp(camera, b.corners_px, spec.object_points(), b.R_pnp, b.T_pnp)
        boards.append(replace(b, R_pnp=R, T_pnp=T))
    return replace(res, camera=camera, boards=tuple(boards), joint_model=None, warnings=[])


def camera_spread(res: CalibrationResult, fit_planes: bool = False) -> dict | None:
    """Per position, the joint fit's pose change (centre mm, z and x axes deg) and the
    turntable axis' (direction deg, point near the LiDAR mm) under the camera's 1-sigma
    (module docstring), in quadrature over the directions; None when the camera was given
    (no uncertainty) or no direction moves the rays."""
    from .calibration_checks import pose_rows
    from .joint import fit_joint

    intr, model = res.intrinsics, res.joint_model
    if intr is None or model is None or not res.positions or not len(intr.image_points):
        return None
    px = np.concatenate([np.asarray(b.corners_px, float).reshape(-1, 2) for b in res.boards]
                        + [np.asarray(c, float).reshape(-1, 2) for p in res.positions[::4]
                           for c in p.camera_lines.centres_px])
    steps = ray_directions(res.camera, spread_covariance(intr), px)
    if not len(steps):
        return None
    psi = {p.index: p.psi_deg for p in res.positions}
    base = {r["index"]: r for r in pose_rows(model, psi)}
    sq = {q: {i: 0.0 for i in psi} for q in ("centre_mm", "z_axis_deg", "x_axis_deg")}
    axis_sq = {"axis_direction_deg": 0.0, "axis_point_mm": 0.0}
    v0 = _vector(res.camera)
    for s in steps:
        moved = fit_joint(_moved(res, _camera_at(res.camera, v0 + s)), fit_planes=fit_planes)
        rows = {r["index"]: r for r in pose_rows(moved, psi)}
        for i in psi:
            a, b = base[i], rows[i]
            sq["centre_mm"][i] += float(np.sum(np.subtract(a["T_mm"], b["T_mm"]) ** 2))
            for q, col in (("z_axis_deg", 2), ("x_axis_deg", 0)):
                c = float(np.clip(np.asarray(a["R"])[:, col] @ np.asarray(b["R"])[:, col], -1, 1))
                sq[q][i] += float(np.degrees(np.arccos(c))) ** 2
        d, p = line_difference(Line3D(model.axis.point, model.axis.direction),
                               Line3D(moved.axis.point, moved.axis.direction), model.T_ref)
        axis_sq["axis_direction_deg"] += d**2
        axis_sq["axis_point_mm"] += p**2
    out: dict = {q: {i: float(np.sqrt(v)) for i, v in col.items()} for q, col in sq.items()}
    out.update({q: float(np.sqrt(v)) for q, v in axis_sq.items()})
    out["directions"] = len(steps)
    return out
