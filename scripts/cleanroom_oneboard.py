"""Clean-room one-board data: `lidarcal planes` folders and `lidarcal laser-plane` photos.

Written only from docs/dataset-format.md (sections "One flat board" and "The laser plane
from a flat board"), the README and the CLI's --help: it does NOT import lidarcal (nor
lidarcal.synthetic), so it shares none of the package's conventions or physics beyond
what the docs state. Plain numpy + cv2 + json.

Physics of its own:
- camera: 1280 x 960 (or 1600 x 1200), 5-coefficient distortion, 2x2 supersampling,
  optical blur, shot + read noise, vignetting, JPEG (4:2:0) at quality 85-92;
- `planes`: a board with physical white margins beyond its pattern, a pole under it, a
  person behind it, sometimes a wall a few cm behind it, a room around; a LiDAR of
  0.25 deg step, 1 mm range quantisation, beam footprint (mixed pixels at edges),
  dropouts written as 0 or empty, both CSV forms (angle/range and x/y) with extra columns;
- `laser-plane`: lights-on colour photos of a red or green line laser (Gaussian sheet,
  multiplicative speckle of 1-2 px grain, clipped white core, blooming into the other
  channels), RGGB Bayer mosaic demosaiced by cv2, ambient light with a gradient, the
  stripe also on the wall behind (shadowed by the board), a photo whose board is
  partly out of view and one whose stripe leaves the board.

Usage:
    python scripts/cleanroom_oneboard.py planes OUT --seed 0 --variant wall
    python scripts/cleanroom_oneboard.py laser OUT --seed 0 --variant red
    python scripts/cleanroom_oneboard.py --evaluate --seeds 0 1 --work /tmp/cr
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

# --------------------------------------------------------------------------- geometry


def rot(axis: str, deg: float) -> np.ndarray:
    """Rotation about a coordinate axis by `deg` degrees (right-handed)."""
    a = np.radians(deg)
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


@dataclass
class Camera:
    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]  # width, height

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "dist": self.dist.tolist(), "image_size": list(self.size)}


def make_camera(rng: np.random.Generator, big: bool = False, small: bool = False) -> Camera:
    w, h = (640, 480) if small else (1600, 1200) if big else (1280, 960)
    f = w * rng.uniform(0.78, 0.95)
    K = np.array([[f, 0, w / 2 + rng.uniform(-15, 15)], [0, f * rng.uniform(0.998, 1.002),
                  h / 2 + rng.uniform(-12, 12)], [0, 0, 1.0]])
    dist = np.array([rng.uniform(-0.32, -0.18), rng.uniform(0.05, 0.14), rng.uniform(-8e-4, 8e-4),
                     rng.uniform(-8e-4, 8e-4), rng.uniform(-0.03, 0.0)])
    return Camera(K, dist, (w, h))


@dataclass
class Rect:
    """A flat rectangle: X = centre + a * u + b * v, |a| <= half_u, |b| <= half_v."""

    centre: np.ndarray
    u: np.ndarray
    v: np.ndarray
    half_u: float
    half_v: float
    kind: str

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter t of origin + t * dirs on the rectangle (inf when missed)."""
        n = self.normal
        den = dirs @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((self.centre - origin) @ n) / den
        X = origin + t[:, None] * dirs
        a = (X - self.centre) @ self.u
        b = (X - self.centre) @ self.v
        ok = (t > 1e-6) & (np.abs(a) <= self.half_u) & (np.abs(b) <= self.half_v) & np.isfinite(t)
        return np.where(ok, t, np.inf)


@dataclass
class Cylinder:
    """A vertical (camera y) cylinder: a person standing behind the board."""

    centre: np.ndarray  # a point on its axis
    radius: float
    y_min: float
    y_max: float
    kind: str = "person"

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        o = origin - self.centre
        a = dirs[:, 0] ** 2 + dirs[:, 2] ** 2
        b = 2 * (o[0] * dirs[:, 0] + o[2] * dirs[:, 2])
        c = o[0] ** 2 + o[2] ** 2 - self.radius**2
        disc = b * b - 4 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(disc)) / (2 * a)
        y = origin[1] + t * dirs[:, 1]
        ok = (disc > 0) & (t > 0) & (y >= self.y_min) & (y <= self.y_max)
        return np.where(ok, t, np.inf)


@dataclass
class Board:
    inner: tuple[int, int]  # inner corners per row, per column (OpenCV patternSize)
    square: float
    margin: tuple[float, float, float, float]  # left, right, top, bottom, mm beyond the pattern
    R: np.ndarray  # board axes in the camera frame (columns: along rows, down columns, normal)
    T: np.ndarray  # the pattern's top-left outer corner in the camera frame

    @property
    def pattern_mm(self) -> tuple[float, float]:
        return (self.inner[0] + 1) * self.square, (self.inner[1] + 1) * self.square

    def rect(self) -> Rect:
        pw, ph = self.pattern_mm
        ml, mr, mt, mb = self.margin
        a0, a1, b0, b1 = -ml, pw + mr, -mt, ph + mb
        c = self.T + self.R[:, 0] * (a0 + a1) / 2 + self.R[:, 1] * (b0 + b1) / 2
        return Rect(c, self.R[:, 0], self.R[:, 1], (a1 - a0) / 2, (b1 - b0) / 2, "board")

    def plane(self) -> tuple[np.ndarray, float]:
        n = self.R[:, 2]
        d = float(n @ self.T)
        if d < 0:
            n, d = -n, -d
        return n, d

    def albedo(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Printed pattern: black squares 0.05, paper 0.85; the top-left square is black."""
        pw, ph = self.pattern_mm
        inside = (a >= 0) & (a < pw) & (b >= 0) & (b < ph)
        i = np.floor(a / self.square).astype(np.int64)
        j = np.floor(b / self.square).astype(np.int64)
        black = inside & ((i + j) % 2 == 0)
        return np.where(black, 0.05, 0.85)


def board_pose(centre: np.ndarray, yaw: float, pitch: float, roll: float, board_size: tuple[float, float]):
    """A board facing the camera (normal towards -z), turned yaw/pitch/roll degrees; returns R, T
    with T the pattern's top-left corner such that the pattern's centre lies at `centre`."""
    R = rot("y", yaw) @ rot("x", pitch) @ rot("z", roll)
    T = centre - R[:, 0] * board_size[0] / 2 - R[:, 1] * board_size[1] / 2
    return R, T


# --------------------------------------------------------------------------- rendering


class Renderer:
    """Renders a camera image by casting one ray per sub-pixel (2 x 2 supersampling)."""

    SS = 2

    def __init__(self, cam: Camera):
        self.cam = cam
        w, h = cam.size
        s = self.SS
        u = (np.arange(w * s) + 0.5) / s - 0.5
        v = (np.arange(h * s) + 0.5) / s - 0.5
        uu, vv = np.meshgrid(u, v)
        pts = np.stack([uu.ravel(), vv.ravel()], 1).reshape(-1, 1, 2).astype(np.float64)
        und = cv2.undistortPoints(pts, cam.K, cam.dist, None, None, None,
                                      (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
        xy = und.reshape(-1, 2)
        self.dirs = np.column_stack([xy, np.ones(len(xy))])
        self.shape = (h * s, w * s)

    def downsample(self, img: np.ndarray) -> np.ndarray:
        h, w = self.cam.size[1], self.cam.size[0]
        return cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)

    def cast(self, surfaces: list) -> tuple[np.ndarray, np.ndarray]:
        """Nearest surface index (-1: none) and ray parameter per sub-pixel."""
        origin = np.zeros(3)
        best = np.full(len(self.dirs), np.inf)
        idx = np.full(len(self.dirs), -1)
        for k, s in enumerate(surfaces):
            t = s.hit(origin, self.dirs)
            closer = t < best
            best[closer] = t[closer]
            idx[closer] = k
        return idx, best


def smooth_texture(rng: np.random.Generator, shape: tuple[int, int], scale: float) -> np.ndarray:
    """Low-frequency random texture in 0..1."""
    small = rng.normal(size=(max(2, int(shape[0] / scale)), max(2, int(shape[1] / scale))))
    big = cv2.resize(small, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    big = (big - big.min()) / (np.ptp(big) + 1e-9)
    return big


def sensor(rng: np.random.Generator, linear_bgr: np.ndarray, bayer: bool, blur_px: float) -> np.ndarray:
    """Linear light (1.0 = full well) -> 8-bit BGR: optical blur, RGGB mosaic, shot + read
    noise, clipping, gamma 1/2.2, demosaic (cv2)."""
    img = cv2.GaussianBlur(linear_bgr, (0, 0), blur_px)
    h, w = img.shape[:2]
    if bayer:
        mosaic = np.empty((h, w))
        mosaic[0::2, 0::2] = img[0::2, 0::2, 2]  # R
        mosaic[0::2, 1::2] = img[0::2, 1::2, 1]  # G
        mosaic[1::2, 0::2] = img[1::2, 0::2, 1]  # G
        mosaic[1::2, 1::2] = img[1::2, 1::2, 0]  # B
        full_well = 4000.0
        e = rng.poisson(np.clip(mosaic, 0, 4) * full_well) / full_well + rng.normal(0, 0.004, mosaic.shape)
        raw = np.clip(e, 0, 1) ** (1 / 2.2)
        raw8 = np.round(raw * 255).astype(np.uint8)
        return cv2.cvtColor(raw8, cv2.COLOR_BayerBG2BGR)
    full_well = 4000.0
    e = rng.poisson(np.clip(img, 0, 4) * full_well) / full_well + rng.normal(0, 0.004, img.shape)
    return np.round(np.clip(e, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8)


def vignetting(cam: Camera, strength: float) -> np.ndarray:
    w, h = cam.size
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - cam.K[0, 2]) ** 2 + (yy - cam.K[1, 2]) ** 2) / (cam.K[0, 0] ** 2)
    return 1.0 / (1 + strength * r2) ** 2


def write_jpeg(path: Path, img: np.ndarray, quality: int) -> None:
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    path.write_bytes(buf.tobytes())


def render_scene(rng, ren: Renderer, board: Board, extras: list[Rect], background_z: float,
                 ambient: float, laser=None):
    """Linear BGR image of the board (+ extras + a textured background wall). `laser`:
    (normal, d, sigma_mm, power, rgb, origin) of a line laser sheet lighting every surface."""
    br = board.rect()
    wall = Rect(np.array([0, 0, background_z]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]),
                1e5, 1e5, "background")
    surfaces = [br, *extras, wall]
    idx, t = ren.cast(surfaces)
    X = t[:, None] * ren.dirs
    alb = np.full(len(X), 0.4)
    on_board = idx == 0
    rel = X[on_board] - board.T
    a, b = rel @ board.R[:, 0], rel @ board.R[:, 1]
    alb[on_board] = board.albedo(a, b)
    for k, s in enumerate(extras, start=1):
        alb[idx == k] = 0.25 if s.kind == "stand" else 0.55
    bg = idx == len(surfaces) - 1
    tex = smooth_texture(rng, ren.shape, 60).ravel()
    alb[bg] = 0.25 + 0.35 * tex[bg]
    alb = alb.reshape(ren.shape)
    h, w = ren.shape
    gradient = 1 + 0.25 * (np.linspace(-1, 1, w)[None, :] * rng.uniform(-1, 1)
                           + np.linspace(-1, 1, h)[:, None] * rng.uniform(-1, 1))
    light = np.array([0.93, 1.0, 1.05]) * rng.uniform(0.95, 1.05, 3)  # B, G, R of the lamp
    img = (alb * ambient * gradient)[..., None] * light[None, None, :]
    laser_img = None
    if laser is not None:
        n, d, sig, power, _rgb, origin = laser
        dist = X @ n - d
        lit = np.exp(-0.5 * (dist / sig) ** 2)
        # the board casts a shadow on what lies behind it
        behind = ~on_board & np.isfinite(t)
        if behind.any():
            seg = X[behind] - origin
            tb = br.hit(origin, seg / np.linalg.norm(seg, axis=1)[:, None])
            shadow = tb < np.linalg.norm(seg, axis=1) - 1.0
            lit_b = lit[behind]
            lit_b[shadow] = 0
            lit[behind] = lit_b
        laser_img = (lit * alb.ravel()).reshape(ren.shape) * power
    img_small = ren.downsample(img.astype(np.float32))
    if laser_img is not None:
        l_small = ren.downsample(laser_img.astype(np.float32))
        return img_small, l_small
    return img_small, None


def speckle(rng: np.random.Generator, shape: tuple[int, int], grain_px: float, contrast: float) -> np.ndarray:
    """Multiplicative laser speckle, mean 1: |complex Gaussian field blurred by the grain|^2."""
    re = cv2.GaussianBlur(rng.normal(size=shape).astype(np.float32), (0, 0), grain_px)
    im = cv2.GaussianBlur(rng.normal(size=shape).astype(np.float32), (0, 0), grain_px)
    i = re**2 + im**2
    i /= i.mean()
    return (1 - contrast) + contrast * i


# --------------------------------------------------------------------------- planes folders


@dataclass
class Lidar:
    R: np.ndarray  # X_cam = R X_lidar + T
    T: np.ndarray
    angles_deg: np.ndarray
    noise_mm: float
    dropout: float


def make_lidar(rng, noise_mm: tuple[float, float] = (2.0, 4.0)) -> Lidar:
    # LiDAR x forward (camera z), y to the left (camera -x), z up (camera -y), a little off
    base = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float)
    R = rot("x", rng.uniform(-3, 3)) @ rot("y", rng.uniform(-4, 4)) @ rot("z", rng.uniform(-2, 2)) @ base
    T = np.array([rng.uniform(-80, 80), rng.uniform(90, 160), rng.uniform(-60, 20)])
    step = 0.25
    angles = np.arange(-135, 135 + step / 2, step)
    return Lidar(R, T, angles, rng.uniform(*noise_mm), 0.01)


def scan(rng, lid: Lidar, surfaces: list) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (mm, 0 = no return) and the true surface index per beam (-1 none, -2 mixed).

    Each beam is 7 sub-rays across one step (its footprint): beams on an edge average the
    ranges of what they hit (mixed pixels); fewer than half hitting = no return."""
    n_sub = 7
    step = np.radians(lid.angles_deg[1] - lid.angles_deg[0])
    th = np.radians(lid.angles_deg)[:, None] + np.linspace(-0.5, 0.5, n_sub)[None, :] * step
    dl = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], -1).reshape(-1, 3)
    dc = dl @ lid.R.T
    best = np.full(len(dc), np.inf)
    idx = np.full(len(dc), -1)
    for k, s in enumerate(surfaces):
        t = s.hit(lid.T, dc)
        c = t < best
        best[c] = t[c]
        idx[c] = k
    best = best.reshape(-1, n_sub)
    idx = idx.reshape(-1, n_sub)
    hit = np.isfinite(best)
    nh = hit.sum(1)
    r = np.where(nh > 0, np.where(hit, best, 0).sum(1) / np.maximum(nh, 1), 0)
    same = (idx == idx[:, :1]).all(1)
    label = np.where(same, idx[:, 0], -2)
    r = np.where(nh * 2 >= n_sub, r, 0.0)
    r = np.where(r > 0, r + rng.normal(0, lid.noise_mm, len(r)), 0)
    r = np.round(r)  # 1 mm quantisation
    r[rng.random(len(r)) < lid.dropout] = 0
    r[r > 30000] = 0
    label = np.where(r > 0, label, -1)
    return r, label


def write_scan_csv(path: Path, angles_deg: np.ndarray, r: np.ndarray, form: str, rng) -> None:
    lines = []
    if form == "angle":
        lines.append("angle_deg,range_mm,intensity")
        for a, x in zip(angles_deg, r):
            rr = "" if x == 0 and rng.random() < 0.5 else f"{x:.0f}"
            lines.append(f"{a:.4f},{rr},{int(rng.uniform(100, 3000)) if x else 0}")
    else:
        lines.append("stamp,x_mm,y_mm")
        th = np.radians(angles_deg)
        for a, x in zip(th, r):
            if x == 0:
                lines.append("0.0,," if rng.random() < 0.5 else "0.0,0,0")
            else:
                lines.append(f"0.0,{x * np.cos(a):.2f},{x * np.sin(a):.2f}")
    path.write_text("\n".join(lines) + "\n")


PLANES_VARIANTS = {
    # name: pattern (inner corners), square mm, margins, wall?, degenerate?, big camera?
    "plain": {"inner": (7, 5), "square": 80.0, "margin": (45, 45, 60, 60), "wall": False, "vertical": False, "big": False},
    "wall": {"inner": (9, 6), "square": 60.0, "margin": (30, 30, 30, 30), "wall": True, "vertical": False, "big": True},
    "vertical": {"inner": (6, 8), "square": 70.0, "margin": (50, 50, 50, 50), "wall": False, "vertical": True, "big": False},
    # a small printed pattern on a large foam board, a wall close behind in every view, the
    # person holding it right behind, a noisier LiDAR
    "clutter": {"inner": (6, 4), "square": 50.0, "margin": (170, 150, 120, 160), "wall": True, "vertical": False,
                "big": False, "wall_every": 1, "wall_gap": (8, 30), "person_gap": (120, 220), "noise": (3.5, 5.0)},
}


def make_planes(out: Path, seed: int, variant: str, n_views: int = 10, small: bool = False) -> dict:
    """A `lidarcal planes` folder: NAME.jpg|png + NAME.csv, camera.json, truth.json."""
    rng = np.random.default_rng(1000 + seed * 7 + list(PLANES_VARIANTS).index(variant))
    cfg = PLANES_VARIANTS[variant]
    out.mkdir(parents=True, exist_ok=True)
    cam = make_camera(rng, cfg["big"], small)
    lid = make_lidar(rng, cfg.get("noise", (2.0, 4.0)))
    ren = Renderer(cam)
    (out / "camera.json").write_text(json.dumps(cam.to_json(), indent=1))
    views = []
    k = 0
    tries = 0
    while k < n_views and tries < 400:
        tries += 1
        size_probe = Board(cfg["inner"], cfg["square"], cfg["margin"], np.eye(3), np.zeros(3))
        pw, ph = size_probe.pattern_mm
        z = rng.uniform(1300, 2600)
        x = rng.uniform(-0.25, 0.25) * z
        if cfg["vertical"]:
            yaw, pitch, roll = rng.uniform(-50, 50), rng.uniform(-3, 3), rng.uniform(-3, 3)
        else:
            yaw, pitch, roll = rng.uniform(-45, 45), rng.uniform(-35, 35), rng.uniform(-20, 20)
        # held so that the scan plane crosses the pattern at some height
        nz = lid.R[:, 2]  # the scan plane's normal: its height at (x, z)
        y_scan = lid.T[1] - (nz[0] * (x - lid.T[0]) + nz[2] * (z - lid.T[2])) / nz[1]
        y = y_scan + rng.uniform(-0.3, 0.3) * ph
        R, T = board_pose(np.array([x, y, z]), yaw, pitch, roll, (pw, ph))
        board = Board(cfg["inner"], cfg["square"], cfg["margin"], R, T)
        # the pattern must be fully in view, and the board facing the camera
        corners = pattern_corners(board)
        proj, _ = cv2.projectPoints(corners, np.zeros(3), np.zeros(3), cam.K, cam.dist)
        proj = proj.reshape(-1, 2)
        w, h = cam.size
        if not ((proj[:, 0] > 25).all() and (proj[:, 0] < w - 25).all() and (proj[:, 1] > 25).all()
                and (proj[:, 1] < h - 25).all()):
            continue
        n, d = board.plane()
        br = board.rect()
        pole = Rect(br.centre + br.v * (br.half_v + 700) + n * 15, br.u, br.v, 18, 700, "stand")
        person = Cylinder(br.centre + n * rng.uniform(*cfg.get("person_gap", (250, 450)))
                          + br.u * rng.uniform(-300, 300), 170,
                          -1500, 1200)
        room = [Rect(np.array([0, 0, 6000.0]), np.array([1.0, 0, 0]), np.array([0, 1.0, 0]), 5000, 3000, "room"),
                Rect(np.array([-3500.0, 0, 2000]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), 5000, 3000, "room"),
                Rect(np.array([3000.0, 0, 2000]), np.array([0, 0, 1.0]), np.array([0, 1.0, 0]), 5000, 3000, "room")]
        extras = [pole]
        if cfg["wall"] and k % cfg.get("wall_every", 2) == 0:
            gap = rng.uniform(*cfg.get("wall_gap", (15, 60)))
            extras.append(Rect(br.centre + n * gap, br.u, br.v, 2500, 1500, "wall"))
        surfaces = [br, *extras, person, *room]
        r, label = scan(rng, lid, surfaces)
        n_board = int((label == 0).sum())
        if n_board < 15:
            continue
        img, _ = render_scene(rng, ren, board, extras, 5500.0, rng.uniform(0.6, 0.85))
        img *= vignetting(cam, rng.uniform(0.1, 0.3))[..., None]
        img8 = sensor(rng, img, bayer=True, blur_px=rng.uniform(0.5, 0.9))
        name = f"view_{k:02d}"
        if k % 3 == 2:
            cv2.imwrite(str(out / f"{name}.png"), img8)
        else:
            write_jpeg(out / f"{name}.jpg", img8, int(rng.integers(85, 93)))
        write_scan_csv(out / f"{name}.csv", lid.angles_deg, r, "xy" if k % 2 else "angle", rng)
        views.append({"name": name, "board_normal": n.tolist(), "board_d": d,
                      "board_beams": np.flatnonzero(label == 0).tolist(),
                      "yaw": yaw, "pitch": pitch, "roll": roll})
        k += 1
    truth = {"R": lid.R.tolist(), "T_mm": lid.T.tolist(), "pattern": list(cfg["inner"]),
             "square_mm": cfg["square"], "range_noise_mm": lid.noise_mm, "variant": variant,
             "seed": seed, "views": views}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


def pattern_corners(board: Board) -> np.ndarray:
    c, r = board.inner
    a, b = np.meshgrid(np.arange(1, c + 1) * board.square, np.arange(1, r + 1) * board.square)
    pts = np.stack([a.ravel(), b.ravel()], 1)
    return (board.T + pts[:, :1] * board.R[:, 0] + pts[:, 1:] * board.R[:, 1]).astype(np.float64)


# --------------------------------------------------------------------------- laser photos


LASER_VARIANTS = {
    "red": {"colour": "red", "rgb": np.array([0.03, 0.10, 1.0]), "big": False, "inner": (8, 6), "square": 30.0,
                "sheet": "vertical"},
    "green": {"colour": "green", "rgb": np.array([0.15, 1.0, 0.12]), "big": True, "inner": (9, 7), "square": 25.0,
                  "sheet": "horizontal"},
    # coarse deep speckle, faint to blinding laser, wide sheets, overexposed rooms, JPEG 70-85
    "harsh": {"colour": "red", "rgb": np.array([0.05, 0.12, 1.0]), "big": False, "inner": (8, 6), "square": 30.0,
              "sheet": "vertical", "harsh": True},
}


def laser_sheet(rng, kind: str) -> tuple[np.ndarray, float, np.ndarray]:
    """A line laser beside the camera: its plane (normal, d >= 0) and its origin."""
    if kind == "vertical":
        origin = np.array([rng.uniform(-260, -150), rng.uniform(-30, 30), rng.uniform(-20, 20)])
        aim = np.array([rng.uniform(-40, 40), 0, 650])
        along = rot("z", rng.uniform(-12, 12)) @ np.array([0, 1.0, 0])
    else:
        origin = np.array([rng.uniform(-40, 40), rng.uniform(150, 240), rng.uniform(-20, 20)])
        aim = np.array([0, rng.uniform(-40, 40), 650])
        along = rot("z", rng.uniform(-12, 12)) @ np.array([1.0, 0, 0])
    n = np.cross(along, aim - origin)
    n /= np.linalg.norm(n)
    d = float(n @ origin)
    if d < 0:
        n, d = -n, -d
    return n, d, origin


def make_laser(out: Path, seed: int, variant: str, n_photos: int = 14, small: bool = False) -> dict:
    """A `lidarcal laser-plane` folder: lights-on colour JPEG photos + camera.json + truth.json.

    The last two photos are hard on purpose: one with the board partly out of view, one whose
    stripe leaves the board (the board pushed aside)."""
    rng = np.random.default_rng(5000 + seed * 11 + list(LASER_VARIANTS).index(variant))
    cfg = LASER_VARIANTS[variant]
    out.mkdir(parents=True, exist_ok=True)
    cam = make_camera(rng, cfg["big"], small)
    ren = Renderer(cam)
    (out / "camera.json").write_text(json.dumps(cam.to_json(), indent=1))
    n, d, origin = laser_sheet(rng, cfg["sheet"])
    along_sheet = np.cross(n, [0, 0, 1.0])
    along_sheet /= np.linalg.norm(along_sheet)
    size_probe = Board(cfg["inner"], cfg["square"], (25, 25, 25, 25), np.eye(3), np.zeros(3))
    pw, ph = size_probe.pattern_mm
    photos = []
    k = 0
    tries = 0
    while k < n_photos and tries < 2000:
        tries += 1
        special = None
        if k == n_photos - 2:
            special = "partly_out"
        elif k == n_photos - 1:
            special = "stripe_leaves"
        z = rng.uniform(480, 900)
        c = np.array([rng.uniform(-0.12, 0.12) * z, rng.uniform(-0.1, 0.1) * z, z])
        yaw, pitch, roll = rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-25, 25)
        if special == "partly_out":  # pushed along the sheet, out of the frame
            c = c + along_sheet * rng.choice([-1, 1]) * rng.uniform(0.3, 0.45) * z
        elif special == "stripe_leaves":  # pushed across the sheet: the line near an edge
            c = c + n * rng.choice([-1, 1]) * rng.uniform(0.3, 0.55) * pw
        R, T = board_pose(c, yaw, pitch, roll, (pw, ph))
        board = Board(cfg["inner"], cfg["square"], (25, 25, 25, 25), R, T)
        corners = pattern_corners(board)
        proj = cv2.projectPoints(corners, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
        w, h = cam.size
        inside = (proj[:, 0] > 20) & (proj[:, 0] < w - 20) & (proj[:, 1] > 20) & (proj[:, 1] < h - 20)
        # where the laser line crosses the pattern, in board units
        sd = corners @ n - d  # signed distance of each inner corner to the laser plane
        frac_pos = (sd > 0).mean()
        if special == "partly_out":
            if not (0.55 < inside.mean() < 0.9) or not (0.3 < frac_pos < 0.7):
                continue
        elif special == "stripe_leaves":
            if not inside.all() or not (0.02 < frac_pos < 0.15 or 0.85 < frac_pos < 0.98):
                continue
        else:
            if not inside.all() or not (0.25 < frac_pos < 0.75):
                continue
        # the laser reaches the board at a useful angle (not grazing)
        if abs(board.plane()[0] @ n) > 0.93:
            continue
        harsh = cfg.get("harsh", False)
        sig = rng.uniform(0.4, 2.2 if harsh else 1.5)  # the sheet's 1-sigma half-thickness, mm
        power = rng.uniform(0.5, 9.0) if harsh else rng.uniform(0.8, 6.0)  # x full scale on white paper
        amb = rng.uniform(0.3, 1.15) if harsh else rng.uniform(0.35, 0.9)
        img, lz = render_scene(rng, ren, board, [], 1400.0 + rng.uniform(0, 600), amb,
                               laser=(n, d, sig, power, cfg["rgb"], origin))
        img *= vignetting(cam, rng.uniform(0.1, 0.35))[..., None]
        sp = speckle(rng, lz.shape, rng.uniform(1.2, 2.0) if harsh else rng.uniform(0.8, 1.5),
                     rng.uniform(0.85, 1.0) if harsh else rng.uniform(0.5, 0.9))
        lz = lz * sp
        # blooming: a clipped core leaks into its neighbours and the other channels
        bloom = cv2.GaussianBlur(np.clip(lz - 1.0, 0, None), (0, 0), 2.0) * 0.15
        img = img + lz[..., None] * cfg["rgb"][None, None, :] + bloom[..., None]
        img8 = sensor(rng, img.astype(np.float32), bayer=True, blur_px=rng.uniform(0.5, 0.8))
        name = f"photo_{k:02d}"
        write_jpeg(out / f"{name}.jpg", img8, int(rng.integers(70, 86) if harsh else rng.integers(85, 93)))
        photos.append({"name": name, "special": special, "distance_mm": float(z),
                       "yaw": yaw, "pitch": pitch, "roll": roll, "sheet_sigma_mm": sig,
                       "power": power})
        k += 1
    truth = {"normal": n.tolist(), "d_mm": d, "laser_origin_mm": origin.tolist(),
             "pattern": list(cfg["inner"]), "square_mm": cfg["square"], "colour": cfg["colour"],
             "variant": variant, "seed": seed, "photos": photos}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return truth


# --------------------------------------------------------------------------- evaluation


def rotation_error_vector(R_est: np.ndarray, R_true: np.ndarray) -> np.ndarray:
    """The small rotation (deg, camera axes) w with R_est = exp(w) R_true."""
    rv, _ = cv2.Rodrigues(R_est @ R_true.T)
    return np.degrees(rv.ravel())


def evaluate_planes(folder: Path, out: Path, lidarcal: str) -> dict:
    truth = json.loads((folder / "truth.json").read_text())
    p, s = truth["pattern"], truth["square_mm"]
    cmd = [lidarcal, "planes", str(folder), "--pattern", f"{p[0]}x{p[1]}", "--square-mm", str(s),
           "--camera", str(folder / "camera.json"), "--out", str(out), "--no-figures"]
    run = subprocess.run(cmd, check=False, capture_output=True, text=True)
    res = {"folder": str(folder), "exit": run.returncode}
    if run.returncode != 0:
        res["stderr"] = run.stderr.strip()[-400:]
        return res
    ex = json.loads((out / "extrinsics.json").read_text())
    R_est, T_est = np.array(ex["R"]), np.array(ex["T_mm"])
    R_true, T_true = np.array(truth["R"]), np.array(truth["T_mm"])
    w = rotation_error_vector(R_est, R_true)
    dT = T_est - T_true
    sr = ex["sigma"]["rotation_deg"]
    st = ex["sigma"]["translation_mm"]

    def zs(err, sig):
        return [None if sg is None else float(e / sg) for e, sg in zip(err, sig)]

    z_rot, z_tr = zs(w, sr), zs(dT, st)
    used = [v for v in ex["views"] if v.get("used")]
    # held-out: views generated beside the folder (truth['heldout']) scored by own code
    res.update({
        "rot_err_deg": float(np.linalg.norm(w)), "rot_err_axes_deg": w.round(4).tolist(),
        "trans_err_mm": float(np.linalg.norm(dT)), "trans_err_axes_mm": dT.round(2).tolist(),
        "sigma_rot_deg": sr, "sigma_trans_mm": st, "z_rot": z_rot, "z_trans": z_tr,
        "max_abs_z": max([abs(z) for z in z_rot + z_tr if z is not None], default=None),
        "undetermined": [u["kind"] for u in ex.get("undetermined", [])],
        "views_used": f"{len(used)}/{len(ex['views'])}", "rms_mm": ex["rms_mm"],
        "range_noise_true_mm": truth["range_noise_mm"],
        "warnings": ex.get("warnings", []),
        "board_beams_recall": board_beam_recall(ex, truth, folder),
    })
    return res


def board_beam_recall(ex: dict, truth: dict, folder: Path) -> dict:
    """Of the returns lidarcal took as board, the share that truly hit the board (precision),
    and the share of the true board returns it took (recall), over used views. `beams` index
    the rows of an angle/range CSV, but the returns (sorted by angle) of an x/y one."""
    tv = {v["name"]: set(v["board_beams"]) for v in truth["views"]}
    tp = fp = fn = 0
    for v in ex["views"]:
        if not v.get("used") or "beams" not in v:
            continue
        got = set(v["beams"])
        csv_path = folder / f"{v['name']}.csv"
        if csv_path.read_text().startswith("stamp,x_mm"):
            _, r = read_scan(csv_path)
            rows = np.flatnonzero(r > 0)  # ascending angle = ascending row here
            got = {int(rows[b]) for b in got}
        true = tv.get(v["name"], set())
        tp += len(got & true)
        fp += len(got - true)
        fn += len(true - got)
    return {"precision": round(tp / max(tp + fp, 1), 4), "recall": round(tp / max(tp + fn, 1), 4)}


def heldout_rms(folder: Path, heldout: Path, ex_path: Path) -> dict:
    """Own held-out check: the estimated pose applied to views it did not see, each view's true
    board returns against that view's board plane from its own photo (cv2.solvePnP)."""
    ex = json.loads(ex_path.read_text())
    R, T = np.array(ex["R"]), np.array(ex["T_mm"])
    truth = json.loads((heldout / "truth.json").read_text())
    cam = json.loads((heldout / "camera.json").read_text())
    K, dist = np.array(cam["K"]), np.array(cam["dist"])
    pattern = tuple(truth["pattern"])
    sq = truth["square_mm"]
    obj = np.zeros((pattern[0] * pattern[1], 3))
    obj[:, :2] = np.mgrid[0:pattern[0], 0:pattern[1]].T.reshape(-1, 2) * sq
    res = []
    for v in truth["views"]:
        imgp = next(p for p in heldout.iterdir() if p.stem == v["name"] and p.suffix in (".png", ".jpg"))
        gray = cv2.imread(str(imgp), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCornersSB(gray, pattern)
        if not ok:
            continue
        ok, rv, tv = cv2.solvePnP(obj, c, K, dist)
        Rb, _ = cv2.Rodrigues(rv)
        n = Rb[:, 2]
        d = float(n @ tv.ravel())
        ang, rng_ = read_scan(heldout / f"{v['name']}.csv")
        beams = np.array(v["board_beams"], int)
        th = np.radians(ang[beams])
        P = np.column_stack([rng_[beams] * np.cos(th), rng_[beams] * np.sin(th), np.zeros(len(beams))])
        Pc = P @ R.T + T
        res.append(float(np.sqrt(np.mean((Pc @ n - d) ** 2))))
    return {"heldout_rms_mm": float(np.sqrt(np.mean(np.square(res)))) if res else None,
            "heldout_views": len(res), "in_sample_rms_mm": ex["rms_mm"]}


def read_scan(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import csv

    rows = list(csv.DictReader(path.open()))
    if "angle_deg" in rows[0]:
        ang = np.array([float(r["angle_deg"]) for r in rows])
        rr = np.array([float(r["range_mm"] or 0) for r in rows])
        return ang, rr
    x = np.array([float(r["x_mm"] or 0) for r in rows])
    y = np.array([float(r["y_mm"] or 0) for r in rows])
    # x/y files of this generator hold one row per beam of 0.25 deg from -135
    ang = np.arange(len(rows)) * 0.25 - 135
    return ang, np.hypot(x, y)


def evaluate_laser(folder: Path, out_json: Path, lidarcal: str, colour: str = "auto") -> dict:
    truth = json.loads((folder / "truth.json").read_text())
    p, s = truth["pattern"], truth["square_mm"]
    cmd = [lidarcal, "laser-plane", str(folder), "--pattern", f"{p[0]}x{p[1]}", "--square-mm", str(s),
           "--camera", str(folder / "camera.json"), "--out", str(out_json), "--laser-colour", colour]
    run = subprocess.run(cmd, check=False, capture_output=True, text=True)
    res = {"folder": str(folder), "exit": run.returncode, "colour_flag": colour}
    if run.returncode != 0:
        res["stderr"] = run.stderr.strip()[-400:]
        return res
    pl = json.loads(out_json.read_text())
    n_est, d_est = np.array(pl["normal"]), float(pl["d_mm"])
    n_true, d_true = np.array(truth["normal"]), float(truth["d_mm"])
    if n_est @ n_true < 0:
        n_est, d_est = -n_est, -d_est
    ang = float(np.degrees(np.arccos(np.clip(n_est @ n_true, -1, 1))))
    # offset where the boards were: the estimated plane's distance from the true plane at the
    # points of the true plane 500-900 mm in front of the camera on the optical axis' side
    pts = []
    for z in (500.0, 700.0, 900.0):
        # a point of the true plane at depth z near the axis
        for x in (-100.0, 0.0, 100.0):
            P = np.array([x, 0.0, z])
            P = P - (P @ n_true - d_true) * n_true
            pts.append(P)
    pts = np.array(pts)
    dist_at_boards = float(np.max(np.abs(pts @ n_est - d_est)))
    used = [i for i in pl["images"] if i["used"]]
    specials = {p_["name"]: p_["special"] for p_ in truth["photos"]}
    sig = pl.get("sigma") or {}
    res.update({
        "angle_deg": round(ang, 4), "d_diff_mm": round(abs(d_est - d_true), 3),
        "dist_at_boards_mm": round(dist_at_boards, 3), "rms_mm": pl["rms_mm"],
        "sigma_normal_deg": sig.get("normal_deg"), "sigma_d_mm": sig.get("d_mm"),
        "used": f"{len(used)}/{len(pl['images'])}",
        "unused": [(i["name"], specials.get(Path(i["name"]).stem)) for i in pl["images"] if not i["used"]],
        "warnings": pl.get("warnings", []),
    })
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("kind", nargs="?", choices=["planes", "laser"])
    ap.add_argument("out", nargs="?", type=Path)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--variant", default=None)
    ap.add_argument("--views", type=int, default=None, help="views / photos to make")
    ap.add_argument("--small", action="store_true", help="a 640 x 480 camera (quick)")
    ap.add_argument("--evaluate", action="store_true", help="generate, run the CLI, compare with truth")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--variants", nargs="+", default=None)
    ap.add_argument("--only", choices=["planes", "laser"], default=None)
    ap.add_argument("--work", type=Path, default=Path("/tmp/cleanroom_oneboard"))
    ap.add_argument("--regenerate", action="store_true",
                    help="remake folders already in --work (default: reuse them)")
    ap.add_argument("--lidarcal", default=str(Path(sys.executable).parent / "lidarcal"))
    a = ap.parse_args(argv)
    if a.evaluate:
        results = []
        if a.only in (None, "planes"):
            for v in a.variants or list(PLANES_VARIANTS):
                if v not in PLANES_VARIANTS:
                    continue
                for s in a.seeds:
                    f = a.work / f"planes_{v}_{s}"
                    h = a.work / f"planes_{v}_{s}_heldout"
                    if a.regenerate or not (h / "truth.json").is_file():
                        make_planes(f, s, v, a.views or 10, a.small)
                        make_planes_heldout(f, h, s, v, a.small)
                    r = evaluate_planes(f, a.work / f"out_planes_{v}_{s}", a.lidarcal)
                    if r["exit"] == 0:
                        r.update(heldout_rms(f, h, a.work / f"out_planes_{v}_{s}" / "extrinsics.json"))
                    results.append(r)
                    print(json.dumps(r), flush=True)
        if a.only in (None, "laser"):
            for v in a.variants or list(LASER_VARIANTS):
                if v not in LASER_VARIANTS:
                    continue
                for s in a.seeds:
                    f = a.work / f"laser_{v}_{s}"
                    if a.regenerate or not (f / "truth.json").is_file():
                        make_laser(f, s, v, a.views or 14, a.small)
                    for colour in ("auto", LASER_VARIANTS[v]["colour"]):
                        r = evaluate_laser(f, a.work / f"plane_{v}_{s}_{colour}.json", a.lidarcal, colour)
                        results.append(r)
                        print(json.dumps(r), flush=True)
        (a.work / "results.json").write_text(json.dumps(results, indent=1))
        return 0
    if a.kind is None or a.out is None:
        ap.error("give KIND OUT, or --evaluate")
    if a.kind == "planes":
        make_planes(a.out, a.seed, a.variant or "plain", a.views or 10, a.small)
    else:
        make_laser(a.out, a.seed, a.variant or "red", a.views or 14, a.small)
    return 0


def make_planes_heldout(folder: Path, heldout: Path, seed: int, variant: str, small: bool = False) -> None:
    """Views of the same rig the fit does not see: same seed's rig, more views, the last 4 kept."""
    make_planes(heldout, seed, variant, n_views=14, small=small)
    truth = json.loads((heldout / "truth.json").read_text())
    for v in truth["views"][:10]:
        for p in heldout.glob(v["name"] + ".*"):
            p.unlink()
    truth["views"] = truth["views"][10:]
    (heldout / "truth.json").write_text(json.dumps(truth, indent=1))


if __name__ == "__main__":
    sys.exit(main())
