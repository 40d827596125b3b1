"""A small simulator for the classic one-board calibration (``lidarcal planes``), with truth.

One flat chessboard in several poses in front of a camera and a 2D LiDAR whose
laser the camera does not see. The scene also holds a back wall, a side wall, the
board's stand and a pole, so the scans carry clutter; ranges get Gaussian noise and
are rounded to integer mm, as real scanners report them. Camera photos are
rendered with the V-rig's renderer (:mod:`lidarcal.synthetic.render`), or, for
fast tests, only the corners are projected with Gaussian noise.

``degenerate="vertical"``: every board vertical (normal horizontal) and the scan
plane exactly horizontal, so the height of the LiDAR along the boards and the
tilt of the scan plane are not observable; ``degenerate="parallel"``: every board
with the same normal.

Frames: camera (OpenCV, mm) at the origin; ``X_cam = R X_lidar + T``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.dataset import BoardSpec, CameraModel, write_json_atomic
from .scene import Cylinder, InfinitePlane, Rect, trace


@dataclass(frozen=True)
class OneBoardView:
    """One simulated view: the board's pose (board frame -> camera, eq. 1), the noisy corners
    (N, 2) in OpenCV order, the scan and which beams hit the board."""

    name: str
    board_R: np.ndarray
    board_T: np.ndarray
    rect: Rect
    corners_px: np.ndarray
    angle_deg: np.ndarray
    range_mm: np.ndarray  # NaN = no return
    on_board: np.ndarray  # bool per beam
    extra: tuple = ()  # surfaces of this view only (a wall behind the board)


@dataclass(frozen=True)
class OneBoardRig:
    """The truth of a simulated one-board recording."""

    camera: CameraModel
    board: BoardSpec
    R: np.ndarray
    T: np.ndarray
    range_noise_mm: float
    corner_noise_px: float
    views: list[OneBoardView]
    surfaces: list


def _rot(axis: np.ndarray, deg: float) -> np.ndarray:
    from ..geometry import rotation_about_axis

    return rotation_about_axis(np.asarray(axis, float), np.radians(deg))


def default_camera() -> CameraModel:
    """A 640 x 480 camera with mild barrel distortion (like the TAPAS recordings' camera)."""
    K = np.array([[650.0, 0, 320.0], [0, 650.0, 240.0], [0, 0, 1]])
    return CameraModel(K, np.array([-0.05, 0.03, 0.0, 0.0, 0.0]), (640, 480), source="oneboard")


def simulate_oneboard(seed: int, n_views: int = 8, *, degenerate: str | None = None,
                      range_noise_mm: float = 3.0, corner_noise_px: float = 0.2,
                      quantise: bool = True, board: BoardSpec | None = None,
                      margin_mm: float = 60.0, camera: CameraModel | None = None,
                      wall_behind_mm: float | None = None) -> OneBoardRig:
    """Simulate ``n_views`` one-board views with known LiDAR pose (see the module docstring).

    ``wall_behind_mm``: in every view a wall parallel to the board, this far behind it (a board
    held in front of a wall: the scan runs wall - board - wall with a small range step at the
    board's edges); the random draws are those without it."""
    if degenerate not in (None, "vertical", "parallel"):
        raise ValueError(f"degenerate must be None, 'vertical' or 'parallel', got {degenerate!r}")
    from ..camera import project_points

    rng = np.random.default_rng(seed)
    cam = camera or default_camera()
    board = board or BoardSpec((8, 5), 80.0)
    # LiDAR: x forward (camera z), z up (camera -y), below and ahead of the camera
    R = np.column_stack([[0.0, 0, 1], [-1.0, 0, 0], [0.0, -1, 0]])
    yaw = rng.uniform(-4, 4)
    if degenerate == "vertical":
        R = _rot(R[:, 2], yaw) @ R  # scan plane exactly horizontal
    else:
        R = _rot(rng.normal(size=3), rng.uniform(2, 5)) @ _rot(R[:, 2], yaw) @ R
    T = np.array([rng.uniform(-60, 60), rng.uniform(100, 200), rng.uniform(80, 180)])
    cols, rows = board.inner_corners
    sq = board.square_mm
    W, H = (cols + 1) * sq + 2 * margin_mm, (rows + 1) * sq + 2 * margin_mm
    z_wall = rng.uniform(3200, 4000)
    x_wall = rng.uniform(1500, 2200) * rng.choice([-1, 1])
    statics = [InfinitePlane(np.array([0.0, 0, 1]), z_wall),
               InfinitePlane(np.array([1.0, 0, 0]) * np.sign(x_wall), abs(x_wall)),
               Cylinder(np.array([rng.uniform(-900, -600), -500.0, rng.uniform(1200, 2000)]),
                        np.array([0.0, 1, 0]), 30.0, 0.0, 3000.0)]
    fixed_tilt = (rng.uniform(-30, 30), rng.uniform(-30, 30))
    views = []
    angles = np.arange(-100.0, 100.0 + 1e-9, 0.25)
    u_l = np.column_stack([np.cos(np.radians(angles)), np.sin(np.radians(angles)),
                           np.zeros(len(angles))])
    dirs = u_l @ R.T
    tries = 0
    while len(views) < n_views:
        tries += 1
        if tries > 200 * n_views:
            raise RuntimeError("could not place the boards in view; widen the camera or move them")
        phi, rho = np.radians(rng.uniform(-15, 15)), rng.uniform(1100, 2000)
        P = T + R @ np.array([np.cos(phi), np.sin(phi), 0.0]) * rho  # on the scan plane
        if degenerate == "vertical":
            pitch, yaw_b = 0.0, rng.uniform(-35, 35)
        elif degenerate == "parallel":
            pitch, yaw_b = fixed_tilt
        else:
            pitch, yaw_b = rng.uniform(-35, 35), rng.uniform(-35, 35)
        n = _rot([0, 1, 0], yaw_b) @ _rot([1, 0, 0], pitch) @ np.array([0.0, 0, -1])
        down = np.array([0.0, 1, 0]) - n[1] * n
        e_v = down / np.linalg.norm(down)
        e_u = np.cross(e_v, n)
        u0, v0 = rng.uniform(0.3, 0.7) * W, rng.uniform(0.25, 0.75) * H
        origin = P - u0 * e_u - v0 * e_v
        rect = Rect(origin, e_u, e_v, W, H, pattern=(cols + 1, rows + 1, sq, margin_mm))
        px = project_points(cam, rect.corners())
        if np.any(rect.corners()[:, 2] < 300) or np.any(px < 12) or np.any(
                px[:, 0] > cam.image_size[0] - 12) or np.any(px[:, 1] > cam.image_size[1] - 12):
            continue
        board_R = np.column_stack([e_u, e_v, np.cross(e_u, e_v)])
        board_T = origin + (margin_mm + sq) * (e_u + e_v)
        obj = board.object_points()
        corners = project_points(cam, obj @ board_R.T + board_T)
        corners = corners + rng.normal(0, corner_noise_px, corners.shape)
        stand = Cylinder(rect.point(W / 2, H), e_v, 20.0, 0.0, 2000.0)
        extra = () if wall_behind_mm is None else (
            InfinitePlane(n, float(n @ P) - wall_behind_mm),)  # n faces the camera
        surfaces = [rect, stand, *extra, *statics]
        t, idx = trace(surfaces, dirs, T[None])
        rng_mm = t + rng.normal(0, range_noise_mm, len(t))
        if quantise:
            rng_mm = np.rint(rng_mm)
        rng_mm[~np.isfinite(t) | (t > 30000)] = np.nan
        on = idx == 0
        if on.sum() < 20:
            continue
        views.append(OneBoardView(f"{len(views):02d}", board_R, board_T, rect, corners, angles,
                                  rng_mm, on, extra))
    return OneBoardRig(cam, board, R, T, range_noise_mm, corner_noise_px, views, statics)


def wall_beside_board(view, dist_mm: float, noise_mm: float = 0.0,
                      rng: np.random.Generator | None = None, beams: int = 120):
    """A copy of a real view (:class:`lidarcal.planes.ViewData`) whose scan beside the board
    (``beams`` beams each side) is a wall ``dist_mm`` behind the board's line, ranges in integer
    mm; with ``rng``, the wall gets the view's own noise about lines and ``noise_mm`` Gaussian
    range noise is added to the board and the wall (scripts/wall_grid.py, tests/test_planes.py).
    The candidates are segmented again and the board's beams forgotten."""
    import copy

    from ..scan_segments import line_segments, local_line_noise

    v = copy.copy(view)
    b = view.beams
    r = view.range_mm.astype(float).copy()
    th = np.radians(view.angle_deg)
    pts = view.points_mm
    c = pts.mean(0)
    u = np.linalg.svd(pts - c)[2][0]
    nrm = np.array([-u[1], u[0]])
    off = nrm @ c + dist_mm * np.sign(nrm @ c)
    sides = (slice(max(b.min() - beams, 0), b.min()), slice(b.max() + 1, b.max() + 1 + beams))
    for s in sides:
        r[s] = np.rint(off / (np.column_stack([np.cos(th[s]), np.sin(th[s])]) @ nrm))
    if rng is not None:
        for s in sides:  # the wall as noisy as the board (the view's own noise about lines)
            r[s] += rng.normal(0, view.sigma_range_mm, len(r[s]))
        span = slice(sides[0].start, sides[1].stop)
        r[span] = np.rint(r[span] + rng.normal(0, noise_mm, len(r[span])))
        v.sigma_range_mm = max(local_line_noise(v.angle_deg, r), 0.3)
    v.range_mm = r
    v.candidates = line_segments(v.angle_deg, r, range_noise_mm=local_line_noise(v.angle_deg, r),
                                 steps=True)[0]
    v.beams = np.zeros(0, int)
    return v


def views_for_planes(rig: OneBoardRig):
    """The views as :func:`lidarcal.planes.calibrate_planes` takes them (board planes from the
    noisy corners, candidate segments from the scans), without rendering photos."""
    from ..planes import ViewData, board_plane
    from ..scan_segments import line_segments, local_line_noise

    out = []
    for v in rig.views:
        sig = local_line_noise(v.angle_deg, v.range_mm)
        vd = ViewData(v.name, board_plane(rig.camera, v.corners_px, rig.board), v.angle_deg,
                      v.range_mm, sig)
        vd.candidates = line_segments(v.angle_deg, v.range_mm, range_noise_mm=sig, steps=True)[0]
        out.append(vd)
    return out


def render_photo(rig: OneBoardRig, view: OneBoardView, seed: int = 0) -> np.ndarray:
    """The camera's photo of one view (8-bit gray), rendered through the lens model with the
    paper rig's exposure and noise settings."""
    from .config import get_rig
    from .render import RayMap, albedo_table, expose_bright, render_view

    cfg = get_rig("paper")
    rays = RayMap.build(rig.camera.K, rig.camera.dist, rig.camera.image_size)
    stand = Cylinder(view.rect.point(view.rect.width / 2, view.rect.height), view.rect.e_v, 20.0,
                     0.0, 2000.0)
    sv = render_view(rays, [view.rect, stand, *view.extra, *rig.surfaces], albedo_table(cfg, "bright"),
                     cfg.supersample)
    return expose_bright(sv.albedo, cfg, np.random.default_rng(seed))


def write_oneboard(rig: OneBoardRig, out: str | Path, seed: int = 0) -> Path:
    """A ``lidarcal planes`` folder: ``NN.png`` (rendered) + ``NN.csv`` (``angle_deg,range_mm``,
    0 = no return) per view, ``camera.json``, ``board.json`` and ``truth.json`` (R, T_mm, noise levels)."""
    import cv2

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for k, v in enumerate(rig.views):
        img = render_photo(rig, v, seed * 1000 + k)
        if not cv2.imwrite(str(out / f"{v.name}.png"), img):
            raise OSError(f"could not write {out / f'{v.name}.png'}")
        r = np.where(np.isfinite(v.range_mm), v.range_mm, 0.0)
        lines = ["angle_deg,range_mm"] + [f"{a:.2f},{x:.0f}" for a, x in zip(v.angle_deg, r)]
        (out / f"{v.name}.csv").write_text("\n".join(lines) + "\n")
    write_json_atomic(out / "camera.json", rig.camera.to_dict())
    write_json_atomic(out / "board.json", {"inner_corners": list(rig.board.inner_corners),
                                           "square_mm": rig.board.square_mm})
    write_json_atomic(out / "truth.json", {"R": rig.R.tolist(), "T_mm": rig.T.tolist(),
                                           "range_noise_mm": rig.range_noise_mm,
                                           "pattern": list(rig.board.inner_corners),
                                           "square_mm": rig.board.square_mm})
    return out
