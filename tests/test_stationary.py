"""Stationary periods of a turntable angle stream (lidarcal.stationary)."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal.stationary import (
    default_min_duration_s,
    default_tolerance_deg,
    encoder_resolution_deg,
    find_stationary,
    rest_noise_deg,
)


def stop_and_go(psi_stops, dwell=1.0, move=0.4, hz=50.0):
    """Readings of a turntable holding each angle for ``dwell`` s and moving (cosine) between."""
    t, p, truth = [], [], []
    t0 = 0.0
    for k, psi in enumerate(psi_stops):
        if k:
            a = psi_stops[k - 1]
            tm = t0 + np.arange(round(move * hz)) / hz
            t += list(tm)
            p += list(a + (psi - a) * 0.5 * (1 - np.cos(np.pi * (tm - t0) / move)))
            t0 += move
        ts = t0 + np.arange(round(dwell * hz)) / hz
        t += list(ts)
        p += [psi] * len(ts)
        truth.append((t0, t0 + dwell, psi))
        t0 += dwell
    return np.array(t), np.array(p), truth


def test_exact_readings_give_every_stop_within_its_hold():
    stops = [10.0, 10.25, 10.5, 10.75, 11.0]
    t, p, truth = stop_and_go(stops)
    tol = default_tolerance_deg(p)
    periods = find_stationary(t, p, tol, default_min_duration_s(0.02, 0.025))
    assert [q.psi_deg for q in periods] == stops
    for q, (a, b, _) in zip(periods, truth):
        # a period reaches into a move by at most the readings within the tolerance of the hold
        # (two readings of this cosine move; tol = 2 x the smallest step)
        assert a - 0.04 - 1e-9 <= q.t_start and q.t_end <= b + 0.04 + 1e-9
        assert q.duration_s > 0.9 * (b - a - 0.04)


def test_quantised_encoder_with_flicker():
    rng = np.random.default_rng(3)
    q = 0.001
    t, p, _ = stop_and_go([0.0, 0.5, 1.0, 1.5], hz=100)
    flick = rng.random(p.size) < 0.2
    read = np.round(p / q) * q + np.where(flick, rng.choice([-q, q], p.size), 0.0)
    assert encoder_resolution_deg(read) == pytest.approx(q, rel=1e-6)
    tol = default_tolerance_deg(read)
    assert 2 * q - 1e-12 <= tol < 0.05  # two counts admit the flicker, far below the 0.5 step
    periods = find_stationary(t, read, tol, 0.1)
    assert len(periods) == 4
    assert np.allclose([x.psi_deg for x in periods], [0.0, 0.5, 1.0, 1.5], atol=1e-9)


def test_noisy_float_readings_noise_estimate_and_merge():
    rng = np.random.default_rng(4)
    sigma = 0.002
    t, p, _ = stop_and_go([5.0, 5.25, 5.5], dwell=3.0, hz=50)
    noisy = p + rng.normal(0, sigma, p.size)
    assert rest_noise_deg(noisy) == pytest.approx(sigma, rel=0.2)
    periods = find_stationary(t, noisy, default_tolerance_deg(noisy), 0.1)
    assert len(periods) == 3  # split holds are merged again
    assert np.allclose([x.psi_deg for x in periods], [5.0, 5.25, 5.5], atol=4 * sigma / np.sqrt(100))


def test_short_pause_and_slow_move_are_not_stationary():
    t = np.arange(0, 4, 0.02)
    p = np.where(t < 1, 0.0, np.where(t < 1.04, 0.3, 0.3 + 0.2 * (t - 1.04)))  # 40 ms pause
    periods = find_stationary(t, p, 0.001, 0.1)
    assert len(periods) == 1 and periods[0].psi_deg == 0.0


def test_bad_arguments():
    t = np.arange(5.0)
    with pytest.raises(ValueError, match="sorted"):
        find_stationary(t[::-1], t, 0.1, 0.1)
    with pytest.raises(ValueError, match="tolerance_deg > 0"):
        find_stationary(t, t, 0.0, 0.1)
    assert find_stationary(t, np.arange(5.0) * 10, 0.1, 0.5) == []
