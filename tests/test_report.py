"""The PDF report and the workbook converter.

The numbers in the report's typst source must equal those computed from
calibration.json / measurements.json by an independent route
(lidarcal.turntable.table1 on the stored pose functions; plain numpy on the
measurement rows).
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidarcal.geometry import unit
from lidarcal.io.dataset import BoardSpec, CameraModel, Dataset, LidarSpec, Position
from lidarcal.report import (
    DECIMALS,
    PAPER_TABLE1,
    ReportInputs,
    build_report_source,
    fnum,
    table1,
    table2,
    write_report,
)
from lidarcal.turntable import Axis, RigidModel, fit_paper, fit_rigid, perturb_pose
from lidarcal.turntable import table1 as turntable_table1

ROOT = Path(__file__).resolve().parent.parent
PDF_MAGIC = b"%PDF-"


def _truth_model(rng: np.random.Generator) -> RigidModel:
    k = unit(np.array([0.0, -1.0, 0.0]) + rng.normal(0, 0.05, 3))
    axis = Axis.from_point_direction(np.array([50.0, 0.0, 1200.0]) + rng.normal(0, 20, 3), k)
    # LiDAR upright: z along -y of the camera, x roughly along camera x
    R = np.column_stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    return RigidModel(axis, 0.0, R, axis.point + np.array([60.0, -30.0, -80.0]))


def _fake(seed: int, n: int = 15, trials: int = 4):
    """A calibration.json / measurements.json / truth.json triple without the pipeline."""
    rng = np.random.default_rng(seed)
    truth_m = _truth_model(rng)
    psi = np.round(np.linspace(0.0, 21.5, n), 4)
    true = truth_m.pose(psi)
    samples = [perturb_pose(p, rng, 0.5, 0.03, 0.08) for p in true]
    paper = fit_paper(psi, samples)
    rigid = fit_rigid(psi, samples, init=paper)

    def rows(poses):
        return [{"index": i, "psi_deg": float(p), **q.to_dict()} for i, (p, q) in
                enumerate(zip(psi, poses))]

    cal = {"format": "lidarcal-calibration/1", "dataset": "/nowhere/fake",
           "camera": {"K": [[2757.4, 0, 831.6], [0, 2758.6, 638.9], [0, 0, 1]],
                      "dist": [-0.076, 0.371, 0, 0, 0], "source": "dataset.json",
                      "image_size": [1624, 1234]},
           "axis": rigid.axis.to_dict(),
           "samples": [{**r, "rotation_residual": 1e-6, "alpha_deg": 120.0} for r in rows(samples)],
           "poses": rows(rigid.pose(psi)), "model": rigid.to_dict(), "method": "rigid",
           "model_paper": paper.to_dict(), "poses_paper": rows(paper.pose(psi)),
           "boards": [{"normal": [0.5, 0, -0.866], "d_mm": -900.0, "reprojection_rms_px": [0.1, 0.09]},
                      {"normal": [-0.5, 0, -0.866], "d_mm": -905.0, "reprojection_rms_px": [0.1, 0.1]}],
           "skipped": [{"index": 99, "reason": "scans/0099.csv: found 1 board segment"}],
           "warnings": ["a warning with under_scores and #hash and $dollar"],
           "provenance": {"lidarcal_version": "0.1.0", "dataset_sha256": "0" * 64,
                          "command": "lidarcal calibrate fake --out x"}}
    truth = {"axis": {"point_mm": truth_m.axis.point.tolist(),
                      "direction": truth_m.axis.direction.tolist()},
             "poses": rows(true),
             "measurements": [{"name": f"trial_{j + 1:02d}", "diameter_mm": 140.0}
                              for j in range(trials)]}
    d = 140.0 + rng.normal(0, 1.5, trials)
    meas = {"format": "lidarcal-measurements/1",
            "measurements": [{"name": f"trial_{j + 1:02d}", "diameter_mm": float(d[j]),
                              "reference_diameter_mm": 140.0, "error_mm": float(d[j] - 140.0),
                              "center_mm": [0, 0, 1500], "normal": [0, 0, -1], "points": 4000,
                              "naive_diameter_mm": float(d[j] - 2.0)} for j in range(trials)]}
    models = {"paper": paper, "rigid": rigid}
    return cal, truth, meas, psi, samples, true, models


def _fake_dataset(tmp_path: Path) -> Dataset:
    pos = [Position(i, 0.25 * i, tmp_path / f"stripes/{i:04d}.png", tmp_path / f"scans/{i:04d}.csv")
           for i in range(15)]
    cam = CameraModel(np.array([[2757.4, 0, 831.6], [0, 2758.6, 638.9], [0, 0, 1]]),
                      np.array([-0.076, 0.371, 0, 0, 0]), (1624, 1234))
    return Dataset(tmp_path, cam, None, BoardSpec((14, 20), 20.0),
                   LidarSpec(-35.0, 35.0, 1 / 12, 700.0, 3000.0), pos, [], (1624, 1234))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_table1_equals_independent_computation(seed):
    cal, truth, _, psi, samples, true, models = _fake(seed)
    t1 = table1(cal, truth)
    assert t1.loc["paper (published)", "centre_mm_mean"] == PAPER_TABLE1["centre_mm"][0]
    for kind, m in models.items():
        for ref_name, ref in (("samples", samples), ("truth", true)):
            want = turntable_table1(m, psi, ref)
            row = t1.loc[f"{kind} function vs {ref_name}"]
            for c in ("centre_mm", "z_axis_deg", "x_axis_deg"):
                # json round trip of the poses: agreement to float precision
                assert row[f"{c}_mean"] == pytest.approx(want[c].mean(), rel=1e-9, abs=1e-9)
                assert row[f"{c}_max"] == pytest.approx(want[c].max(), rel=1e-9, abs=1e-9)
    # the rigid model is fitted with the known angles: it beats the noisy samples against truth
    assert t1.loc["rigid function vs truth", "centre_mm_mean"] < \
        t1.loc["samples vs truth", "centre_mm_mean"]


def test_table2_summary():
    _, truth, meas, *_ = _fake(3, trials=7)
    df, s = table2(meas, truth)
    d = np.array([m["diameter_mm"] for m in meas["measurements"]])
    assert s["trials"] == 7
    assert s["mean_diameter_mm"] == pytest.approx(d.mean())
    assert s["mean_error_mm"] == pytest.approx((d - 140).mean())
    assert s["mean_abs_error_mm"] == pytest.approx(np.abs(d - 140).mean())
    assert s["naive_mean_abs_error_mm"] == pytest.approx(np.abs(d - 142).mean())
    assert list(df["name"]) == [m["name"] for m in meas["measurements"]]


def _table1_block(src: str) -> str:
    i = src.index("Table 1: fitted pose function")
    return src[i:src.index("\n)]", i)]


def test_source_numbers_match_json(tmp_path):
    cal, truth, meas, psi, samples, true, models = _fake(4)
    ds = _fake_dataset(tmp_path)
    inp = ReportInputs(ds, cal, meas, truth)
    src = build_report_source(inp, tmp_path, figures=False)
    block = _table1_block(src)
    for kind, m in models.items():
        for ref_name, ref in (("samples", samples), ("truth", true)):
            want = turntable_table1(m, psi, ref)
            line = next(ln for ln in block.splitlines() if f"{kind} function vs {ref_name}" in ln)
            cells = re.findall(r"\[([^\[\]]*)\]", line)[1:]
            exp = []
            for c in ("centre_mm", "z_axis_deg", "x_axis_deg"):
                exp += [fnum(want[c].mean(), DECIMALS[c]), fnum(want[c].max(), DECIMALS[c])]
            assert cells == exp, (kind, ref_name)
    d = np.array([m["diameter_mm"] for m in meas["measurements"]])
    assert fnum(np.abs(d - 140).mean(), 2) in src[src.index("Table 2"):]
    assert fnum(d.mean(), 2) in src
    # nothing from the JSON leaks into markup unescaped
    assert '#"a warning with under_\u200bscores and #hash and $dollar"' in src
    assert not list(tmp_path.glob("*.png"))


def test_report_pdf_without_images(tmp_path):
    """The whole typst path compiles (tables, figures from the JSON only) into a PDF."""
    import typst

    cal, truth, meas, *_ = _fake(5)
    ds = _fake_dataset(tmp_path / "ds")
    inp = ReportInputs(ds, cal, meas, truth)
    work = tmp_path / "work"
    work.mkdir()
    src = build_report_source(inp, work)
    (work / "r.typ").write_text(src)
    typst.compile(str(work / "r.typ"), output=str(tmp_path / "r.pdf"), root=str(work))
    assert (tmp_path / "r.pdf").read_bytes()[:5] == PDF_MAGIC
    assert len(list(work.glob("fig_*_trajectories.png"))) == 1
    assert not [n for n in inp.notes if "trajector" in n or "residual" in n]
    # the fake dataset has no image files: the figures that need them are skipped with a note
    assert any("board detection" in n for n in inp.notes)


def _with_edge_model(meas: dict, source: str, sigma_mm: float, references=()) -> dict:
    """measurements.json of lidarcal.disc: per-trial sigma and reference flag, the edge model."""
    rows = [{**m, "diameter_sigma_mm": sigma_mm, "reference": m["name"] in references,
             "diameter_half_mm": m["diameter_mm"] + 0.6, "beam_spacing_mm": 2.0 + 0.05 * k,
             "edge_offset_mm": 0.3, "mixed_share": 0.9} for k, m in enumerate(meas["measurements"])]
    return {**meas, "measurements": rows, "warnings": ["a reference disc disagrees by 5 sigma"],
            "edge_model": {"type": "offset_beam_spacing", "source": source, "echo": "mixed",
                           "k": 0.0751, "k_sigma": 0.0029, "references": list(references)}}


def _table2_block(src: str) -> str:
    i = src.index("Section 3.2")
    return src[i:src.index("\n)]", i)]


@pytest.mark.parametrize("seed", [6, 7])
def test_table2_sigma_column_and_reference_trials(tmp_path, seed):
    """Sigma column, the reference trial marked and left out of the statistics, the edge model
    stated, and the 2-sigma share counted against the true diameters."""
    cal, truth, meas, *_ = _fake(seed, trials=6)
    meas = _with_edge_model(meas, "reference", 1.0, references=("trial_01",))
    df, s = table2(meas, truth)
    d = np.array([m["diameter_mm"] for m in meas["measurements"]])
    test = d[1:]  # trial_01 is the reference
    assert list(df["reference"]) == [True] + [False] * 5
    assert s["tests"] == 5 and s["references"] == 1
    assert s["mean_abs_error_mm"] == pytest.approx(np.abs(test - 140).mean())
    assert s["mean_diameter_mm"] == pytest.approx(test.mean())
    inside = int(np.sum(np.abs(test - 140.0) <= 2.0))
    assert (s["within_2sigma"], s["within_2sigma_of"]) == (inside, 5)

    src = build_report_source(ReportInputs(_fake_dataset(tmp_path), cal, meas, truth), tmp_path,
                              figures=False)
    block = _table2_block(src)
    assert "[σ]" in block
    for k, m in enumerate(meas["measurements"]):
        line = next(ln for ln in block.splitlines() if f"trial_\u200b{k + 1:02d}" in ln)
        cells = re.findall(r"\[([^\[\]]*)\]", line)
        assert cells[5:8] == [fnum(m["diameter_mm"], 2), fnum(1.0, 2),
                              (f"({fnum(d[k] - 140, 2, sign=True)})" if k == 0
                               else fnum(d[k] - 140, 2, sign=True))]
        assert ("(ref.)" in line) == (k == 0)
    assert fnum(np.abs(test - 140).mean(), 2) in block
    text = src[src.index("Section 3.2"):]
    assert "fitted on the reference disc #\"trial_\u200b01\"" in text
    assert "k = 0.075 ± 0.003 edge spacings" in text
    assert f"within 2 σ for {inside} of 5 test trials" in text
    assert "a reference disc disagrees by 5 sigma" in src[:src.index("Provenance")]  # summary


def test_table2_prior_and_old_measurements(tmp_path):
    cal, truth, meas, *_ = _fake(8, trials=4)
    ds = _fake_dataset(tmp_path)
    prior = _with_edge_model(meas, "prior", 0.5)
    text = build_report_source(ReportInputs(ds, cal, prior, truth), tmp_path, figures=False)
    text = text[text.index("Section 3.2"):]
    assert "the prior, no reference disc" in text and "(ref.)" not in text
    d = np.array([m["diameter_mm"] for m in meas["measurements"]])
    assert f"within 2 σ for {int(np.sum(np.abs(d - 140) <= 1.0))} of 4 test trials" in text
    # a measurements.json from before the edge model: no sigma column, said so, still a table
    old = build_report_source(ReportInputs(ds, cal, meas, truth), tmp_path, figures=False)
    block = _table2_block(old)
    assert "[σ]" not in block and "within 2 σ" not in old
    assert "records none" in old[old.index("Section 3.2"):]
    assert fnum(np.abs(d - 140).mean(), 2) in block


# ---------------------------------------------------------------- end to end on a simulated rig


def _simulate(out: Path) -> Path:
    from lidarcal.synthetic import simulate

    # three positions over the whole sweep, no intrinsics views, no disc sweeps: fast
    return Path(simulate(out, seed=0, rig="paper", positions=[0, 43, 86], with_sweeps=False,
                         with_intrinsics=False, overwrite=True))


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "rig"
    return _simulate(out)


@pytest.fixture(scope="module")
def calibrated(small_dataset, tmp_path_factory) -> Path:
    """The folder holding ``lidarcal calibrate``'s calibration.json of :func:`small_dataset`."""
    from lidarcal.cli import main

    cal_dir = tmp_path_factory.mktemp("cal")
    assert main(["calibrate", str(small_dataset), "--out", str(cal_dir), "--no-progress"]) == 0
    return cal_dir


def test_report_end_to_end(small_dataset, calibrated, tmp_path):
    from lidarcal.cli import main

    cal_dir = tmp_path / "cal"
    cal_dir.mkdir()
    (cal_dir / "calibration.json").write_bytes((calibrated / "calibration.json").read_bytes())
    ds_json = json.loads((small_dataset / "dataset.json").read_text())
    meas = None
    if ds_json.get("measurements"):
        assert main(["measure", str(small_dataset), "--calibration", str(cal_dir),
                     "--out", str(cal_dir)]) == 0
        meas = cal_dir / "measurements.json"
    keep = tmp_path / "src"
    pdf = write_report(small_dataset, tmp_path / "report.pdf", calibration=cal_dir / "calibration.json",
                       measurements=meas, command="pytest", keep_source=keep)
    assert pdf.read_bytes()[:5] == PDF_MAGIC
    src = (keep / "report.typ").read_text()
    cal = json.loads((cal_dir / "calibration.json").read_text())
    truth = json.loads((small_dataset / "truth.json").read_text())
    t1 = table1(cal, truth)
    block = _table1_block(src)
    r = t1.loc["rigid function vs samples"]
    assert fnum(r["centre_mm_mean"], DECIMALS["centre_mm"]) in block
    assert fnum(r["x_axis_deg_max"], DECIMALS["x_axis_deg"]) in block
    # every figure was drawn
    assert "not drawn" not in src, [ln for ln in src.splitlines() if "not drawn" in ln]
    for name in ("corners", "stripes", "scan", "frames", "trajectories", "residuals"):
        assert list(keep.glob(f"fig_*_{name}.png")), name


_SPY = """
import os, sys
from pathlib import Path
import lidarcal.scene3d as scene3d
from lidarcal.report import write_report

calls = []
real = scene3d.rig_figure
def spy(*a, **kw):
    calls.append(kw)
    return real(*a, **kw)
scene3d.rig_figure = spy
ds, cal, out, keep = sys.argv[1:5]
write_report(ds, out, calibration=cal, command="test", keep_source=keep)
print("rig_figure calls", len(calls), sorted(calls[0]) if calls else "")
"""


def test_report_3d_figure_from_pyvista_without_display(small_dataset, calibrated, tmp_path):
    """The frames figure is the pyvista rig scene, rendered off screen with no display."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["MPLBACKEND"] = "Agg"
    keep = tmp_path / "src"
    res = subprocess.run([sys.executable, "-c", _SPY, str(small_dataset),
                          str(calibrated / "calibration.json"), str(tmp_path / "r.pdf"), str(keep)],
                         capture_output=True, text=True, env=env, timeout=600, check=False)
    assert res.returncode == 0, res.stderr
    assert "rig_figure calls 1 ['K', 'aperture_deg', 'image_size']" in res.stdout, res.stdout
    assert (tmp_path / "r.pdf").read_bytes()[:5] == PDF_MAGIC
    src = (keep / "report.typ").read_text()
    assert "not drawn" not in src, [ln for ln in src.splitlines() if "not drawn" in ln]
    png = list(keep.glob("fig_*_frames.png"))
    assert len(png) == 1 and f'image("{png[0].name}"' in src
    import matplotlib.image as mpimg

    img = mpimg.imread(png[0])[..., :3]
    # the rendered scene, not a blank window: the purple turntable axis and the orange fans show
    purple = (np.abs(img - np.array([0.5, 0.0, 0.5])).max(axis=-1) < 0.15).mean()
    fan = ((img[..., 0] > 0.9) & (img[..., 1] > 0.7) & (img[..., 1] < 0.95) & (img[..., 2] < 0.85)).mean()
    assert purple > 1e-4 and fan > 0.01, (purple, fan)


# ---------------------------------------------------------------- workbook


def _tiny_notebook(folder: Path) -> None:
    import nbformat as nbf

    nb = nbf.v4.new_notebook()
    nb.cells = [
        nbf.v4.new_markdown_cell("# 01 Tiny\n\n## 1.5 Pose, eq. (13)\n\n$$R = [l_1^c\\ l_2^c\\ "
                                 "l_1^c \\times l_2^c][l_1^l\\ l_2^l\\ l_1^l \\times l_2^l]^{-1} "
                                 "\\tag{13}$$\n\nand $\\alpha = \\arccos(l_1 \\cdot l_2)$, $E = \\Pi_1 \\cap \\Pi_2$."),
        nbf.v4.new_code_cell("import numpy as np\nimport matplotlib.pyplot as plt\n"
                             "print('mean', np.arange(4).mean())"),
        nbf.v4.new_code_cell("fig, ax = plt.subplots(figsize=(4, 3))\nax.plot([0, 1], [0, 1])\n"
                             "plt.show()"),
    ]
    nbf.write(nb, folder / "01_tiny.ipynb")
    nbf.write(nbf.v4.new_notebook(), folder / "notes.ipynb")  # not numbered: ignored


def test_workbook_builds_pdf(tmp_path):
    pytest.importorskip("nbclient")
    pytest.importorskip("pypandoc")
    nbdir = tmp_path / "nb"
    nbdir.mkdir()
    _tiny_notebook(nbdir)
    out = tmp_path / "out" / "workbook.pdf"
    keep = tmp_path / "keep"
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "workbook.py"), str(nbdir), str(out),
                          "--keep", str(keep)], capture_output=True, text=True, timeout=300, check=False)
    assert res.returncode == 0, res.stderr
    assert out.read_bytes()[:5] == PDF_MAGIC
    src = (keep / "workbook.typ").read_text()
    assert "mean 1.5" in src  # the executed output
    assert "(13)" in src  # the equation number survived
    assert "times" in src and "arccos" in src  # LaTeX became typst math
    pngs = list((keep / "media").glob("*.png"))
    assert len(pngs) == 1 and f'image("media/{pngs[0].name}"' in src
    assert "notes.ipynb" not in src


def test_workbook_no_notebooks(tmp_path):
    res = subprocess.run([sys.executable, str(ROOT / "scripts" / "workbook.py"), str(tmp_path),
                          str(tmp_path / "x.pdf")], capture_output=True, text=True, timeout=60, check=False)
    assert res.returncode == 1 and "no numbered notebooks" in res.stderr
    assert not (tmp_path / "x.pdf").exists()


def test_uncertainty_summary_counts_coverage():
    """Two positions, errors 0.1 mm / 0.3 mm against sigma 0.1 mm: the 2-sigma count is exact."""
    from lidarcal.geometry import Pose
    from lidarcal.report import uncertainty_summary

    I = np.eye(3)
    truth = {"poses": [{"index": i, **Pose(I, np.zeros(3)).to_dict()} for i in (0, 1)]}
    cal = {"poses": [{"index": 0, **Pose(I, np.array([0.1, 0, 0])).to_dict()},
                     {"index": 1, **Pose(I, np.array([0.3, 0, 0])).to_dict()}],
           "sigma": {"axis_direction_deg": 0.01, "poses": [
               {"index": i, "centre_mm": 0.1, "z_axis_deg": 0.001, "x_axis_deg": None}
               for i in (0, 1)]}}
    text = uncertainty_summary(cal, truth)
    assert text.startswith("centre 0.100 mm")
    # centre inside at 0 only; z inside at both (no rotation error); x sigma unknown -> inside
    assert "within 2 sigma for 83 %" in text and "jitter" not in text
    assert uncertainty_summary({"poses": []}, truth) == ""
    cal["sigma"]["angle_jitter_deg"] = 0.0031
    assert "encoder jitter 0.0031 deg" in uncertainty_summary(cal, truth)


def _ranging_block(src: str) -> str:
    i = src.index("=== Ranging model of the LiDAR")
    return src[i:src.index("\n=", i + 4) if "\n=" in src[i + 4:] else len(src)]


def test_report_states_ranging_terms(tmp_path):
    """With a calibration.json ``ranging`` block the report tables both terms with their
    1-sigma next to the pose function; without one it says the ranges were taken as exact."""
    from lidarcal.ranging import RangingModel

    cal, truth, meas, *_ = _fake(5)
    ds = _fake_dataset(tmp_path)
    rm = RangingModel(8.137, 0.162, 5.71, 0.43, estimated=("offset", "dark_extra"),
                      determined=("offset", "dark_extra"))
    src = build_report_source(ReportInputs(ds, {**cal, "method": "joint", "ranging": rm.to_dict()},
                                           meas, truth), tmp_path, figures=False)
    block = _ranging_block(src)
    assert src.index("Table 1: fitted pose function") < src.index("=== Ranging model")
    assert "#table(columns: 4" in block
    assert "[zero offset], [+8.14], [0.16], [from the data]" in block
    assert "[dark-square extra], [+5.71], [0.43], [from the data]" in block
    assert "taken as exact" not in block and "1-sigma include their uncertainty" in block
    import typst

    (tmp_path / "r.typ").write_text(src)
    typst.compile(str(tmp_path / "r.typ"), output=str(tmp_path / "r.pdf"), root=str(tmp_path))
    assert (tmp_path / "r.pdf").read_bytes()[:5] == PDF_MAGIC
    src = build_report_source(ReportInputs(ds, cal, meas, truth), tmp_path, figures=False)
    block = _ranging_block(src)
    assert "ranges taken as exact" in block and "#table" not in block
    assert "include their uncertainty" not in block
