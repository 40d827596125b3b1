"""The report's figures: section-1 objects re-computed on one representative position,
and the plots (from :mod:`lidarcal.plots`) saved as PNG; a failing figure becomes a note."""

from __future__ import annotations

import os
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry import Pose
from ..io.dataset import CameraModel, Dataset
from .inputs import ReportInputs
from .markup import esc
from .tables import _poses

FIG_DPI = 150


class _Figures:
    """Saves figures as PNG in ``folder``; a failing figure becomes a note, not a crash."""

    def __init__(self, folder: Path, notes: list[str], enabled: bool = True):
        self.folder = folder
        self.notes = notes
        self.count = 0
        self.enabled = enabled

    def __call__(self, name: str, make: Callable[[], object], caption: str,
                 width: str = "100%", photo: bool = False) -> str:
        """``photo``: the figure shows a photograph, saved as JPEG (quality 85; a PNG of a
        photo is ~1 MB)."""
        if not self.enabled:
            return ""
        try:
            fig = make()
        except Exception as e:  # noqa: BLE001  (a figure must never stop the report)
            msg = f"figure '{name}' not drawn: {type(e).__name__}: {e}"
            self.notes.append(msg)
            if os.environ.get("LIDARCAL_DEBUG"):
                traceback.print_exc()
            return f"#notebox[{esc(msg)}]\n"
        if fig is None:
            return ""
        self.count += 1
        fname = f"fig_{self.count:02d}_{name}.{'jpg' if photo else 'png'}"
        fig.savefig(self.folder / fname, dpi=FIG_DPI, **({"pil_kwargs": {"quality": 85}} if photo else {}))
        return (f'#figure(image("{fname}", width: {width}), caption: [{esc(caption)}])\n')


def _camera_from_cal(cal: dict, ds: Dataset) -> CameraModel:
    c = cal["camera"]
    size = tuple(c.get("image_size") or ds.image_size)
    return CameraModel(np.asarray(c["K"], float), np.asarray(c["dist"], float), size,
                       c.get("source", "dataset.json"), c.get("rms_px"))


def _representative(ds: Dataset, cal: dict):
    """The position shown in the section-1 figures: the middle used position."""
    used = sorted(int(r["index"]) for r in cal.get("samples", []))
    if not used:
        return None
    want = used[len(used) // 2]
    return next((p for p in ds.positions if p.index == want), None)


@dataclass
class _Detail:
    """Section-1 objects re-computed for the figures (None when unavailable)."""

    boards: tuple | None = None
    board_image: np.ndarray | None = None
    position: object | None = None  # dataset Position
    stripe_image: np.ndarray | None = None
    solved: object | None = None  # pipeline.PositionResult
    scan: tuple | None = None  # (angle_deg, range_mm)
    intrinsics: object | None = None


def _detail(inp: ReportInputs) -> _Detail:
    from .. import pipeline
    from ..io.dataset import read_image, read_scan, read_stripe_image

    ds, cal, res = inp.dataset, inp.cal, inp.result
    det = _Detail()
    camera = res.camera if res is not None else _camera_from_cal(cal, ds)
    try:
        det.board_image = read_image(ds.board_image, camera.image_size)
        det.boards = res.boards if res is not None else \
            pipeline.find_boards(ds, camera, det.board_image)
    except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
        inp.notes.append(f"board detection for the figures failed: {e}")
        return det
    pos = _representative(ds, cal)
    det.position = pos
    if pos is None:
        return det
    try:
        det.stripe_image = read_stripe_image(pos.stripe_image, camera.image_size)
        det.scan = read_scan(pos.scan, ds.lidar)
        found = [p for p in (res.positions if res is not None else []) if p.index == pos.index]
        det.solved = found[0] if found else _resolve_position(pos, camera, det.boards, ds, cal)
    except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
        inp.notes.append(f"position {pos.index} could not be re-solved for the figures: {e}")
    if cal["camera"].get("source") == "intrinsics":
        if res is not None and res.intrinsics is not None:
            det.intrinsics = res.intrinsics
        else:
            try:
                from ..camera import calibrate_intrinsics

                det.intrinsics = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board,
                                                      ds.image_size)
            except Exception as e:  # noqa: BLE001  (note it in the report, keep going)
                inp.notes.append(f"intrinsics could not be re-run for the figure: {e}")
    return det


def _resolve_position(pos, camera: CameraModel, boards, ds: Dataset, cal: dict):
    """Section 1 again at one position, with the pipeline's own per-position step and the
    dataset's stripe reflectance ratio (from calibration.json when stored there, else
    re-estimated from the positions the calibration used, as the pipeline does)."""
    from .. import pipeline

    rho = cal.get("reflectance_ratio", (cal.get("stripe") or {}).get("reflectance_ratio"))
    if rho is None:  # as calibrate reads it (the boards' maps blurred to the stripe frames')
        used = {int(r["index"]) for r in cal.get("samples", [])}
        boards, rho, _ = pipeline.matched_albedo(
            camera, boards, [p for p in ds.positions if p.index in used], ds.lidar.laser_colour)
    return pipeline.solve_position(pos, camera, boards, ds.lidar, rho)


def _reprojection_errors(intr) -> tuple[list[np.ndarray], list[str]]:
    import cv2

    cam = intr.camera
    errs, labels = [], []
    for k, (ip, op) in enumerate(zip(intr.image_points, intr.object_points)):
        if k >= len(intr.rvecs):
            break
        proj, _ = cv2.projectPoints(np.asarray(op, float), np.asarray(intr.rvecs[k], float),
                                    np.asarray(intr.tvecs[k], float), cam.K, cam.dist)
        errs.append(proj.reshape(-1, 2) - np.asarray(ip, float).reshape(-1, 2))
        labels.append(Path(intr.files_used[k]).name if k < len(intr.files_used) else f"view {k}")
    return errs, labels


def _plot_reprojection(intr):
    from ..plots import plot_reprojection_errors

    errs, labels = _reprojection_errors(intr)
    if not errs:
        raise ValueError("no per-view poses stored with the intrinsics result")
    return plot_reprojection_errors(errs, labels)


def _plot_scan(det: _Detail):
    from ..plots import plot_scan_split
    from ..scan import scan_points

    ang, rng = det.scan
    pts = np.asarray(scan_points(ang, rng))
    seg, ll = det.solved.segments, det.solved.lidar_lines
    n = len(pts)

    def mask(idx):
        m = np.zeros(n, bool)
        if idx is not None and len(idx):
            idx = np.asarray(idx)
            if idx.dtype == bool:
                return idx[:n]
            m[idx.astype(int)] = True
        return m

    i1 = getattr(seg, "index1", getattr(seg, "first", None))
    i2 = getattr(seg, "index2", getattr(seg, "second", None))
    rej = mask(getattr(seg, "rejected1", None)) | mask(getattr(seg, "rejected2", None))
    lines = []
    E = np.asarray(ll.E, float)
    for l in (ll.l1, ll.l2):
        lines.append((E, np.asarray(l, float)))
    return plot_scan_split(pts, mask(i1), mask(i2), lines, E, rej)


def _trimmed(fig, margin: int = 12):
    """A rendered scene (a Figure holding one image, :mod:`lidarcal.scene3d`) cropped to its
    content: the white border of the render window would shrink the scene on the page."""
    from matplotlib.figure import Figure

    img = np.asarray(fig.axes[0].images[0].get_array())
    ink = np.any(img[..., :3] < (250 if img.dtype == np.uint8 else 250 / 255), axis=-1)
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    if not len(rows):
        return fig
    h, w = ink.shape
    img = img[max(rows[0] - margin, 0):min(rows[-1] + margin + 1, h),
              max(cols[0] - margin, 0):min(cols[-1] + margin + 1, w)]
    out = Figure(figsize=(6.4, 6.4 * img.shape[0] / img.shape[1]))
    ax = out.add_axes((0, 0, 1, 1))
    ax.imshow(img)
    ax.set_axis_off()
    return out


def _plot_frames(inp: ReportInputs, det: _Detail):
    from ..scan import scan_points

    samples = [Pose.from_dict(r) for r in inp.cal.get("samples", [])]
    pick = samples[:: max(1, len(samples) // 4)][:5]
    corners = []
    obj = inp.dataset.v_board.object_points()
    for b in det.boards:
        corners.append(obj @ np.asarray(b.R, float).T + np.asarray(b.T, float))
    scan = None
    if det.scan is not None and det.solved is not None:
        pts = np.asarray(scan_points(*det.scan), float)
        if pts.shape[1] == 2:
            pts = np.column_stack([pts, np.zeros(len(pts))])
        seg = det.solved.segments
        keep = [np.asarray(getattr(seg, k), int) for k in ("index1", "index2")
                if getattr(seg, k, None) is not None]
        if keep:  # the board segments only: background returns would dwarf the rig
            pts = pts[np.concatenate(keep)]
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        scan = det.solved.pose.apply(pts)
    ax = inp.cal.get("axis")
    axis = (ax["point_mm"], ax["direction"]) if ax else None
    cam = inp.cal["camera"]
    lid = inp.dataset.lidar
    from ..scene3d import rig_figure  # the pyvista scene, rendered off screen

    return _trimmed(rig_figure(pick, corners, scan, axis, K=np.asarray(cam["K"], float),
                               image_size=tuple(cam.get("image_size") or inp.dataset.image_size),
                               aperture_deg=(lid.angle_min_deg, lid.angle_max_deg)))


def _plot_traj(inp: ReportInputs):
    from ..plots import plot_trajectories
    from ..turntable import model_from_dict

    cal = inp.cal
    rows = cal.get("samples", [])
    psi = np.array([r["psi_deg"] for r in rows], float)
    samples = [Pose.from_dict(r) for r in rows]
    model = model_from_dict(cal["model"])
    grid = np.linspace(psi.min(), psi.max(), 200)
    curve = model.pose(grid)
    truth = None
    if inp.truth is not None and inp.truth.get("poses"):
        tp = _poses(inp.truth["poses"])
        truth = [tp[int(r["index"])] for r in rows if int(r["index"]) in tp]
    ax = cal["axis"]
    return plot_trajectories(psi, samples, curve=curve, axis=(ax["point_mm"], ax["direction"]),
                             truth=truth)


@dataclass
class _DiscTrial:
    """The trial shown in section 3.2: its dataset entry, its measurements.json row and the
    disc re-measured from the sweep (diameter replaced by the stored, edge-corrected one)."""

    spec: object  # dataset Measurement
    row: dict
    measurement: object  # measure.DiscMeasurement
    sweep: object  # the sweep DataFrame


def _disc_trial(inp: ReportInputs) -> _DiscTrial:
    """The first trial that is not a reference (a reference's diameter is fitted), re-measured."""
    from dataclasses import replace

    from ..api import load_calibration
    from ..disc import edge_footprint
    from ..io.dataset import read_sweep
    from ..measure import measure_disc

    ds = inp.dataset
    rows = {r.get("name"): r for r in (inp.meas or {}).get("measurements", [])}
    specs = [m for m in ds.measurements if not rows.get(m.name, {}).get("reference")]
    if not specs:
        specs = list(ds.measurements)
    if not specs:
        raise ValueError("dataset.json lists no measurement sweeps")
    m = specs[0]
    cal = load_calibration(inp.calibration_path)
    sweep = read_sweep(m.sweep, ds.lidar)
    r = measure_disc(sweep, cal, ds.lidar, footprint=edge_footprint())
    row = rows.get(m.name, {})
    if row.get("diameter_mm") is not None:
        r = replace(r, diameter_mm=float(row["diameter_mm"]))
    return _DiscTrial(m, row, r, sweep)


def _plot_disc(inp: ReportInputs, trial: _DiscTrial):
    from ..plots import plot_disc_cloud

    m, r, sweep = trial.spec, trial.measurement, trial.sweep
    pts = getattr(r, "cloud", None)
    if pts is None or np.ndim(pts) != 2:
        from ..api import load_calibration

        cal = load_calibration(inp.calibration_path)
        ok = np.isfinite(sweep["range_mm"].to_numpy())
        pts = cal.points(sweep["psi_deg"].to_numpy()[ok], sweep["angle_deg"].to_numpy()[ok],
                         sweep["range_mm"].to_numpy()[ok])
    disc = getattr(r, "disc_mask", None)
    rim = getattr(r, "rim_mask", None)
    cross = getattr(r, "crossings", None)
    inl = getattr(r, "crossing_inlier", None)
    if cross is not None and inl is not None and len(inl) == len(cross):
        cross = np.asarray(cross)[np.asarray(inl, bool)]

    class _C:
        centre = np.asarray(r.center_mm, float)
        normal = np.asarray(r.normal, float)
        radius = float(r.diameter_mm) / 2

    bounds = None
    if getattr(r, "boundary_inside", None) is not None and getattr(r, "boundary_outside", None) is not None:
        bounds = (r.boundary_inside, r.boundary_outside)
    return plot_disc_cloud(pts, disc, rim, _C, m.reference_diameter_mm, rim_estimates=cross,
                           rim_bounds=bounds,
                           title=f"Disc point cloud, {m.name} (section 3.2)")
