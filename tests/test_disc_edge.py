"""The disc's edge model: reference discs of known size, or the prior with its sigma (lidarcal.disc).

Sweeps of discs of 100, 140 and 200 mm from the simulator (lidarcal.synthetic, sweeps only),
with both echo models: energy-weighted Gaussian spot ("gaussian") and first echo of a
uniform spot ("first-echo"), measured with the true pose function.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from lidarcal.disc import (
    EdgeModel,
    edge_footprint,
    edge_spacing_mm,
    fit_edge_model,
    mixed_share,
    random_sigma_mm,
)
from lidarcal.io.dataset import DatasetError, LidarSpec
from lidarcal.measure import measure_disc
from lidarcal.synthetic.config import get_rig
from lidarcal.synthetic.lidar import beam_angles_deg, simulate_scans
from lidarcal.synthetic.truth import STREAM_SWEEP, _rng, make_truth

ROOT = Path(__file__).resolve().parents[1]
SIM = ROOT / "data" / "paper_rig"


def discs(rig_name: str, footprint: str, seed: int, diameters=(100.0, 140.0, 200.0)) -> list[dict]:
    rig = get_rig(rig_name).with_(footprint_model=footprint, disc_diameters_mm=tuple(diameters),
                                  n_discs=len(diameters))
    truth = make_truth(seed, rig, with_intrinsics=False)
    lidar = LidarSpec(rig.lidar_angle_min_deg, rig.lidar_angle_max_deg, rig.lidar_angle_step_deg,
                      rig.lidar_range_min_mm, rig.lidar_range_max_mm)
    out = []
    for j, d in enumerate(truth.discs):
        R, T = truth.poses_at(d.psi_true_deg)
        r = simulate_scans(d.surfaces, R, T, rig, _rng(seed, STREAM_SWEEP, j))
        P, B = r.shape
        sweep = pd.DataFrame({"psi_deg": np.repeat(d.psi_deg, B), "angle_deg": np.tile(beam_angles_deg(rig), P),
                              "range_mm": np.where(r > 0, r, np.nan).ravel()})
        m = measure_disc(sweep, truth, lidar, footprint=edge_footprint())  # as measure_dataset
        u = edge_spacing_mm(m, truth.pose_at(float(np.median(d.psi_deg))).T, rig.lidar_angle_step_deg)
        out.append({"true": 2 * d.disc.radius, "half": m.diameter_mm, "sigma": m.diameter_std_mm, "u": u,
                    "mixed": mixed_share(m.info), "fit_sigma": max(m.diameter_std_mm, random_sigma_mm(m))})
    return out


@pytest.fixture(scope="module", params=[("paper", "gaussian", 1), ("paper", "first-echo", 2),
                                        ("wide", "first-echo", 3)], ids=lambda p: f"{p[0]}-{p[1]}-{p[2]}")
def rig_discs(request):
    return discs(*request.param), request.param


def test_first_echo_model_makes_discs_look_larger_by_a_constant(rig_discs):
    rows, (_, fp, _) = rig_discs
    err = np.array([r["half"] - r["true"] for r in rows])
    if fp == "first-echo":  # rim at a quarter of the spot: outside the half-share rim, any size
        assert np.all(err > 0.5), err
        assert np.ptp(err / np.array([r["u"] for r in rows])) < 0.25, err  # a constant in beam spacings
        assert all(r["mixed"] < 0.4 for r in rows)   # no mixed ranges: the rim shows it
    else:
        assert all(r["mixed"] > 0.6 for r in rows)


def test_reference_140_calibrates_100_and_200(rig_discs):
    rows, _ = rig_discs
    ref = [r for r in rows if r["true"] == 140.0]
    em = fit_edge_model(["ref"], *(np.array([r[k] for r in ref]) for k in ("half", "sigma", "u", "true")))
    assert em.source == "reference" and not em.warnings
    errs = [em.apply(r["half"], r["sigma"], r["u"])[0] - r["true"] for r in rows if r["true"] != 140.0]
    # the random part of a diameter on these rigs is ~0.05 (paper) to ~0.3 mm (wide, 2 mm noise)
    assert np.mean(np.abs(errs)) <= 0.4, errs


def test_prior_sigma_covers_the_true_error(rig_discs):
    rows, (rig, fp, _) = rig_discs
    em = EdgeModel.prior(float(np.median([r["mixed"] for r in rows])))
    assert em.echo == ("mixed" if fp == "gaussian" else "first-echo")
    for r in rows:
        d, s = em.apply(r["half"], r["sigma"], r["u"])
        assert s > 0 and abs(d - r["true"]) <= 2 * s, (d, r, s)
    limit = 1.5 if rig == "paper" else 2.5
    assert np.mean([abs(em.apply(r["half"], r["sigma"], r["u"])[0] - r["true"]) for r in rows]) <= limit


def test_each_disc_as_reference_covers_the_others_within_two_sigma():
    """Six discs of one rig (seed 3: four tilted 22-25 deg to the beam, two facing it), each in
    turn the reference for the other five: the diameter's 1-sigma covers 2 sigma in >= 90 % of
    the 30 pairs. Reading the mixed ranges without the discs' cos(incidence) and without the rim
    stretch (the edge model before) covered 67 % of them, with twice the mean |error|."""
    rows = discs("paper", "gaussian", 3, (100.0, 140.0, 200.0, 100.0, 140.0, 200.0))
    covered, errs = [], []
    for ref in rows:
        em = fit_edge_model(["ref"], *(np.array([ref[k]]) for k in ("half", "fit_sigma", "u", "true")))
        for r in rows:
            if r is not ref:
                d, s = em.apply(r["half"], r["fit_sigma"], r["u"])
                covered.append(abs(d - r["true"]) <= 2 * s)
                errs.append(abs(d - r["true"]))
    assert np.mean(covered) >= 0.9, (np.mean(covered), errs)
    # the random part of one diameter here is ~0.01-0.03 mm (fit sigma); with the reference's own
    assert np.mean(errs) <= 0.04, errs


def test_range_offset_error_scales_the_diameter_as_propagated():
    """A range offset error e scales a disc at range rho by -e / rho across the beams, not
    along them: a = -D (1 + cos^2 i) / (2 rho) (the disc here is tilted ~23 deg, a is 8 % below
    -D / rho); through one reference of the same size at the same range it cancels (c = 0)."""
    from dataclasses import dataclass

    from lidarcal.disc import offset_sensitivity
    from lidarcal.ranging import RangingModel

    rig = get_rig("paper").with_(disc_diameters_mm=(200.0,), n_discs=1)
    truth = make_truth(2, rig, with_intrinsics=False)
    lidar = LidarSpec(rig.lidar_angle_min_deg, rig.lidar_angle_max_deg, rig.lidar_angle_step_deg,
                      rig.lidar_range_min_mm, rig.lidar_range_max_mm)
    d = truth.discs[0]
    R, T = truth.poses_at(d.psi_true_deg)
    r = simulate_scans(d.surfaces, R, T, rig, _rng(2, STREAM_SWEEP, 0))
    P, B = r.shape
    sweep = pd.DataFrame({"psi_deg": np.repeat(d.psi_deg, B), "angle_deg": np.tile(beam_angles_deg(rig), P),
                          "range_mm": np.where(r > 0, r, np.nan).ravel()})

    @dataclass
    class Shifted:  # the true poses with a wrong range offset
        ranging: RangingModel

        def pose(self, psi_deg):
            return truth.pose(psi_deg)

    e = 5.0
    m0 = measure_disc(sweep, Shifted(RangingModel()), lidar)
    m1 = measure_disc(sweep, Shifted(RangingModel(offset_mm=e)), lidar)
    view = m0.center_mm - truth.pose_at(float(np.median(d.psi_deg))).T
    rho = float(np.linalg.norm(view))
    cos_i = abs(m0.normal @ view) / rho
    a = offset_sensitivity([m0.diameter_mm], [rho], [2.0], [False], [cos_i])[0]
    assert a == pytest.approx(-m0.diameter_mm * (1 + cos_i**2) / (2 * rho)) and cos_i < 0.95
    # 5 mm at ~1.5 m: -0.62 mm (-D e / rho would be -0.68); the fit's own change is ~0.01 mm
    assert m1.diameter_mm - m0.diameter_mm == pytest.approx(a * e, abs=0.02)
    c = offset_sensitivity([200.0, 200.0, 100.0], [rho, rho, rho], [2.0, 2.0, 2.0], [True, False, False])
    assert c[:2] == pytest.approx([0.0, 0.0], abs=1e-12) and c[2] == pytest.approx(100.0 / rho)


def test_three_references_show_the_discs_own_scatter():
    """References whose k_i scatter by tau beyond their fits' sigma: ``k_scatter`` estimates tau
    (its square is unbiased while tau dominates) and enters every measured disc's sigma;
    with one reference it is 0 (unknown)."""
    rng = np.random.default_rng(11)
    tau, sig_k, u = 0.02, 0.005, 2.0
    est = []
    for _ in range(2000):
        ki = 0.1 + tau * rng.normal(size=5) + sig_k * rng.normal(size=5)
        em = fit_edge_model(list("abcde"), 140.0 + 2 * u * ki, np.full(5, 2 * u * sig_k), np.full(5, u),
                            np.full(5, 140.0))
        est.append(em.k_scatter)
    assert np.mean(np.square(est)) == pytest.approx(tau**2, rel=0.05)
    _, s = em.apply(100.0, 0.0, u)
    want = np.hypot(2 * u * em.k_sigma, 2 * u * em.k_scatter)
    assert s == pytest.approx(want) and em.to_dict()["k_scatter"] == em.k_scatter
    one = fit_edge_model(["a"], np.array([140.4]), np.array([0.02]), np.array([u]), np.array([140.0]))
    assert one.k_scatter == 0.0


def test_prior_intervals():
    mixed, first, unknown = EdgeModel.prior(0.9), EdgeModel.prior(0.05), EdgeModel.prior(None)
    assert mixed.k == pytest.approx(0.15) and mixed.k_sigma == pytest.approx(0.3 / np.sqrt(12))
    assert first.k == pytest.approx(0.3) and unknown.k == first.k and unknown.echo == "unknown"


def test_implausible_reference_warns():
    em = fit_edge_model(["a"], np.array([150.0]), np.array([0.05]), np.array([2.0]), np.array([140.0]))
    assert any("outside the plausible" in w for w in em.warnings)
    em = fit_edge_model(["a", "b"], np.array([140.5, 142.5]), np.array([0.05, 0.05]), np.array([2.0, 2.0]),
                        np.array([140.0, 140.0]))
    assert any("disagree" in w for w in em.warnings)


def _lidarcal(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *args], capture_output=True, text=True,
                          check=False)


@pytest.mark.skipif(not (SIM / "truth.json").is_file(), reason="bundled dataset not generated")
def test_cli_measure_reference_and_sigma(tmp_path):
    from test_cloud import truth_calibration

    cal = truth_calibration(SIM, tmp_path / "cal")
    truth = {m["name"]: m for m in json.loads((SIM / "truth.json").read_text())["measurements"]}
    r = _lidarcal("measure", str(SIM), "--calibration", str(cal), "--out", str(tmp_path / "m0"))
    assert r.returncode == 0, r.stderr
    m0 = json.loads((tmp_path / "m0" / "measurements.json").read_text())
    assert m0["edge_model"]["source"] == "prior" and m0["edge_model"]["echo"] == "mixed"
    for row in m0["measurements"]:
        assert row["diameter_sigma_mm"] > 0 and row["reference"] is False
        assert abs(row["diameter_mm"] - truth[row["name"]]["diameter_mm"]) <= 2 * row["diameter_sigma_mm"]
    r = _lidarcal("measure", str(SIM), "--calibration", str(cal), "--out", str(tmp_path / "m1"),
                  "--reference", "trial_01")
    assert r.returncode == 0, r.stderr
    m1 = json.loads((tmp_path / "m1" / "measurements.json").read_text())
    assert m1["edge_model"]["source"] == "reference" and m1["edge_model"]["references"] == ["trial_01"]
    rows = m1["measurements"]
    assert [row["reference"] for row in rows] == [row["name"] == "trial_01" for row in rows]
    errs = [row["diameter_mm"] - truth[row["name"]]["diameter_mm"] for row in rows if not row["reference"]]
    assert np.mean(np.abs(errs)) <= 0.4
    r = _lidarcal("measure", str(SIM), "--calibration", str(cal), "--out", str(tmp_path / "m2"),
                  "--reference", "nope")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "--reference nope" in r.stderr
    assert not (tmp_path / "m2" / "measurements.json").exists()


def test_reference_needs_known_diameter(tmp_path):
    import shutil

    from test_cloud import truth_calibration

    from lidarcal.disc import measure_dataset

    ds = tmp_path / "ds"
    shutil.copytree(SIM, ds, ignore=shutil.ignore_patterns("stripes", "scans", "intrinsics"))
    meta = json.loads((ds / "dataset.json").read_text())
    del meta["measurements"][0]["reference_diameter_mm"]
    (ds / "dataset.json").write_text(json.dumps(meta))
    cal = truth_calibration(SIM, tmp_path / "cal")
    with pytest.raises(DatasetError, match="reference_diameter_mm is not"):
        measure_dataset(ds, cal, references=["trial_01"])


def test_cli_simulate_footprint_and_disc_sizes(monkeypatch, tmp_path):
    """``simulate --footprint first-echo --disc-diameters 100,140,200`` reaches the rig config."""
    from lidarcal import synthetic
    from lidarcal.cli import main

    seen = {}

    def fake(out, seed, rig, **kw):
        seen["rig"] = rig
        return out

    monkeypatch.setattr(synthetic, "simulate", fake)
    assert main(["simulate", str(tmp_path), "--footprint", "first-echo", "--disc-diameters", "100,140,200"]) == 0
    rig = seen["rig"]
    assert rig.footprint_model == "first-echo" and rig.disc_diameters_mm == (100.0, 140.0, 200.0)
    assert [rig.disc_diameter(j) for j in range(4)] == [100.0, 140.0, 200.0, 100.0]
    with pytest.raises(SystemExit):
        main(["simulate", str(tmp_path), "--disc-diameters", "100,-5"])


def test_simulated_first_echo_truth_and_references():
    """The truth and dataset.json carry each disc's own diameter and the echo model."""
    from lidarcal.synthetic.writer import dataset_json

    rig = get_rig("paper").with_(footprint_model="first-echo", disc_diameters_mm=(100.0, 200.0), n_discs=3)
    truth = make_truth(4, rig, with_intrinsics=False)
    t = truth.to_dict()
    assert [m["diameter_mm"] for m in t["measurements"]] == [100.0, 200.0, 100.0]
    assert t["noise"]["footprint_model"] == "first-echo"
    refs = [m["reference_diameter_mm"] for m in dataset_json(truth, False, True)["measurements"]]
    assert refs == [100.0, 200.0, 100.0]
    assert "footprint_model" not in make_truth(4, "paper", with_discs=False, with_intrinsics=False).to_dict()["noise"]


def test_table2_columns_carry_sigma_and_reference_flags():
    from lidarcal.disc import table2_columns

    meas = {"measurements": [
        {"name": "a", "diameter_mm": 140.1, "diameter_sigma_mm": 0.4, "reference_diameter_mm": 140.0,
         "error_mm": 0.1, "reference": True},
        {"name": "b", "diameter_mm": 99.8, "reference_diameter_mm": 100.0, "error_mm": -0.2}]}
    cols = table2_columns(meas)
    assert cols["name"] == ["a", "b"] and cols["diameter_sigma_mm"] == [0.4, None]
    assert cols["reference"] == [True, False] and cols["error_mm"] == [0.1, -0.2]


def test_the_reference_is_chosen_from_the_data():
    """Notebook 06's reference: the first sweep with a reference_diameter_mm, when another is left
    to measure; none (prior mode only) without one or with a single sweep."""
    from types import SimpleNamespace as NS

    from lidarcal.disc import reference_choice

    def ds(*refs):
        return NS(measurements=[NS(name=f"disc_{k}", reference_diameter_mm=r) for k, r in enumerate(refs)])

    assert reference_choice(ds(None, 140.0, 100.0)) == "disc_1"
    assert reference_choice(ds(140.0, 140.0)) == "disc_0"
    assert reference_choice(ds(None, None)) is None
    assert reference_choice(ds(140.0)) is None and reference_choice(ds()) is None


@pytest.mark.skipif(not (SIM / "truth.json").is_file(), reason="bundled dataset not generated")
def test_a_calibration_of_another_dataset_and_camera_is_named(tmp_path):
    # measuring with another rig's calibration.json gave wrong diameters without a word
    from test_cloud import truth_calibration

    from lidarcal.disc import measure_dataset

    cal = truth_calibration(SIM, tmp_path / "cal")
    d = json.loads(cal.read_text())
    cal.write_text(json.dumps({**d, "dataset": str(SIM)}))
    assert not any("another dataset" in w for w in measure_dataset(SIM, cal).attrs["warnings"])
    cal.write_text(json.dumps({**d, "dataset": str(tmp_path / "other_rig"),
                               "camera": {"K": [[1000, 0, 640], [0, 1000, 360], [0, 0, 1]],
                                          "image_size": [1280, 720]}}))
    w = [w for w in measure_dataset(SIM, cal).attrs["warnings"] if "another dataset" in w]
    assert len(w) == 1 and w[0].startswith(f"{cal}: made from another dataset")
    assert "with another camera" in w[0] and "same rig, unmoved" in w[0]
