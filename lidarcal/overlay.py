"""The picture users check first: LiDAR returns projected onto the camera image.

A return ``(angle, range)`` is the LiDAR-frame point ``(r cos a, r sin a, 0)``
(eq. 6); with a calibration it is ``X = R p + T`` in the camera frame (eq. 28 at
one turntable angle) and projects through the lens (``cv2.projectPoints``, with
distortion). If the calibration is right, returns on the board fall on the
board in the photo and the scan line bends with the scene's edges.

Functions return a :class:`matplotlib.figure.Figure` (no pyplot);
:func:`save_figure` writes a PNG atomically.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from .io.dataset import CameraModel


def project_returns(camera: CameraModel, R: np.ndarray, T: np.ndarray, angle_deg: np.ndarray,
                    range_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (N, 2), camera-frame depth z (N,) and a mask of returns in front of the camera
    and inside the image. No-return beams (NaN range) are masked out."""
    from .camera import project_points
    from .scan import scan_points

    p = scan_points(angle_deg, range_mm)
    X = np.column_stack([p, np.zeros(len(p))]) @ np.asarray(R, float).T + np.asarray(T, float)
    ok = np.isfinite(X[:, 0]) & (X[:, 2] > 1.0)
    px = np.full((len(X), 2), np.nan)
    if ok.any():
        px[ok] = project_points(camera, X[ok])
    w, h = camera.image_size
    with np.errstate(invalid="ignore"):
        ok &= (px[:, 0] >= -0.5) & (px[:, 0] <= w - 0.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= h - 0.5)
    return px, X[:, 2], ok


def lidar_on_image(image: np.ndarray, camera: CameraModel, R: np.ndarray, T: np.ndarray,
                   angle_deg: np.ndarray, range_mm: np.ndarray,
                   highlight: np.ndarray | None = None, outline_px: np.ndarray | None = None,
                   title: str = "LiDAR returns on the camera image",
                   point_size: float = 4.0) -> Figure:
    """The scan drawn on the photo: every return coloured by its range (mm), the
    ``highlight`` returns (beam indices or a boolean mask, e.g. the board segment) ringed
    in red; ``outline_px`` (M, 2), optional, is a polygon (e.g. the board's outline);
    ``point_size`` in points^2.

    ``R``, ``T``: the LiDAR pose, ``X_cam = R X_lidar + T`` (mm).
    """
    from .plots import _figure, _show_image

    px, _, ok = project_returns(camera, R, T, angle_deg, range_mm)
    rng = np.asarray(range_mm, float)
    fig = _figure(7.0, 5.6)
    ax = fig.add_subplot()
    _show_image(ax, image)
    if outline_px is not None:
        o = np.asarray(outline_px, float)
        ax.plot(np.r_[o[:, 0], o[:1, 0]], np.r_[o[:, 1], o[:1, 1]], "-", color="yellow", lw=1,
                label="board outline")
    sc = ax.scatter(px[ok, 0], px[ok, 1], c=rng[ok], s=point_size, cmap="turbo", lw=0)
    if highlight is not None:
        hl = np.zeros(len(rng), bool)
        hl[np.asarray(highlight)] = True
        m = hl & ok
        ax.scatter(px[m, 0], px[m, 1], s=18, facecolors="none", edgecolors="red", lw=0.6,
                   label=f"board returns ({int(m.sum())})")
    fig.colorbar(sc, ax=ax, shrink=0.8, label="range (mm)")
    ax.set_title(f"{title} ({int(ok.sum())} of {int(np.isfinite(rng).sum())} returns in view)")
    if outline_px is not None or highlight is not None:
        ax.legend(loc="lower right", fontsize=8)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike, dpi: int = 100) -> Path:
    """Write ``fig`` as a PNG through a temporary file and a rename (never half-written)."""
    from .io.dataset import write_atomic

    return write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=dpi, format="png"), ".png")


def overlay_calibration(dataset: str | os.PathLike, calibration: str | os.PathLike, index: int,
                        out_png: str | os.PathLike | None = None) -> Figure:
    """A turntable dataset's scan at position ``index`` drawn on its stripe image with a
    ``calibration.json``: the pose at the position's turntable angle,
    ``lidarcal.load_calibration(path).pose(psi)``; the background is the stripe image in red
    over the dimmed ``board.png``. Returns the figure; writes it to
    ``out_png`` when given. The laser's stripe in the image and the projected returns
    must coincide when the calibration is right.
    """
    from .api import load_calibration
    from .io.dataset import DatasetError, load_dataset, read_image, read_scan

    ds = load_dataset(dataset)
    pos = [p for p in ds.positions if p.index == index]
    if not pos:
        raise DatasetError(ds.root / "positions.csv", f"no position with index {index}; give one "
                                                      "of its indices, "
                                            f"{ds.positions[0].index}..{ds.positions[-1].index}")
    p = pos[0]
    cal = load_calibration(calibration)
    pose = cal.pose(p.psi_deg)
    ang, rng = read_scan(p.scan, ds.lidar)
    img_path = p.stripe_image
    stripe = read_image(img_path, ds.image_size, colour="max")
    img = np.repeat(stripe[..., None], 3, axis=2)  # the stripe in red over the dimmed board photo
    if ds.board_image.exists():  # (optional here; read, and refused, when it is there)
        board = (0.5 * read_image(ds.board_image, ds.image_size)).astype(np.uint8)
        img = np.stack([board, board, np.maximum(board, stripe)], axis=2)
    camera = ds.camera
    if isinstance(cal.data.get("camera"), dict) and "K" in cal.data["camera"]:
        from .io.dataset import parse_camera

        camera = parse_camera(cal.data["camera"], cal.path)
    if camera is None:
        from .pipeline import camera_for

        camera, _ = camera_for(ds)
    fig = lidar_on_image(img, camera, pose.R, pose.T, ang, rng,
                         title=f"position {index}, psi {p.psi_deg:g} deg", point_size=0.5)
    if out_png is not None:
        save_figure(fig, out_png)
    return fig
