"""Accuracy study (lidarcal.study): the Monte Carlo machinery on one small rig."""

from __future__ import annotations

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
