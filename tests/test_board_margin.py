"""The physical board's margins measured in the photos (lidarcal.board_margin)."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.board_margin import SIDES, combine_margins, measure_margins, side_edges
from lidarcal.io.dataset import BoardSpec, parse_camera, read_json_object
from lidarcal.planes import board_plane, choose_corner_set, find_board
from lidarcal.synthetic.oneboard import render_photo, simulate_oneboard

TAPAS = Path(__file__).resolve().parents[1] / "data" / "real_tapas"


@pytest.mark.parametrize("seed,margin", [(0, 60.0), (1, 40.0)])
def test_margins_match_the_simulator(seed, margin):
    rig = simulate_oneboard(seed, 3, margin_mm=margin)
    per_view = []
    for k, v in enumerate(rig.views):
        bp = board_plane(rig.camera, v.corners_px, rig.board)
        per_view.append(side_edges(render_photo(rig, v, k), rig.camera, bp.R, bp.T, rig.board))
    m = combine_margins(per_view)
    for side in SIDES:  # 1 mm resampling; corners at 0.2 px: the edge within 2 mm
        assert m.margin_mm[side] is not None, side
        assert abs(m.margin_mm[side] - margin) <= 2.0, (side, m.margin_mm[side])
        assert m.grown(side, 999.0) < 999.0


def test_tapas_margins_agree_across_views():
    cam = parse_camera(read_json_object(TAPAS / "camera.json", "", ""), TAPAS / "camera.json")
    board = BoardSpec((8, 5), 100.0)
    images, poses, boards = [], [], []
    for png in sorted(TAPAS.glob("*.png")):
        img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
        found = find_board(img, board)
        bp = choose_corner_set([board_plane(cam, c, b) for c, b in found])
        images.append(img)
        poses.append((bp.R, bp.T))
        boards.append(bp.board)
    m = measure_margins(images, cam, poses, boards)
    # the top edge is in every photo: every view finds it within a few mm of the median
    top = [e["top"].margin_mm for e in m.per_view if "top" in e]
    assert len(top) == len(images)
    assert m.margin_mm["top"] is not None and 40.0 < m.margin_mm["top"] < 65.0
    assert np.all(np.abs(np.array(top) - m.margin_mm["top"]) <= 3.0), top
    for side in SIDES:  # accepted sides are well inside today's assumed margin (300 mm)
        assert m.margin_mm[side] is None or m.grown(side, 300.0) < 100.0
