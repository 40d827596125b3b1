"""The whole calibration, dataset folder in, ``calibration.json`` out.

Section 1 of the paper runs once per turntable position (in parallel worker
processes); section 2 fits the pose function of the turntable angle to the
single-shot samples. Policy for bad positions: a position whose files are
broken or whose stripe/scan cannot be solved fails alone: it is skipped with a
warning naming its file (kept in ``skipped`` and ``warnings``) while at least
``MIN_POSITIONS`` usable positions remain, as OpenCV's and Kalibr's tools drop
the frames they cannot use. ``strict`` makes any failure stop the run with a
one-line error naming the file (exit 2). Positions can also be dropped
explicitly (``skip``). Dataset-wide inputs (dataset.json, positions.csv,
board.png, the camera) are always fatal.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import sys
from concurrent.futures import Future, ProcessPoolExecutor, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from . import __version__
from .board import (
    BoardView,
    find_boards,
    find_v_boards,
    inner_diagonal_mm,
    small_square_warnings,
)
from .calibration_checks import (
    JOINT_RIGID_SIGMAS,
    check_angle_scale,
    check_z_axis_hint,
    joint_rigid_warnings,
    pose_rows,
    setup_warnings,
)
from .camera import IntrinsicsResult, add_views, calibrate_intrinsics
from .camera_spread import camera_spread
from .geometry import Pose
from .io.dataset import (
    CALIBRATION_FORMAT,
    MEASUREMENTS_FORMAT,
    REFLECTANCE_IMAGES,
    CameraModel,
    Dataset,
    DatasetError,
    ImagePrefetch,
    LidarSpec,
    Position,
    load_dataset,
    prefetch_stripe_images,
    read_image,
    read_scan,
    read_stripe_image,
    spread_indices,
    write_json_atomic,
)
from .pose import single_shot_pose
from .scan import LidarLines, VSegments, fit_v_lines, split_v, v_segment_limit_mm
from .stripe import (
    CameraLines,
    camera_lines,
    reflectance_samples,
)
from .stripe_albedo import albedo_blur, blur_blackness
from .trace import mark
from .turn_scale import turn_scale_warnings
from .turntable import fit_paper, fit_rigid, unwrap_angles_deg

if TYPE_CHECKING:
    import pandas as pd

MIN_POSITIONS = 3
METHODS = ("joint", "rigid", "paper")
DEFAULT_METHOD = "joint"  # the most accurate on our rendered rigs (see README, issue 6 note)


@dataclass
class PositionResult:
    """Section 1 at one turntable position: camera lines, scan lines, the single-shot pose."""

    index: int
    psi_deg: float
    camera_lines: CameraLines
    segments: VSegments
    lidar_lines: LidarLines
    pose: Pose


@dataclass
class CalibrationResult:
    dataset: Dataset
    camera: CameraModel
    intrinsics: IntrinsicsResult | None
    boards: tuple[BoardView, BoardView]
    positions: list[PositionResult]
    skipped: list[tuple[int, str]]
    paper_model: object
    rigid_model: object
    method: str
    warnings: list[str] = field(default_factory=list)
    joint_model: object | None = None
    # dataset_hash(dataset), being computed in a thread while the pose functions are fitted
    dataset_sha256: Future | None = field(default=None, repr=False, compare=False)

    @property
    def models(self) -> dict[str, object]:
        """Every pose function fitted: "paper", "rigid" and (when run) "joint"."""
        out = {"paper": self.paper_model, "rigid": self.rigid_model}
        if self.joint_model is not None:
            out["joint"] = self.joint_model
        return out

    @property
    def model(self):
        """The pose function that fills ``poses`` (``method``)."""
        return self.models[self.method]

    @property
    def psi_deg(self) -> np.ndarray:
        return np.array([p.psi_deg for p in self.positions])

    @property
    def samples(self) -> dict[int, Pose]:
        return {p.index: p.pose for p in self.positions}

    def fitted(self, model=None) -> dict[int, Pose]:
        """The pose function at every position (at its jitter-corrected angle when the
        function carries corrections, as the joint fit does)."""
        m = self.model if model is None else model
        at = getattr(m, "position_psi", lambda i, psi: psi)
        return {p.index: m.pose(at(p.index, p.psi_deg)) for p in self.positions}

    def summary(self) -> str:
        ax = self.model.axis
        return (f"camera from {self.camera.source}; {len(self.positions)} positions used, "
                f"{len(self.skipped)} skipped; pose function '{self.method}'; axis direction "
                f"{np.array2string(ax.direction, precision=5)} through "
                f"{np.array2string(ax.point, precision=2)} mm")


def solve_position(pos: Position, camera: CameraModel, boards: tuple[BoardView, BoardView],
                    lidar: LidarSpec, rho: float | None) -> PositionResult:
    """Paper section 1 at one position: stripe lines (1.3), scan lines (1.4), pose (1.5).

    ``rho`` is the stripe's black/white reflectance ratio on the boards (one per dataset).
    """
    img = _stripe_image(pos, camera, lidar.laser_colour)
    try:
        cl = camera_lines(camera, img, boards, rho=rho)
    except ValueError as e:
        raise DatasetError(pos.stripe_image, f"{e}; check this position or drop it with "
                                             f"--skip {pos.index}") from None
    ang, rng = read_scan(pos.scan, lidar)
    try:
        seg = split_v(ang, rng, alpha=cl.alpha, max_segment_mm=v_segment_limit_mm(
            [inner_diagonal_mm(camera, b) for b in boards]))
        ll = fit_v_lines(seg.points1, seg.points2, cl.alpha)  # (the eq. 6 points of the beams)
    except ValueError as e:
        raise DatasetError(pos.scan, f"{e}; check this position or drop it with "
                                     f"--skip {pos.index}") from None
    try:
        pose = single_shot_pose(cl.l, cl.E, cl.alpha, ll, lidar.z_axis_hint)
    except ValueError as e:
        raise DatasetError(pos.scan, f"no pose from this scan and stripe image ({e}); check this "
                                     f"position or drop it with --skip {pos.index}") from None
    return PositionResult(pos.index, pos.psi_deg, cl, seg, ll, pose)


def solve_safe(args) -> PositionResult | DatasetError:
    """:func:`solve_position`, its failure returned (a named DatasetError), never raised: a
    position that fails alone."""
    try:
        return solve_position(*args)
    except DatasetError as e:
        return e
    except Exception as e:  # noqa: BLE001  (unforeseen input: the position fails alone, named)
        pos = args[0]
        return DatasetError(pos.stripe_image, f"position {pos.index} could not be solved "
                                              f"({type(e).__name__}: {e}); check it or drop it "
                                              f"with --skip {pos.index}")


# per-worker constants of a run (camera, boards with their blackness maps, LiDAR spec), set
# once by the pool initializer instead of being pickled with every task; "images" (decoded
# stripe images, an ImagePrefetch) is set in the parent and inherited by forked workers
_WORKER: dict = {}


def _stripe_image(pos: Position, camera: CameraModel, laser_colour: str = "auto") -> np.ndarray:
    """The stripe image of ``pos``: prefetched when available, else read now."""
    pre = _WORKER.get("images")
    img = None if pre is None else pre.get(pos)
    return read_stripe_image(pos.stripe_image, camera.image_size, laser_colour) \
        if img is None else img


def _fork_context():
    """The "fork" start method where it exists and is safe (Linux): workers inherit the
    parent's imported modules and prefetched images instead of re-importing and re-reading."""
    if sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("fork")
    return None


def _init_worker(camera: CameraModel, boards: tuple[BoardView, BoardView],
                 lidar: LidarSpec) -> None:
    _WORKER.update(camera=camera, boards=boards, lidar=lidar)
    mark("worker-init")


def _solve_task(task: tuple[Position, float | None]) -> PositionResult | DatasetError:
    pos, rho = task
    out = solve_safe((pos, _WORKER["camera"], _WORKER["boards"], _WORKER["lidar"], rho))
    mark("task", index=pos.index)
    return out


def camera_for(ds: Dataset) -> tuple[CameraModel, IntrinsicsResult | None]:
    """The stored camera of dataset.json when present, else one calibrated from ``intrinsics/``."""
    if ds.camera is not None:
        return ds.camera, None
    if ds.intrinsics_board is None:
        raise DatasetError(ds.dataset_json, "no 'camera' and no 'intrinsics_board' to calibrate with")
    res = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board, ds.image_size)
    # the V's two boards in board.png are views of the same camera: they join the fit
    try:
        views = find_v_boards(read_image(ds.board_image, ds.image_size), ds.v_board, res.camera)
    except (ValueError, DatasetError):
        return res.camera, res  # find_boards reports board.png's problem
    res = add_views(res, [v.corners_px for v in views], [ds.v_board.object_points()] * 2,
                    [f"{ds.board_image.name} board {k}" for k in range(2)],
                    [ds.v_board.pattern_size] * 2)
    return res.camera, res


def dataset_reflectance_ratio(camera: CameraModel, boards: tuple[BoardView, BoardView],
                              positions: list[Position], n_images: int = REFLECTANCE_IMAGES,
                              laser_colour: str = "auto") -> float | None:
    """The stripe's black/white reflectance ratio, pooled over a few positions spread over the
    sweep (a property of board and laser, the same at every position): the ratio of
    :func:`dataset_albedo`, as calibrate reads it. None when it cannot be seen."""
    return dataset_albedo(camera, boards, positions, n_images, laser_colour)[0]


def dataset_albedo(camera: CameraModel, boards: tuple[BoardView, BoardView],
                   positions: list[Position], n_images: int = REFLECTANCE_IMAGES,
                   laser_colour: str = "auto") -> tuple[float | None, float]:
    """``(rho, blur_px)``: the stripe's black/white reflectance ratio and the stripe frames' blur
    beyond board.png's (:func:`lidarcal.stripe_albedo.albedo_blur`), from a few stripe images
    spread over the sweep (:func:`_rho_picks`); blur 0 where none is seen, and then rho is
    :func:`lidarcal.stripe.estimate_reflectance_ratio`'s to the bit. Unreadable images are
    left to the per-position step, which reports them. ``laser_colour``: how colour stripe
    images become the laser's response (``lidar.laser_colour``)."""
    samples = []
    for k in _rho_picks(positions, n_images):
        try:
            img = _stripe_image(positions[k], camera, laser_colour)
        except DatasetError:
            continue
        got = reflectance_samples(camera, img, boards)
        if got is None:
            return None, 0.0
        samples += got
    return albedo_blur(samples) if samples else (None, 0.0)


def matched_albedo(camera: CameraModel, boards: tuple[BoardView, BoardView],
                   positions: list[Position], laser_colour: str = "auto"
                   ) -> tuple[tuple[BoardView, BoardView], float | None, float]:
    """``(boards, rho, blur_px)`` as calibrate uses them: :func:`dataset_albedo`, and the
    boards' blackness maps blurred by the stripe frames' extra blur
    (:func:`lidarcal.stripe_albedo.blur_blackness`; as they are when none is seen)."""
    rho, blur = dataset_albedo(camera, boards, positions, laser_colour=laser_colour)
    return blur_blackness(boards, blur), rho, blur


def blur_warning(ds: Dataset, blur_px: float) -> str:
    """The warning of a run whose stripe frames are blurrier than board.png."""
    return (f"{ds.root / 'stripes'}: the stripe images are blurrier than {ds.board_image.name} "
            f"(an extra Gaussian of {blur_px:.1f} px: focus or aperture changed between them, "
            f"the stripe frames shook, or {ds.board_image.name} is noisy); the squares' albedo "
            f"map is blurred to match (take {ds.board_image.name} with the stripe frames' focus "
            f"and aperture)")


def _rho_picks(positions: list[Position], n_images: int = REFLECTANCE_IMAGES) -> list[int]:
    """Indices of the positions spread over the sweep that the reflectance ratio is pooled from
    (:func:`lidarcal.io.dataset.prefetch_stripe_images` decodes them first)."""
    return spread_indices(len(positions), n_images)


def calibrate(dataset: str | os.PathLike | Dataset, *, skip: list[int] | tuple = (),
              strict: bool = False, method: str = DEFAULT_METHOD, progress: bool = False,
              workers: int | None = None, images: ImagePrefetch | None = None,
              skip_failed: bool | None = None, fit_planes: bool = False,
              boards: tuple[BoardView, BoardView] | None = None) -> CalibrationResult:
    """Run sections 1 and 2 of the paper on a dataset folder.

    ``method`` picks the pose function that fills ``poses``: "joint" (the joint
    maximum-likelihood fit of :mod:`lidarcal.joint`, with uncertainties), "rigid"
    (a rigid rotation fitted to the single-shot samples) or "paper" (the paper's
    chain, eqs. 15-27). The paper's and the rigid fits are always computed (the
    joint fit starts from them). When the joint fit fails the rigid fit is used,
    with a warning.
    ``strict``: a position that cannot be solved stops the run (:class:`DatasetError`
    naming its file) instead of being skipped with a warning (the default, while at
    least ``MIN_POSITIONS`` remain). ``skip_failed`` is accepted for old callers and
    ignored (skipping is the default now).
    ``fit_planes``: the joint fit also refines the two board planes (``lidarcal.joint.fit_joint``;
    helps where the one board image is weak, e.g. a wide-angle camera calibrated from photos;
    several times slower).
    ``images``: stripe images already being decoded (:class:`lidarcal.io.dataset.ImagePrefetch`);
    by default they are decoded in a background thread while the boards are found. Either
    way the decoding stops (:meth:`~lidarcal.io.dataset.ImagePrefetch.close`) before the
    positions are solved; the images not decoded by then are read by the workers.
    ``boards``: the V's two boards already found in ``board.png`` with the dataset's stored
    camera (:func:`lidarcal.board.find_boards` with ``ds.camera``, as ``lidarcal calibrate``
    does while the heavier modules import); ignored when the camera comes from
    ``intrinsics/`` (the boards are then found with the camera fitted here).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    from .ranging import ranging_prior

    ranging_prior(ds.raw, ds.dataset_json)  # lidar.range_offset_* checked before any work
    skip = set(skip)
    unknown = sorted(skip - {p.index for p in ds.positions})
    if unknown:
        raise DatasetError(ds.root / "positions.csv",
                           f"--skip {' '.join(map(str, unknown))}: no position with that index; "
                           f"the indices are {_index_ranges([p.index for p in ds.positions])}")
    todo = [p for p in ds.positions if p.index not in skip]
    own = images is None
    if own:
        images = prefetch_stripe_images(ds, todo)
    try:
        camera, intr = camera_for(ds)
        mark("camera")
        if boards is None or ds.camera is None:
            boards = find_boards(ds, camera)
        mark("boards")
        _WORKER["images"] = images  # an image not decoded yet is read on demand
        # the stripe's reflectance ratio (a few images) while the last images are decoded
        # the boards' albedo maps as sharp as the stripe frames
        boards, rho, blur = matched_albedo(camera, boards, todo, ds.lidar.laser_colour)
        mark("rho")
        # stopped, not waited for: no thread runs when the workers fork, and the images not
        # decoded yet are decoded by the workers, on both cores, instead of by one thread
        images.close()
        mark("decode-stopped")
        res = _calibrate(ds, camera, intr, boards, todo, skip, strict, method, progress,
                         workers, rho, fit_planes)
        if blur:
            res.warnings.insert(0, blur_warning(ds, blur))
        return res
    finally:
        _WORKER.pop("images", None)
        if own:
            images.close()


def _index_ranges(indices: list[int]) -> str:
    """``[0, 1, 2, 5, 7, 8]`` as ``0-2, 5, 7-8``."""
    idx, parts, start = sorted(indices), [], None
    for k, i in enumerate(idx):
        start = i if start is None else start
        if k + 1 == len(idx) or idx[k + 1] != i + 1:
            parts.append(f"{start}" if start == i else f"{start}-{i}")
            start = None
    return ", ".join(parts)


@contextmanager
def _worker_pool(workers: int, camera: CameraModel, boards: tuple[BoardView, BoardView],
                 lidar: LidarSpec):
    """A process pool with the run's constants set once per worker; on any error (or
    Ctrl-C) the queued tasks are cancelled and the workers joined before it propagates.
    After the last result the workers exit while the caller goes on (the pool's own
    thread joins them; at the latest the interpreter does, at exit)."""
    ex = ProcessPoolExecutor(max_workers=workers, initializer=_init_worker,
                             initargs=(camera, boards, lidar), mp_context=_fork_context())
    try:
        yield ex
    except BaseException:
        ex.shutdown(wait=True, cancel_futures=True)
        raise
    ex.shutdown(wait=False)
    mark("pool-released")


def _calibrate(ds: Dataset, camera: CameraModel, intr: IntrinsicsResult | None,
               boards: tuple[BoardView, BoardView], todo: list[Position], skip: set[int],
               strict: bool, method: str, progress: bool, workers: int | None,
               rho: float | None, fit_planes: bool = False) -> CalibrationResult:
    skipped = [(i, "dropped on request (--skip)") for i in sorted(skip)]
    warnings: list[str] = []
    todo, wrap = _unwrapped(ds, todo)
    warnings += wrap
    workers = workers or min(2, os.cpu_count() or 1)
    if workers > 1 and len(todo) > 4:
        # camera, boards and LiDAR spec go to each worker once (initializer), not with each task
        with _worker_pool(workers, camera, boards, ds.lidar) as ex:
            chunk = max(1, min(2, len(todo) // (4 * workers)))  # small: little tail imbalance
            outcomes = list(_progress(ex.map(_solve_task, [(p, rho) for p in todo],
                                             chunksize=chunk), len(todo), progress))
            mark("positions")
    else:
        jobs = [(p, camera, boards, ds.lidar, rho) for p in todo]
        outcomes = [solve_safe(j) for j in _progress(jobs, len(jobs), progress)]
    results, failed = _apply_skip_policy(ds, todo, outcomes, strict)
    sha256 = _hash_in_background(ds)
    skipped += [(i, str(e)) for i, e in failed]
    warnings += [f"{e}; position {i} skipped (--strict stops instead)" for i, e in failed]
    psi = np.array([r.psi_deg for r in results])
    samples = [r.pose for r in results]
    warnings += check_z_axis_hint(ds, samples)
    warnings += check_angle_scale(ds, psi, samples)
    paper = fit_paper(psi, samples)
    rigid = fit_rigid(psi, samples, init=paper)
    mark("fits")
    warnings += setup_warnings(psi, results)
    warnings += small_square_warnings(boards, ds.v_board, ds.board_image)
    warnings += list(intr.warnings) if intr is not None else []
    res = CalibrationResult(ds, camera, intr, boards, results, skipped, paper, rigid, method,
                            warnings, dataset_sha256=sha256)
    if method == "joint":
        from .joint import fit_joint

        mark("joint-import")
        try:
            res.joint_model = fit_joint(res, fit_planes=fit_planes)
        except (ValueError, np.linalg.LinAlgError) as e:
            res.method = "rigid"
            warnings.append(f"the joint fit failed ({e}); 'poses' holds the rigid fit instead")
        else:
            warnings += [f"joint fit: {w}" for w in res.joint_model.warnings]
            warnings += joint_rigid_warnings(res)
            warnings += turn_scale_warnings(res, psi, samples, JOINT_RIGID_SIGMAS)
            # the photos' camera's own uncertainty, through the stripes' rays as well
            try:
                spread = camera_spread(res, fit_planes=fit_planes)
            except (ValueError, np.linalg.LinAlgError) as e:
                spread = None
                warnings.append(f"{ds.root / 'intrinsics'}: the camera's uncertainty could not be "
                                f"carried into 'sigma' ({e}); the sigmas leave it out: add "
                                "intrinsics photos (board tilted 30-45 deg towards each side)")
            if spread is not None:
                res.joint_model.info["camera_spread"] = spread
        mark("joint")
    return res


def _unwrapped(ds: Dataset, todo: list[Position]) -> tuple[list[Position], list[str]]:
    """The positions with their angles as one sweep (:func:`lidarcal.turntable.unwrap_angles_deg`:
    a controller wrapping at 360 deg), and a warning naming positions.csv when they changed."""
    psi = np.array([p.psi_deg for p in todo])
    u = unwrap_angles_deg(psi)
    if np.array_equal(u, psi):
        return todo, []
    out = [replace(p, psi_deg=float(a)) for p, a in zip(todo, u)]
    text = (f"{ds.root / 'positions.csv'}: psi_deg wraps at 360 deg (from {psi.min():g} to "
            f"{psi.max():g}); taken as one sweep from {u.min():g} to {u.max():g} deg (the "
            "same poses: a turn by psi + 360 deg is a turn by psi)")
    return out, [text]


def _apply_skip_policy(ds: Dataset, todo: list[Position], outcomes: list, strict: bool
                       ) -> tuple[list[PositionResult], list[tuple[int, DatasetError]]]:
    """Solved positions and the failed ones (index, error), per the module's policy: a
    failure is fatal when ``strict`` or when fewer than ``MIN_POSITIONS`` would remain
    (the first failure is raised then, naming its file, with the count)."""
    results = [o for o in outcomes if not isinstance(o, DatasetError)]
    failed = [(p.index, o) for p, o in zip(todo, outcomes) if isinstance(o, DatasetError)]
    if failed and strict:
        raise failed[0][1]
    if len(results) < MIN_POSITIONS:
        if failed:
            first = failed[0][1]
            raise DatasetError(first.path, f"{first.problem} ({len(failed)} of {len(todo)} "
                                           f"positions failed, {len(results)} usable; the turntable "
                                           f"fit needs at least {MIN_POSITIONS})")
        raise DatasetError(ds.root / "positions.csv",
                           f"only {len(results)} usable position(s), the turntable fit needs at least "
                           f"{MIN_POSITIONS}; capture more positions")
    return results, failed


def _progress(it, total: int, enabled: bool):
    if not enabled:
        return it
    from tqdm import tqdm

    return tqdm(it, total=total, desc="positions", unit="pos", leave=False)


def dataset_hash(ds: Dataset) -> str:
    """SHA-256 over dataset.json, positions.csv and every file they reference (provenance;
    a referenced file that is missing, as a skipped position's may be, counts as missing)."""
    h = hashlib.sha256()
    files = [ds.dataset_json, ds.root / "positions.csv", ds.board_image]
    for p in ds.positions:
        files += [p.stripe_image, p.scan]
    for f in files:
        h.update(os.path.relpath(f, ds.root).encode())  # files may live outside the folder
        h.update(f.read_bytes() if f.is_file() else b"<missing>")
    return h.hexdigest()


def _hash_in_background(ds: Dataset) -> Future:
    """:func:`dataset_hash` in a thread of its own: file reads and SHA-256 (OpenSSL) release
    the GIL, so it runs on the core the serial pose-function fits leave idle; its result
    (or its error) is taken by :func:`calibration_dict`. The thread ends by itself."""
    ex = ThreadPoolExecutor(max_workers=1, thread_name_prefix="lidarcal-hash")
    try:
        return ex.submit(dataset_hash, ds)
    finally:
        ex.shutdown(wait=False)


def _dataset_sha256(res: CalibrationResult) -> str:
    mark("hash-start")
    out = dataset_hash(res.dataset) if res.dataset_sha256 is None else res.dataset_sha256.result()
    mark("hash")
    return out


def calibration_dict(res: CalibrationResult, command: str | None = None) -> dict:
    """``calibration.json`` per the contract, plus optional extensions."""
    ds = res.dataset
    psi = {p.index: p.psi_deg for p in res.positions}
    # calibrated from intrinsics/: with every view's reprojection RMS and the k3 choice
    cam = res.intrinsics.to_dict() if res.intrinsics is not None else res.camera.to_dict()
    samples = []
    for p in res.positions:
        row = {"index": p.index, "psi_deg": p.psi_deg, **p.pose.to_dict(),
               "rotation_residual": float(p.pose.residual),
               "alpha_deg": float(np.degrees(p.camera_lines.alpha))}
        samples.append(row)
    out = {
        "format": CALIBRATION_FORMAT,
        "dataset": str(ds.root),
        "camera": cam,
        "axis": {"point_mm": res.model.axis.point.tolist(),
                 "direction": res.model.axis.direction.tolist()},
        "samples": samples,
        "poses": pose_rows(res.model, psi),
        "model": res.model.to_dict(),
        "method": res.method,
    }
    for name, m in res.models.items():
        if name != res.method:
            out[f"model_{name}"] = m.to_dict()
            out[f"poses_{name}"] = pose_rows(m, psi)
    if res.joint_model is not None:
        out["sigma"] = sigma_block(res.joint_model, res.positions)
    if res.method == "joint" and getattr(res.joint_model, "ranging", None) is not None:
        out["ranging"] = res.joint_model.ranging.to_dict()  # lidarcal.ranging
    zones = res.joint_model.info.get("scan_edge_zones") if res.joint_model is not None else None
    if zones is not None:  # lidarcal.scan_edges: returns dropped at each segment's ends
        out["scan_edge_zones"] = {"outer_returns": zones.outer, "hinge_returns": zones.hinge,
                                  "noise_mm": _finite_or_none(zones.noise_mm)}
    if res.joint_model is not None and res.joint_model.info.get("fit_planes"):
        # --fit-planes: the board planes the joint fit refined (``boards`` keeps the camera's)
        out["boards_joint"] = [pl.to_dict() for pl in res.joint_model.info["board_planes"]]
    out.update({
        "boards": [{**b.plane.to_dict(), "reprojection_rms_px": float(b.reprojection_rms_px[0]),
                    "pnp": {**b.plane_pnp.to_dict(),
                            "reprojection_rms_px": float(b.reprojection_rms_px[1])}}
                   for b in res.boards],
        "skipped": [{"index": i, "reason": r} for i, r in res.skipped],
        "warnings": list(res.warnings),
        "provenance": {"lidarcal_version": __version__, "dataset_sha256": _dataset_sha256(res),
                       "command": command},
    })
    return out


def _finite_or_none(v: float) -> float | None:
    return float(v) if np.isfinite(v) else None


def sigma_block(model, positions: list[PositionResult]) -> dict:
    """``calibration.json`` ``sigma``: 1-sigma uncertainties of the joint fit (issue 6).

    Per position the centre (mm, RMS length of the error vector) and the z and x axes
    (deg); for the turntable axis its direction (deg) and its position near the LiDAR
    (mm). ``null`` marks a quantity the data do not determine. The full covariance of
    the 10 rig parameters is ``model.covariance``. Positions are at their jitter-corrected
    angles and include the remaining angle uncertainty; ``angle_jitter_deg`` is the
    estimated encoder jitter (0: none detected).
    """
    psi = np.array([p.psi_deg for p in positions], dtype=float)
    cols = model.position_sigma_columns([p.index for p in positions], psi)
    spread = model.info.get("rigid_spread")  # joint_rigid_warnings: widened to cover both fits
    # turn_scale_warnings: widened by what the encoder's scale error does to the poses;
    # camera_spread: by what the photos' camera's 1-sigma does to them
    for sp in (spread, model.info.get("turn_scale_spread"), model.info.get("camera_spread")):
        if sp is None:
            continue
        for q in ("centre_mm", "z_axis_deg", "x_axis_deg"):
            cols[q] = np.hypot(cols[q], [sp[q].get(p.index, 0.0) for p in positions])
        for q in ("axis_direction_deg", "axis_point_mm"):
            cols[q] = np.hypot(cols[q], sp[q])
    rows = [{"index": p.index, "psi_deg": p.psi_deg,
             **{q: _finite_or_none(cols[q][j]) for q in ("centre_mm", "z_axis_deg", "x_axis_deg")}}
            for j, p in enumerate(positions)]
    return {"level": "1-sigma", "method": "joint", **({"widened_to_rigid": True} if spread else {}),
            **({"widened_to_turn_scale": True} if "turn_scale_spread" in model.info else {}),
            **({"widened_to_camera": True} if "camera_spread" in model.info else {}),
            "angle_jitter_deg": float(model.jitter_deg),
            "axis_direction_deg": _finite_or_none(cols["axis_direction_deg"][0]),
            "axis_point_mm": _finite_or_none(cols["axis_point_mm"][0]),
            "noise": {k: float(v) for k, v in model.noise.items()},
            "poses": rows}


def write_calibration(res: CalibrationResult, out_dir: str | os.PathLike,
                      command: str | None = None) -> Path:
    path = Path(out_dir) / "calibration.json"
    out = calibration_dict(res, command)
    mark("calibration-dict")
    write_json_atomic(path, out)
    return path


def measure_dataset(dataset: str | os.PathLike, calibration: str | os.PathLike,
                    references: list[str] | None = None) -> pd.DataFrame:
    """Every entry of dataset.json ``measurements``, measured with a calibration (section 3.2),
    with the edge model (reference discs or the prior) applied; see :mod:`lidarcal.disc`."""
    from .disc import measure_dataset as _measure

    return _measure(dataset, calibration, references)


def write_measurements(table: pd.DataFrame, out_dir: str | os.PathLike,
                       dataset: str | os.PathLike) -> Path:
    path = Path(out_dir) / "measurements.json"
    # a column mixing numbers and None (e.g. spot_sigma_mm) comes back as NaN: write null
    rows = [{k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in r.items()}
            for r in table.to_dict(orient="records")]
    extra = {k: table.attrs[k] for k in ("edge_model", "warnings") if k in table.attrs}
    write_json_atomic(path, {"format": MEASUREMENTS_FORMAT, "dataset": str(Path(dataset).resolve()),
                             **extra, "measurements": rows})
    return path
