"""The ``lidarcal`` command line.

Every bad input ends with one line ``error: FILE: what is wrong; what to do`` on
stderr and exit status 2 (``--debug`` shows the traceback); outputs are written
to a temporary file and renamed, so nothing is ever half-written.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from pathlib import Path

import numpy as np

from .dataset import DatasetError


def _pattern(text: str) -> tuple[int, int]:
    try:
        a, b = text.lower().split("x")
        return int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected COLSxROWS inner corners like 9x6, got {text!r}") from None


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lidarcal", description=__doc__.splitlines()[0])
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("simulate", help="write a synthetic dataset (with truth.json)")
    s.add_argument("out", type=Path)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--rig", default="paper", help="rig preset: paper, wide, harsh")
    s.add_argument("--positions", type=int, default=None, help="number of turntable positions")
    s.add_argument("--no-sweeps", action="store_true", help="skip the disc-measurement sweeps")
    s.add_argument("--overwrite", action="store_true")

    s = sub.add_parser("intrinsics", help="calibrate camera intrinsics from chessboard photos")
    s.add_argument("images", type=Path, help="folder of chessboard images")
    s.add_argument("--pattern", type=_pattern, required=True, help="inner corners, e.g. 9x6")
    s.add_argument("--square-mm", type=float, required=True)
    s.add_argument("-o", "--out", type=Path, default=None, help="write camera.json here")

    s = sub.add_parser("laser-plane", help="the plane of a line laser from photos of it on a "
                                           "flat chessboard")
    s.add_argument("photos", type=Path, help="folder of lights-on photos of the laser on the board")
    s.add_argument("--pattern", type=_pattern, required=True, help="inner corners, e.g. 8x5 (or 5x8)")
    s.add_argument("--square-mm", type=float, required=True)
    s.add_argument("--camera", type=Path, required=True, help="camera.json (K, dist, image_size)")
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
    s.add_argument("--skip-failed", action="store_true",
                   help="skip positions that cannot be solved (warning) while >= 3 remain")
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

    s = sub.add_parser("report", help="write the PDF calibration report")
    s.add_argument("dataset", type=Path)
    s.add_argument("--out", type=Path, required=True, help="report PDF path")
    s.add_argument("--calibration", type=Path, default=None)
    s.add_argument("--measurements", type=Path, default=None)
    return p


def _cmd_simulate(a: argparse.Namespace) -> int:
    from .synthetic import simulate

    path = simulate(a.out, seed=a.seed, rig=a.rig, n_positions=a.positions,
                    with_sweeps=not a.no_sweeps, overwrite=a.overwrite)
    print(f"wrote dataset {path}")
    return 0


def _cmd_intrinsics(a: argparse.Namespace) -> int:
    from .camera import calibrate_intrinsics
    from .dataset import BoardSpec, write_json_atomic

    if not a.images.is_dir():
        raise DatasetError(a.images, "not a folder of chessboard images")
    paths = sorted(p for p in a.images.iterdir()
                   if p.suffix.lower() in {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
    if not paths:
        raise DatasetError(a.images, "holds no .png/.jpg/.bmp/.tif images")
    res = calibrate_intrinsics(paths, BoardSpec(a.pattern, a.square_mm))
    cam = res.camera
    K, d = cam.K, cam.dist
    print(f"views used {len(res.files)} of {len(paths)}; image {cam.image_size[0]}x{cam.image_size[1]}")
    print(f"fx {K[0, 0]:.3f}  fy {K[1, 1]:.3f}  cx {K[0, 2]:.3f}  cy {K[1, 2]:.3f}")
    print("dist k1 k2 p1 p2 k3: " + " ".join(f"{v:.6f}" for v in d))
    print(f"RMS reprojection error {cam.rms_px:.4f} px")
    if a.out is not None:
        write_json_atomic(a.out, cam.to_dict())
        print(f"wrote {a.out}")
    return 0


def _cmd_laser_plane(a: argparse.Namespace) -> int:
    from .dataset import BoardSpec
    from .laserplane import laser_plane, read_camera_json, write_laser_plane

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


def _cmd_calibrate(a: argparse.Namespace) -> int:
    from .dataset import ImagePrefetch, load_dataset

    ds = load_dataset(a.dataset)
    skip = set(a.skip)
    # decode the stripe images in a background thread while the heavier modules import
    images = ImagePrefetch([p for p in ds.positions if p.index not in skip], ds.image_size,
                           laser_colour=ds.lidar.laser_colour)
    from .pipeline import calibrate, write_calibration

    res = calibrate(ds, skip=a.skip, skip_failed=a.skip_failed,
                    progress=not a.no_progress and sys.stderr.isatty(), method=a.method,
                    images=images)
    for w in res.warnings:
        print(f"warning: {w}", file=sys.stderr)
    path = write_calibration(res, a.out, command=" ".join(["lidarcal", *sys.argv[1:]]))
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

    table = measure_dataset(a.dataset, a.calibration)
    path = write_measurements(table, a.out, a.dataset)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print(f"wrote {path}")
    return 0


def _cmd_report(a: argparse.Namespace) -> int:
    from .report import write_report

    path = write_report(a.dataset, a.out, calibration=a.calibration, measurements=a.measurements,
                        command=" ".join(["lidarcal", *sys.argv[1:]]))
    print(f"wrote {path}")
    return 0


COMMANDS = {"simulate": _cmd_simulate, "intrinsics": _cmd_intrinsics, "calibrate": _cmd_calibrate,
            "laser-plane": _cmd_laser_plane,
            "pose": _cmd_pose, "measure": _cmd_measure, "report": _cmd_report}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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


if __name__ == "__main__":
    sys.exit(main())
