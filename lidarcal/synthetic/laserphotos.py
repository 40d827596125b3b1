"""Lights-on colour photos of a line laser on a flat chessboard, with a truth plane.

The test data of :mod:`lidarcal.laserplane` (section 1.3 on its own): a lit
chessboard in several poses, a red (or green, blue) line laser whose sheet is a
fixed plane in the camera frame, photographed in colour. Reuses the V rig's
image formation (:mod:`lidarcal.synthetic.render`): the exact lens model per
pixel, anti-aliased squares, the laser sheet's Gaussian profile with the
stripe albedo on black squares, then per colour channel: ambient light times
the board's albedo and a slight tint, the laser in its own channel with some
crosstalk into the others (a strong core clips to white, as real sensors do),
optical blur, shot and read noise, 8 bits, optionally JPEG.

Special photos for the difficult cases: ``miss`` (the laser passes beside the
board), ``overexposed`` (white squares clip, the laser core is white).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..geometry import Plane, Pose, rotation_about_axis, unit
from ..io.dataset import write_json_atomic
from .config import PAPER
from .render import RayMap, albedo_table, render_view, stripe_signal
from .scene import InfinitePlane, Rect

_CHANNEL = {"blue": 0, "green": 1, "red": 2}


@dataclass(frozen=True)
class LaserPhotoConfig:
    """Everything the laser-photo renderer varies (mm, px, DN)."""

    image_size: tuple[int, int] = (1280, 960)
    f_px: float = 1150.0
    dist: tuple[float, ...] = (-0.12, 0.08, 0.0004, -0.0003, 0.0)
    inner_corners: tuple[int, int] = (8, 5)
    square_mm: float = 30.0
    distance_mm: tuple[float, float] = (550.0, 900.0)
    tilt_deg: float = 35.0
    laser_colour: str = "red"
    sheet_sigma_mm: float = 0.5
    laser_peak_dn: float = 700.0          # laser channel on a white square (clips: saturated core)
    crosstalk: float = 0.12               # share of the laser in the other two channels
    white_dn: float = 150.0               # lit white square
    tint: tuple[float, float, float] = (0.95, 1.0, 1.04)   # B, G, R gain of the room light
    black_albedo: float = 0.12
    stripe_albedo_black: float = 0.25
    psf_sigma_px: float = 0.8
    read_noise_dn: float = 1.5
    shot_noise_gain: float = 0.15
    jpeg_quality: int | None = None


def _camera_K(cfg: LaserPhotoConfig) -> np.ndarray:
    w, h = cfg.image_size
    return np.array([[cfg.f_px, 0, (w - 1) / 2 + 7.0], [0, cfg.f_px * 1.001, (h - 1) / 2 - 5.0],
                     [0, 0, 1.0]])


def sample_laser_plane(rng: np.random.Generator, cfg: LaserPhotoConfig) -> tuple[Plane, Pose]:
    """A laser sheet through an emitter beside the camera that crosses the view near its
    centre, its trace inclined in the image (any orientation): (plane, emitter pose).

    The emitter pose has its z axis on the plane's normal and its x axis (the sheet's
    forward direction) towards the middle of the working range.
    """
    z_mid = float(np.mean(cfg.distance_mm))
    P0 = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), z_mid])
    a = np.radians(rng.uniform(-60, 60))
    n = unit(np.array([np.cos(a), np.sin(a), rng.uniform(-0.3, 0.3)]))
    plane = Plane.from_normal_point(n, P0)
    n = plane.normal  # (its sign convention: d >= 0)
    X0 = np.array([-160.0 * np.sign(n[0] + 1e-9), 60.0, 0.0])
    E = X0 - plane.distance(X0[None])[0] * n
    x = unit((P0 - E) - ((P0 - E) @ n) * n)
    return plane, Pose(np.column_stack([x, np.cross(n, x), n]), E)


def _board_rect(cfg: LaserPhotoConfig, R: np.ndarray, centre: np.ndarray) -> Rect:
    cols, rows = cfg.inner_corners
    sq = cfg.square_mm
    margin = sq
    width, height = (cols + 1) * sq + 2 * margin, (rows + 1) * sq + 2 * margin
    origin = centre - R[:, 0] * width / 2 - R[:, 1] * height / 2
    return Rect(origin, R[:, 0], R[:, 1], width, height, pattern=(cols + 1, rows + 1, sq, margin))


def sample_board(rng: np.random.Generator, cfg: LaserPhotoConfig, plane: Plane, K: np.ndarray,
                 miss: bool = False) -> Rect:
    """A board pose whose pattern the laser crosses (``miss``: passes beside it), fully in view."""
    w, h = cfg.image_size
    cols, rows = cfg.inner_corners
    half_w, half_h = (cols + 3) * cfg.square_mm / 2, (rows + 3) * cfg.square_mm / 2
    for _ in range(500):
        z = rng.uniform(*cfg.distance_mm)
        # a point of the laser plane at depth z, somewhere in the middle of the image
        u, v = rng.uniform(0.3, 0.7) * w, rng.uniform(0.3, 0.7) * h
        ray = np.linalg.solve(K, np.array([u, v, 1.0]))
        t = plane.d / (plane.normal @ ray) if abs(plane.normal @ ray) > 1e-6 else -1
        if not (0.6 * z < t * ray[2] < 1.4 * z):
            continue
        C = t * ray
        tilt = np.radians(cfg.tilt_deg)
        R = (rotation_about_axis(np.array([0, 0, 1.0]), rng.uniform(-np.pi, np.pi))
             @ rotation_about_axis(np.array([1.0, 0, 0]), rng.uniform(-tilt, tilt))
             @ rotation_about_axis(np.array([0, 1.0, 0]), rng.uniform(-tilt, tilt)))
        if R[2, 2] < 0:
            R = R @ np.diag([1.0, -1.0, -1.0])
        # shift the board in its own plane across the stripe: by up to 0.35 of its size, or
        # (miss) far enough that the stripe passes beside it
        s = unit(np.cross(R[:, 2], np.cross(plane.normal, R[:, 2])))
        reach = abs(s @ R[:, 0]) * half_w + abs(s @ R[:, 1]) * half_h
        off = rng.uniform(1.3, 1.6) * reach if miss else rng.uniform(-0.35, 0.35) * reach
        C = C + off * s * rng.choice([-1.0, 1.0])
        rect = _board_rect(cfg, R, C)
        corners = rect.corners()
        if np.any(corners[:, 2] < 100):
            continue
        px = corners @ K.T
        px = px[:, :2] / px[:, 2:]
        if np.all((px[:, 0] > 25) & (px[:, 0] < w - 25) & (px[:, 1] > 25) & (px[:, 1] < h - 25)):
            return rect
    raise ValueError("cannot place a board in view; widen distance_mm or shrink the board")


def render_photo(cfg: LaserPhotoConfig, K: np.ndarray, board: Rect, plane: Pose,
                 rng: np.random.Generator, exposure: float = 1.0) -> np.ndarray:
    """One lights-on BGR photo (uint8) of ``board`` with the laser sheet ``plane`` on it."""
    dist = np.asarray(cfg.dist, float)
    rays = RayMap.build(K, dist, cfg.image_size)
    wall = InfinitePlane(np.array([0.0, 0.0, 1.0]), float(board.origin[2]) + 800.0)
    rig = PAPER.with_(black_albedo=cfg.black_albedo, wall_albedo=0.45,
                      stripe_albedo_black=cfg.stripe_albedo_black, stripe_albedo_wall=0.5,
                      stripe_peak_dn=1.0, lidar_angle_min_deg=-80.0, lidar_angle_max_deg=80.0)
    view = render_view(rays, [board, wall], albedo_table(rig, "bright"), 4)
    r_ref = float(np.linalg.norm(board.point(board.width / 2, board.height / 2) - plane.T))
    laser = stripe_signal(rays, view, [board, wall], plane, rig, cfg.sheet_sigma_mm, r_ref, rng)
    k = _CHANNEL[cfg.laser_colour]
    chans = []
    for c in range(3):
        gain = 1.0 if c == k else cfg.crosstalk
        sig = exposure * (cfg.white_dn * cfg.tint[c] * view.albedo + cfg.laser_peak_dn * gain * laser)
        sig = cv2.GaussianBlur(sig.astype(np.float32), (0, 0), cfg.psf_sigma_px)
        sd = np.sqrt(cfg.read_noise_dn ** 2 + cfg.shot_noise_gain * np.maximum(sig, 0))
        chans.append(sig + rng.standard_normal(sig.shape, dtype=np.float32) * sd)
    img = np.clip(np.rint(np.stack(chans, axis=2)), 0, 255).astype(np.uint8)
    if cfg.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(cfg.jpeg_quality)])
        if not ok:
            raise OSError("cannot encode a JPEG")
        img = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return img


def write_laser_photos(out: str | Path, seed: int = 0, n_photos: int = 14,
                       cfg: LaserPhotoConfig | None = None, miss: tuple[int, ...] = (),
                       overexposed: tuple[int, ...] = ()) -> Path:
    """Write ``out/NN.png`` photos, ``out/camera.json`` and ``out/truth.json`` (the plane).

    ``miss``: indices of photos where the laser passes beside the board;
    ``overexposed``: indices exposed 1.8x (white squares clip, the core is white).
    truth.json: ``{"laser_plane": {"normal", "d_mm"}, "pattern", "square_mm",
    "photos": [{"name", "kind", "R", "T_mm"}]}`` (board pose of the first inner corner).
    """
    cfg = cfg or LaserPhotoConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng([seed, 7001])
    K = _camera_K(cfg)
    plane, emitter = sample_laser_plane(rng, cfg)
    photos = []
    for j in range(n_photos):
        prng = np.random.default_rng([seed, 7002, j])
        board = sample_board(prng, cfg, plane, K, miss=j in miss)
        img = render_photo(cfg, K, board, emitter, prng, 1.8 if j in overexposed else 1.0)
        name = f"{j:02d}.png"
        if not cv2.imwrite(str(out / name), img):
            raise OSError(f"{out / name}: cannot write image")
        R = np.column_stack([board.e_u, board.e_v, board.normal])
        first = board.point(2 * cfg.square_mm, 2 * cfg.square_mm)
        kind = "miss" if j in miss else "overexposed" if j in overexposed else "normal"
        photos.append({"name": name, "kind": kind, "R": R.tolist(), "T_mm": first.tolist()})
    write_json_atomic(out / "camera.json", {"K": K.tolist(), "dist": list(cfg.dist),
                                            "image_size": list(cfg.image_size),
                                            "source": "lidarcal.synthetic.laserphotos"})
    truth = {"laser_plane": {"normal": plane.normal.tolist(), "d_mm": float(plane.d)},
             "laser_colour": cfg.laser_colour, "pattern": list(cfg.inner_corners),
             "square_mm": cfg.square_mm, "seed": seed, "photos": photos}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    return out
