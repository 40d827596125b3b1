"""The camera from the photos, refined with the V's boards of board.png (add_views), against
the truth of a small simulated wide-angle rig; its quality checks."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from lidarcal.camera import add_views, project_points
from lidarcal.evaluate import match_planes, plane_error, truth_board_planes, truth_camera
from lidarcal.io.dataset import load_dataset
from lidarcal.pipeline import camera_for, find_boards
from lidarcal.synthetic import simulate


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    """Wide rig (k1 = -0.30), 3 positions: its 18 photos, board.png and truth."""
    path = simulate(tmp_path_factory.mktemp("wide") / "w5", seed=5, rig="wide", n_positions=3,
                    with_sweeps=False)
    ds = load_dataset(path)
    return ds, json.loads((path / "truth.json").read_text()), camera_for(ds)


def test_v_boards_join_the_camera_and_planes_match_truth(wide) -> None:
    """Both boards of board.png join the fit (listed in camera.json with their RMS, near the
    corners' noise); the V planes with that camera are within 0.06 deg and 0.4 mm of truth
    (measured on seeds 37, 39, 1: at most 0.018 deg and 0.14 mm)."""
    ds, truth, (cam, intr) = wide
    assert intr is not None and not intr.warnings
    d = intr.to_dict()
    assert [v["name"] for v in d["extra_views"]] == ["board.png board 0", "board.png board 1"]
    assert all(0 < v["rms_px"] < 0.1 for v in d["extra_views"])
    tc = truth_camera(truth, ds.image_size)
    assert abs(cam.K[0, 0] / tc.K[0, 0] - 1) < 5e-4 and abs(cam.K[1, 1] / tc.K[1, 1] - 1) < 5e-4
    TB = truth_board_planes(truth)
    boards = find_boards(ds, cam)
    planes = [b.plane_pnp for b in boards]
    for pl, m in zip(planes, match_planes(planes, TB)):
        e = plane_error(pl, TB[m])
        assert e["normal_deg"] < 0.06 and e["offset_mm"] < 0.4


def test_a_view_of_another_camera_is_left_out(wide) -> None:
    """A board seen by another lens (k1 -0.25 instead of -0.30) or with one corner 3 px off
    does not join: a warning names it and the camera is the photos' own."""
    ds, truth, (_, intr) = wide
    res = replace(intr, extra_views=(), warnings=())  # the photos' points, a good camera
    tc = truth_camera(truth, ds.image_size)
    other = type(tc)(tc.K, np.array([-0.25, 0.12, 0.0008, -0.0006, -0.02]), tc.image_size)
    obj = ds.v_board.object_points()
    b = truth["boards"][0]
    P = np.asarray(b["inner_corners_mm"], float)
    far = project_points(other, P)
    planted = project_points(tc, P)
    planted[20] += [3.0, 0.0]
    out = add_views(res, [far, planted], [obj, obj], ["far", "planted"],
                    [ds.v_board.pattern_size] * 2)
    assert len(out.warnings) == 2
    assert "far:" in out.warnings[0] and "planted:" in out.warnings[1]
    assert not out.extra_views and np.array_equal(out.camera.K, res.camera.K)
    # the same board's true corners (plus 0.03 px noise) do join
    ok = add_views(res, [project_points(tc, P)
                         + np.random.default_rng(1).normal(0, 0.03, planted.shape)],
                   [obj], ["true"], [ds.v_board.pattern_size])
    assert not ok.warnings and [n for n, _ in ok.extra_views] == ["true"]
