"""3D scenes of the rig and of sweeps with pyvista (plots.py stays matplotlib).

What a scene holds: the camera (its frustum from ``K`` and the image size),
the LiDAR frame at a few turntable angles (x red, y green, z blue), the
turntable axis, the two chessboards of the V, the laser fans (the scan plane
over the LiDAR's aperture), sweep clouds coloured by range or psi, and a
fitted disc. Everything is in the camera frame (OpenCV: x right, y down,
z forward), mm.

Where it shows:

- **JupyterLab, interactive**: :func:`show` with ``interactive=True`` uses
  pyvista's ``trame`` backend when the optional extra is installed
  (``pip install 'lidarcal[interactive]'``), else falls back to a static image.
- **nbval, PDFs, scripts**: static, rendered off screen. Without a display
  (no ``DISPLAY``) this module sets ``pv.OFF_SCREEN`` and asks VTK for its
  EGL window (``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow``), which renders
  without an X server and without VTK's "bad X server connection" warning.
- **The report**: :func:`rig_figure` / :func:`disc_figure` return a
  matplotlib Figure holding the rendering (same inputs as
  :func:`lidarcal.plots.plot_frames_3d` / ``plot_disc_cloud``);
  :func:`scene_figure_png` writes any scene to a PNG.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np

WINDOW = (1000, 700)
_HEADLESS = sys.platform.startswith("linux") and not os.environ.get("DISPLAY") \
    and not os.environ.get("WAYLAND_DISPLAY")
if _HEADLESS:  # before the first render window is made (read by VTK's window factory)
    os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")

import pyvista as pv

if _HEADLESS:
    pv.OFF_SCREEN = True


def new_plotter(window_size: tuple[int, int] = WINDOW, off_screen: bool | None = None) -> pv.Plotter:
    """A white-background plotter (off screen when headless or asked)."""
    p = pv.Plotter(off_screen=_HEADLESS if off_screen is None else off_screen, window_size=window_size)
    p.set_background("white")
    return p


def _as_pose(pose):
    from .geometry import Pose

    if isinstance(pose, Pose):
        return pose
    return Pose(np.asarray(pose["R"], float), np.asarray(pose["T_mm"], float))


def add_camera(p: pv.Plotter, K: np.ndarray, image_size: tuple[int, int], depth_mm: float = 250.0,
               color: str = "black") -> None:
    """The camera at the origin: its frustum to ``depth_mm`` (pinhole, ``K``; distortion ignored)."""
    K = np.asarray(K, float)
    w, h = image_size
    uv = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    rays = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], np.ones(4)])
    c = depth_mm * rays
    pts = np.vstack([np.zeros(3), c])
    lines = [2, 0, 1, 2, 0, 2, 2, 0, 3, 2, 0, 4, 5, 1, 2, 3, 4, 1]
    p.add_mesh(pv.PolyData(pts, lines=lines), color=color, line_width=2, label="camera")


def add_frame(p: pv.Plotter, pose, length_mm: float = 80.0, line_width: float = 3.0) -> None:
    """A LiDAR frame: x red, y green, z blue, ``X_cam = R @ X_lidar + T``."""
    pose = _as_pose(pose)
    for k, col in enumerate(("red", "green", "blue")):
        seg = np.vstack([pose.T, pose.T + length_mm * pose.R[:, k]])
        p.add_mesh(pv.Line(seg[0], seg[1]), color=col, line_width=line_width)


def add_axis(p: pv.Plotter, point_mm: np.ndarray, direction: np.ndarray, near_mm: np.ndarray,
             half_length_mm: float = 250.0) -> None:
    """The turntable axis, a segment centred on the foot of ``near_mm`` (e.g. the LiDAR centre)."""
    a = np.asarray(point_mm, float)
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    foot = a + ((np.asarray(near_mm, float) - a) @ d) * d
    p.add_mesh(pv.Line(foot - half_length_mm * d, foot + half_length_mm * d), color="purple",
               line_width=4, label="turntable axis")


def add_board(p: pv.Plotter, corners_mm: np.ndarray, color: str = "lightgray") -> None:
    """A chessboard: the surface through its corner points (N, 3), camera frame."""
    pts = np.asarray(corners_mm, float).reshape(-1, 3)
    surf = pv.PolyData(pts).delaunay_2d()
    p.add_mesh(surf, color=color, opacity=0.8, show_edges=False)
    p.add_points(pts, color="black", point_size=3)


def add_laser_fan(p: pv.Plotter, pose, angle_min_deg: float, angle_max_deg: float, range_mm: float,
                  color: str = "orange", opacity: float = 0.25) -> None:
    """The scan plane: a fan over the LiDAR's aperture out to ``range_mm`` (eq. 6 in the x-y plane)."""
    pose = _as_pose(pose)
    th = np.radians(np.linspace(angle_min_deg, angle_max_deg, 64))
    rim = range_mm * np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
    pts = pose.apply(np.vstack([np.zeros(3), rim]))
    faces = np.column_stack([np.full(63, 3), np.zeros(63, int), np.arange(1, 64), np.arange(2, 65)]).ravel()
    p.add_mesh(pv.PolyData(pts, faces=faces), color=color, opacity=opacity)


def add_cloud(p: pv.Plotter, points_mm: np.ndarray, scalars: np.ndarray | None = None,
              name: str = "range_mm", point_size: float = 2.0, cmap: str = "viridis") -> None:
    """Points (N, 3), coloured by ``scalars`` (e.g. range_mm or psi_deg) with a scalar bar."""
    pts = np.asarray(points_mm, float)
    ok = np.all(np.isfinite(pts), axis=1)
    cloud = pv.PolyData(pts[ok])
    if scalars is not None:
        cloud.point_data[name] = np.asarray(scalars, float)[ok]
        p.add_mesh(cloud, scalars=name, cmap=cmap, point_size=point_size,
                   render_points_as_spheres=False, scalar_bar_args={"title": name, "color": "black"})
    else:
        p.add_mesh(cloud, color="gray", point_size=point_size, render_points_as_spheres=False)


def add_disc(p: pv.Plotter, center_mm: np.ndarray, normal: np.ndarray, diameter_mm: float,
             color: str = "crimson", opacity: float = 0.45) -> None:
    """A fitted disc: its face and its rim circle."""
    c = np.asarray(center_mm, float)
    n = np.asarray(normal, float)
    p.add_mesh(pv.Disc(center=c, inner=0.0, outer=diameter_mm / 2, normal=n, c_res=90),
               color=color, opacity=opacity)
    rim = pv.Circle(radius=diameter_mm / 2, resolution=180)
    rim = rim.extract_feature_edges(boundary_edges=True, feature_edges=False, manifold_edges=False)
    from .geometry import plane_basis

    B = plane_basis(n / np.linalg.norm(n))
    rim.points = c + np.asarray(rim.points)[:, :2] @ B
    p.add_mesh(rim, color=color, line_width=3)


def _look(p: pv.Plotter, direction=(-0.55, -0.45, -1.0)) -> None:
    """View from behind and above the camera (OpenCV: y down), whole scene in view."""
    p.view_vector(np.asarray(direction, float), viewup=(0.0, -1.0, 0.0))
    p.reset_camera()


def rig_plotter(poses: Sequence, boards_corners_mm: Sequence[np.ndarray] = (),
                scan_mm: np.ndarray | None = None, axis: tuple | None = None,
                K: np.ndarray | None = None, image_size: tuple[int, int] | None = None,
                aperture_deg: tuple[float, float] | None = None, fan_range_mm: float | None = None,
                window_size: tuple[int, int] = WINDOW) -> pv.Plotter:
    """The rig: camera frustum, LiDAR frames at ``poses``, axis, boards, scan points, laser fans.

    Same inputs as :func:`lidarcal.plots.plot_frames_3d` (poses: Pose or
    ``{"R", "T_mm"}``; ``axis``: ``(point_mm, direction)``) plus the camera
    (``K``, ``image_size``) and the aperture for the fans (first and last pose).
    """
    p = new_plotter(window_size)
    poses = [_as_pose(q) for q in poses]
    allp = [q.T[None] for q in poses] + [np.asarray(c, float).reshape(-1, 3) for c in boards_corners_mm]
    extent = float(np.ptp(np.vstack(allp), axis=0).max()) if allp else 1000.0
    for q in poses:  # frames a tenth of the scene, so they show at its scale
        add_frame(p, q, length_mm=max(0.1 * extent, 50.0))
    for c in boards_corners_mm:
        add_board(p, c)
    if scan_mm is not None and len(scan_mm):
        add_cloud(p, scan_mm, None, point_size=4)
    if axis is not None and poses:
        add_axis(p, axis[0], axis[1], np.mean([q.T for q in poses], axis=0))
    if aperture_deg is not None and poses:
        if fan_range_mm is None:
            allc = np.vstack([np.asarray(c).reshape(-1, 3) for c in boards_corners_mm]) \
                if len(boards_corners_mm) else None
            fan_range_mm = float(np.median(np.linalg.norm(allc - poses[0].T, axis=1))) \
                if allc is not None else 1000.0
        for q in {id(poses[0]): poses[0], id(poses[-1]): poses[-1]}.values():
            add_laser_fan(p, q, aperture_deg[0], aperture_deg[1], fan_range_mm)
    if K is not None and image_size is not None:
        add_camera(p, K, image_size)
    _look(p)
    p.camera.zoom(1.3)
    return p


def result_plotter(result, model=None, frames: int = 3, window_size: tuple[int, int] = WINDOW) -> pv.Plotter:
    """The rig of a :class:`lidarcal.pipeline.CalibrationResult`: boards (from the board views),
    camera, the LiDAR frame at ``frames`` angles over the turntable range (``model``, default
    the result's pose function), its axis and the laser fans at the first and last angle."""
    model = result.model if model is None else model
    psi = np.sort(np.asarray(result.psi_deg, float))
    pick = psi[np.linspace(0, len(psi) - 1, max(frames, 1)).round().astype(int)]
    obj = result.dataset.v_board.object_points()
    corners = [obj @ np.asarray(b.R, float).T + np.asarray(b.T, float) for b in result.boards]
    ax = model.axis
    lid = result.dataset.lidar
    return rig_plotter([model.pose(float(a)) for a in pick], corners, None, (ax.point, ax.direction),
                       K=result.camera.K, image_size=result.camera.image_size,
                       aperture_deg=(lid.angle_min_deg, lid.angle_max_deg), window_size=window_size)


def sweep_plotter(points_mm: np.ndarray, scalars: np.ndarray | None = None, name: str = "range_mm",
                  disc=None, window_size: tuple[int, int] = WINDOW) -> pv.Plotter:
    """A sweep cloud coloured by ``scalars`` and, when given, the fitted disc
    (a :class:`lidarcal.measure.DiscMeasurement` or ``(center_mm, normal, diameter_mm)``)."""
    p = new_plotter(window_size)
    add_cloud(p, points_mm, scalars, name)
    if disc is not None:
        c, n, d = (disc.center_mm, disc.normal, disc.diameter_mm) if hasattr(disc, "center_mm") else disc
        add_disc(p, c, n, d)
    _look(p, direction=(-0.35, -0.3, -1.0))
    return p


def screenshot(p: pv.Plotter, path: str | os.PathLike | None = None) -> np.ndarray:
    """Render off screen: the image (H, W, 3) uint8, also written to ``path`` (PNG) when given."""
    img = p.screenshot(None, return_img=True)
    if path is not None:
        import matplotlib.image as mpimg

        from .io.dataset import write_atomic

        write_atomic(path, lambda t: mpimg.imsave(t, img))
    p.close()
    return img


def scene_figure_png(p: pv.Plotter, path: str | os.PathLike) -> Path:
    """Write a scene (e.g. from :func:`rig_plotter` / :func:`sweep_plotter`) to a PNG; returns the path."""
    screenshot(p, path)
    return Path(path)


def _figure_of(img: np.ndarray, title: str | None = None):
    from matplotlib.figure import Figure

    h, w = img.shape[:2]
    fig = Figure(figsize=(6.4, 6.4 * h / w))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(img)
    ax.set_axis_off()
    if title:
        ax.set_title(title)
    return fig


def rig_figure(poses: Sequence, boards_corners_mm: Sequence[np.ndarray] = (),
               scan_mm: np.ndarray | None = None, axis: tuple | None = None, **kw):
    """:func:`rig_plotter` rendered into a matplotlib Figure (for the PDF report)."""
    return _figure_of(screenshot(rig_plotter(poses, boards_corners_mm, scan_mm, axis, **kw)))


def disc_figure(measurement, color_by: str = "range"):
    """A measured disc's sweep (``DiscMeasurement.cloud``) with the fitted disc, as a Figure."""
    pts = measurement.cloud
    c = np.asarray(measurement.center_mm, float)
    near = np.linalg.norm(pts - c, axis=1) < 3.0 * measurement.diameter_mm
    scal = np.linalg.norm(pts[near], axis=1) if color_by == "range" else None
    p = sweep_plotter(pts[near], scal, "distance_mm", disc=measurement)
    return _figure_of(screenshot(p))


def show(p: pv.Plotter, interactive: bool = False):
    """Show a scene in a notebook: ``trame`` (interactive) when asked and installed, else static."""
    backend = "static"
    if interactive:
        try:
            import trame  # noqa: F401
            import trame_vtk  # noqa: F401

            backend = "trame"
        except ImportError:
            backend = "static"
    return p.show(jupyter_backend=backend)
