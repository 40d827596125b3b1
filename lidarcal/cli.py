"""The ``lidarcal`` command line.

Every bad input ends with one line ``error: FILE: what is wrong; what to do`` on
stderr and exit status 2 (``--debug`` shows the traceback); outputs are written
to a temporary file and renamed, so nothing is ever half-written.
"""

from __future__ import annotations

import argparse
import gc
import os
import sys
import traceback
from contextlib import contextmanager, suppress
from pathlib import Path

from .trace import mark


def _numpy_one_blas_thread():
    """Import numpy with OpenBLAS on one thread in this process (its worker processes are
    forked from it and each takes a core: BLAS threads would only compete with them;
    measured on the bundled dataset: 0.2 s less CPU per calibration, same
    calibration.json), then restore the environment so that child processes
    (notebook kernels) keep their own setting. No effect when numpy is already loaded."""
    keys = ("OPENBLAS_NUM_THREADS",)
    old = {k: os.environ.get(k) for k in keys}
    for k in keys:
        os.environ.setdefault(k, "1")
    try:
        import numpy
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    return numpy


np = _numpy_one_blas_thread()
mark("numpy")
# OpenCV's own warnings (e.g. imread of an unreadable file) are not one line naming what to do;
# the readers check their files and say so themselves
os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")

from .io.dataset import DatasetError, check_output

mark("cli")


class _Parser(argparse.ArgumentParser):
    """argparse, with a bad argument in one line like every other error:
    ``error: --seed: invalid int value: 'x'; see 'lidarcal simulate --help'`` (exit 2)."""

    def error(self, message: str):
        what, sep, problem = message.partition(": ")
        if not (sep and what.startswith("argument ")):
            what, problem = self.prog, message
        else:
            what = what[len("argument "):].split("/")[-1]
        self.exit(2, f"error: {what}: {' '.join(problem.split())}; see '{self.prog} --help'\n")


def _pattern(text: str) -> tuple[int, int]:
    try:
        a, b = text.lower().split("x")
        return int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners like 9x6, got {text!r}") from None


def _diameters(text: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected diameters in mm like 100,140,200, got {text!r}") from None
    if not vals or min(vals) <= 0:
        raise argparse.ArgumentTypeError(f"diameters must be > 0 mm, got {text!r}")
    return vals


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v > 0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return v


def _at_least_3(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v < 3:
        raise argparse.ArgumentTypeError(f"expected an integer >= 3 (the method needs at least 3 "
                                         f"positions), got {text!r}")
    return v


def _non_negative(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = float("nan")
    if not v >= 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


def _chessboard_options(s: argparse.ArgumentParser, example: str, camera: bool = False,
                        default_from: str | None = None) -> None:
    """The chessboard's ``--pattern`` and ``--square-mm`` (and the ``--camera`` it is seen by);
    with ``default_from`` they are optional, read from that file when not given."""
    req = default_from is None
    note = "" if req else f" (default: {default_from})"
    s.add_argument("--pattern", type=_pattern, required=req, default=None,
                   help=f"inner corners, e.g. {example}{note}")
    s.add_argument("--square-mm", type=_positive, required=req, default=None,
                   help=f"side of a square, mm{note}")
    if camera:
        s.add_argument("--camera", type=Path, required=True, help="camera.json (K, dist, image_size)")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="lidarcal", description=__doc__.splitlines()[0])
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write a synthetic dataset (with truth.json)")
    s.add_argument("out", type=Path)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--rig", default="paper", choices=["paper", "wide", "harsh"], help="rig preset")
    s.add_argument("--positions", type=_at_least_3, default=None,
                   help="number of turntable positions (>= 3)")
    s.add_argument("--no-sweeps", action="store_true", help="skip the disc-measurement sweeps")
    s.add_argument("--footprint", choices=["gaussian", "first-echo"], default=None,
                   help="LiDAR echo model: gaussian (energy-weighted mixed ranges, default) or "
                        "first-echo (uniform spot, nearest surface with >= 25%% of the energy)")
    s.add_argument("--disc-diameters", type=_diameters, default=None, metavar="D1,D2,...",
                   help="disc sizes in mm, used in turn by the trials (e.g. 100,140,200)")
    s.add_argument("--overwrite", action="store_true")
    s.add_argument("--no-intrinsics", action="store_true",
                   help="skip the intrinsics chessboard photos (dataset.json then holds the camera)")
    s.add_argument("--range-offset-mm", type=float, default=0.0,
                   help="LiDAR zero offset: every range reads this much too far (default 0)")
    s.add_argument("--dark-extra-mm", type=float, default=0.0,
                   help="returns from black squares read this much farther (default 0)")
    s.add_argument("--range-quantum-mm", type=_non_negative, default=0.0,
                   help="round ranges to multiples of this, e.g. 1 (default 0: not quantised)")
    s.add_argument("--range-noise-mm", type=_non_negative, default=None,
                   help="LiDAR range noise, 1 sigma (default: the rig's)")
    s.add_argument("--antialias", choices=["grid", "multi-jittered"], default=None,
                   help="sub-pixel samples of the images' edges: grid (default; edges along the "
                        "pixel rows rendered up to 1/8 px off) or multi-jittered")

    s = sub.add_parser("import", help="turn a ROS 1 / ROS 2 bag into a dataset folder (or, "
                                      "with --views, a folder of one-board views)")
    s.add_argument("bag", type=Path, help="ROS 1 .bag file or ROS 2 bag folder (sqlite3, mcap)")
    s.add_argument("--rig", type=Path, default=None,
                   help="RIG.json (docs/ros-bags.md); required for a turntable bag")
    s.add_argument("--out", type=Path, required=True,
                   help="dataset folder to write (with --views: the folder of views)")
    s.add_argument("--views", action="store_true",
                   help="one-board recording: write the still moments as NAME.png + NAME.csv "
                        "view pairs for `lidarcal planes` (+ camera.json from CameraInfo)")
    s.add_argument("--image-topic", help="--views: the camera's Image or CompressedImage topic "
                                         "(default: the only one)")
    s.add_argument("--camera-info-topic", help="--views: sensor_msgs/CameraInfo topic (default: "
                                               "the only one, or the image topic's)")
    s.add_argument("--min-scans", type=int, default=None,
                   help="--views: a still interval holds at least this many scans (default 5)")
    s.add_argument("--pattern", type=_pattern, default=None,
                   help="--views: the board's inner corners, e.g. 8x5 (writes board.json, read "
                        "by `lidarcal planes`)")
    s.add_argument("--square-mm", type=_positive, default=None,
                   help="--views: the board's square side, mm (with --pattern)")
    s.add_argument("--scan-topic", help="sensor_msgs/LaserScan topic (default: the only one)")
    s.add_argument("--stripe-topic", help="dark stripe frames, Image or CompressedImage "
                                          "(default: the image topic named *stripe*, or the "
                                          "only one)")
    s.add_argument("--board-topic", help="lit board frames (default: the image topic named "
                                         "*board*, or the only one); equal to --stripe-topic: "
                                         "one camera, lit and dark frames told apart")
    s.add_argument("--board-image", type=Path, help="the lit board image as a file instead")
    s.add_argument("--angle-topic", help="turntable angle, JointState or Float64 "
                                         "(default: the only one, or the one named *turntable*)")
    s.add_argument("--joint", help="the turntable's name in a JointState with several joints "
                                   "(default: the only joint that holds and steps)")
    s.add_argument("--angle-unit", choices=["rad", "deg"], default="rad",
                   help="unit of a Float64 angle topic (JointState is always radians)")
    s.add_argument("--tolerance-deg", type=float, default=None,
                   help="a position holds the angle within this (default: from the encoder "
                        "resolution and noise seen in the bag)")
    s.add_argument("--min-duration-s", type=float, default=None,
                   help="a position holds at least this long (default: 3 angle readings, 4 scans)")
    s.add_argument("--frame-guard-s", type=float, default=0.0,
                   help="use a frame only if its stamp is this far inside a position (exposure)")
    s.add_argument("--overwrite", action="store_true")
    s.add_argument("--no-progress", action="store_true")

    s = sub.add_parser("intrinsics", help="calibrate camera intrinsics from chessboard photos")
    s.add_argument("images", type=Path, help="folder of chessboard images")
    _chessboard_options(s, "9x6")
    s.add_argument("-o", "--out", type=Path, default=None, help="write camera.json here")

    s = sub.add_parser("laser-plane", help="the plane of a line laser from photos of it on a "
                                           "flat chessboard")
    s.add_argument("photos", type=Path, help="folder of lights-on photos of the laser on the board")
    _chessboard_options(s, "8x5 (or 5x8)", camera=True)
    s.add_argument("--out", type=Path, required=True, help="plane.json to write")
    s.add_argument("--laser-colour", default="auto",
                   choices=["auto", "red", "green", "blue", "gray"],
                   help="the laser's colour (gray: a NIR laser); auto decides from the photos")

    s = sub.add_parser("calibrate", help="calibrate the LiDAR pose function from a dataset")
    s.add_argument("dataset", type=Path)
    s.add_argument("--out", type=Path, required=True, help="output folder for calibration.json")
    s.add_argument("--method", choices=["joint", "rigid", "paper"], default="joint",
                   help="which pose function fills 'poses': joint (default; the joint fit of all "
                        "scan points and stripe centres, with 1-sigma uncertainties), rigid (a "
                        "rigid rotation fitted to the single-shot poses) or paper (the paper's "
                        "chain, eqs. 15-27); all are stored")
    s.add_argument("--skip", type=int, nargs="*", default=[], help="position indices to drop")
    s.add_argument("--strict", action="store_true",
                   help="stop (exit 2) at the first position that cannot be solved; by default "
                        "it is skipped with a warning naming its file while >= 3 positions remain")
    s.add_argument("--fit-planes", action="store_true",
                   help="the joint fit also refines the two board planes from the scans and "
                        "stripes (helps where board.png is weak, e.g. a wide-angle camera "
                        "calibrated from photos; several times slower)")
    s.add_argument("--skip-failed", action="store_true",
                   help="no effect, kept so old commands still run: skipping failed positions "
                        "is the default (see --strict)")
    s.add_argument("--no-progress", action="store_true")

    s = sub.add_parser("pose", help="evaluate a calibration's pose function at turntable angles")
    s.add_argument("calibration", type=Path)
    s.add_argument("--psi", type=float, nargs="+", required=True, help="turntable angles, deg")
    s.add_argument("--model", choices=["poses", "paper", "rigid", "joint"], default="poses",
                   help="pose function: the one that filled 'poses' (default) or a stored one")

    s = sub.add_parser("measure", help="measure the objects swept in a dataset")
    s.add_argument("dataset", type=Path)
    s.add_argument("--calibration", type=Path, required=True)
    s.add_argument("--out", type=Path, required=True, help="output folder for measurements.json")
    s.add_argument("--reference", nargs="+", metavar="NAME", default=None,
                   help="measurements whose reference_diameter_mm calibrates the edge model "
                        "(applied to the others); without: the prior, with its sigma")

    s = sub.add_parser("cloud", help="export sweeps as point clouds (eq. 28): .ply, .pcd, .vtp, .csv")
    s.add_argument("dataset", type=Path)
    s.add_argument("--calibration", type=Path, required=True)
    g = s.add_mutually_exclusive_group(required=True)
    g.add_argument("--sweep", nargs="+", metavar="NAME", help="measurement name(s) in dataset.json")
    g.add_argument("--all", action="store_true", help="every sweep, one file each in the --out folder")
    s.add_argument("--out", type=Path, required=True,
                   help="output file (one sweep; suffix .ply/.pcd/.vtp/.csv) or folder")
    s.add_argument("--frame", choices=["camera", "home"], default="camera",
                   help="camera (default) or home: the LiDAR frame at turntable angle 0")
    s.add_argument("--format", choices=["ply", "pcd", "vtp", "csv"], default="ply",
                   help="format of files written into a folder (default ply, binary)")

    s = sub.add_parser("planes", help="classic one-board calibration (Zhang-Pless) of a LiDAR "
                                      "against a camera from photo + scan pairs")
    s.add_argument("folder", type=Path, help="folder of NAME.png|jpg + NAME.csv pairs")
    _chessboard_options(s, "8x5", camera=True, default_from="FOLDER/board.json")
    s.add_argument("--out", type=Path, required=True, help="output folder for extrinsics.json")
    s.add_argument("--no-figures", action="store_true", help="skip OUT/projection_NAME.png")
    _assumed_margin_option(s)

    s = sub.add_parser("overlay", help="draw a dataset position's scan on its image with a "
                                       "calibration")
    s.add_argument("dataset", type=Path)
    s.add_argument("--calibration", type=Path, required=True)
    s.add_argument("--index", type=int, required=True, help="position index")
    s.add_argument("--out", type=Path, required=True, help="PNG path")

    s = sub.add_parser("report", help="write the PDF calibration report (a turntable dataset, or a "
                                      "folder of photo + scan pairs: the one-board method)")
    s.add_argument("dataset", type=Path, help="dataset folder, or folder of NAME.png|jpg + NAME.csv "
                                              "pairs with camera.json")
    s.add_argument("--out", type=Path, required=True, help="report PDF path")
    s.add_argument("--calibration", type=Path, default=None,
                   help="calibration.json to show (a pairs folder: an extrinsics.json to score on "
                        "these views)")
    s.add_argument("--measurements", type=Path, default=None)
    s.add_argument("--camera", type=Path, default=None,
                   help="pairs folder only: camera.json (default: FOLDER/camera.json)")
    s.add_argument("--pattern", type=_pattern, default=None,
                   help="pairs folder only: inner corners (default: FOLDER/board.json)")
    s.add_argument("--square-mm", type=_positive, default=None,
                   help="pairs folder only: side of a square, mm (default: FOLDER/board.json)")
    _assumed_margin_option(s, "pairs folder only: ")

    s = sub.add_parser("check", help="check a dataset before calibrating: detections per position, "
                                     "no fits; exit 0 usable, 1 problems, 2 unreadable")
    s.add_argument("dataset", type=Path)
    s.add_argument("--sheet", type=Path, default=None,
                   help="contact sheet (.png or .pdf; default: NAME-check.png in the current folder)")
    s.add_argument("--no-sheet", action="store_true", help="write no contact sheet")

    s = sub.add_parser("workbook", help="run the numbered notebooks on a dataset, write one PDF")
    s.add_argument("dataset", type=Path)
    s.add_argument("--out", type=Path, required=True, help="workbook PDF path")
    s.add_argument("--timeout", type=int, default=900, help="per-cell timeout, s (default 900)")
    s.add_argument("--notebooks", default=None,
                   help="comma-separated notebook numbers to run, e.g. 01,02,05 (default: all)")
    s.add_argument("--notebook-dir", type=Path, default=None,
                   help="folder of the numbered notebooks (default: the repository's notebooks/)")
    s.add_argument("--keep", type=Path, default=None,
                   help="also copy the executed notebooks and the typst source here")
    return p


def _cmd_simulate(a: argparse.Namespace) -> int:
    from .synthetic import simulate
    from .synthetic.config import get_rig

    check_output(a.out, "folder")

    rig = get_rig(a.rig)
    if a.footprint is not None:
        rig = rig.with_(footprint_model=a.footprint)
    if a.disc_diameters is not None:
        rig = rig.with_(disc_diameters_mm=a.disc_diameters)
    if a.range_offset_mm or a.dark_extra_mm or a.range_quantum_mm:
        rig = rig.with_(range_offset_mm=a.range_offset_mm, dark_extra_mm=a.dark_extra_mm,
                        range_quantum_mm=a.range_quantum_mm)
    if a.range_noise_mm is not None:
        rig = rig.with_(range_noise_mm=a.range_noise_mm)
    if a.antialias is not None:
        rig = rig.with_(antialias=a.antialias)
    path = simulate(a.out, seed=a.seed, rig=rig, n_positions=a.positions,
                    with_sweeps=not a.no_sweeps, overwrite=a.overwrite,
                    with_intrinsics=False if a.no_intrinsics else None)
    print(f"wrote dataset {path}")
    return 0


def _cmd_import(a: argparse.Namespace) -> int:
    from .io.bag import import_bag

    check_output(a.out, "folder")
    turntable = {"--rig": a.rig, "--stripe-topic": a.stripe_topic, "--board-topic": a.board_topic,
                 "--board-image": a.board_image, "--angle-topic": a.angle_topic, "--joint": a.joint,
                 "--tolerance-deg": a.tolerance_deg, "--min-duration-s": a.min_duration_s}
    if a.views:
        return _cmd_import_views(a, [k for k, v in turntable.items() if v is not None])
    views_only = {"--image-topic": a.image_topic, "--camera-info-topic": a.camera_info_topic,
                  "--min-scans": a.min_scans, "--pattern": a.pattern, "--square-mm": a.square_mm}
    given = [k for k, v in views_only.items() if v is not None]
    if given:
        raise DatasetError(a.bag, f"{given[0]} is for a one-board recording: add --views")
    if a.rig is None:
        raise DatasetError(a.bag, "a turntable bag needs --rig RIG.json (docs/ros-bags.md); for "
                                  "a one-board recording pass --views")

    res = import_bag(a.bag, a.rig, a.out, scan_topic=a.scan_topic, stripe_topic=a.stripe_topic,
                     board_topic=a.board_topic, angle_topic=a.angle_topic, joint=a.joint,
                     angle_unit=a.angle_unit, board_image=a.board_image,
                     tolerance_deg=a.tolerance_deg, min_duration_s=a.min_duration_s,
                     frame_guard_s=a.frame_guard_s, overwrite=a.overwrite,
                     progress=not a.no_progress and sys.stderr.isatty())
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    psi = [p.psi_deg for p in res.positions]
    print(f"{len(psi)} positions, psi {min(psi):.4f}..{max(psi):.4f} deg (tolerance "
          f"{res.tolerance_deg:.3g} deg, min duration {res.min_duration_s:.3g} s); "
          f"{len(res.sweeps)} sweep(s)")
    print(f"wrote dataset {res.out}")
    return 0


def _cmd_import_views(a: argparse.Namespace, turntable_options: list[str]) -> int:
    from .io.bag_views import import_views

    if turntable_options:
        raise DatasetError(a.bag, f"{turntable_options[0]} is for a turntable bag, not with "
                                  "--views; leave it out")
    res = import_views(a.bag, a.out, scan_topic=a.scan_topic, image_topic=a.image_topic,
                       camera_info_topic=a.camera_info_topic,
                       min_scans=5 if a.min_scans is None else a.min_scans,
                       pattern=a.pattern, square_mm=a.square_mm, overwrite=a.overwrite,
                       progress=not a.no_progress and sys.stderr.isatty())
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    merged = sum(len(v.intervals) - 1 for v in res.views)
    print(f"{res.n_intervals} still interval(s) -> {len(res.views)} views ({merged} merged into "
          f"a view of the same pose, {res.n_drifting} drifting; {res.scan_runs} still "
          f"run(s) of the scans, {res.frame_runs} of the frames; scan noise "
          f"{res.scan_noise_mm:.3g} mm, frame noise {res.frame_noise:.3g} gray levels); "
          f"camera.json {'written' if res.camera_written else 'not written'}"
          + ("; board.json written" if a.pattern is not None else ""))
    print(f"wrote views {res.out}")
    return 0


def _cmd_intrinsics(a: argparse.Namespace) -> int:
    from .camera import calibrate_intrinsics
    from .io.dataset import BoardSpec, write_json_atomic

    if a.out is not None:
        check_output(a.out, "file")
    if not a.images.is_dir():
        raise DatasetError(a.images, "not a folder of chessboard images; give the folder that "
                                     "holds the photos")
    paths = sorted(p for p in a.images.iterdir()
                   if p.suffix.lower() in {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
    if not paths:
        raise DatasetError(a.images, "holds no .png/.jpg/.bmp/.tif images; give the folder that "
                                     "holds the photos")
    res = calibrate_intrinsics(paths, BoardSpec(a.pattern, a.square_mm))
    cam = res.camera
    K, d = cam.K, cam.dist
    print(f"views used {len(res.files_used)} of {len(paths)}; image "
          f"{cam.image_size[0]}x{cam.image_size[1]}")
    for w in res.warnings:  # photos left out (each named) and the folder's checks
        print(f"warning: {w}", file=sys.stderr)
    print(f"fx {K[0, 0]:.3f}  fy {K[1, 1]:.3f}  cx {K[0, 2]:.3f}  cy {K[1, 2]:.3f}")
    if res.sigma_px is not None:
        print("1-sigma (leave-out spread) fx {:.3f}  fy {:.3f}  cx {:.3f}  cy {:.3f} px"
              .format(*res.sigma_px))
    print("dist k1 k2 p1 p2 k3: " + " ".join(f"{v:.6f}" for v in d))
    print(f"RMS reprojection error {cam.rms_px:.4f} px")
    if a.out is not None:
        write_json_atomic(a.out, res.to_dict())
        print(f"wrote {a.out}")
    return 0


def _cmd_laser_plane(a: argparse.Namespace) -> int:
    from .io.dataset import BoardSpec
    from .laserplane import laser_plane, read_camera_json, write_laser_plane

    check_output(a.out, "file")
    res = laser_plane(a.photos, BoardSpec(a.pattern, a.square_mm), read_camera_json(a.camera),
                      a.laser_colour)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    n_used = sum(p.used for p in res.photos)
    print(f"photos used {n_used} of {len(res.photos)}; normal "
          f"{np.array2string(res.plane.normal, precision=6)}, d {res.plane.d:.3f} mm, "
          f"rms {res.rms_mm:.3f} mm")
    print(f"wrote {write_laser_plane(res, a.out)}")
    return 0


def _reuse_freed_memory() -> None:
    """Let glibc's malloc keep and reuse freed memory in this process (``mallopt(3)``).

    By default every block above a dynamic threshold (128 kB, raised as blocks are freed)
    is mapped from the kernel when allocated and unmapped when freed, and the top of the
    heap is handed back, so each image-sized temporary of the board search (4-32 MB)
    touches fresh pages: ~50,000 page faults and ~0.1 s of kernel CPU in ``calibrate``,
    measured on the bundled dataset. With a fixed mapping threshold of 32 MB (glibc's
    maximum) and a heap trimmed only past 256 MB, the freed blocks are reused instead.
    Only how memory is recycled changes (not what is computed); the peak memory is kept
    until the process exits. No effect outside glibc (Linux).
    """
    try:
        os.confstr("CS_GNU_LIBC_VERSION")
    except (ValueError, OSError, AttributeError):
        return
    import ctypes

    libc = ctypes.CDLL(None)
    m_trim_threshold, m_mmap_threshold = -1, -3  # <malloc.h>
    libc.mallopt(m_trim_threshold, 256 << 20)
    libc.mallopt(m_mmap_threshold, 32 << 20)


@contextmanager
def _imports_without_gc():
    """Import with the cyclic garbage collector paused, then freeze what was imported.

    scipy's import creates ~250k long-lived objects and next to no garbage; the collector
    rescanning them during the import, at every later full collection and at exit cost
    ~0.1 s of CPU per run. Frozen (:func:`gc.freeze`), collections skip them, and forked
    workers do not copy their pages. :func:`main` unfreezes them when called in-process.
    """
    if not gc.isenabled():  # the caller manages the collector
        yield
        return
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        gc.enable()


@contextmanager
def _importing_in_background(module: str):
    """Import ``module`` in a thread while the block runs; joined when the block is left
    (result or error), so no thread outlives it. An import error is left for the caller's
    own import of ``module`` to raise, with its traceback."""
    import importlib
    import threading

    def target() -> None:
        with suppress(Exception):  # raised again, with its traceback, by the caller's import
            importlib.import_module(module, __package__)

    t = threading.Thread(target=target, name=f"import {module}")
    t.start()
    try:
        yield
    finally:
        t.join()


def _cmd_calibrate(a: argparse.Namespace) -> int:
    from .io.dataset import load_dataset, prefetch_stripe_images

    check_output(a.out, "folder")
    ds = load_dataset(a.dataset)
    mark("dataset")
    skip = set(a.skip)
    todo = [p for p in ds.positions if p.index not in skip]
    # the stripe images decode in a background thread while the heavier modules (scipy)
    # import in another; the boards of board.png, which need neither, are found meanwhile
    # (OpenCV releases the GIL). Leaving a block (result or error) stops and joins its thread
    # before anything is printed
    with prefetch_stripe_images(ds, todo) as images:
        boards = None
        with _imports_without_gc():
            with _importing_in_background(".pipeline"):
                if ds.camera is not None:  # else the camera comes from intrinsics/ first
                    from .board import find_boards

                    boards = find_boards(ds, ds.camera)
                    mark("early-boards")
            from .pipeline import calibrate, write_calibration
        mark("imports")
        res = calibrate(ds, skip=a.skip, strict=a.strict,
                        progress=not a.no_progress and sys.stderr.isatty(), method=a.method,
                        images=images, fit_planes=a.fit_planes, boards=boards)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    mark("calibrated")
    path = write_calibration(res, a.out, command=" ".join(["lidarcal", *sys.argv[1:]]))
    mark("written")
    print(res.summary())
    print(f"wrote {path}")
    return 0


def _cmd_pose(a: argparse.Namespace) -> int:
    from .api import load_calibration

    cal = load_calibration(a.calibration, model=a.model)
    np.set_printoptions(precision=6, suppress=True)
    for psi in a.psi:
        pose = cal.pose(psi)
        print(f"psi {psi:g} deg")
        print("R =")
        print(pose.R)
        print("T_mm =", pose.T)
        if hasattr(cal.model, "sigma"):  # the joint fit carries its covariance
            sg = cal.model.sigma(psi)
            print(f"1-sigma: centre {sg['centre_mm']:.4f} mm, z axis {sg['z_axis_deg']:.5f} deg, "
                  f"x axis {sg['x_axis_deg']:.5f} deg")
    return 0


def _cmd_measure(a: argparse.Namespace) -> int:
    from .pipeline import measure_dataset, write_measurements

    check_output(a.out, "folder")
    table = measure_dataset(a.dataset, a.calibration, references=a.reference)
    for w in table.attrs.get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    path = write_measurements(table, a.out, a.dataset)
    cols = ["name", "diameter_mm", "diameter_sigma_mm", "reference_diameter_mm", "error_mm", "reference"]
    print(table[cols].to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    em = table.attrs.get("edge_model", {})
    if em:
        print(f"edge model ({em['source']}): rim offset {em['k']:.3f} +- {em['k_sigma']:.3f} beam spacings"
              + (f" ({', '.join(em['wide_spot'])}: their own, wide spot)" if em.get("wide_spot") else ""))
    print(f"wrote {path}")
    return 0


def _cmd_cloud(a: argparse.Namespace) -> int:
    from .cloud import dataset_clouds

    check_output(a.out, "file" if a.sweep and len(a.sweep) == 1 else "folder")
    for path in dataset_clouds(a.dataset, a.calibration, None if a.all else a.sweep, a.out,
                               frame=a.frame, fmt=a.format):
        print(f"wrote {path}")
    return 0


def _cmd_report(a: argparse.Namespace) -> int:
    from .report import write_report
    from .workbook import input_kind

    check_output(a.out, "file")
    command = " ".join(["lidarcal", *sys.argv[1:]])
    pairs_only = [f"--{k.replace('_', '-')}" for k in ("camera", "pattern", "square_mm")
                  if getattr(a, k) is not None] + (["--assumed-margin"] if a.assumed_margin else [])
    if a.camera is not None or input_kind(a.dataset) == "view-pairs":
        from .io.pairs import board_spec
        from .report.oneboard import write_oneboard_report

        if a.measurements is not None:
            raise DatasetError(a.measurements, "a folder of photo + scan pairs has no measurements; "
                                               "leave --measurements out")
        path = write_oneboard_report(a.dataset, a.out, a.camera or a.dataset / "camera.json",
                                     board_spec(a.dataset, a.pattern, a.square_mm),
                                     calibration=a.calibration, command=command,
                                     assumed_margin=a.assumed_margin)
        print(f"wrote {path}")
        return 0
    if pairs_only:
        raise DatasetError(a.dataset, f"{', '.join(pairs_only)}: for a folder of photo + scan "
                                      "pairs only; a turntable dataset names its camera and boards "
                                      "in dataset.json")
    path = write_report(a.dataset, a.out, calibration=a.calibration, measurements=a.measurements,
                        command=command)
    print(f"wrote {path}")
    return 0


def _cmd_check(a: argparse.Namespace) -> int:
    from .check import run_check

    if a.sheet is not None and not a.no_sheet:
        check_output(a.sheet, "file")
        if a.sheet.suffix.lower() not in (".png", ".pdf"):  # said before the report, not after
            raise DatasetError(a.sheet, "the contact sheet must be a .png or .pdf file; give "
                                        "--sheet NAME.png or NAME.pdf (or --no-sheet)")
    return run_check(a.dataset, sheet=None if a.no_sheet else (a.sheet or "default"))


def _cmd_workbook(a: argparse.Namespace) -> int:
    from .workbook import write_workbook

    check_output(a.out, "file")
    select = a.notebooks.split(",") if a.notebooks else None
    path = write_workbook(a.dataset, a.out, notebook_dir=a.notebook_dir, select=select,
                          timeout=a.timeout, keep=a.keep)
    print(f"wrote {path}")
    return 0


def _assumed_margin_option(s: argparse.ArgumentParser, prefix: str = "") -> None:
    s.add_argument("--assumed-margin", action="store_true",
                   help=prefix + "do not measure the board's margins beyond its pattern in the "
                        "photos; the scan's cut assumes half the pattern's shorter side")


def _cmd_planes(a: argparse.Namespace) -> int:
    from .io.pairs import board_spec
    from .planes import run_planes, write_extrinsics
    from .planes_plots import write_projections

    check_output(a.out, "folder")
    if a.square_mm is not None and a.square_mm <= 0:
        raise DatasetError(a.folder, f"--square-mm must be positive, got {a.square_mm:g}")
    res = run_planes(a.folder, a.camera, board_spec(a.folder, a.pattern, a.square_mm),
                     assumed_margin=a.assumed_margin)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    if not a.no_figures:
        write_projections(res, a.out)
    path = write_extrinsics(res, a.out, command=" ".join(["lidarcal", *sys.argv[1:]]))
    u = res.uncertainty
    fmt = lambda v: "null" if v is None else f"{v:.3g}"
    print(f"views used {sum(res.used)} of {len(res.views)}; point-to-plane RMS {res.total_rms_mm:.2f} mm")
    print("R =\n" + np.array2string(res.R, precision=6, suppress_small=True))
    print("T_mm =", np.array2string(res.T, precision=2, suppress_small=True))
    print(f"1-sigma rotation deg (x, y, z): {', '.join(fmt(v) for v in u.rotation_deg)}; "
          f"translation mm: {', '.join(fmt(v) for v in u.translation_mm)}")
    bm = res.board_margins
    if bm is not None:
        print("board margins beyond the pattern (mm): " + ", ".join(
            f"{a} {bm[f'{a}_mm']:.1f} +- {bm[f'sigma_{a}_mm']:.1f}" if bm[f"{a}_mm"] is not None
            else f"{a} {bm['assumed_mm']:g} assumed (not measured)" for a in "uv"))
    print(f"wrote {path}")
    return 0


def _cmd_overlay(a: argparse.Namespace) -> int:
    from .overlay import overlay_calibration

    check_output(a.out, "file")
    overlay_calibration(a.dataset, a.calibration, a.index, a.out)
    print(f"wrote {a.out}")
    return 0


COMMANDS = {
    "simulate": _cmd_simulate,
    "import": _cmd_import,
    "check": _cmd_check,
    "intrinsics": _cmd_intrinsics,
    "laser-plane": _cmd_laser_plane,
    "calibrate": _cmd_calibrate,
    "pose": _cmd_pose,
    "measure": _cmd_measure,
    "cloud": _cmd_cloud,
    "planes": _cmd_planes,
    "overlay": _cmd_overlay,
    "report": _cmd_report,
    "workbook": _cmd_workbook,
}


def main(argv: list[str] | None = None) -> int:
    """The command line ``argv`` (None: this process's own, ``sys.argv[1:]``); exit status."""
    args = build_parser().parse_args(argv)
    mark("args")
    if argv is None and args.command == "calibrate":  # this process is the command
        _reuse_freed_memory()
    frozen = gc.get_freeze_count()
    try:
        return COMMANDS[args.command](args)
    except DatasetError as e:
        if args.debug:
            traceback.print_exc()
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (ValueError, FileExistsError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        msg = " ".join(str(e).split())
        if isinstance(e, OSError) and e.filename and e.strerror:  # the file first, as above
            msg = f"{e.filename}: {e.strerror}; check the path and its permissions"
        print(f"error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001  (a bug or unforeseen input: still one line, no traceback)
        if args.debug:
            traceback.print_exc()
        msg = " ".join(str(e).split())
        print(f"error: unexpected {type(e).__name__}: {msg}; rerun with --debug for the traceback "
              "and please report it", file=sys.stderr)
        return 2
    finally:
        if argv is not None and not frozen:  # called in-process: the collector as it was
            gc.unfreeze()
        mark("main-end")


if __name__ == "__main__":
    sys.exit(main())
