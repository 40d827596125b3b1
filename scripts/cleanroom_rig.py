"""A clean-room turntable V-board rig simulator, written from the docs alone.

Written only from docs/dataset-format.md, docs/capture-guide.md, the README and
the paper notes: it does NOT use ``lidarcal.synthetic`` (nor any of lidarcal),
so that its conventions and its physics are an independent reading of the
data contract. Its rendering choices differ on purpose: per-pixel ray casting
through OpenCV's lens model (5- or 8-coefficient distortion) with box
supersampling, a laser sheet of Gaussian thickness growing with range,
speckle, shot and read noise, gamma, a scanner whose spot is traced by
sub-rays (energy-weighted mixed ranges or a first-echo threshold), range
quantisation and dropouts, a turntable axis away from the LiDAR's centre,
encoder jitter, a room around the rig, and disc sweeps.

    python scripts/cleanroom_rig.py OUT --variant hd --seed 1
    python scripts/cleanroom_rig.py --evaluate WORKDIR --variants hd,sxga_rational --seeds 1,2

``--evaluate`` generates each variant x seed, runs ``lidarcal check``,
``lidarcal calibrate`` and ``lidarcal measure`` from the command line and
compares their output with this simulator's own truth.json (its own comparison:
LiDAR centre error mm, z / x axis error deg, axis direction deg, the share of
positions within 2 reported sigma, disc diameter error).
"""

from __future__ import annotations

import argparse
import csv
import gzip
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

# ----------------------------------------------------------------- variants


@dataclass
class Variant:
    """Everything a variant changes; every number a rig parameter, read by the renderer."""

    name: str
    image_size: tuple[int, int]
    f_px: float
    dist: tuple[float, ...]
    camera_in_json: bool  # False: camera from intrinsics/ photos only
    supersample: int
    board_corners: tuple[int, int]  # [per_row (across the board), per_column (along the hinge)]
    square_mm: float
    hinge_distance_mm: float
    v_angle_deg: float
    lidar_step_deg: float
    lidar_fov_deg: float
    range_min_mm: float
    range_max_mm: float
    range_noise_mm: float
    range_quantum_mm: float
    range_offset_mm: float
    dropout: float
    echo: str  # "mixed" (energy-weighted mean range) or "first" (first surface over a threshold)
    spot_sigma_steps: float  # the beam spot's 1-sigma across the beam, in angle steps
    upside_down: bool
    colour: str  # "gray" or "red" (BGR, a red laser seen by a colour camera)
    gamma: float  # output = 255 (linear / 255) ** gamma
    sheet_sigma_mm: float  # laser sheet's 1-sigma thickness at the LiDAR ...
    sheet_div_mrad: float  # ... growing with range
    speckle: float  # speckle contrast (std / mean of the multiplicative field)
    n_positions: int
    psi_zero_deg: float  # the controller's reading at the middle of the sweep
    psi_decreasing: bool
    encoder_jitter_deg: float
    no_return: str  # how a no-return is written: "0", "", "inf"
    intrinsics_corners: tuple[int, int] = (9, 7)
    intrinsics_square_mm: float = 30.0
    disc_diameters_mm: tuple[float, ...] = (120.0, 120.0)
    blur_px: float = 0.6
    extra: dict = field(default_factory=dict)


VARIANTS = {
    # A full-HD camera, 5-coefficient barrel distortion in dataset.json; a 270 deg
    # scanner with 0.25 deg steps; gray stripe images; mixed ranges at edges.
    "hd": Variant(
        name="hd", image_size=(1920, 1080), f_px=1750.0,
        dist=(-0.21, 0.12, 4e-4, -3e-4, -0.02), camera_in_json=True, supersample=2,
        board_corners=(8, 11), square_mm=30.0, hinge_distance_mm=1300.0, v_angle_deg=118.0,
        lidar_step_deg=0.25, lidar_fov_deg=270.0, range_min_mm=100.0, range_max_mm=8000.0,
        range_noise_mm=1.5, range_quantum_mm=1.0, range_offset_mm=0.0, dropout=0.01,
        echo="mixed", spot_sigma_steps=0.6, upside_down=False, colour="gray", gamma=1.0,
        sheet_sigma_mm=1.2, sheet_div_mrad=1.2, speckle=0.2, n_positions=25,
        psi_zero_deg=47.0, psi_decreasing=False, encoder_jitter_deg=0.002, no_return="0"),
    # 1280 x 1024 camera with an 8-coefficient (rational) lens, calibrated by lidarcal
    # from intrinsics/ photos (its 5-coefficient model cannot hold it exactly); a red
    # laser in BGR frames with a camera gamma; a 180 deg scanner, 0.5 deg steps.
    "sxga_rational": Variant(
        name="sxga_rational", image_size=(1280, 1024), f_px=1150.0,
        dist=(0.35, -0.05, -2e-4, 3e-4, 0.02, 0.62, -0.02, 0.05), camera_in_json=False,
        supersample=3, board_corners=(7, 10), square_mm=35.0, hinge_distance_mm=1250.0,
        v_angle_deg=126.0, lidar_step_deg=0.5, lidar_fov_deg=180.0, range_min_mm=50.0,
        range_max_mm=6000.0, range_noise_mm=2.0, range_quantum_mm=1.0, range_offset_mm=6.0,
        dropout=0.02, echo="mixed", spot_sigma_steps=0.5, upside_down=False, colour="red",
        gamma=0.8, sheet_sigma_mm=1.5, sheet_div_mrad=1.5, speckle=0.25, n_positions=21,
        psi_zero_deg=210.0, psi_decreasing=True, encoder_jitter_deg=0.0, no_return="inf",
        disc_diameters_mm=(150.0, 150.0)),
    # A coarse first-echo scanner mounted upside down (z_axis_hint [0, 1, 0]), 1 deg
    # steps over 240 deg, 3 mm noise in 2 mm steps, angles wrapping through 360 deg.
    "coarse_lidar": Variant(
        name="coarse_lidar", image_size=(1600, 1200), f_px=1900.0,
        dist=(-0.12, 0.25, 0.0, 0.0, -0.1), camera_in_json=True, supersample=2,
        board_corners=(9, 12), square_mm=25.0, hinge_distance_mm=1150.0, v_angle_deg=112.0,
        lidar_step_deg=0.36, lidar_fov_deg=240.0, range_min_mm=60.0, range_max_mm=5600.0,
        range_noise_mm=3.0, range_quantum_mm=2.0, range_offset_mm=0.0, dropout=0.03,
        echo="first", spot_sigma_steps=1.5, upside_down=True, colour="gray", gamma=1.0,
        sheet_sigma_mm=2.0, sheet_div_mrad=2.0, speckle=0.3, n_positions=23,
        psi_zero_deg=359.0, psi_decreasing=False, encoder_jitter_deg=0.0, no_return=""),
}


# ----------------------------------------------------------------- geometry


def rot(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Right-handed rotation by angle about a unit axis (Rodrigues, via OpenCV)."""
    return cv2.Rodrigues(np.asarray(axis, float).reshape(3, 1) * angle_rad)[0]


def unit(v: np.ndarray) -> np.ndarray:
    return np.asarray(v, float) / np.linalg.norm(v)


@dataclass
class Board:
    """A planar rectangle: X = origin + a * u + b * v, a in [0, width], b in [0, height]."""

    origin: np.ndarray
    u: np.ndarray  # across (from the hinge outwards)
    v: np.ndarray  # along the hinge
    width: float
    height: float
    pattern_origin: tuple[float, float]  # (a, b) of the pattern's outer corner
    square: float
    squares: tuple[int, int]  # (across, along)

    @property
    def normal(self) -> np.ndarray:
        return unit(np.cross(self.u, self.v))

    def hit(self, o: np.ndarray, d: np.ndarray):
        """Ray parameter t (inf where missed) and board coordinates (a, b)."""
        n = self.normal
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            t = ((self.origin - o) @ n) / den
            rel = o + t[:, None] * d - self.origin
            a = rel @ self.u
            b = rel @ self.v
        ok = (t > 1e-6) & (a >= 0) & (a <= self.width) & (b >= 0) & (b <= self.height)
        return np.where(ok, t, np.inf), a, b

    def black(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """True on the pattern's black squares."""
        i = np.floor((a - self.pattern_origin[0]) / self.square)
        j = np.floor((b - self.pattern_origin[1]) / self.square)
        inside = (i >= 0) & (i < self.squares[0]) & (j >= 0) & (j < self.squares[1])
        return inside & ((i + j) % 2 == 0)

    def corners(self) -> np.ndarray:
        """Inner corners in the camera frame, row by row."""
        nx, ny = self.squares[0] - 1, self.squares[1] - 1
        a = self.pattern_origin[0] + self.square * (1 + np.arange(nx))
        b = self.pattern_origin[1] + self.square * (1 + np.arange(ny))
        A, B = np.meshgrid(a, b)
        return self.origin + A.reshape(-1, 1) * self.u + B.reshape(-1, 1) * self.v

    def outline(self) -> np.ndarray:
        w, h = self.width, self.height
        return np.array([self.origin + a * self.u + b * self.v for a, b in
                         [(0, 0), (w, 0), (w, h), (0, h)]])


@dataclass
class Room:
    """An axis-aligned box around the rig (camera frame): every ray hits one face."""

    lo: np.ndarray
    hi: np.ndarray

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (self.lo - o) / d
            t2 = (self.hi - o) / d
        t = np.where(d > 0, t2, t1)
        t = np.where(np.isfinite(t) & (t > 0), t, np.inf)
        return t.min(axis=1)


@dataclass
class Disc:
    centre: np.ndarray
    normal: np.ndarray
    radius: float

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        den = d @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.centre - o) @ self.normal) / den
        x = o + t[:, None] * d
        ok = (t > 0) & (np.linalg.norm(x - self.centre, axis=1) <= self.radius)
        return np.where(ok, t, np.inf)


@dataclass
class Post:
    """A vertical cylinder (camera y) of radius r at (x, z), between y0 and y1."""

    x: float
    z: float
    r: float
    y0: float
    y1: float

    def hit(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        ox, oz = o[..., 0] - self.x, o[..., 2] - self.z
        dx, dz = d[:, 0], d[:, 2]
        a = dx * dx + dz * dz
        b = 2 * (ox * dx + oz * dz)
        c = ox * ox + oz * oz - self.r ** 2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
        y = o[..., 1] + t * d[:, 1]
        ok = (disc > 0) & (t > 0) & (y >= self.y0) & (y <= self.y1)
        return np.where(ok, t, np.inf)


@dataclass
class Rig:
    variant: Variant
    seed: int
    K: np.ndarray
    dist: np.ndarray
    boards: list[Board]
    room: Room
    post: Post
    axis_point: np.ndarray
    axis_dir: np.ndarray
    psi_ref: float
    R_ref: np.ndarray
    T_ref: np.ndarray
    psis: np.ndarray = None  # reported
    psis_true: np.ndarray = None

    def pose(self, psi_true: float) -> tuple[np.ndarray, np.ndarray]:
        """The rigid turntable model: X_cam = R X_lidar + T, turned about the axis."""
        Q = rot(self.axis_dir, np.radians(psi_true - self.psi_ref))
        return Q @ self.R_ref, self.axis_point + Q @ (self.T_ref - self.axis_point)


def build_rig(v: Variant, seed: int) -> Rig:
    rng = np.random.default_rng(seed)
    w, h = v.image_size
    K = np.array([[v.f_px * (1 + rng.uniform(-0.01, 0.01)), 0, w / 2 + rng.uniform(-15, 15)],
                  [0, v.f_px * (1 + rng.uniform(-0.01, 0.01)), h / 2 + rng.uniform(-15, 15)],
                  [0, 0, 1.0]])
    dist = np.array(v.dist, float) * (1 + rng.uniform(-0.1, 0.1, len(v.dist)))
    # The V: hinge about vertical (camera -y is up), opening towards camera and LiDAR.
    H = v.hinge_distance_mm * (1 + rng.uniform(-0.05, 0.05))
    hinge_pt = np.array([rng.uniform(-60, 60), rng.uniform(40, 90), H])
    hinge_dir = unit(np.array([rng.uniform(-0.05, 0.05), -1.0, rng.uniform(-0.08, 0.08)]))
    lidar_c = np.array([rng.uniform(-260, -150), rng.uniform(90, 140), rng.uniform(-40, 60)])
    bis = (lidar_c / 2) - hinge_pt  # towards the middle of camera and LiDAR
    bis = unit(bis - (bis @ hinge_dir) * hinge_dir)
    bis = rot(hinge_dir, np.radians(rng.uniform(-6, 6))) @ bis
    e = unit(np.cross(hinge_dir, bis))
    half = np.radians(v.v_angle_deg + rng.uniform(-3, 3)) / 2
    nx, ny = v.board_corners
    sq = v.square_mm
    m_hinge, m_out, m_v = 1.0 * sq, 1.3 * sq, 1.2 * sq
    width = m_hinge + (nx + 1) * sq + m_out
    height = 2 * m_v + (ny + 1) * sq
    boards = []
    for sgn in (+1, -1):
        u = unit(np.cos(half) * bis + sgn * np.sin(half) * e)
        vv = hinge_dir
        if np.cross(u, vv) @ (-hinge_pt) < 0:  # normal (u x v) towards the camera
            vv = -vv
        origin = hinge_pt - vv * height / 2
        boards.append(Board(origin, u, vv, width, height, (m_hinge, m_v), sq, (nx + 1, ny + 1)))
    # LiDAR at the reference angle: x towards the hinge (a few deg off), z up.
    x_l = unit(rot(np.array([0, -1.0, 0]), np.radians(rng.uniform(-8, 8))) @ unit(hinge_pt - lidar_c))
    up = unit(np.array([rng.uniform(-0.04, 0.04), -1.0, rng.uniform(-0.04, 0.04)]))
    z_l = unit(up - (up @ x_l) * x_l)
    if v.upside_down:
        z_l = -z_l
    y_l = np.cross(z_l, x_l)
    R_ref = np.column_stack([x_l, y_l, z_l])
    # Turntable axis: about the scan plane's horizontal line across the view (it
    # nods the scan plane), tilted a few deg, passing 30-80 mm from the centre.
    across = unit(np.cross(up, x_l))
    axis_dir = unit(across + rng.uniform(-0.06, 0.06, 3))
    if rng.random() < 0.5:
        axis_dir = -axis_dir
    off = rng.normal(size=3)
    off -= (off @ axis_dir) * axis_dir
    axis_point = lidar_c + unit(off) * rng.uniform(30, 80)
    room = Room(np.array([-2600.0, -1800.0, -1500.0]),
                np.array([2400.0, 1100.0, H + rng.uniform(350, 900)]))
    post = Post(hinge_pt[0] + rng.uniform(450, 650), H + rng.uniform(-100, 200), 35.0,
                hinge_pt[1] - 700, 1100.0)
    return Rig(v, seed, K, dist, boards, room, post, axis_point, axis_dir,
               0.0, R_ref, lidar_c)


# ----------------------------------------------------------------- camera rays


def pixel_rays(K, dist, size, ss):
    """Unit rays (camera frame) of ss x ss sub-pixel samples of every pixel.

    Pixel (u, v) has its centre at integer coordinates (OpenCV). The lens model is
    inverted by cv2.undistortPoints (iterated to 1e-12) and checked by re-projection."""
    w, h = size
    off = (np.arange(ss) + 0.5) / ss - 0.5
    us = (np.arange(w)[:, None] + off[None, :]).ravel()
    vs = (np.arange(h)[:, None] + off[None, :]).ravel()
    U, V = np.meshgrid(us, vs)  # (h*ss, w*ss)
    pts = np.stack([U.ravel(), V.ravel()], axis=1).astype(np.float64)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 60, 1e-12)
    out = np.empty_like(pts)
    step = 1 << 20
    for i in range(0, len(pts), step):
        out[i:i + step] = cv2.undistortPoints(
            pts[i:i + step].reshape(-1, 1, 2), K, dist, None, None, criteria=crit).reshape(-1, 2)
    sub = np.arange(0, len(pts), 997)
    back = cv2.projectPoints(np.column_stack([out[sub], np.ones(len(sub))]), np.zeros(3),
                             np.zeros(3), K, dist)[0].reshape(-1, 2)
    err = np.abs(back - pts[sub]).max()
    if err > 0.02:
        raise RuntimeError(f"lens inversion failed: {err:.3f} px")
    d = np.column_stack([out, np.ones(len(out))])
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32), (h * ss, w * ss)


def downsample(img: np.ndarray, ss: int, blur_px: float = 0.0) -> np.ndarray:
    """The pixels' values: the lens' Gaussian blur applied to the sub-pixel samples (so that
    edges are anti-aliased before sampling), then each pixel's ss x ss samples averaged
    (its area)."""
    if blur_px > 0:
        img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur_px * ss)
    H, W = img.shape
    return img.reshape(H // ss, ss, W // ss, ss).mean(axis=(1, 3))


@dataclass
class Surfaces:
    """Per camera sub-ray: what it hits first and where (fixed for a dataset)."""

    which: np.ndarray  # 0, 1 board; 2 post; 3 room
    X: np.ndarray  # (n, 3) float32 hit point
    albedo: np.ndarray  # visible albedo
    normal: np.ndarray  # (n, 3) surface normal
    cos_cam: np.ndarray  # cos of the viewing angle


def cast_scene(rig: Rig, d: np.ndarray, boards=True) -> Surfaces:
    o = np.zeros(3)
    ts = []
    coords = []
    for b in rig.boards:
        t, a, bb = b.hit(o, d)
        ts.append(t if boards else np.full(len(d), np.inf))
        coords.append((a, bb))
    ts.append(rig.post.hit(o, d))
    ts.append(rig.room.hit(o, d))
    T = np.stack(ts, axis=1)
    which = T.argmin(axis=1)
    t = T[np.arange(len(d)), which]
    X = d * t[:, None]
    alb = np.full(len(d), 0.35, np.float32)
    nrm = np.zeros((len(d), 3), np.float32)
    for k, b in enumerate(rig.boards):
        m = which == k
        blk = b.black(coords[k][0][m], coords[k][1][m])
        alb[m] = np.where(blk, 0.05, 0.85)
        nrm[m] = b.normal
    m = which == 2
    nrm[m] = np.column_stack([X[m, 0] - rig.post.x, np.zeros(m.sum()), X[m, 2] - rig.post.z])
    nrm[m] /= np.linalg.norm(nrm[m], axis=1, keepdims=True)
    alb[m] = 0.2
    m = which == 3
    if m.any():
        xm = X[m]
        lo, hi = rig.room.lo, rig.room.hi
        face = np.argmin(np.minimum(np.abs(xm - lo), np.abs(xm - hi)), axis=1)
        n3 = np.zeros((m.sum(), 3))
        n3[np.arange(len(face)), face] = 1.0
        nrm[m] = n3
        alb[m] = 0.3 + 0.08 * np.sin(xm[:, 0] / 170.0) * np.cos(xm[:, 1] / 230.0)
    cos_cam = np.abs(np.einsum("ij,ij->i", nrm, d))
    return Surfaces(which.astype(np.int8), X.astype(np.float32), alb, nrm, cos_cam)


def sensor(linear: np.ndarray, rng, v: Variant, gain_e=3.0, read_dn=1.2) -> np.ndarray:
    """Shot noise, read noise, gamma, 8-bit quantisation (the blur is in :func:`downsample`)."""
    e = rng.poisson(np.clip(linear, 0, None) * gain_e) / gain_e
    e = e + rng.normal(0, read_dn, e.shape)
    e = 255.0 * np.clip(e / 255.0, 0, None) ** v.gamma
    return np.clip(np.round(e), 0, 255).astype(np.uint8)


def render_lit(rig: Rig, surf: Surfaces, shape, ss, rng, level=205.0) -> np.ndarray:
    """The bright board image: Lambertian under a diffuse light near the camera."""
    shade = 0.55 + 0.45 * surf.cos_cam
    img = downsample((level * surf.albedo * shade).reshape(shape), ss, rig.variant.blur_px)
    return sensor(img, rng, rig.variant)


def laser_visible(rig: Rig, X: np.ndarray, R, T) -> np.ndarray:
    """True where the segment LiDAR -> X is not blocked by a board or the post."""
    d = X - T
    L = np.linalg.norm(d, axis=1)
    d = d / L[:, None]
    free = np.ones(len(X), bool)
    for b in rig.boards:
        t, _, _ = b.hit(T, d)
        free &= ~(t < L - 0.5)
    free &= ~(rig.post.hit(T, d) < L - 0.5)
    return free


def stripe_linear(rig: Rig, surf: Surfaces, shape, ss, psi_true) -> np.ndarray:
    """The scan sheet's irradiance x albedo on every surface it reaches, per pixel (linear)."""
    v = rig.variant
    R, T = rig.pose(psi_true)
    n_l = R[:, 2].astype(np.float32)
    z_all = surf.X @ n_l - np.float32(T @ R[:, 2])  # distance to the scan plane
    sig_max = v.sheet_sigma_mm + v.sheet_div_mrad * 1e-3 * v.range_max_mm
    idx = np.nonzero(np.abs(z_all) < 5 * sig_max)[0]
    Xl = (surf.X[idx] - T) @ R  # LiDAR frame
    r = np.hypot(Xl[:, 0], Xl[:, 1])
    sig = v.sheet_sigma_mm + v.sheet_div_mrad * 1e-3 * r
    z = Xl[:, 2]
    theta = np.degrees(np.arctan2(Xl[:, 1], Xl[:, 0]))
    keep = (np.abs(z) < 5 * sig) & (np.abs(theta) <= v.lidar_fov_deg / 2) & (r > 50)
    idx, r, sig, z = idx[keep], r[keep], sig[keep], z[keep]
    lin = np.zeros(len(surf.X), np.float32)
    if len(idx):
        vis = laser_visible(rig, surf.X[idx].astype(float), R, T)
        idx, r, sig, z = idx[vis], r[vis], sig[vis], z[vis]
        bd = surf.X[idx] - T
        bd /= np.linalg.norm(bd, axis=1, keepdims=True)
        cos_in = np.abs(np.einsum("ij,ij->i", bd, surf.normal[idx]))
        # a fan of constant power per angle: irradiance ~ 1 / (range x sheet width)
        lin[idx] = surf.albedo[idx] * np.exp(-0.5 * (z / sig) ** 2) * cos_in / (sig * r)
    return downsample(lin.reshape(shape), ss, v.blur_px)


def exposure(rig: Rig, surf: Surfaces, shape, ss, psi_true) -> float:
    """The operator's fixed exposure: the stripe's typical peak at 235 / (1 + 2.5 speckle)."""
    lin = stripe_linear(rig, surf, shape, ss, psi_true)
    col_max = lin.max(axis=0)
    col_max = col_max[col_max > 0.2 * col_max.max()]
    return 235.0 / (1 + 2.5 * rig.variant.speckle) / float(np.percentile(col_max, 90))


def render_stripe(rig: Rig, surf: Surfaces, shape, ss, rng, psi_true, gain: float):
    """The dark stripe image: sheet, speckle, faint ambient light, sensor."""
    v = rig.variant
    img = gain * stripe_linear(rig, surf, shape, ss, psi_true)
    # speckle: a multiplicative field of grain ~1.5 px, new in every frame
    sp = rng.normal(size=img.shape).astype(np.float32)
    sp = cv2.GaussianBlur(sp, (0, 0), 1.5)
    sp *= v.speckle / max(sp.std(), 1e-9)
    img = img * np.clip(1 + sp, 0, None)
    ambient = downsample((4.0 * surf.albedo * (0.5 + 0.5 * surf.cos_cam)).reshape(shape), ss,
                         v.blur_px)
    if v.colour == "gray":
        return sensor(img + ambient, rng, v)
    chans = [sensor(0.04 * img + ambient, rng, v), sensor(0.09 * img + ambient, rng, v),
             sensor(img + ambient, rng, v)]
    return np.dstack(chans)  # BGR


# ----------------------------------------------------------------- LiDAR


def beam_angles(v: Variant) -> np.ndarray:
    n = round(v.lidar_fov_deg / v.lidar_step_deg)
    return -v.lidar_fov_deg / 2 + v.lidar_step_deg * np.arange(n + 1)


def scan(rig: Rig, psi_true: float, rng, disc: Disc | None = None, with_board=True):
    """One scan: ranges (nan = no return) per beam, and the true ranges."""
    v = rig.variant
    R, T = rig.pose(psi_true)
    ang = np.radians(beam_angles(v))
    step = np.radians(v.lidar_step_deg)
    offs = np.linspace(-2.2, 2.2, 11) * v.spot_sigma_steps * step
    wts = np.exp(-0.5 * (offs / (v.spot_sigma_steps * step)) ** 2)
    nb = len(ang)
    rng_sub = np.empty((nb, len(offs)))
    refl = np.empty((nb, len(offs)))
    dark = np.zeros((nb, len(offs)), bool)
    for j, o in enumerate(offs):
        a = ang + o
        dl = np.column_stack([np.cos(a), np.sin(a), np.zeros(nb)])
        d = dl @ R.T
        ts = []
        blk = []
        for b in rig.boards:
            t, aa, bb = b.hit(T, d)
            ts.append(t if with_board else np.full(nb, np.inf))
            blk.append(b.black(aa, bb))
        # the V and its stand are taken away for the disc sweeps
        ts.append(rig.post.hit(T, d) if with_board else np.full(nb, np.inf))
        ts.append(disc.hit(T, d) if disc is not None else np.full(nb, np.inf))
        ts.append(rig.room.hit(T, d))
        Tm = np.stack(ts, axis=1)
        w = Tm.argmin(axis=1)
        rng_sub[:, j] = Tm[np.arange(nb), w]
        rf = np.select([w <= 1, w == 2, w == 3], [0.8, 0.3, 0.7], 0.5)
        for k in range(2):
            m = (w == k) & blk[k]
            rf[m] = 0.25
            dark[m, j] = True
        refl[:, j] = rf
    rng_sub = np.where(np.isfinite(rng_sub), rng_sub, 1e9)
    energy = wts[None, :] * refl / np.maximum(rng_sub, 1.0) ** 2
    if v.echo == "mixed":
        r = (energy * rng_sub).sum(1) / energy.sum(1)
    else:  # first echo: the nearest surface (within 30 mm) holding >= 30 % of the energy
        order = np.argsort(rng_sub, axis=1)
        rs = np.take_along_axis(rng_sub, order, 1)
        es = np.take_along_axis(energy, order, 1)
        share = np.cumsum(es, 1) / es.sum(1, keepdims=True)
        r = np.full(nb, np.nan)
        for i in range(nb):
            # group sub-rays into surfaces by range jumps
            cut = np.nonzero(np.diff(rs[i]) > 30.0)[0]
            starts = np.r_[0, cut + 1]
            ends = np.r_[cut + 1, len(rs[i])]
            for s0, s1 in zip(starts, ends):
                if share[i, s1 - 1] - (share[i, s0 - 1] if s0 else 0) >= 0.3:
                    r[i] = (es[i, s0:s1] * rs[i, s0:s1]).sum() / es[i, s0:s1].sum()
                    break
    centre = len(offs) // 2
    r_true = rng_sub[:, centre].copy()
    noise = v.range_noise_mm * (1 + (r / 4000.0) ** 2)
    meas = r + v.range_offset_mm + rng.normal(0, 1, nb) * noise
    if v.range_quantum_mm > 0:
        meas = np.round(meas / v.range_quantum_mm) * v.range_quantum_mm
    # weak returns (black print, the dark post) drop out three times as often
    p_drop = v.dropout * np.where(refl[:, centre] < 0.35, 3.0, 1.0)
    drop = rng.random(nb) < p_drop
    bad = drop | ~np.isfinite(r) | (r > v.range_max_mm) | (r < v.range_min_mm)
    meas[bad] = np.nan
    return meas, r_true


def write_scan(path: Path, v: Variant, ranges: np.ndarray) -> None:
    ang = beam_angles(v)
    with open(path, "w", newline="") as f:
        f.write("angle_deg,range_mm\n")
        f.writelines(f"{a:.6f},{v.no_return if not np.isfinite(r) else format(r, '.1f')}\n" for a, r in zip(ang, ranges))


# ----------------------------------------------------------------- sweep planning


def stripe_ok(rig: Rig, psi_true: float) -> bool:
    """Both boards crossed by the sheet well inside their patterns, and hit by the scan."""
    R, T = rig.pose(psi_true)
    n_l = R[:, 2]
    for b in rig.boards:
        # the sheet's line on the board: b-coordinate where the plane crosses at each a
        a = np.linspace(b.pattern_origin[0], b.pattern_origin[0] + b.squares[0] * b.square, 20)
        # n_l . (origin + a u + bb v - T) = 0
        den = n_l @ b.v
        if abs(den) < 1e-6:
            return False
        bb = (n_l @ (T - b.origin) - a * (n_l @ b.u)) / den
        lo = b.pattern_origin[1] + 1.0 * b.square
        hi = b.pattern_origin[1] + (b.squares[1] - 1.0) * b.square
        if bb.min() < lo or bb.max() > hi:
            return False
        # the V within the LiDAR's field of view
        X = b.origin + a[:, None] * b.u + bb[:, None] * b.v
        Xl = (X - T) @ R
        th = np.degrees(np.arctan2(Xl[:, 1], Xl[:, 0]))
        if np.abs(th).max() > rig.variant.lidar_fov_deg / 2 - 2:
            return False
    return True


def plan_positions(rig: Rig, rng) -> None:
    v = rig.variant
    grid = np.arange(-30, 30.01, 0.1)
    ok = np.array([stripe_ok(rig, g) for g in grid])
    if not ok[len(grid) // 2]:
        raise RuntimeError("the reference pose does not see both boards")
    c = len(grid) // 2
    lo = c
    while lo > 0 and ok[lo - 1]:
        lo -= 1
    hi = c
    while hi < len(grid) - 1 and ok[hi + 1]:
        hi += 1
    span = 0.85 * (grid[hi] - grid[lo])
    mid = 0.5 * (grid[hi] + grid[lo])
    rel = mid + np.linspace(-span / 2, span / 2, v.n_positions)
    # the controller's reading: its own zero, maybe counting down
    # If the controller counts down, its positive steps turn the table left-handedly
    # about our axis: the true right-handed axis for reported angles is -axis_dir.
    if v.psi_decreasing:
        rig.axis_dir = -rig.axis_dir
        rel = -rel
    reported = v.psi_zero_deg + rel
    rig.psi_ref = float(v.psi_zero_deg)
    jitter = rng.normal(0, v.encoder_jitter_deg, len(rel)) if v.encoder_jitter_deg else 0.0
    rig.psis_true = reported + jitter
    rig.psis = np.round(reported, 3)


# ----------------------------------------------------------------- intrinsics photos


def render_intrinsics(rig: Rig, d: np.ndarray, shape, ss, rng, out: Path, n_views=14):
    v = rig.variant
    nx, ny = v.intrinsics_corners
    sq = v.intrinsics_square_mm
    W = (nx + 1 + 2) * sq
    Hh = (ny + 1 + 2) * sq
    w, h = v.image_size
    fx = rig.K[0, 0]
    out.mkdir(parents=True, exist_ok=True)
    made = 0
    tries = 0
    while made < n_views and tries < 200:
        tries += 1
        dist_mm = rng.uniform(1.3, 2.4) * fx * W / w
        # aim the board's centre at a spot spread over the image
        gx, gy = (made % 4 + rng.uniform(0.2, 0.8)) / 4, ((made // 4) % 3 + rng.uniform(0.2, 0.8)) / 3
        ray = np.array([(gx * w - rig.K[0, 2]) / fx, (gy * h - rig.K[1, 2]) / rig.K[1, 1], 1.0])
        c = unit(ray) * dist_mm
        tilt = rot(unit(rng.normal(size=3) * [1, 1, 0.3]), np.radians(rng.uniform(10, 40)))
        u = tilt @ np.array([1.0, 0, 0])
        vv = tilt @ np.array([0, 1.0, 0])
        if np.cross(u, vv) @ c > 0:
            vv = -vv
        b = Board(c - u * W / 2 - vv * Hh / 2, u, vv, W, Hh, (sq, sq), sq, (nx + 1, ny + 1))
        corners = b.corners()
        px = cv2.projectPoints(corners, np.zeros(3), np.zeros(3), rig.K, rig.dist)[0].reshape(-1, 2)
        if (px.min() < 15) or (px[:, 0].max() > w - 15) or (px[:, 1].max() > h - 15):
            continue
        t, a, bb = b.hit(np.zeros(3), d)
        hit = np.isfinite(t)
        alb = np.where(hit, np.where(b.black(a, bb), 0.05, 0.85), 0.25).astype(np.float32)
        cosv = np.where(hit, np.abs(d @ b.normal), 0.7)
        lin = downsample((200.0 * alb * (0.6 + 0.4 * cosv)).reshape(shape), ss, v.blur_px)
        cv2.imwrite(str(out / f"view_{made:02d}.png"), sensor(lin, rng, v))
        made += 1
    return made


# ----------------------------------------------------------------- dataset


def make_variant(variant: str, n_positions: int | None = None,
                 overrides: dict | None = None) -> Variant:
    """A named variant, with its count of positions and any field overridden."""
    fields = dict(VARIANTS[variant].__dict__)
    if n_positions:
        fields["n_positions"] = n_positions
    for k, val in (overrides or {}).items():
        if k not in fields:
            raise KeyError(f"no variant field {k!r}")
        fields[k] = type(fields[k])(val) if not isinstance(fields[k], tuple) else tuple(val)
    return Variant(**fields)


def generate(out: Path, variant: str, seed: int, sweeps: bool = True,
             n_positions: int | None = None, overrides: dict | None = None) -> dict:
    v = make_variant(variant, n_positions, overrides)
    rng = np.random.default_rng(10_000 + seed)
    rig = build_rig(v, seed)
    plan_positions(rig, rng)
    out.mkdir(parents=True, exist_ok=True)
    (out / "stripes").mkdir(exist_ok=True)
    (out / "scans").mkdir(exist_ok=True)
    ss = v.supersample
    d, shape = pixel_rays(rig.K, rig.dist, v.image_size, ss)
    surf = cast_scene(rig, d)
    cv2.imwrite(str(out / "board.png"), render_lit(rig, surf, shape, ss, rng))
    order = np.arange(v.n_positions)
    gain = exposure(rig, surf, shape, ss, float(rig.psis_true[v.n_positions // 2]))
    rows = []
    poses = []
    for i in order:
        psi_t = float(rig.psis_true[i])
        img = render_stripe(rig, surf, shape, ss, rng, psi_t, gain)
        cv2.imwrite(str(out / "stripes" / f"{i:04d}.png"), img)
        meas, _ = scan(rig, psi_t, rng)
        write_scan(out / "scans" / f"{i:04d}.csv", v, meas)
        reported = float(rig.psis[i])
        if v.psi_zero_deg + 20 > 360:  # a controller that wraps at 360 deg
            reported = reported % 360.0
        rows.append({"index": int(i), "psi_deg": f"{reported:.3f}",
                     "stripe_image": f"stripes/{i:04d}.png", "scan": f"scans/{i:04d}.csv"})
        R, T = rig.pose(psi_t)
        poses.append({"index": int(i), "psi_deg": reported, "psi_true_deg": psi_t,
                      "R": R.tolist(), "T_mm": T.tolist()})
    cols = ["scan", "psi_deg", "index", "stripe_image"] if v.name == "sxga_rational" else \
        ["index", "psi_deg", "stripe_image", "scan"]
    with open(out / "positions.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=cols)
        wr.writeheader()
        for r in rows:
            wr.writerow(r)
    ds = {
        "format": "lidarcal-dataset/1",
        "v_board": {"inner_corners": list(v.board_corners), "square_mm": v.square_mm},
        "lidar": {"angle_min_deg": float(beam_angles(v)[0]),
                  "angle_max_deg": float(beam_angles(v)[-1]),
                  "angle_step_deg": v.lidar_step_deg,
                  "range_min_mm": v.range_min_mm, "range_max_mm": v.range_max_mm,
                  "z_axis_hint": [0, 1, 0] if v.upside_down else [0, -1, 0]},
    }
    if v.camera_in_json:
        ds["camera"] = {"image_size": list(v.image_size), "K": rig.K.tolist(),
                        "dist": rig.dist.tolist()}
    else:
        n = render_intrinsics(rig, d, shape, ss, rng, out / "intrinsics")
        ds["intrinsics_board"] = {"inner_corners": list(v.intrinsics_corners),
                                  "square_mm": v.intrinsics_square_mm}
        ds["_intrinsics_views"] = n
    truth_meas = []
    if sweeps:
        ds["measurements"] = []
        (out / "measure").mkdir(exist_ok=True)
        for j, diam in enumerate(v.disc_diameters_mm):
            name = f"disc_{j + 1:02d}"
            disc, psis = plan_disc(rig, rng, diam)
            write_sweep(out / "measure" / f"{name}.csv.gz", rig, rng, disc, psis)
            ds["measurements"].append({"name": name, "sweep": f"measure/{name}.csv.gz",
                                       "object": "disc", "reference_diameter_mm": diam})
            truth_meas.append({"name": name, "diameter_mm": diam,
                               "center_mm": disc.centre.tolist(),
                               "normal": disc.normal.tolist()})
    ds.pop("_intrinsics_views", None)
    (out / "dataset.json").write_text(json.dumps(ds, indent=1))
    truth = {
        "generator": "scripts/cleanroom_rig.py", "rig": v.name, "seed": seed,
        "camera": {"K": rig.K.tolist(), "dist": rig.dist.tolist(),
                   "image_size": list(v.image_size)},
        "boards": [{"normal": b.normal.tolist(), "d_mm": float(b.normal @ b.origin),
                    "outline_mm": b.outline().tolist(), "corners_mm": b.corners().tolist()}
                   for b in rig.boards],
        "axis": {"point_mm": rig.axis_point.tolist(), "direction": rig.axis_dir.tolist()},
        "psi_ref_deg": rig.psi_ref,
        "pose_ref": {"R": rig.R_ref.tolist(), "T_mm": rig.T_ref.tolist()},
        "poses": poses,
        "measurements": truth_meas,
        "ranging": {"offset_mm": v.range_offset_mm, "dark_extra_mm": 0.0,
                    "quantum_mm": v.range_quantum_mm},
        "noise": {"range_noise_mm": v.range_noise_mm, "echo": v.echo,
                  "spot_sigma_deg": v.spot_sigma_steps * v.lidar_step_deg,
                  "encoder_noise_deg": v.encoder_jitter_deg},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def plan_disc(rig: Rig, rng, diameter: float):
    """A disc at 1.2-1.8 m (at least 300 mm before the wall), in the scan plane at a psi
    inside the sweep."""
    v = rig.variant
    i_mid = rng.integers(len(rig.psis_true) // 4, 3 * len(rig.psis_true) // 4)
    psi_c = float(rig.psis_true[i_mid])
    R, T = rig.pose(psi_c)
    beam = np.radians(rng.uniform(-25, 25))
    ray = R @ np.array([np.cos(beam), np.sin(beam), 0.0])
    wall = float(rig.room.hit(T, ray[None, :])[0])  # a disc in front of the wall behind it
    dist = min(rng.uniform(1200, 1800), wall - rng.uniform(300, 600))
    c = T + ray * dist
    towards = unit(T - c)
    tilt = rot(unit(np.cross(towards, rng.normal(size=3))), np.radians(rng.uniform(0, 30)))
    disc = Disc(c, tilt @ towards, diameter / 2)
    # psi range: from the first to the last scan that hits the disc, plus margins
    grid = np.arange(-12, 12.001, 0.1)
    hits = []
    for g in grid:
        Rg, Tg = rig.pose(psi_c + g)
        a = np.radians(beam_angles(v))
        dd = np.column_stack([np.cos(a), np.sin(a), np.zeros(len(a))]) @ Rg.T
        hits.append(np.isfinite(disc.hit(Tg, dd)).any())
    hits = np.array(hits)
    g_hit = grid[hits]
    lo, hi = g_hit.min() - 0.6, g_hit.max() + 0.6
    return disc, psi_c + np.arange(lo, hi + 1e-9, 0.05)


def write_sweep(path: Path, rig: Rig, rng, disc: Disc, psis_true: np.ndarray) -> None:
    """Long form sweep, psi_deg as the controller reports it (same zero as positions)."""
    v = rig.variant
    ang = beam_angles(v)
    with gzip.open(path, "wt", newline="") as f:
        f.write("psi_deg,angle_deg,range_mm\n")
        for p in psis_true:
            meas, _ = scan(rig, float(p), rng, disc=disc, with_board=False)
            rep = p % 360.0 if v.psi_zero_deg + 20 > 360 else p
            for a, r in zip(ang, meas):
                f.write(f"{rep:.3f},{a:.6f},{v.no_return if not np.isfinite(r) else format(r, '.1f')}\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", nargs="?", type=Path, help="dataset folder to write")
    ap.add_argument("--variant", default="hd", choices=sorted(VARIANTS))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--positions", type=int, default=None, help="override the variant's count")
    ap.add_argument("--no-sweeps", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a variant field, e.g. --set v_angle_deg=100")
    ap.add_argument("--evaluate", type=Path, default=None, metavar="WORKDIR")
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--lidarcal", default=str(Path(sys.executable).parent / "lidarcal"))
    a = ap.parse_args(argv)
    overrides = {}
    for kv in a.set:
        k, _, val = kv.partition("=")
        overrides[k] = [float(x) for x in val.split(",")] if "," in val else (
            val if k in ("echo", "colour", "no_return", "name") else float(val))
    if a.evaluate:
        from cleanroom_eval import evaluate  # beside this script; it imports generate from here

        a.evaluate.mkdir(parents=True, exist_ok=True)
        rows = evaluate(a.evaluate, a.variants.split(","), [int(s) for s in a.seeds.split(",")],
                        a.lidarcal, a.positions, overrides, sweeps=not a.no_sweeps)
        (a.evaluate / "summary.json").write_text(json.dumps(rows, indent=1))
        return 0
    if a.out is None:
        ap.error("give OUT or --evaluate WORKDIR")
    generate(a.out, a.variant, a.seed, sweeps=not a.no_sweeps, n_positions=a.positions,
             overrides=overrides)
    return 0


if __name__ == "__main__":
    sys.exit(main())
