"""Sampling the rig geometry per seed: camera, V-board, LiDAR on the turntable, discs.

Everything is in the camera frame (OpenCV axes), mm. The turntable model is the
project's convention: ``pose(psi) = Rot(axis through a, direction k, psi - psi_ref)
o pose(psi_ref)``, increasing psi rotating right-handedly about ``k``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import Line3D, Plane, Pose, rotation_about_axis, unit
from .config import RigConfig, get_rig
from .scene import WALL, Cylinder, Disc, InfinitePlane, Rect

# independent random streams: np.random.default_rng([seed, STREAM, index])
STREAM_GEOMETRY, STREAM_BOARD_IMAGE, STREAM_STRIPE, STREAM_SCAN = 1, 2, 3, 4
STREAM_INTRINSICS, STREAM_DISC, STREAM_SWEEP, STREAM_FIELD = 5, 6, 7, 8

_DOWN = np.array([0.0, 1.0, 0.0])   # camera +y: down
_FORWARD = np.array([0.0, 0.0, 1.0])


def _footprint_truth(rig: RigConfig) -> dict:
    """The LiDAR's echo model in truth.json (only when it is not the default Gaussian one)."""
    if rig.footprint_model == "gaussian":
        return {}
    return {"footprint_model": rig.footprint_model, "echo_threshold": rig.echo_threshold}


def _antialias_truth(rig: RigConfig) -> dict:
    """The images' anti-aliasing in truth.json (only when it is not the default grid)."""
    if rig.antialias == "grid":
        return {}
    return {"antialias": rig.antialias, "supersample": rig.supersample}


def _rng(seed: int, stream: int, index: int = 0) -> np.random.Generator:
    return np.random.default_rng([int(seed), stream, int(index)])


def _uniform(rng: np.random.Generator, r: tuple[float, float]) -> float:
    return float(rng.uniform(r[0], r[1]))


def _perp_unit(v: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random unit vector perpendicular to ``v``."""
    a = rng.normal(size=3)
    a -= (a @ v) * v / (v @ v)
    return unit(a)


def _tilted(v: np.ndarray, max_deg: float, rng: np.random.Generator) -> np.ndarray:
    """``v`` tilted by a random angle up to ``max_deg`` about a random perpendicular axis."""
    ang = np.radians(rng.uniform(0, max_deg))
    return rotation_about_axis(_perp_unit(v, rng), ang) @ unit(v)


def project_points(points: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) to distorted pixels (N, 2) with OpenCV's model."""
    p = np.asarray(points, dtype=float).reshape(-1, 1, 3)
    px, _ = cv2.projectPoints(p, np.zeros(3), np.zeros(3), np.asarray(K, float), np.asarray(dist, float))
    return px.reshape(-1, 2)


@dataclass(frozen=True)
class BoardTruth:
    """One chessboard of the V: the physical rectangle (chessboard + white margin)."""

    rect: Rect
    inner_corners: tuple[int, int]
    square_mm: float
    margin_mm: float

    @property
    def plane(self) -> Plane:
        return Plane.from_normal_point(self.rect.normal, self.rect.origin)

    def inner_corners_mm(self) -> np.ndarray:
        """Inner corners, row by row (``per_row`` fastest), as ``BoardSpec.object_points`` (N, 3)."""
        cols, rows = self.inner_corners
        u = self.margin_mm + self.square_mm * (1 + np.arange(cols))
        v = self.margin_mm + self.square_mm * (1 + np.arange(rows))
        uu, vv = np.meshgrid(u, v)
        return self.rect.point(uu.ravel(), vv.ravel())

    def chessboard_outline_mm(self) -> np.ndarray:
        m, w, h = self.margin_mm, self.rect.width, self.rect.height
        return self.rect.point(np.array([m, w - m, w - m, m]), np.array([m, m, h - m, h - m]))

    def to_dict(self) -> dict:
        pl = self.plane
        return {"normal": pl.normal, "d_mm": pl.d,
                "outline_mm": self.rect.corners(),
                "chessboard_outline_mm": self.chessboard_outline_mm(),
                "u_axis": self.rect.e_u, "v_axis": self.rect.e_v,
                "size_mm": [self.rect.width, self.rect.height],
                "inner_corners_mm": self.inner_corners_mm()}


@dataclass(frozen=True)
class DiscTrial:
    """One disc-measurement sweep: the scene and the turntable angles."""

    name: str
    disc: Disc
    post: Cylinder
    wall: Rect
    psi_deg: np.ndarray        # reported
    psi_true_deg: np.ndarray   # true (encoder noise removed)

    @property
    def surfaces(self) -> list:
        return [self.disc, self.post, self.wall]

    def to_dict(self) -> dict:
        return {"name": self.name, "diameter_mm": 2 * self.disc.radius, "center_mm": self.disc.centre,
                "normal": self.disc.normal, "psi_range_deg": [float(self.psi_deg[0]), float(self.psi_deg[-1])],
                "n_psi": len(self.psi_deg),
                "wall": {"outline_mm": self.wall.corners()},
                "post": {"point_mm": self.post.point, "direction": self.post.direction,
                         "radius_mm": self.post.radius}}


@dataclass(frozen=True)
class IntrinsicsView:
    board: Rect
    R: np.ndarray   # columns: board u, v, normal axes in the camera frame
    T: np.ndarray   # first inner corner, mm

    def to_dict(self) -> dict:
        return {"R": self.R, "T_mm": self.T}


@dataclass(frozen=True)
class RigTruth:
    """The sampled geometry of one simulated dataset (no rendering)."""

    rig: RigConfig
    seed: int
    K: np.ndarray
    dist: np.ndarray
    boards: list[BoardTruth]
    v_angle_deg: float
    hinge: Line3D
    wall: InfinitePlane
    posts: list[Cylinder]
    axis_point: np.ndarray
    axis_direction: np.ndarray
    psi_ref_deg: float
    pose_ref: Pose
    psi_deg: np.ndarray        # reported, per position
    psi_true_deg: np.ndarray   # true
    sheet_sigma_mm: float
    discs: list[DiscTrial] = field(default_factory=list)
    intrinsics_views: list[IntrinsicsView] = field(default_factory=list)

    @property
    def image_size(self) -> tuple[int, int]:
        return self.rig.image_size

    @property
    def surfaces(self) -> list:
        """The calibration scene: both boards, the posts, the wall."""
        return [b.rect for b in self.boards] + list(self.posts) + [self.wall]

    @property
    def board_planes(self) -> list[Plane]:
        return [b.plane for b in self.boards]

    def pose_at(self, psi_true_deg: float) -> Pose:
        """True LiDAR pose at a true turntable angle (the axis model, exactly)."""
        Rk = rotation_about_axis(self.axis_direction, np.radians(psi_true_deg - self.psi_ref_deg))
        a = self.axis_point
        return Pose(Rk @ self.pose_ref.R, a + Rk @ (self.pose_ref.T - a))

    def pose(self, psi_deg: float) -> Pose:
        """:meth:`pose_at` as a pose function (:class:`lidarcal.measure.PoseFunction`), the
        angle taken as the true one: measurements with the true rig."""
        return self.pose_at(psi_deg)

    def poses_at(self, psi_true_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised :meth:`pose_at`: ``(R (N, 3, 3), T (N, 3))``."""
        th = np.radians(np.asarray(psi_true_deg, dtype=float) - self.psi_ref_deg)
        Rk = Rotation.from_rotvec(np.outer(th, self.axis_direction)).as_matrix()
        a = self.axis_point
        return Rk @ self.pose_ref.R, a + Rk @ (self.pose_ref.T - a)

    @property
    def poses(self) -> list[Pose]:
        return [self.pose_at(p) for p in self.psi_true_deg]

    def laser_plane(self, pose: Pose) -> Plane:
        """The scan plane (LiDAR z = 0) in the camera frame."""
        return Plane.from_normal_point(pose.z_axis, pose.T)

    def to_dict(self, indices: list[int] | None = None) -> dict:
        idx = range(len(self.psi_deg)) if indices is None else indices
        rig = self.rig
        return {
            "generator": "lidarcal.synthetic",
            "rig": rig.name,
            "seed": self.seed,
            "camera": {"K": self.K, "dist": self.dist, "image_size": list(rig.image_size)},
            "boards": [b.to_dict() for b in self.boards],
            "v_angle_deg": self.v_angle_deg,
            "hinge": {"point_mm": self.hinge.point, "direction": self.hinge.direction},
            "axis": {"point_mm": self.axis_point, "direction": self.axis_direction},
            "psi_ref_deg": self.psi_ref_deg,
            "pose_ref": self.pose_ref.to_dict(),
            "poses": [{"index": int(i), "psi_deg": float(self.psi_deg[i]),
                       "psi_true_deg": float(self.psi_true_deg[i]),
                       **self.pose_at(self.psi_true_deg[i]).to_dict()} for i in idx],
            "laser_sheet_sigma_mm": self.sheet_sigma_mm,
            "wall": {"normal": self.wall.normal, "d_mm": self.wall.d},
            "posts": [{"point_mm": p.point, "direction": p.direction, "radius_mm": p.radius,
                       "s_range_mm": [p.s_min, p.s_max]} for p in self.posts],
            "noise": {"range_noise_mm": rig.range_noise_mm, "encoder_noise_deg": rig.encoder_noise_deg,
                      "beam_exit_mm": rig.beam_exit_mm, "beam_divergence_mrad": rig.beam_divergence_mrad,
                      "mixed_dominant": rig.mixed_dominant, "spurious_rate": rig.spurious_rate,
                      "drop_rate": rig.drop_rate, "read_noise_dn": rig.read_noise_dn,
                      "bright_noise_dn": rig.bright_noise_dn, "psf_sigma_px": rig.psf_sigma_px,
                      **_footprint_truth(rig), **_antialias_truth(rig)},
            "intrinsics_views": [v.to_dict() for v in self.intrinsics_views],
            "measurements": [d.to_dict() for d in self.discs],
            **ranging_truth(rig),
        }


def ranging_truth(rig: RigConfig) -> dict:
    """truth.json's ``ranging`` block (the LiDAR's systematic ranging errors), only when any is set.

    ``offset_mm``: every valid range reads this much too far; ``dark_extra_mm``:
    returns from black squares read this much farther still; ``quantum_mm``:
    ranges are multiples of it (0 = not quantised); ``incidence_extra_mm`` and
    ``scale_error`` when set (:mod:`lidarcal.synthetic.lidar`). Absent = no ranging errors,
    so the default rigs' truth.json is unchanged.
    """
    terms = (rig.range_offset_mm, rig.dark_extra_mm, rig.range_quantum_mm)
    extra = {k: float(v) for k, v in (("incidence_extra_mm", rig.incidence_extra_mm),
                                      ("scale_error", rig.range_scale_error)) if v}
    if not any(terms) and not extra:
        return {}
    return {"ranging": {**dict(zip(("offset_mm", "dark_extra_mm", "quantum_mm"), map(float, terms))),
                        **extra}}


# ----------------------------------------------------------------------------- sampling

def _visible(points: np.ndarray, K: np.ndarray, dist: np.ndarray, size: tuple[int, int],
             border: float) -> bool:
    if np.any(points[:, 2] <= 50):
        return False
    px = project_points(points, K, dist)
    w, h = size
    return bool(np.all((px[:, 0] >= border) & (px[:, 0] <= w - 1 - border)
                       & (px[:, 1] >= border) & (px[:, 1] <= h - 1 - border)))


def _rect_edge_points(rect: Rect, n: int = 16) -> np.ndarray:
    s = np.linspace(0, 1, n)
    u = np.concatenate([s * rect.width, np.full(n, rect.width), s * rect.width, np.zeros(n)])
    v = np.concatenate([np.zeros(n), s * rect.height, np.full(n, rect.height), s * rect.height])
    return rect.point(u, v)


def _sample_v_board(rng: np.random.Generator, rig: RigConfig) -> tuple[list[BoardTruth], float, Line3D]:
    cols, rows = rig.v_inner_corners
    sq, margin = rig.v_square_mm, rig.v_margin_squares * rig.v_square_mm
    width, height = (cols + 1) * sq + 2 * margin, (rows + 1) * sq + 2 * margin
    zh = _uniform(rng, rig.hinge_distance_mm)
    phi = np.radians(_uniform(rng, rig.v_angle_deg))
    h = _tilted(_DOWN, rig.v_tilt_deg, rng)                       # hinge direction (down)
    b = -_FORWARD + 0.0
    b = rotation_about_axis(h, np.radians(rng.uniform(-rig.v_yaw_deg, rig.v_yaw_deg))) @ b
    b = unit(b - (b @ h) * h)                                      # bisector, towards the camera
    s = unit(np.cross(h, b))
    centre = np.array([rng.uniform(-0.03, 0.03) * zh, rng.uniform(-0.02, 0.02) * zh, zh])
    top = centre - 0.5 * height * h
    boards = []
    for sign in (1.0, -1.0):
        e_u = np.cos(phi / 2) * b + sign * np.sin(phi / 2) * s
        rect = Rect(top, e_u, h, width, height, pattern=(cols + 1, rows + 1, sq, margin))
        boards.append(BoardTruth(rect, (cols, rows), sq, margin))
    if rng.random() < 0.5:
        boards.reverse()
    return boards, float(np.degrees(phi)), Line3D(centre, h)


def _stripe_ok(boards: list[BoardTruth], R: np.ndarray, T: np.ndarray, rig: RigConfig,
               sigma: float, strict: bool) -> bool:
    """Both stripes cross both boards inside the (chessboard) area, aperture and range window."""
    amin, amax = rig.lidar_angle_min_deg + 1.0, rig.lidar_angle_max_deg - 1.0
    n = R[:, :, 2]
    d = np.einsum("ij,ij->i", n, T)
    for bd in boards:
        r = bd.rect
        den = n @ r.e_v
        if np.any(np.abs(den) < 0.3):
            return False
        lo = (bd.margin_mm if strict else 0.0) + 4 * sigma + 1.0
        for u in (0.0, r.width):
            v = (d - n @ r.origin - u * (n @ r.e_u)) / den
            if np.any(v < lo) or np.any(v > r.height - lo):
                return False
            p = r.origin + u * r.e_u + v[:, None] * r.e_v
            q = np.einsum("nji,nj->ni", R, p - T)
            ang = np.degrees(np.arctan2(q[:, 1], q[:, 0]))
            rr = np.hypot(q[:, 0], q[:, 1])
            if (np.any(ang < amin) or np.any(ang > amax)  # the aperture (any side of the scanner)
                    or np.any(rr < rig.lidar_range_min_mm * 1.05) or np.any(rr > rig.lidar_range_max_mm * 0.95)):
                return False
    return True


def _sample_calibration(rng: np.random.Generator, rig: RigConfig, seed: int, strict: bool) -> RigTruth | None:
    K, dist = np.asarray(rig.K, float), np.asarray(rig.dist, float)
    boards, phi_deg, hinge = _sample_v_board(rng, rig)
    pts = np.vstack([_rect_edge_points(b.rect) for b in boards])
    if not _visible(pts, K, dist, rig.image_size, rig.image_border_px):
        return None
    # LiDAR at the middle position: aims at the middle of the hinge, upright, small misalignment
    T_mid = np.array([_uniform(rng, r) for r in rig.lidar_offset_mm])
    x0 = unit(hinge.point - T_mid)
    z0 = unit(-_DOWN - (-_DOWN @ x0) * x0)
    R0 = np.column_stack([x0, np.cross(z0, x0), z0])
    mis = np.radians(rig.lidar_misalign_deg)
    yaw = rng.uniform(-mis, mis) + np.radians(rig.lidar_yaw_deg)
    roll = rng.uniform(-mis, mis) + np.radians(rig.lidar_roll_deg)
    R_mid = rotation_about_axis(z0, yaw) @ rotation_about_axis(x0, roll) @ R0
    pose_mid = Pose(R_mid, T_mid)
    # turntable axis: along +-camera x, tilted; passes lever_arm from the LiDAR centre
    k = _tilted(np.array([1.0, 0, 0]), rig.axis_tilt_deg, rng) * (1.0 if rng.random() < 0.5 else -1.0)
    lever = _uniform(rng, rig.lever_arm_mm)
    a = T_mid + lever * _perp_unit(k, rng)
    a = a - (a @ k) * k + (T_mid @ k) * k        # foot of the LiDAR centre on the axis is a
    n = rig.n_positions
    psi0 = round(_uniform(rng, rig.psi0_deg), 2)
    psi = np.array([float(f"{psi0 + i * rig.psi_step_deg:.4f}") for i in range(n)])
    psi_ref = float(psi0 + rig.psi_step_deg * (n - 1) / 2)
    sigma = _uniform(rng, rig.sheet_sigma_mm)
    truth = RigTruth(rig, seed, K, dist, boards, phi_deg, hinge, InfinitePlane(np.array([0, 0, 1.0]), 1e9),
                     [], a, k, psi_ref, pose_mid, psi, psi.copy(), sigma)
    if not _stripe_ok(boards, *truth.poses_at(psi), rig, sigma, strict):
        return None
    # background wall and the posts
    wall_n = _tilted(_FORWARD, rig.wall_tilt_deg, rng)
    wall_z = max(_uniform(rng, rig.wall_distance_mm), hinge.point[2] + rig.wall_min_gap_mm)
    wall = InfinitePlane(wall_n, float(wall_n @ np.array([0, 0, wall_z])))
    h = hinge.direction
    bis = unit(sum(b.rect.e_u for b in boards))
    bottom = hinge.point + 0.5 * boards[0].rect.height * h
    r1 = _uniform(rng, rig.post_radius_mm)
    stand = Cylinder(bottom - bis * (r1 + 5), h, r1, 0.0, 2000.0)
    side = boards[int(rng.integers(2))].rect
    outer = side.point(side.width, side.height / 2)
    lat = unit(side.e_u - (side.e_u @ bis) * bis)
    r2 = _uniform(rng, rig.post_radius_mm)
    pole_pt = outer + lat * rng.uniform(80, 250) - bis * rng.uniform(60, 300)
    pole = Cylinder(pole_pt, h, r2, -3000.0, 2000.0)
    psi_true = psi + (rng.normal(0, rig.encoder_noise_deg, n) if rig.encoder_noise_deg > 0 else 0.0)
    return RigTruth(rig, seed, K, dist, boards, phi_deg, hinge, wall, [stand, pole], a, k, psi_ref,
                    pose_mid, psi, psi_true, sigma)


def _sample_intrinsics_views(truth: RigTruth) -> list[IntrinsicsView]:
    rig = truth.rig
    cols, rows = rig.intrinsics_inner_corners
    sq = rig.intrinsics_square_mm
    margin = sq
    width, height = (cols + 1) * sq + 2 * margin, (rows + 1) * sq + 2 * margin
    w_img, h_img = rig.image_size
    fx = truth.K[0, 0]
    views = []
    for j in range(rig.n_intrinsics_views):
        rng = _rng(truth.seed, STREAM_INTRINSICS, j)
        cell = j % 9
        for attempt in range(200):
            relax = attempt > 100
            fill = _uniform(rng, rig.intrinsics_fill) * (0.8 if relax else 1.0)
            z = fx * width / (fill * w_img)
            cx = (cell % 3 + rng.uniform(0.1, 0.9)) / 3 if not relax else rng.uniform(0.3, 0.7)
            cy = (cell // 3 + rng.uniform(0.1, 0.9)) / 3 if not relax else rng.uniform(0.3, 0.7)
            if j >= 9:  # second round: anywhere, stronger tilts
                cx, cy = rng.uniform(0.15, 0.85), rng.uniform(0.15, 0.85)
            ray = np.linalg.solve(truth.K, np.array([cx * w_img, cy * h_img, 1.0]))
            centre = ray * z
            tilt = np.radians(rig.intrinsics_tilt_deg)
            R = (rotation_about_axis(np.array([0, 0, 1.0]), rng.uniform(-0.35, 0.35))
                 @ rotation_about_axis(np.array([1.0, 0, 0]), rng.uniform(-tilt, tilt))
                 @ rotation_about_axis(np.array([0, 1.0, 0]), rng.uniform(-tilt, tilt)))
            if np.degrees(np.arccos(np.clip(R[2, 2], -1, 1))) > rig.intrinsics_tilt_deg:
                continue
            origin = centre - R[:, 0] * width / 2 - R[:, 1] * height / 2
            rect = Rect(origin, R[:, 0], R[:, 1], width, height, pattern=(cols + 1, rows + 1, sq, margin))
            if _visible(_rect_edge_points(rect), truth.K, truth.dist, rig.image_size, 12):
                first = rect.point(margin + sq, margin + sq)
                views.append(IntrinsicsView(rect, R, first))
                break
        else:
            raise ValueError(f"cannot place intrinsics view {j} in the image; check intrinsics_fill")
    return views


def _sample_disc(truth: RigTruth, j: int) -> DiscTrial | None:
    rig = truth.rig
    rng = _rng(truth.seed, STREAM_DISC, j)
    lo, hi = truth.psi_deg[0], truth.psi_deg[-1]
    for _ in range(200):
        psi_t = rng.uniform(lo + 0.15 * (hi - lo), hi - 0.15 * (hi - lo))
        pose = truth.pose_at(psi_t)
        beta = np.radians(rng.uniform(-rig.disc_beam_angle_deg, rig.disc_beam_angle_deg))
        D = _uniform(rng, rig.disc_distance_mm)
        c = pose.apply(np.array([D * np.cos(beta), D * np.sin(beta), 0.0]))[0]
        view = unit(c - pose.T)
        normal = _tilted(-view, rig.disc_tilt_deg, rng)
        R = rig.disc_diameter(j) / 2
        disc = Disc(c, normal, R)
        # a background panel (finite: beams past it get no return) behind the disc
        wall_n = _tilted(view, 10.0, rng)
        e_v = unit(_DOWN - (_DOWN @ wall_n) * wall_n)
        e_u = np.cross(e_v, wall_n)
        wc = c + view * _uniform(rng, rig.disc_wall_gap_mm)
        side = rig.disc_wall_size_mm
        wall = Rect(wc - 0.5 * side * (e_u + e_v), e_u, e_v, side, side, plain=WALL)
        back = -normal
        tilt = np.arccos(np.clip(abs(normal @ view), 0, 1))
        pr = rng.uniform(5.0, 8.0)
        post = Cylinder(c + back * (pr + 3 + R * np.tan(tilt)), _DOWN, pr, 0.0, 1500.0)
        # true-angle range where the scan plane cuts the disc
        grid = np.arange(psi_t - 30, psi_t + 30, 0.01)
        Rg, Tg = truth.poses_at(grid)
        nz = Rg[:, :, 2]
        dist = np.abs(np.einsum("ij,ij->i", nz, c - Tg))
        hit = dist <= R * np.sqrt(np.clip(1 - (nz @ normal) ** 2, 0, None))
        if not hit.any() or hit[0] or hit[-1]:
            continue
        g_lo, g_hi = grid[hit][0] - rig.sweep_margin_deg, grid[hit][-1] + rig.sweep_margin_deg
        step = rig.sweep_step_deg
        ks = np.arange(np.floor(g_lo / step), np.ceil(g_hi / step) + 1)
        psi = np.array([float(f"{k * step:.4f}") for k in ks])
        # the disc must stay inside the aperture and the range window over the sweep
        ok = True
        ring_u = _perp_unit(normal, np.random.default_rng(1))
        ring_v = np.cross(normal, ring_u)
        ts = np.linspace(0, 2 * np.pi, 24, endpoint=False)
        rim = c + R * (np.outer(np.cos(ts), ring_u) + np.outer(np.sin(ts), ring_v))
        for g in (psi[0], psi_t, psi[-1]):
            q = truth.pose_at(g).inverse_apply(np.vstack([rim, c]))
            ang = np.degrees(np.arctan2(q[:, 1], q[:, 0]))
            rr = np.linalg.norm(q, axis=1)
            if (np.any(ang < rig.lidar_angle_min_deg + 2) or np.any(ang > rig.lidar_angle_max_deg - 2)
                    or np.any(rr < rig.lidar_range_min_mm * 1.1) or np.any(rr > rig.lidar_range_max_mm * 0.8)):
                ok = False
        if not ok:
            continue
        psi_true = psi + (rng.normal(0, rig.encoder_noise_deg, len(psi)) if rig.encoder_noise_deg > 0 else 0.0)
        return DiscTrial(f"trial_{j + 1:02d}", disc, post, wall, psi, psi_true)
    return None


def make_truth(seed: int, rig: str | RigConfig = "paper", *, with_discs: bool = True,
               with_intrinsics: bool = True) -> RigTruth:
    """Sample the geometry of a simulated dataset (cheap, no rendering); deterministic per seed.

    Rejection sampling within the rig's ranges until the whole V is visible in
    the image, both stripes cross both boards (inside the chessboard area if
    possible, else inside the board) at every position, and the scan plane
    meets both boards within the LiDAR's aperture and range window.
    """
    rig = get_rig(rig)
    if rig.n_positions < 3:
        raise ValueError(f"n_positions must be >= 3, got {rig.n_positions}")
    rng = _rng(seed, STREAM_GEOMETRY)
    truth = None
    for attempt in range(3000):
        truth = _sample_calibration(rng, rig, seed, strict=attempt < 1500)
        if truth is not None:
            break
    if truth is None:
        raise ValueError(f"rig {rig.name!r}: no geometry satisfies the visibility and stripe "
                         "constraints; widen hinge_distance_mm / lidar_offset_mm or shorten the sweep")
    discs = []
    if with_discs:
        for j in range(rig.n_discs):
            d = _sample_disc(truth, j)
            if d is None:
                raise ValueError(f"rig {rig.name!r}: cannot place disc trial {j + 1}")
            discs.append(d)
    views = _sample_intrinsics_views(truth) if with_intrinsics else []
    return replace(truth, discs=discs, intrinsics_views=views)
