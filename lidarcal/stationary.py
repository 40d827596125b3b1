"""Stationary periods of a turntable angle stream: where the turntable held a position.

A *stationary period* is a maximal run of consecutive angle readings whose spread
(max - min) stays within ``tolerance_deg`` and that lasts at least ``min_duration_s``.
Calibration positions are the stationary periods of a stop-and-go recording; scans and
frames taken outside them (while the turntable moves) are never used.

Defaults come from the angle stream itself (:func:`default_tolerance_deg`,
:func:`default_min_duration_s`); ``docs/ros-bags.md`` explains them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Period:
    """Readings ``first..last`` (inclusive) held within the tolerance; times in s, angle in deg."""

    first: int
    last: int
    t_start: float
    t_end: float
    psi_deg: float  # median of the readings in the period

    @property
    def duration_s(self) -> float:
        return self.t_end - self.t_start

    def contains(self, t0: float, t1: float | None = None) -> bool:
        """Whether the interval ``[t0, t1]`` (or the instant ``t0``) lies inside the period."""
        return self.t_start <= t0 and (t0 if t1 is None else t1) <= self.t_end


def encoder_resolution_deg(psi_deg: np.ndarray) -> float:
    """Smallest non-zero step between consecutive readings (the encoder's quantum, or the
    smallest step of a move when the readings at rest are exact); 0 when nothing moves."""
    d = np.abs(np.diff(np.asarray(psi_deg, dtype=float)))
    d = d[d > 0]
    return float(d.min()) if d.size else 0.0


def rest_noise_deg(psi_deg: np.ndarray) -> float:
    """1-sigma noise of the readings, from the median second difference.

    A second difference ``psi[i+1] - 2 psi[i] + psi[i-1]`` is 0 at rest and at constant
    speed (a sweep), small in a smooth move, and has sigma ``sqrt(6) * noise`` for
    independent noise, so ``median|d2| / (0.6745 sqrt 6)`` is the noise whenever more than
    half of the readings are at rest or at constant speed. Exact readings give 0.
    """
    p = np.asarray(psi_deg, dtype=float)
    if p.size < 3:
        return 0.0
    d2 = np.abs(p[2:] - 2.0 * p[1:-1] + p[:-2])
    return float(np.median(d2) / (0.6745 * np.sqrt(6.0)))


def default_tolerance_deg(psi_deg: np.ndarray) -> float:
    """``max(2 * resolution, 6 * rest noise, 1e-6)`` deg.

    Two encoder quanta admit a reading that flickers by one count at rest; six sigma of
    the noise keeps a noisy reading still for ~ the whole period (the spread of 100
    Gaussian readings is about 5 sigma; a hold split by a stray reading is merged again).
    The floor only guards exact, unmoving streams.
    """
    return max(2.0 * encoder_resolution_deg(psi_deg), 6.0 * rest_noise_deg(psi_deg), 1e-6)


def default_min_duration_s(angle_period_s: float, scan_period_s: float) -> float:
    """``max(3 angle periods, 4 scan periods)``: a hold is seen in >= 3 readings and is long
    enough for >= 3 whole scans (the per-beam clipped mean of 3 rejects one bad scan)."""
    return max(3.0 * angle_period_s, 4.0 * scan_period_s)


def median_period_s(t_s: np.ndarray) -> float:
    """Median time between consecutive messages (s); inf for fewer than 2."""
    t = np.sort(np.asarray(t_s, dtype=float))
    return float(np.median(np.diff(t))) if t.size >= 2 else float("inf")


def find_stationary(t_s: np.ndarray, psi_deg: np.ndarray, tolerance_deg: float,
                    min_duration_s: float) -> list[Period]:
    """Stationary periods of the readings ``psi_deg`` at times ``t_s`` (sorted), in time order.

    Greedy from the first reading: a run grows while its spread stays within
    ``tolerance_deg``; a run lasting ``>= min_duration_s`` is a period and the next run
    starts after it, otherwise the next run starts one reading later. Consecutive periods
    whose angles differ by no more than the tolerance (a hold split by one stray reading)
    are merged.
    """
    t = np.asarray(t_s, dtype=float)
    psi = np.asarray(psi_deg, dtype=float)
    if t.shape != psi.shape or t.ndim != 1:
        raise ValueError(f"t_s and psi_deg must be 1-D of one length, got {t.shape}, {psi.shape}")
    if np.any(np.diff(t) < 0):
        raise ValueError("t_s must be sorted")
    if not tolerance_deg > 0 or not min_duration_s >= 0:
        raise ValueError(f"need tolerance_deg > 0 and min_duration_s >= 0, got "
                         f"{tolerance_deg}, {min_duration_s}")
    n = len(psi)
    runs: list[tuple[int, int]] = []
    i = 0
    while i < n:
        lo = hi = psi[i]
        j = i
        while j + 1 < n:
            v = psi[j + 1]
            lo2, hi2 = min(lo, v), max(hi, v)
            if hi2 - lo2 > tolerance_deg:
                break
            lo, hi, j = lo2, hi2, j + 1
        if t[j] - t[i] >= min_duration_s and j > i:
            runs.append((i, j))
            i = j + 1
        else:
            i += 1
    merged: list[tuple[int, int]] = []
    for a, b in runs:
        if merged:
            pa, pb = merged[-1]
            if abs(np.median(psi[a:b + 1]) - np.median(psi[pa:pb + 1])) <= tolerance_deg:
                merged[-1] = (pa, b)
                continue
        merged.append((a, b))
    return [Period(a, b, float(t[a]), float(t[b]), float(np.median(psi[a:b + 1])))
            for a, b in merged]
