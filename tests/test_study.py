"""Accuracy study (lidarcal.study): the Monte Carlo machinery on one small rig."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lidarcal.evaluate import pose_error
from lidarcal.study import (
    StudySetting,
    coverage,
    run_study,
    simulate_rig,
    small_settings,
    stripe_centres_truth,
    summarise,
    sweep_settings,
)

FAST = StudySetting(name="fast", n_positions=6, methods=("samples", "paper", "rigid", "joint"))


@pytest.fixture(scope="module")
def table():
    return run_study([FAST], n_rigs=1, seed=3)


def test_run_study_rows_and_columns(table):
    assert set(table["method"]) == set(FAST.methods)
    n = table["n_used"].iloc[0]
    assert (table.groupby("method").size() == n).all()  # one row per position and method
    for col in ("centre_mm", "z_axis_deg", "x_axis_deg", "axis_direction_deg", "sigma_centre_mm",
                "fit_s", "range_noise_mm", "stripe_noise_px"):
        assert col in table
    joint = table[table.method == "joint"]
    assert joint["sigma_centre_mm"].notna().all()
    assert table[table.method == "paper"]["sigma_centre_mm"].isna().all()


def test_joint_beats_single_shot_samples(table):
    mean = table.groupby("method")[["centre_mm", "x_axis_deg"]].mean()
    assert mean.loc["joint", "centre_mm"] < mean.loc["samples", "centre_mm"]
    assert mean.loc["joint", "x_axis_deg"] < mean.loc["samples", "x_axis_deg"]


def test_summary_and_coverage(table):
    s = summarise(table)
    assert s.loc[("fast", "joint"), "rigs"] == 1
    c = coverage(table)
    assert 0.0 <= c.loc[("fast", "joint"), "all"] <= 1.0
    assert ("fast", "paper") not in c.index


def test_simulated_stripe_lies_on_the_true_line():
    """Noise-free simulated centres back-project onto the true laser plane (sub-micrometre)."""
    from lidarcal.camera import backproject_to_plane
    from lidarcal.geometry import Plane

    sim = simulate_rig(4, StudySetting(n_positions=4, stripe_noise_px=0.0, stripe_offset_px=0.0,
                                       corner_noise_px=0.0, corner_tilt_deg=0.0,
                                       corner_offset_mm=0.0, range_noise_mm=0.2))
    truth = sim.truth
    pose = sim.true_poses[0]
    laser = Plane.from_normal_point(pose.z_axis, pose.T)
    for b in truth.boards:
        c = stripe_centres_truth(sim.result.camera, b, laser, pose, truth.rig)
        assert len(c) > 100
        X = backproject_to_plane(sim.result.camera, c, b.plane)
        assert np.abs(laser.distance(X)).max() < 1e-3
    # with exact camera inputs and little range noise the single-shot pose is close to the truth
    p0 = sim.result.positions[0]
    e = pose_error(p0.pose, sim.true_poses[p0.index])
    assert e["centre_mm"] < 0.2 and e["z_axis_deg"] < 1e-3


def test_settings_helpers():
    names = [s.name for s in sweep_settings()]
    assert names[0] == "baseline" and "range=2mm" in names and "positions=87" in names
    assert "range=1mm" not in names and "positions=22" not in names  # = the baseline
    assert all(s.n_positions >= 3 for s in small_settings())
    assert StudySetting(n_positions=87).psi_step_deg == pytest.approx(0.25)


def test_failed_rig_is_recorded_not_raised():
    bad = StudySetting(name="bad", rig="no-such-rig")
    out = run_study([bad], n_rigs=1)
    assert list(out["method"]) == ["failed"] and "unknown rig" in out["error"].iloc[0]
    assert summarise(out).empty


RANGING = StudySetting(name="ranging", n_positions=8, range_offset_mm=8.0, dark_extra_mm=6.0,
                       methods=("rigid", "joint_exact", "joint"))


@pytest.fixture(scope="module")
def ranging_table():
    return run_study([RANGING], n_rigs=1, seed=5)


def test_study_scans_carry_the_offset_and_the_dark_bias():
    """The study's scans come from the simulator's scan model with the setting's ranging
    errors: on the same rig and noise draws, every board return reads the offset farther,
    plus the dark extra on black squares (8 or 8 + 6 mm farther; in between for beams whose
    footprint straddles a square edge)."""
    base = StudySetting(n_positions=3, range_noise_mm=0.0)
    sims = [simulate_rig(9, replace(base, range_offset_mm=o, dark_extra_mm=d))
            for o, d in ((0.0, 0.0), (8.0, 6.0))]
    diffs = []
    for p0, p1 in zip(*(s.result.positions for s in sims)):
        pts = (p0.segments.points1, p1.segments.points1)
        b0, b1 = (np.round(np.degrees(np.arctan2(p[:, 1], p[:, 0])), 3) for p in pts)
        _, i0, i1 = np.intersect1d(b0, b1, return_indices=True)  # the same beams
        diffs.append(np.linalg.norm(pts[1][i1], axis=1) - np.linalg.norm(pts[0][i0], axis=1))
    d = np.concatenate(diffs)
    assert len(d) > 300
    assert d.min() > 8.0 - 0.3 and d.max() < 14.0 + 0.3
    assert np.mean(np.abs(d - 8.0) < 0.3) > 0.25 and np.mean(np.abs(d - 14.0) < 0.3) > 0.25


def test_ranging_sweep_recovers_the_terms(ranging_table):
    """With ranges 8 mm too far and black squares 6 mm farther the joint fit with the ranging
    model recovers both terms within 3 of its sigmas and the centre; without it the centre is
    off by about the offset."""
    from lidarcal.study import summarise_ranging

    s = summarise_ranging(ranging_table).loc["ranging"]
    j = s.loc["joint"]
    assert abs(j["offset_est_mm"] - 8.0) < 3 * j["offset_sigma_mm"]
    assert abs(j["dark_extra_est_mm"] - 6.0) < 3 * j["dark_extra_sigma_mm"]
    assert j["centre_mm"] < 1.0
    assert s.loc["joint_exact", "centre_mm"] > 5.0 and s.loc["rigid", "centre_mm"] > 5.0
    assert np.isnan(s.loc["joint_exact", "offset_est_mm"])  # no ranging model there


def test_ranging_sweep_command(tmp_path):
    """``python -m lidarcal.study --ranging OUT.csv`` writes the rows and the summary."""
    import subprocess
    import sys

    import pandas as pd

    out = tmp_path / "r.csv"
    p = subprocess.run([sys.executable, "-m", "lidarcal.study", "--ranging", str(out), "--rigs", "1",
                        "--offsets", "8", "--darks", "0", "--workers", "1"],
                       check=False, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    s = pd.read_csv(tmp_path / "r_summary.csv", index_col=[0, 1])
    assert set(s.index.get_level_values("method")) == {"samples", "paper", "rigid", "joint_exact",
                                                        "joint"}
    assert s.loc[("offset=8mm dark=0mm", "joint"), "range_offset_mm"] == 8.0
    assert abs(s.loc[("offset=8mm dark=0mm", "joint"), "offset_est_mm"] - 8.0) < 2.0
