"""scripts/combo_sweep.py: combos built from the three sweeps' builders, the truth of an
imported bag re-indexed, the outcome classes (no simulation: the sweep itself is a study)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
sys.path.insert(0, str(SCRIPTS))
import combo_sweep as cs


def test_build_combines_the_sweeps_parts():
    """A camera variant, two LiDAR variants and two capture cases make one rig and one case;
    the LiDAR changes land on the camera variant's preset, the turntable keeps its span."""
    c = cs.build(("R:cam_barrel", "L:noise10", "L:encoder0.02", "C:lit60", "C:blur2"), 12)
    assert c.rig.name.startswith("wide") and c.rig.dist[0] == -0.4
    assert c.rig.range_noise_mm == 10.0 and c.rig.encoder_noise_deg == 0.02
    wide = cs.WIDE
    assert c.rig.n_positions == 12
    assert c.rig.psi_step_deg * 11 == pytest.approx(wide.psi_step_deg * (wide.n_positions - 1), abs=1e-3)
    assert c.capture.name == "lit60+blur2" and c.capture.stripes is not None and c.capture.board is None
    assert c.bag is None and not c.sweeps
    # a colour frame goes last, whatever the order given
    assert cs.build(("C:red60", "C:blur2"), 12).capture.name == "blur2+red60"
    assert cs.build(("L:disc_near", "B:png"), 12).sweeps and cs.build(("B:png",), 12).bag == "png"


@pytest.mark.parametrize("parts", [
    ("R:v_tiny_8px", "R:v_small_far"),      # both set the V-board
    ("R:paper", "L:wide"),                  # two presets
    ("C:red60", "C:green120"),              # two colour frames
    ("L:unsorted", "L:psiwrap"),            # two positions.csv rewrites
    ("B:png", "B:raw"),
])
def test_build_refuses_parts_that_conflict(parts):
    with pytest.raises(ValueError):
        cs.build(parts, 12)


def test_random_combos_are_seeded_and_buildable():
    a, b = cs.random_combos(12, 3), cs.random_combos(12, 3)
    assert a == b and len(a) == 12 and a != cs.random_combos(12, 4)
    for parts in a.values():
        assert 2 <= len(parts) <= 4 and not set(parts) & cs._SKIP_RANDOM
        cs.build(parts, 12)


def test_truth_of_an_import_follows_its_numbering(tmp_path):
    """lidarcal import numbers positions in recording order (and unwraps angles): the truth
    pose of each imported row is the one at its angle, modulo 360 deg."""
    folder, imported = tmp_path / "f", tmp_path / "i"
    folder.mkdir(), imported.mkdir()
    poses = [{"index": i, "psi_deg": psi, "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "T_mm": [i, 0, 0]}
             for i, psi in enumerate([358.0, 359.0, 0.5, 1.5])]
    (folder / "truth.json").write_text(json.dumps({"poses": poses, "axis": {}}))
    (imported / "positions.csv").write_text(
        "index,psi_deg,stripe_image,scan\n0,361.5,a,b\n1,358.0,a,b\n2,360.5,a,b\n3,359.0,a,b\n")
    cs._truth_for_import(folder, imported)
    got = json.loads((imported / "truth.json").read_text())
    assert [(p["index"], p["T_mm"][0]) for p in got["poses"]] == [(0, 3), (1, 0), (2, 2), (3, 1)]
    assert got["axis"] == {}


@pytest.mark.parametrize(("row", "want"), [
    ({"cov2s": 1.0, "worst_ratio": 1.5, "centre_mm": 0.2, "n_doubt": 0}, "good"),
    ({"cov2s": 0.9, "worst_ratio": 2.5, "centre_mm": 0.2, "n_doubt": 0}, "good"),
    ({"cov2s": 0.75, "worst_ratio": 5.1, "centre_mm": 0.13, "n_doubt": 0}, "SILENT"),
    ({"cov2s": 0.2, "worst_ratio": 2.8, "centre_mm": 4.6, "n_doubt": 0}, "SILENT"),
    ({"cov2s": 0.75, "worst_ratio": 5.1, "centre_mm": 0.13, "n_doubt": 1}, "warned"),
    ({"cov2s": 0.5, "worst_ratio": 2.5, "centre_mm": 1.5, "n_doubt": 0}, "good-ish"),
])
def test_outcome_classes(row, want):
    assert cs.classify(row) == want


def test_a_skip_or_blur_note_is_no_warning_about_the_result():
    assert not cs.doubting("/x/stripes: the stripe images are blurrier than board.png (an extra "
                           "Gaussian of 2.0 px); the squares' albedo map is blurred to match")
    assert not cs.doubting("/x/stripes/0003.png: board 1: only 52 % of the stripe centres lie on "
                           "one curve (need 60 %); position 3 skipped (--strict stops instead)")
    assert cs.doubting("the joint fit's LiDAR centre is 7.05 mm (4.3 sigma) from the rigid fit's "
                       "at position 11: the joint sigmas understate its error here")


def test_one_line_refusal_and_traceback():
    ok = subprocess.CompletedProcess([], 2, "", "error: /x/board.png: found 0 of the 2 chessboards\n")
    assert cs._failure(ok)[0] == "refused"
    tb = subprocess.CompletedProcess([], 1, "", "Traceback (most recent call last):\n  x\nKeyError: 1\n")
    assert cs._failure(tb)[0] == "CRASH"
    listed = subprocess.run([sys.executable, str(SCRIPTS / "combo_sweep.py"), "--hand", "--list"],
                            capture_output=True, text=True, check=False)
    assert listed.returncode == 0 and "bag_lit_frames" in listed.stdout
