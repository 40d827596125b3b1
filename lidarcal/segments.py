"""Straight segments of a real 2D scan: the candidates for a flat board (``lidarcal planes``).

Real scans hold clutter, mounts, walls and people; real ranges are integer mm and
some scanners repeat a range over neighbouring beams. Runs of neighbouring returns
(broken at missing beams and at range jumps no surface up to 80 deg incidence can
make) are cut into lines by sequential RANSAC with TLS refits, which stray returns
and mixed pixels do not split. The noise about lines is measured on the scan itself
(:func:`local_line_noise`).

Convention: LiDAR frame, beam angle 0 = x axis, mm (eq. 6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scan import estimate_range_noise, scan_points

#: Minimum returns on a segment.
MIN_POINTS = 8


@dataclass(frozen=True)
class Segment:
    """A straight run of returns: beam indices ``beams`` into the scan, TLS line fit."""

    beams: np.ndarray
    points: np.ndarray  # (N, 2) LiDAR frame, mm
    rms_mm: float

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(self.points[-1] - self.points[0]))


def _line_residuals(p: np.ndarray) -> np.ndarray:
    c = p.mean(0)
    q = p - c
    _, _, vt = np.linalg.svd(q, full_matrices=False)
    return q @ vt[-1]


def scan_segments(angle_deg: np.ndarray, range_mm: np.ndarray, sigma_mm: float | None = None,
                  min_points: int = MIN_POINTS) -> list[Segment]:
    """Straight segments of one scan (split-and-merge on runs of neighbouring returns).

    Runs break where a beam has no return (more than one in a row) or the range jumps
    by more than a surface at 80 deg incidence would explain (plus ``6 sigma``); each
    run is split recursively at its farthest point from the fitted line while that
    distance exceeds ``max(4 sigma_q, 0.005 range)``, where ``sigma_q`` adds the
    quantisation of integer-mm ranges (1/12 mm^2) to the range noise; adjacent
    pieces on one line are merged again. Pieces with fewer than ``min_points`` are
    dropped.
    """
    a = np.radians(np.asarray(angle_deg, float))
    r = np.asarray(range_mm, float)
    if sigma_mm is None:
        sigma_mm = local_line_noise(angle_deg, range_mm)
    sq = float(np.sqrt(max(sigma_mm, 0.3) ** 2 + 1.0 / 12.0))
    p = scan_points(np.degrees(a), r)
    valid = np.flatnonzero(np.isfinite(p[:, 0]))
    if len(valid) < min_points:
        return []
    step = float(np.median(np.diff(a))) if len(a) > 1 else 0.0
    runs, start = [], 0
    for k in range(1, len(valid)):
        i, j = valid[k - 1], valid[k]
        gap = j - i
        jump = abs(r[j] - r[i])
        allowed = 6.0 * (gap * step) * min(r[i], r[j]) + 6 * sq
        if gap > 2 or jump > allowed:
            runs.append(valid[start:k])
            start = k
    runs.append(valid[start:])
    out: list[Segment] = []
    for run in runs:
        if len(run) >= min_points:
            for b in _extract_lines(p, run, sq, min_points, rng=np.random.default_rng(len(run))):
                q = p[b]
                out.append(Segment(b, q, float(np.sqrt(np.mean(_line_residuals(q) ** 2)))))
    return sorted(out, key=lambda s: int(s.beams[0]))


def local_line_noise(angle_deg: np.ndarray, range_mm: np.ndarray, window: int = 15) -> float:
    """Noise (mm) about straight lines: the median over windows of ``window`` neighbouring
    returns of their TLS residual RMS (``n - 2`` degrees of freedom).

    Unlike second differences of ranges, this is not fooled by scanners that repeat a
    range over neighbouring beams (the real UTM-30LX recordings repeat 28-32 %), and it
    includes the integer-mm quantisation; windows across a jump or a corner are outvoted.
    """
    p = scan_points(angle_deg, range_mm)
    ok = np.isfinite(p[:, 0])
    out = []
    for s in range(0, len(p) - window + 1, max(1, window // 3)):
        if ok[s:s + window].all():
            r = _line_residuals(p[s:s + window])
            out.append(np.sqrt(np.sum(r ** 2) / (window - 2)))
    if len(out) < 3:
        try:
            return max(estimate_range_noise(range_mm), 0.5)
        except ValueError:
            return 1.0
    return float(max(np.median(out), 0.3))


def _tolerance(p: np.ndarray, sq: float) -> float:
    """Inlier band of a line: 3 sigma (range noise and quantisation), at least 0.3 % of the range
    (boards are not perfectly flat)."""
    return max(3.0 * sq, 0.003 * float(np.median(np.hypot(p[:, 0], p[:, 1]))))


def _extract_lines(p: np.ndarray, beams: np.ndarray, sq: float, min_points: int,
                   rng: np.random.Generator, trials: int = 200, max_gap: int = 3
                   ) -> list[np.ndarray]:
    """Sequential RANSAC on one run of beams: the line with most inliers (band
    :func:`_tolerance`), refitted by TLS on them; its longest block of inliers (outlier gaps up
    to ``max_gap`` beams bridged) is a segment, and the beams left of and right of the block
    are searched the same way. Robust to stray returns and mixed pixels, which a split at the
    farthest point is not."""
    if len(beams) < min_points:
        return []
    q = p[beams]
    tol = _tolerance(q, sq)
    n = len(q)
    i = rng.integers(n, size=trials)
    j = (i + rng.integers(1, n, size=trials)) % n
    d = q[j] - q[i]
    ln = np.hypot(d[:, 0], d[:, 1])
    ok = ln > 0
    if not ok.any():
        return []
    i, d, ln = i[ok], d[ok], ln[ok]
    nrm = np.column_stack([-d[:, 1], d[:, 0]]) / ln[:, None]
    off = np.einsum("ij,ij->i", q[i], nrm)
    inl = np.abs(q @ nrm.T - off) <= tol
    best = inl[:, int(np.argmax(inl.sum(0)))]
    for _ in range(3):  # TLS refit on the inliers
        if best.sum() < 2:
            break
        c = q[best].mean(0)
        _, _, vt = np.linalg.svd(q[best] - c, full_matrices=False)
        best = np.abs((q - c) @ vt[-1]) <= tol
    idx = np.flatnonzero(best)
    if len(idx) < min_points:
        return []
    cuts = np.flatnonzero(np.diff(idx) > max_gap + 1) + 1
    blocks = np.split(idx, cuts)
    blk = max(blocks, key=len)
    if len(blk) < min_points:
        return []
    a, b = int(blk[0]), int(blk[-1]) + 1
    seg = beams[a:b][best[a:b]]
    return (_extract_lines(p, beams[:a], sq, min_points, rng, trials, max_gap) + [seg]
            + _extract_lines(p, beams[b:], sq, min_points, rng, trials, max_gap))
