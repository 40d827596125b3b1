"""Truth generator for the scan/pose tests: a V-board in the camera frame, a LiDAR pose, a ray-cast scan.

Not the full-image simulator (``lidarcal.synthetic``): only what sections 1.4-1.5
need. Everything is in the camera frame (OpenCV: x right, y down, z forward), mm.

Scene: two finite planar boards hinged along a (nearly vertical) line ~1.1 m
away, opening towards the camera (concave V); a background wall; a vertical
post beside the V. The scan: each beam is cast as a few sub-rays across its
footprint; when they hit different surfaces (a depth edge) the return is their
weighted mean range (a mixed pixel floating between board edge and wall).
Then Gaussian range noise, spurious random ranges and dropped beams.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from lidarcal.geometry import Plane, Pose, intersect_planes, unit

NONE, BOARD1, BOARD2, WALL, POST, MIXED, SPURIOUS = range(7)


@dataclass
class VTruth:
    boards: list[Plane]
    hinge: np.ndarray  # a point on the hinge line (camera)
    h: np.ndarray  # hinge direction
    u: np.ndarray  # (2, 3): in-plane directions from the hinge out over each board
    width: float
    half_height: float
    opening: float  # dihedral angle between the boards, rad
    wall: Plane
    post_centre: np.ndarray
    post_radius: float
    pose: Pose  # LiDAR in camera: X_c = R X_l + T
    E_cam: np.ndarray
    l_cam: np.ndarray  # (2, 3): stripe directions on board 1, board 2
    alpha: float
    hinge_gap: float = 0.0  # boards start this far from the hinge line (a slot at the hinge)

    @property
    def E_lidar(self) -> np.ndarray:
        return self.pose.inverse_apply(self.E_cam)[0, :2]


def nominal_R(upright: bool = True) -> np.ndarray:
    """LiDAR x along camera +z; z along camera -y (upright) or +y (upside down)."""
    x = np.array([0.0, 0, 1])
    z = np.array([0.0, -1, 0]) if upright else np.array([0.0, 1, 0])
    return np.column_stack([x, np.cross(z, x), z])


def make_truth(rng: np.random.Generator, *, upright: bool = True,
               opening_deg: tuple[float, float] = (110.0, 130.0),
               hinge_gap_mm: float = 0.0) -> VTruth:
    opening = np.radians(rng.uniform(*opening_deg))
    hinge = np.array([rng.uniform(-80, 80), 150.0 + rng.uniform(-30, 30), rng.uniform(1000, 1200)])
    tilt = Rotation.from_rotvec(rng.normal(0, np.radians(3), 3)).as_matrix()
    h = tilt @ np.array([0.0, 1, 0])
    yaw = rng.uniform(-np.radians(20), np.radians(20))
    mz = np.array([0.0, 0, -1])
    b = Rotation.from_rotvec(yaw * h).as_matrix() @ unit(mz - (mz @ h) * h)
    s = np.cross(h, b)
    u = np.vstack([np.cos(opening / 2) * b + np.sin(opening / 2) * s,
                   np.cos(opening / 2) * b - np.sin(opening / 2) * s])
    boards = [Plane.from_normal_point(np.cross(h, uk), hinge) for uk in u]

    dR = Rotation.from_rotvec(rng.normal(0, np.radians(3), 3)).as_matrix()
    R = dR @ nominal_R(upright)
    T = np.array([rng.uniform(-30, 30), 150 + rng.uniform(-20, 20), rng.uniform(-30, 30)])
    pose = Pose(R, T)
    laser = Plane.from_normal_point(R[:, 2], T)
    E_cam = intersect_planes(boards[0], boards[1], laser)
    l_cam = []
    for pl, uk in zip(boards, u):
        lk = unit(np.cross(pl.normal, laser.normal))
        l_cam.append(lk if lk @ uk > 0 else -lk)
    l_cam = np.vstack(l_cam)
    alpha = float(np.arccos(np.clip(l_cam[0] @ l_cam[1], -1, 1)))
    wall = Plane.from_normal_point(unit(np.array([rng.normal(0, 0.05), 0, 1.0])),
                                   np.array([0, 0, rng.uniform(2300, 2700)]))
    side = rng.choice([-1, 1])
    post = np.array([side * rng.uniform(380, 500), 0.0, rng.uniform(1300, 1700)])
    return VTruth(boards, hinge, h, u, 300.0, 250.0, opening, wall, post, 30.0, pose,
                  E_cam, l_cam, alpha, hinge_gap_mm)


def _cast(tr: VTruth, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of rays from the LiDAR centre along camera-frame ``dirs`` (M, 3): range, label."""
    o = tr.pose.T
    M = len(dirs)
    best = np.full(M, np.inf)
    lab = np.full(M, NONE)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, (pl, uk) in enumerate(zip(tr.boards, tr.u)):
            t = (pl.d - pl.normal @ o) / (dirs @ pl.normal)
            X = o + t[:, None] * dirs
            a = (X - tr.hinge) @ uk
            c = (X - tr.hinge) @ tr.h
            ok = (t > 0) & (a >= tr.hinge_gap) & (a <= tr.width) & (np.abs(c) <= tr.half_height)
            upd = ok & (t < best)
            best[upd], lab[upd] = t[upd], BOARD1 + k
        t = (tr.wall.d - tr.wall.normal @ o) / (dirs @ tr.wall.normal)
        upd = (t > 0) & (t < best)
        best[upd], lab[upd] = t[upd], WALL
        # vertical post (axis along camera y): solve in the x-z plane
        d2 = dirs[:, [0, 2]]
        w = (o - tr.post_centre)[[0, 2]]
        A = (d2 ** 2).sum(1)
        B = 2 * d2 @ w
        C = w @ w - tr.post_radius ** 2
        disc = B ** 2 - 4 * A * C
        t = (-B - np.sqrt(np.maximum(disc, 0))) / (2 * A)
        upd = (disc > 0) & (t > 0) & (t < best)
        best[upd], lab[upd] = t[upd], POST
    return best, lab


def simulate_scan(tr: VTruth, rng: np.random.Generator, *, angle_min_deg: float = -35.0,
                  angle_max_deg: float = 35.0, angle_step_deg: float = 0.083333,
                  sigma_mm: float = 1.0, spurious: float = 0.01, dropout: float = 0.02,
                  n_sub: int = 8, range_max_mm: float = 4000.0):
    """Ray-cast scan: (angle_deg, range_mm with NaN, true label per beam)."""
    n = round((angle_max_deg - angle_min_deg) / angle_step_deg) + 1
    ang = angle_min_deg + np.arange(n) * angle_step_deg
    off = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    sub = np.radians(ang[:, None] + off[None, :] * angle_step_deg).ravel()
    dl = np.column_stack([np.cos(sub), np.sin(sub), np.zeros_like(sub)])
    rng_sub, lab_sub = _cast(tr, dl @ tr.pose.R.T)
    rng_sub, lab_sub = rng_sub.reshape(n, n_sub), lab_sub.reshape(n, n_sub)
    dc = np.column_stack([np.cos(np.radians(ang)), np.sin(np.radians(ang)), np.zeros(n)])
    rho, lab = _cast(tr, dc @ tr.pose.R.T)
    group = np.where(np.isin(lab_sub, (BOARD1, BOARD2)), BOARD1, lab_sub)
    mixed = np.any(group != group[:, :1], axis=1)
    rho = np.where(mixed, rng_sub.mean(1), rho)
    lab = np.where(mixed, MIXED, lab)
    rho = rho + rng.normal(0, sigma_mm, n)
    sp = rng.random(n) < spurious
    rho[sp] = rng.uniform(100, range_max_mm, sp.sum())
    lab[sp] = SPURIOUS
    drop = rng.random(n) < dropout
    rho[drop] = np.nan
    lab[drop] = NONE
    rho[~np.isfinite(rho) | (rho > range_max_mm)] = np.nan
    return ang, rho, lab
