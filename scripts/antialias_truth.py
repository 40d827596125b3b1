"""board.png's V corners against truth with the regular and the multi-jittered anti-aliasing.

For each rig preset and seed, board.png is rendered (only it: no dataset is written) with the
regular 4 x 4 grid of sub-pixel samples (the default), the multi-jittered 4 x 4 pattern and
the multi-jittered 8 x 8 (:func:`lidarcal.synthetic.render.subpixel_offsets`); the V's corners
that ``calibrate`` uses (:func:`lidarcal.board.find_v_boards`, with the true camera) are
compared with the true projections of truth's board corners: RMS and max (px) per board.

    .venv/bin/python scripts/antialias_truth.py wide 1 5 37 7
    .venv/bin/python scripts/antialias_truth.py paper 11 3
"""

from __future__ import annotations

import argparse

import numpy as np

from lidarcal.board import find_v_boards
from lidarcal.io.dataset import BoardSpec, CameraModel
from lidarcal.synthetic import make_truth, project_points
from lidarcal.synthetic.config import get_rig
from lidarcal.synthetic.render import RayMap, albedo_table, expose_bright, render_view
from lidarcal.synthetic.truth import STREAM_BOARD_IMAGE, _rng

PATTERNS = (("grid", 4), ("multi-jittered", 4), ("multi-jittered", 8))


def corner_errors(rig_name: str, seed: int, pattern: str, n_sub: int) -> list[np.ndarray]:
    """Per board of the V: found corner minus true projection (N, 2), px."""
    rig = get_rig(rig_name).with_(antialias=pattern, supersample=n_sub, n_positions=3)
    truth = make_truth(seed, rig, with_discs=False, with_intrinsics=False)
    cam = CameraModel(np.asarray(truth.K, float), np.asarray(truth.dist, float), rig.image_size)
    spec = BoardSpec(tuple(rig.v_inner_corners), rig.v_square_mm)
    rays = RayMap.build(truth.K, truth.dist, rig.image_size)
    view = render_view(rays, truth.surfaces, albedo_table(rig, "bright"), n_sub, pattern)
    img = expose_bright(view.albedo, rig, _rng(seed, STREAM_BOARD_IMAGE))
    true_px = [project_points(b.inner_corners_mm(), truth.K, truth.dist) for b in truth.boards]
    out = []
    for v in find_v_boards(img, spec, cam):
        c = v.corners_px
        t = min(true_px, key=lambda q: float(np.linalg.norm(q.mean(0) - c.mean(0))))
        out.append(c - t[np.argmin(np.linalg.norm(c[:, None] - t[None], axis=2), axis=1)])
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rig")
    ap.add_argument("seeds", type=int, nargs="+")
    args = ap.parse_args()
    for seed in args.seeds:
        for pattern, n in PATTERNS:
            cells = [f"board {k}: rms {np.sqrt(np.mean(np.sum(e ** 2, 1))):.4f} max "
                     f"{np.linalg.norm(e, axis=1).max():.4f} px"
                     for k, e in enumerate(corner_errors(args.rig, seed, pattern, n))]
            print(f"{args.rig} seed {seed} {pattern} {n}x{n}: " + " | ".join(cells), flush=True)


if __name__ == "__main__":
    main()
