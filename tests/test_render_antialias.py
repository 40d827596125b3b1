"""The simulator's area anti-aliasing against truth: where an edge is rendered, and the V's
corners that board.png then shows (render.subpixel_offsets)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from lidarcal.board import find_v_boards
from lidarcal.io.dataset import BoardSpec, CameraModel, read_image
from lidarcal.synthetic import make_truth, project_points
from lidarcal.synthetic.config import WIDE
from lidarcal.synthetic.render import (
    RayMap,
    albedo_table,
    expose_bright,
    render_view,
    subpixel_offsets,
)
from lidarcal.synthetic.scene import WALL, WHITE, InfinitePlane, Rect
from lidarcal.synthetic.truth import STREAM_BOARD_IMAGE, _rng

N_SUB = 4
SIZE = 48
F, Z = 1000.0, 1000.0


def _rendered_edge_px(edge_px: float, axis: int, pattern: str) -> np.ndarray:
    """Per image column (axis 0: a horizontal edge) or row (axis 1: a vertical one), the edge
    position (px) read from the rendered area: white covers ``[-0.5, edge]`` of the image, the
    wall (albedo ``a``) the rest, so the white area of a line of pixels is
    ``sum (albedo - a) / (1 - a)``. Distortion-free camera: rays and Jacobians are exact."""
    c = (SIZE - 1) / 2.0
    K = np.array([[F, 0.0, c], [0.0, F, c], [0.0, 0.0, 1.0]])
    rays = RayMap.build(K, np.zeros(5), (SIZE, SIZE))
    far = 10.0 * SIZE * Z / F  # mm: beyond the image on the other three sides
    e = (edge_px - c) * Z / F  # the edge on the board, mm
    u, v = np.eye(3)[axis], np.eye(3)[1 - axis]  # v runs across the edge
    board = Rect(np.array([0.0, 0.0, Z]) - far * u + (e - far) * v, u, v, 2 * far, far,
                 plain=WHITE)
    wall = InfinitePlane(np.array([0.0, 0.0, 1.0]), 2 * Z)
    table = albedo_table(WIDE, "bright")
    alb = render_view(rays, [board, wall], table, N_SUB, pattern).albedo.astype(float)
    a = table[WALL]
    return ((alb - a) / (1.0 - a)).sum(axis=axis) - 0.5


@pytest.mark.parametrize("axis", [0, 1])
def test_edges_along_pixel_rows_rendered_where_they_are(axis: int) -> None:
    """An edge along the pixel rows (or columns) at any sub-pixel phase: with the
    multi-jittered pattern its rendered area puts it within half a step 1/n^2 of the truth;
    the regular grid rounds it to steps of 1/n (up to 1/(2n) = 0.125 px off at n = 4)."""
    phases = np.linspace(0.0, 1.0, 23, endpoint=False)
    err = {p: np.array([_rendered_edge_px(20.0 + f, axis, p) - (20.0 + f) for f in phases])
           for p in ("grid", "multi-jittered")}
    assert np.abs(err["multi-jittered"]).max() <= 0.5 / N_SUB ** 2 + 1e-6
    assert np.abs(err["grid"]).max() > 0.1  # the artifact the new pattern removes
    assert np.abs(err["grid"]).max() <= 0.5 / N_SUB + 1e-6


def test_multi_jittered_pattern_is_stratified() -> None:
    """One sample per cell of the n x n grid, n^2 distinct rows and columns, centred."""
    for n in (2, 3, 4, 6):
        o = subpixel_offsets(n, "multi-jittered")
        assert o.shape == (n * n, 2)
        for k in range(2):
            strata = np.floor((o[:, k] + 0.5) * n * n).astype(int)
            assert sorted(strata) == list(range(n * n))
        cells = {tuple(c) for c in np.floor((o + 0.5) * n).astype(int)}
        assert len(cells) == n * n
        assert np.allclose(o.mean(axis=0), 0.0)
    assert np.array_equal(np.unique(subpixel_offsets(4, "grid")[:, 0]), [-0.375, -0.125, 0.125,
                                                                         0.375])
    with pytest.raises(ValueError, match="unknown anti-aliasing pattern"):
        subpixel_offsets(4, "random")


def test_wide_board_png_corners_against_truth() -> None:
    """board.png of the wide rig (seed 37): the V's corners, found with the true camera, against
    the true projections. With the regular grid the corner rows nearest the horizon (their
    square edges along the pixel rows) were 0.08-0.10 px off and board 0 0.030 px rms;
    multi-jittered: 0.008 px rms on both boards (measured), as with 16 x 16 grid samples."""
    rig = WIDE.with_(antialias="multi-jittered", n_positions=3)
    truth = make_truth(37, rig, with_discs=False, with_intrinsics=False)
    cam = CameraModel(np.asarray(truth.K, float), np.asarray(truth.dist, float), rig.image_size)
    spec = BoardSpec(tuple(rig.v_inner_corners), rig.v_square_mm)
    rays = RayMap.build(truth.K, truth.dist, rig.image_size)
    view = render_view(rays, truth.surfaces, albedo_table(rig, "bright"), rig.supersample,
                       rig.antialias)
    img = expose_bright(view.albedo, rig, _rng(37, STREAM_BOARD_IMAGE))
    true_px = [project_points(b.inner_corners_mm(), truth.K, truth.dist) for b in truth.boards]
    for v in find_v_boards(img, spec, cam):
        c = v.corners_px
        t = min(true_px, key=lambda q: float(np.linalg.norm(q.mean(0) - c.mean(0))))
        d = np.linalg.norm(c[:, None] - t[None], axis=2)
        e = c - t[np.argmin(d, axis=1)]
        assert np.sqrt(np.mean(np.sum(e ** 2, axis=1))) < 0.015
        assert np.abs(e).max() < 0.05


def test_cli_simulate_antialias_and_range_noise(tmp_path) -> None:
    """``lidarcal simulate OUT --rig wide --antialias multi-jittered --range-noise-mm 0.5``: the
    low-scan-noise wide variant (issue 13's camera-side study) from the command line; truth.json
    records both, and board.png is the one the multi-jittered pattern renders."""
    out = tmp_path / "w"
    r = subprocess.run([sys.executable, "-m", "lidarcal", "simulate", str(out), "--rig", "wide",
                        "--seed", "2", "--positions", "3", "--no-sweeps", "--no-intrinsics",
                        "--antialias", "multi-jittered", "--range-noise-mm", "0.5"],
                       check=False, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    noise = json.loads((out / "truth.json").read_text())["noise"]
    assert noise["range_noise_mm"] == 0.5
    assert noise["antialias"] == "multi-jittered" and noise["supersample"] == 4
    rig = WIDE.with_(antialias="multi-jittered", n_positions=3)
    truth = make_truth(2, rig, with_discs=False, with_intrinsics=False)
    rays = RayMap.build(truth.K, truth.dist, rig.image_size)
    img = expose_bright(render_view(rays, truth.surfaces, albedo_table(rig, "bright"), 4,
                                    "multi-jittered").albedo, rig, _rng(2, STREAM_BOARD_IMAGE))
    assert np.array_equal(read_image(out / "board.png"), img)
    bad = subprocess.run([sys.executable, "-m", "lidarcal", "simulate", str(tmp_path / "x"),
                          "--antialias", "random"], check=False, capture_output=True,
                         text=True)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr
