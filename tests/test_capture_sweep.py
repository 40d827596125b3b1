"""scripts/capture_sweep.py (perturbed captures -> calibrate -> truth) on one small case."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "capture_sweep.py"


def test_capture_sweep_one_case(small_dataset, tmp_path):
    """A bright reflection beside the stripe of every frame of the 4-position paper rig:
    calibrate uses every position and the truth lies within 2 sigma (the row says so); the
    perturbed copy is written beside the dataset's own files (hard links) and kept."""
    out = tmp_path / "rows.csv"
    r = subprocess.run([sys.executable, str(SCRIPT), str(small_dataset), "--work",
                        str(tmp_path / "work"), "--cases", "blob255", "--csv", str(out), "--keep"],
                       capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(out.open()))
    assert [row["case"] for row in rows] == ["blob255"]
    row = rows[0]
    assert row["exit"] == "0" and row["used"] == "4" and row["skipped"] == "0", row
    assert float(row["cov2s"]) == 1.0 and float(row["centre_mm"]) < 0.5, row
    case = tmp_path / "work" / "blob255"
    assert (case / "out" / "calibration.json").is_file()
    scan = min((case / "scans").iterdir())
    assert scan.samefile(small_dataset / "scans" / scan.name)  # hard-linked, not copied
    stripe = min((case / "stripes").glob("*.png"))
    assert stripe.stat().st_ino != (small_dataset / "stripes" / stripe.name).stat().st_ino
    listed = subprocess.run([sys.executable, str(SCRIPT), "--list"], capture_output=True,
                            text=True, check=False)
    assert listed.returncode == 0 and "png_16bit" in listed.stdout.split()
