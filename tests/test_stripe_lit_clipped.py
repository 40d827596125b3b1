"""Stripe frames taken with the room lights on and the laser overexposed (the acceptance's
"harsher captures"): the lit board near the clip level, a clipped and blooming stripe, hot
pixels. The stripe centres are checked against the true stripe line of truth.json
(:func:`lidarcal.evaluate.stripe_errors_px`) on the harsh rig, whose stripe is dim on black
squares and runs along square edges: each board's stripe passes its gates with centres on
the truth, or fails them (a skip), never wrong centres."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.board import find_boards
from lidarcal.evaluate import match_planes, stripe_errors_px, truth_board_planes
from lidarcal.io.dataset import load_dataset, read_stripe_image
from lidarcal.pipeline import matched_albedo
from lidarcal.stripe import _board_inputs, board_stripe_centres
from lidarcal.stripe_profile import _coarse_line, _noise_sigma, _saturated_centres
from lidarcal.synthetic import simulate

SWEEP = Path(__file__).resolve().parents[1] / "scripts" / "capture_sweep.py"


def _sweep():
    """scripts/capture_sweep.py as a module (its perturbations, as the sweep applies them)."""
    if "capture_sweep" not in sys.modules:
        spec = importlib.util.spec_from_file_location("capture_sweep", SWEEP)
        mod = importlib.util.module_from_spec(spec)
        sys.modules["capture_sweep"] = mod  # (its dataclasses look their module up)
        spec.loader.exec_module(mod)
    return sys.modules["capture_sweep"]


@pytest.fixture(scope="module")
def harsh3(tmp_path_factory):
    """The harsh rig, 3 positions: dataset, truth, clean board image and stripe images."""
    root = simulate(tmp_path_factory.mktemp("harsh") / "h3", seed=61, rig="harsh",
                    n_positions=3, with_intrinsics=False, with_sweeps=False)
    ds = load_dataset(root)
    board = cv2.imread(str(ds.board_image), cv2.IMREAD_GRAYSCALE)
    stripes = [cv2.imread(str(p.stripe_image), cv2.IMREAD_GRAYSCALE) for p in ds.positions]
    return ds, json.loads((root / "truth.json").read_text()), board, stripes


def _perturbed(harsh3, tmp_path, gain, bloom, level, hot):
    """A copy of the stripe frames as capture_sweep's saturate(gain, bloom) + lights_on(level)
    (+ hot_pixels(hot)) writes them; the dataset with those frames."""
    cs = _sweep()
    ds, truth, board, stripes = harsh3
    fs = [cs.saturate(gain, bloom), cs.lights_on(level)] + ([cs.hot_pixels(hot)] if hot else [])
    f = cs.compose(*fs)
    out = []
    for pos, img in zip(ds.positions, stripes):
        p = tmp_path / f"{pos.index:04d}.png"
        cv2.imwrite(str(p), f(img, cs.Ctx(board, np.random.default_rng([0, pos.index, 0]),
                                          pos.index, truth)))
        out.append(read_stripe_image(p, ds.camera.image_size))
    return out


#: per board, measured with the fix on these 3 positions under the three cases below:
#: rms 0.34-0.60 px, |mean| <= 0.15 px from the true stripe (the clean frames of the
#: 15-position seed-61 harsh rig, positions 0-2: rms 0.43-0.49 px, |mean| <= 0.09 px; the
#: old code's boards that passed their gates under lit120_sat_hot: 7.5 px rms): bounds 1.25 x
#: the largest rms and 1.6 x the largest |mean| measured
RMS_PX, MEAN_PX = 0.75, 0.25


@pytest.mark.parametrize("gain,bloom,level,hot,must_pass", [
    (3.0, 0.3, 120, 300, True),    # capture_sweep's lit120_sat_hot (the old code: "not one
                                   # smooth curve" on every board, 5-9 px off the truth)
    (2.5, 0.8, 150, 0, True),      # the old code: "not one smooth curve"
    (4.0, 0.8, 120, 300, False),   # white squares 2 noise sigmas below the clip: the old code
                                   # found no stripe; now found, some boards judged faint
])
def test_lit_clipped_stripe_on_truth(harsh3, tmp_path, gain, bloom, level, hot, must_pass):
    ds, truth, _, _ = harsh3
    images = _perturbed(harsh3, tmp_path, gain, bloom, level, hot)
    boards = find_boards(ds, ds.camera)
    boards, rho, _ = matched_albedo(ds.camera, boards, ds.positions)
    order = match_planes([b.plane for b in boards], truth_board_planes(truth))
    passed = 0
    for pos, img in zip(ds.positions, images):
        centres, _, problems = board_stripe_centres(ds.camera, img, boards, rho=rho)
        for k in range(2):
            assert len(centres[k]) > 100, (pos.index, k, problems[k])
            e = stripe_errors_px(centres[k], truth, pos.index, order[k], ds.camera.image_size)
            if problems[k] is None or not must_pass:
                # the centres a calibration may use (and here also those judged faint) lie
                # on the true stripe
                assert np.sqrt(np.mean(e ** 2)) < RMS_PX and abs(e.mean()) < MEAN_PX, \
                    (pos.index, k, float(np.sqrt(np.mean(e ** 2))), float(e.mean()))
            passed += problems[k] is None
            if must_pass:
                assert problems[k] is None, (pos.index, k, problems[k])
            else:
                assert problems[k] is None or "faint" in problems[k], problems[k]
    assert passed >= (6 if must_pass else 1)


def test_coarse_line_of_a_clipped_stripe(harsh3, tmp_path):
    """Lights so bright that the white squares lie 2 noise sigmas below the clip: no
    threshold above the background separates the stripe; its clipped core gives the coarse
    line, within a few px of the truth along the board."""
    ds, truth, _, _ = harsh3
    img = _perturbed(harsh3, tmp_path, 4.0, 0.8, 120, 300)[0]
    boards = find_boards(ds, ds.camera)
    order = match_planes([b.plane for b in boards], truth_board_planes(truth))
    for k, (sub, msub, _, origin) in enumerate(_board_inputs(img, boards, False)):
        line = _coarse_line(sub, msub, _noise_sigma(sub, msub, sub), sub)
        assert line is not None
        c, t = line
        xs = np.flatnonzero(msub.any(axis=0))
        x = np.linspace(xs[0], xs[-1], 9)
        pts = np.column_stack([x, c[1] + t[1] / t[0] * (x - c[0])]) + np.asarray(origin, float)
        e = stripe_errors_px(pts, truth, ds.positions[0].index, order[k], ds.camera.image_size)
        assert np.abs(e).max() < 3.0, e


def test_saturated_centre_on_a_square_edge():
    """A clipped symmetric stripe over a lit board: backgrounds 200 DN (white) and 40 DN
    (black) leave 55 and 215 DN of headroom, the stripe 0.3 times as bright on black. On
    one square, or with an edge beyond the run's flanks, the centre is the stripe's (to
    the linear interpolation of its flanks); when an edge lies under the run (the core on
    black, its tail on white clipped) the profile is dropped (NaN), never pulled towards
    the white side."""
    j = np.arange(61, dtype=float)
    centre = 30.3
    stripe = 400 * np.exp(-0.5 * ((j - centre) / 2.5) ** 2)
    rows, bl = [], []
    for blk in (np.zeros_like(j), (j < 10).astype(float), (j >= 45).astype(float),
                (j < 31).astype(float), (j < 33).astype(float)):
        rows.append(np.minimum(200 - 160 * blk + stripe * (1 - 0.7 * blk), 255.0))
        bl.append(blk)
    prof, bprof = np.array(rows), np.array(bl)
    s = prof - (200 - 160 * bprof)
    cen = np.full(len(prof), centre + 1.0)  # a centroid pulled off the centre
    got, peak = _saturated_centres(prof, s, cen, np.full(len(prof), 55.0), bprof, noise=3.0)
    assert np.all(np.abs(got[:3] - centre) < 0.05), got  # one square; edges far
    assert np.isnan(got[3]) and np.isnan(got[4]), got  # an edge under the run: dropped
    assert np.all(peak[:3] > 55.0 * np.sqrt(3))  # the headroom times the plateau's root length
    # without a blackness map the run is taken as it is (the albedo cannot be judged)
    got, _ = _saturated_centres(prof, s, cen, np.full(len(prof), 55.0))
    assert np.all(np.isfinite(got)) and abs(got[0] - centre) < 0.05
