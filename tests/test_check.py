"""``lidarcal check``: the per-position detections without the fits, its exit status and sheet."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lidarcal.check import check_dataset, saturated_share
from lidarcal.evaluate import truth_board_planes, truth_laser_plane, truth_poses


def lidarcal(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "lidarcal", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, check=False)


def test_good_dataset_is_usable_and_the_sheet_is_written(small_dataset, tmp_path):
    r = lidarcal("check", small_dataset, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "usable: every detection succeeded at all 4 positions" in r.stdout
    assert r.stderr == ""
    sheet = tmp_path / f"{small_dataset.name}-check.png"  # the default: beside the caller
    img = cv2.imread(str(sheet))
    assert img is not None and img.shape[1] > img.shape[0]  # one A4 landscape page
    for row in (small_dataset / "positions.csv").read_text().splitlines()[1:]:
        assert f"{float(row.split(',')[1]):.2f}" in r.stdout  # every position's angle is listed


def test_detections_agree_with_the_truth(small_dataset):
    """The stripe lines' angle alpha (section 1.3) from the check's centres matches the angle
    between the true stripe lines; both sides of the V are found in every scan."""
    res = check_dataset(small_dataset)
    truth = json.loads((small_dataset / "truth.json").read_text())
    n1, n2 = (p.normal for p in truth_board_planes(truth)[:2])
    assert res.usable and len(res.positions) == 4
    for p in res.positions:
        nL = truth_laser_plane(truth_poses(truth)[p.index]).normal
        l1, l2 = np.cross(n1, nL), np.cross(n2, nL)
        acute = np.degrees(np.arccos(abs(l1 @ l2) / np.linalg.norm(l1) / np.linalg.norm(l2)))
        alpha_true = 180.0 - acute  # the stripes leave E in opposite senses: the V's obtuse opening
        assert abs(p.alpha_deg - alpha_true) < 0.2, (p.index, p.alpha_deg, alpha_true)
        assert min(p.n_centres) > 100 and min(p.v_points) > 50
        assert p.saturated_share == 0.0  # the simulator's stripe peaks at 235 DN
        assert abs(p.v_opening_deg - p.alpha_deg) < 1.0  # scan and camera see the same V


def test_saturated_share_counts_clipped_core_pixels():
    img = np.zeros((20, 30), np.uint8)
    img[9:12, :] = 200
    img[9:12, :6] = 255  # 6 of 30 columns clipped
    centres = np.column_stack([np.arange(30) + 0.2, np.full(30, 10.1)])
    assert saturated_share(img, centres) == pytest.approx(6 / 30)
    assert saturated_share(img, np.empty((0, 2))) == 0.0
    # the clipped columns' centres dropped (lidarcal.stripe_clipped drops clipped profiles that
    # cross a square edge): the stripe is read there between its neighbours all the same
    kept = centres[[0, *range(6, 30)]]
    assert saturated_share(img, kept) == pytest.approx(6 / 30)
    # one stripe per board: the gap between the boards (columns 17-18) is not read
    assert saturated_share(img, [kept[:12], kept[14:]]) == pytest.approx(6 / 28)


def test_a_dark_stripe_image_is_a_problem_naming_it(dataset_copy, tmp_path):
    bad = dataset_copy / "stripes" / "0002.png"
    cv2.imwrite(str(bad), np.zeros_like(cv2.imread(str(bad), cv2.IMREAD_UNCHANGED)))
    r = lidarcal("check", dataset_copy, "--sheet", tmp_path / "sheet.pdf")
    assert r.returncode == 1, r.stdout + r.stderr
    problems = [ln for ln in r.stdout.splitlines() if ln.startswith("problem:")]
    assert problems and all("0002.png" in ln and "--skip 2" in ln for ln in problems)
    assert (tmp_path / "sheet.pdf").read_bytes()[:5] == b"%PDF-"


def test_a_saturated_stripe_is_a_problem(dataset_copy):
    path = dataset_copy / "stripes" / "0001.png"
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(path), np.clip(img.astype(np.int32) * 3, 0, 255).astype(np.uint8))
    r = lidarcal("check", dataset_copy, "--no-sheet", cwd=dataset_copy)
    assert r.returncode == 1
    assert "0001.png" in r.stdout and "saturated; lower the exposure" in r.stdout
    assert not list(dataset_copy.glob("*-check.png"))  # --no-sheet writes none


def test_saturated_stripes_are_problems_but_the_positions_still_count(dataset_copy):
    # calibrate uses saturated stripes (their centres come from the unclipped flanks), so check
    # must not call every position unusable when all are saturated, only name each image
    for path in sorted((dataset_copy / "stripes").glob("*.png")):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), np.clip(img.astype(np.int32) * 3, 0, 255).astype(np.uint8))
    res = check_dataset(dataset_copy)
    assert not res.usable
    assert all(p.detected and not p.ok and p.saturated_share > 0.05 for p in res.positions)
    assert not any("usable position" in p for p in res.problems), res.problems
    assert sum("saturated; lower the exposure" in p for p in res.all_problems) == 4


def test_a_corrupt_stripe_image_and_a_missing_scan_are_problems(dataset_copy):
    (dataset_copy / "stripes" / "0000.png").write_bytes(b"not a png")
    (dataset_copy / "scans" / "0003.csv").unlink()
    res = check_dataset(dataset_copy)
    assert not res.usable
    text = "\n".join(res.all_problems)
    assert "0000.png: cannot be decoded" in text and "0003.csv: missing scan" in text
    assert res.positions[1].ok and res.positions[2].ok


def test_unreadable_dataset_exits_2_with_one_line(dataset_copy):
    (dataset_copy / "dataset.json").write_text("{not json")
    r = lidarcal("check", dataset_copy, "--no-sheet")
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "dataset.json: not valid JSON" in lines[0]


def test_readme_own_rig_commands(dataset_copy, tmp_path):
    """The README's "Calibrate your own rig" sequence after the import: check, calibrate, report
    (the workbook step is tests/test_workbook.py, the import tests/ the bag reader's)."""
    out = tmp_path / "OUT"
    r = lidarcal("check", dataset_copy, cwd=tmp_path)
    assert r.returncode == 0 and (tmp_path / f"{dataset_copy.name}-check.png").is_file(), r.stdout
    r = lidarcal("calibrate", dataset_copy, "--out", out)
    assert r.returncode == 0, r.stderr
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["format"] == "lidarcal-calibration/1" and len(cal["poses"]) == 4
    r = lidarcal("report", dataset_copy, "--out", out / "report.pdf")
    assert r.returncode == 0, r.stderr
    assert (out / "report.pdf").read_bytes()[:5] == b"%PDF-"


@pytest.mark.parametrize("content", [b"not a png", None], ids=["corrupt", "missing"])
def test_an_unreadable_board_image_is_exit_2_naming_it_like_a_missing_one(dataset_copy, tmp_path,
                                                                          content):
    # board.png is always fatal (README): a corrupt one was a listed problem (exit 1) while a
    # missing one was exit 2
    board = dataset_copy / "board.png"
    if content is None:
        board.unlink()
    else:
        board.write_bytes(content)
    r = lidarcal("check", dataset_copy, "--sheet", tmp_path / "sheet.png")
    assert r.returncode == 2, r.stdout + r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith(f"error: {board}: ")
    assert "Traceback" not in r.stderr and not (tmp_path / "sheet.png").exists()


def test_angles_wrapping_at_360_are_one_sweep_as_calibrate_reads_them(dataset_copy):
    """A controller that wraps at 360 deg (found by scripts/cleanroom_rig.py, coarse_lidar):
    `check` reported a 12-deg sweep through 0 as a span of 358 deg with steps "from 0.52 to
    348.5 deg" (and could not warn about a short span); it now reads the angles as calibrate
    does, one sweep, and says so naming positions.csv."""
    import csv

    from lidarcal.workbook import summarise_dataset

    before = check_dataset(dataset_copy)
    s0 = summarise_dataset(before.dataset)
    path = dataset_copy / "positions.csv"
    rows = list(csv.DictReader(path.open()))
    lo = min(float(r["psi_deg"]) for r in rows)
    for r in rows:  # the same steps, the sweep starting 0.3 deg before the wrap
        r["psi_deg"] = f"{(float(r['psi_deg']) - lo + 359.7) % 360.0:.4f}"
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    psis = [float(r["psi_deg"]) for r in rows]
    assert min(psis) < 1.0 and max(psis) > 359.0
    after = check_dataset(dataset_copy)
    s1 = summarise_dataset(after.dataset)
    assert after.usable
    assert s1.psi_max_deg - s1.psi_min_deg == pytest.approx(s0.psi_max_deg - s0.psi_min_deg, abs=1e-3)
    assert s1.psi_step_deg == pytest.approx(s0.psi_step_deg, abs=1e-3)
    assert any("wraps at 360 deg" in n and "positions.csv" in n for n in after.notes)
    assert not any("angle steps vary" in n for n in after.notes)
