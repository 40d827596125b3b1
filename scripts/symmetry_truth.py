"""board.png's V corners with and without the point-symmetry refinement, against truth.

Datta, Kim, Kanade (2009) refinement as ``find_v_boards`` applies it
(:func:`lidarcal.board.symmetric_refinement`, :mod:`lidarcal.corner_symmetry`) beside the
corners ``sharpest_corners`` keeps without it (detector or SB accuracy): corner RMS (px)
against the true projections, the V planes' solvePnP errors (normal deg, offset mm), with
the camera ``calibrate`` uses (dataset.json's, or the intrinsics photos plus the V's boards
by :func:`lidarcal.pipeline.camera_for`, itself with and without the refinement of the V's
and of the photos' corners) and with the true camera; and the refinement's CPU time per
board.png (both boards, best of 5).

    .venv/bin/python scripts/symmetry_truth.py /tmp/w37 [/tmp/w39 ...]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

import lidarcal.board as board_mod
import lidarcal.camera as camera_mod
from lidarcal.board import find_v_boards, plane_from_pose, pose_pnp, symmetric_refinement
from lidarcal.camera import project_points
from lidarcal.corners import _gray
from lidarcal.evaluate import plane_error, truth_board_planes, truth_camera
from lidarcal.io.dataset import load_dataset, read_image
from lidarcal.pipeline import camera_for


def with_refinement(refine: bool, f, *args):
    """``f(*args)`` with the symmetric refinement of the V's corners (``sharpest_corners``)
    and of the intrinsics photos' corners (``calibrate_intrinsics``) switched on or off."""
    keep = board_mod.SYMMETRIC_REFINEMENT, camera_mod.SYMMETRIC_PHOTOS
    board_mod.SYMMETRIC_REFINEMENT = camera_mod.SYMMETRIC_PHOTOS = refine
    try:
        return f(*args)
    finally:
        board_mod.SYMMETRIC_REFINEMENT, camera_mod.SYMMETRIC_PHOTOS = keep


def refinement_cpu_s(gray: np.ndarray, views, ds, cam) -> float:
    """CPU seconds of :func:`symmetric_refinement` on both boards (best of 5)."""
    best = np.inf
    for _ in range(5):
        t0 = time.process_time()
        for v in views:
            symmetric_refinement(gray, v.corners_px, ds.v_board, cam)
        best = min(best, time.process_time() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", type=Path, nargs="+")
    args = ap.parse_args()
    pd.set_option("display.width", 220)
    pd.set_option("display.max_rows", 500)
    rows, cpu = [], {}
    for path in args.datasets:
        truth = json.loads((path / "truth.json").read_text())
        ds = load_dataset(path)
        tcam = truth_camera(truth, ds.image_size)
        img = read_image(ds.board_image, ds.image_size)
        TB = truth_board_planes(truth)
        tcorners = [project_points(tcam, np.asarray(b["inner_corners_mm"], float))
                    for b in truth["boards"]]
        obj = ds.v_board.object_points()
        cams = {"true": {False: tcam, True: tcam}}
        cams["calibrate"] = {r: with_refinement(r, camera_for, ds)[0] for r in (False, True)}
        for cname, by_refine in cams.items():
            for refine in (False, True):
                cam = by_refine[refine]
                views = with_refinement(refine, find_v_boards, img, ds.v_board, cam)
                if cname == "calibrate" and not refine:
                    cpu[path.name] = refinement_cpu_s(_gray(img), views, ds, cam)
                for v in views:
                    c = v.corners_px
                    tb = min(range(2), key=lambda k: np.linalg.norm(tcorners[k].mean(0)
                                                                    - c.mean(0)))
                    d = np.linalg.norm(c[:, None] - tcorners[tb][None], axis=2)
                    e = c - tcorners[tb][np.argmin(d, axis=1)]
                    R, T = pose_pnp(cam, c, obj)
                    pe = plane_error(plane_from_pose(R, T), TB[tb])
                    rows.append({"dataset": path.name, "camera": cname, "board": tb,
                                 "refined": refine,
                                 "rms_px": float(np.sqrt(np.mean(np.sum(e ** 2, 1)))),
                                 "normal_deg": pe["normal_deg"], "offset_mm": pe["offset_mm"]})
        print(pd.DataFrame([r for r in rows if r["dataset"] == path.name]).round(4)
              .to_string(index=False), f"\nrefinement CPU {1000 * cpu[path.name]:.1f} ms",
              flush=True)
    df = pd.DataFrame(rows)
    cols = ["rms_px", "normal_deg", "offset_mm"]
    print(df.groupby(["camera", "dataset", "refined"], sort=False)[cols].mean().round(4)
          .unstack("refined").to_string())
    print(df.groupby(["camera", "refined"], sort=False)[cols].mean().round(4))
    print("refinement CPU ms per board.png:", {k: round(1000 * v, 1) for k, v in cpu.items()})


if __name__ == "__main__":
    main()
