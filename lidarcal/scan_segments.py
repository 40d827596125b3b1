"""Straight pieces of a 2D scan: points (eq. 6), range noise, robust lines, segmentation.

Steps (1)-(3) of the V segmentation (:func:`lidarcal.scan.split_v`), usable for any board:
:func:`line_segments` cuts a scan into straight pieces (runs of connected returns, a top-down
split only where a second line halves the robust residual scale, a robust line per piece), so
a staircase of dark squares read a few mm farther, integer-mm ranges (``q^2 / 12``) and real
range ripple keep a board in one piece. It serves the V-board pipeline (``split_v``) and the
classic one-board calibration (:mod:`lidarcal.planes`, whose candidates are these pieces). The
noise is either from second differences (:func:`effective_range_noise`) or about straight lines
(:func:`local_line_noise`, for scanners that repeat a range over neighbouring beams).

Convention: the LiDAR frame is the scanner's (beam angle 0 = x axis, 90 deg = y axis); scan
points lie in its z = 0 plane. Lengths in mm, angles in radians inside (``_deg`` names at the
edges). Beams are in ascending angle order. :mod:`lidarcal.scan` re-exports the public names.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .geometry import MAD_TO_SIGMA, median

_TAN_MAX_INCIDENCE = 6.0  # surfaces up to ~80 deg incidence count as continuous
# a piece is two lines only if the second line at least halves the robust residual scale: a
# kink (the hinge, a mount) does; structure along one surface (a staircase of dark squares read
# farther, quantised ranges, a real sensor's range ripple) does not
_SPLIT_GAIN = 0.5
_LEVEL_RUN = 4  # consecutive beams off the line at one level: a square, not an outlier
#: Minimum inliers on a straight piece.
MIN_POINTS = 8
_SEED = np.random.SeedSequence(0)  # the RANSAC draws of every scan: default_rng(0)'s


# ---------------------------------------------------------------------------
# eq. (6)

def scan_points(angle_deg: np.ndarray, range_mm: np.ndarray) -> np.ndarray:
    """Scan points in the LiDAR plane, eq. (6): ``x = rho cos(theta), y = rho sin(theta)``.

    Parameters
    ----------
    angle_deg : array, shape (N,)
        Beam angles, degrees.
    range_mm : array, shape (N,)
        Ranges, mm; NaN (or <= 0) = no return.

    Returns
    -------
    points : array, shape (N, 2)
        Row ``i`` belongs to beam ``i`` (the index mapping is kept); beams
        without a return give a NaN row.
    """
    a = np.radians(np.asarray(angle_deg, dtype=float))
    r = np.asarray(range_mm, dtype=float)
    if a.shape != r.shape or a.ndim != 1:
        raise ValueError(f"angle_deg and range_mm must be 1-D of equal length, got {a.shape} "
                         f"and {r.shape}")
    r = np.where(np.isfinite(r) & (r > 0), r, np.nan)
    pts = np.empty((len(r), 2))
    np.multiply(r, np.cos(a), out=pts[:, 0])
    np.multiply(r, np.sin(a), out=pts[:, 1])
    return pts


def estimate_range_noise(range_mm: np.ndarray) -> float:
    """Robust range-noise estimate (mm) from second differences of neighbouring beams.

    On a smooth surface ``rho[i-1] - 2 rho[i] + rho[i+1]`` is noise with
    variance ``6 sigma^2`` (the curvature term is negligible at LiDAR angular
    steps); the MAD makes jumps, spurious returns and mixed pixels harmless.
    Only triples of three consecutive valid beams are used.
    """
    r = np.asarray(range_mm, dtype=float)
    d2 = r[:-2] - 2 * r[1:-1] + r[2:]
    d2 = d2[np.isfinite(d2)]
    if len(d2) < 5:
        raise ValueError(f"too few consecutive returns ({len(d2)} triples) to estimate the "
                         "range noise; pass range_noise_mm")
    # (the MAD ignores the order: d2, a temporary, is partitioned in place)
    return float(MAD_TO_SIGMA * median(np.abs(d2 - median(d2, overwrite=True)), overwrite=True)
                 / np.sqrt(6.0))


def estimate_range_quantum(range_mm: np.ndarray) -> float:
    """The ranges' resolution (mm): the smallest gap between distinct valid ranges, 0 if none.

    A Hokuyo UTM-30LX reports integer mm (1.0), a dataset written with one
    decimal 0.1. Accepted only when at least 99 % of the valid ranges are
    multiples of it (else 0: not quantised).
    """
    r = np.asarray(range_mm, dtype=float)
    r = r[np.isfinite(r) & (r > 0)]
    gaps = np.diff(np.sort(r))
    gaps = gaps[gaps > 0]  # between distinct ranges (np.diff(np.unique(r)))
    if len(gaps) < 2:  # fewer than 3 distinct ranges
        return 0.0
    q = float(gaps.min())
    k = r / q
    if q <= 0 or np.count_nonzero(np.abs(k - np.rint(k)) <= 1e-6) / len(k) < 0.99:  # (mean)
        return 0.0
    return q


def effective_range_noise(range_mm: np.ndarray) -> float:
    """Range noise (mm) for the segmentation thresholds: ``sqrt(sigma^2 + q^2 / 12)``.

    ``sigma`` from second differences (:func:`estimate_range_noise`), ``q`` the
    ranges' quantum (:func:`estimate_range_quantum`), whose rounding error is
    uniform with variance ``q^2 / 12``: on real quantised scans a third of the
    neighbouring ranges are equal, the second differences mostly 0 and their
    MAD alone would call the noise nil.
    """
    sigma = estimate_range_noise(range_mm)
    q = estimate_range_quantum(range_mm)
    return float(np.sqrt(sigma ** 2 + q ** 2 / 12.0))


# ---------------------------------------------------------------------------
# small 2D line helpers (total least squares)

@dataclass(frozen=True)
class Line2D:
    """Line ``normal . p = offset`` in the LiDAR plane, ``|normal| = 1``, mm."""

    normal: np.ndarray
    offset: float

    @property
    def direction(self) -> np.ndarray:
        return np.array([-self.normal[1], self.normal[0]])

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed orthogonal distance of points (N, 2), mm."""
        return np.asarray(points, dtype=float) @ self.normal - self.offset

    def foot(self, point: np.ndarray) -> np.ndarray:
        """Orthogonal projection of one point onto the line."""
        p = np.asarray(point, dtype=float)
        return p - (p @ self.normal - self.offset) * self.normal


def fit_line_2d(points: np.ndarray) -> Line2D:
    """Total-least-squares line through 2D points (minimises orthogonal distances).

    The normal is the eigenvector of the smallest eigenvalue of the centred points'
    2 x 2 scatter matrix (the last right singular vector), in closed form: the line's
    direction is at ``0.5 atan2(2 s_xy, s_xx - s_yy)``.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2:
        raise ValueError(f"A line needs points with shape (N >= 2, 2), got {p.shape}")
    x, y = p.T
    cx, cy = np.add.reduce(x) / len(p), np.add.reduce(y) / len(p)  # the centroid (as x.sum())
    dx, dy = x - cx, y - cy  # centred, each contiguous
    a = 0.5 * float(np.arctan2(2.0 * float(dx @ dy), float(dx @ dx) - float(dy @ dy)))
    nx, ny = -math.sin(a), math.cos(a)  # (math's sin and cos round as numpy's do)
    return Line2D(np.array([nx, ny]), nx * float(cx) + ny * float(cy))


def _tls_sse_splits(p: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """TLS sum of squared orthogonal residuals of p[:k] + p[k:] for k in [lo, hi) (prefix sums)."""
    q = p - np.add.reduce(p) / len(p)  # (p.mean(0))
    n = len(q)

    def sse(cnt, sx, sy, sxx, sxy, syy):
        mx, my = sx / cnt, sy / cnt
        a = sxx - cnt * mx * mx
        b = sxy - cnt * mx * my
        c = syy - cnt * my * my
        # smallest eigenvalue of [[a, b], [b, c]]
        return np.maximum(0.5 * (a + c) - np.sqrt(0.25 * (a - c) ** 2 + b * b), 0.0)

    x, y = q[:, 0], q[:, 1]
    cs = np.zeros((5, n + 1))  # cs[:, i]: the moments of p[:i], one contiguous row each
    np.cumsum(np.array([x, y, x * x, x * y, y * y]), axis=1, out=cs[:, 1:])
    k = np.arange(lo, hi)
    left = cs[:, lo:hi]  # moments of p[:k], then of p[k:]: both sides in one pass
    both = sse(np.concatenate([k, n - k]).astype(float),
               *np.concatenate([left, cs[:, -1:] - left], axis=1))
    return both[:len(k)] + both[len(k):]


def _tls_sse_three(p: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TLS sum of squared orthogonal residuals of ``p[:i] + p[i:j] + p[j:]`` for every pair
    ``i < j`` leaving at least ``m`` points in each piece (prefix sums, all pairs at once).

    Returns ``(sse, i, j)``, each shape (pairs,)."""
    q = p - np.add.reduce(p) / len(p)
    n = len(q)
    x, y = q[:, 0], q[:, 1]
    cs = np.zeros((5, n + 1))
    np.cumsum(np.array([x, y, x * x, x * y, y * y]), axis=1, out=cs[:, 1:])
    i, j = np.triu_indices(n + 1, k=m)
    keep = (i >= m) & (j <= n - m)
    i, j = i[keep], j[keep]

    def sse(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        c = (hi - lo).astype(float)
        sx, sy, sxx, sxy, syy = cs[:, hi] - cs[:, lo]
        mx, my = sx / c, sy / c
        a, b, d = sxx - c * mx * mx, sxy - c * mx * my, syy - c * my * my
        return np.maximum(0.5 * (a + d) - np.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0)

    return sse(np.zeros_like(i), i) + sse(i, j) + sse(j, np.full_like(j, n)), i, j


def _mad_scale(r: np.ndarray) -> float:
    """Robust scale of residuals: 1.4826 x median absolute deviation from their median."""
    return float(MAD_TO_SIGMA * median(np.abs(r - median(r)), overwrite=True))


class _PieceScales:
    """Robust residual scales of TLS lines through pieces ``p[a:b]`` of one run of points,
    each line fitted once: the top-down split (:func:`_split_into_lines`) and the merge
    (:func:`_merge_collinear`) ask for the same pieces (a split's two halves are the next
    level's pieces; a merge test of two halves is the split test that cut them). The robust
    line of a final piece starts from the same TLS line when RANSAC keeps all its points
    (:meth:`fitted`)."""

    def __init__(self, p: np.ndarray) -> None:
        self.p = p
        self._fit: dict[tuple[int, int], tuple[Line2D, np.ndarray]] = {}
        self._one: dict[tuple[int, int], float] = {}
        self._two: dict[tuple[int, int, int], float] = {}
        self._three: dict[tuple[int, int, int, int], float] = {}

    def residuals(self, a: int, b: int) -> np.ndarray:
        """Signed orthogonal residuals of ``p[a:b]`` to their TLS line."""
        if (a, b) not in self._fit:
            q = self.p[a:b]
            line = fit_line_2d(q)
            self._fit[a, b] = line, line.distance(q)
        return self._fit[a, b][1]

    def fitted(self, a: int, b: int) -> tuple[Line2D, np.ndarray] | None:
        """The TLS line of ``p[a:b]`` and its residuals when the split or the merge fitted it."""
        return self._fit.get((a, b))

    def one(self, a: int, b: int) -> float:
        """MAD scale of the residuals of one line through ``p[a:b]``."""
        if (a, b) not in self._one:
            self._one[a, b] = _mad_scale(self.residuals(a, b))
        return self._one[a, b]

    def two(self, a: int, k: int, b: int) -> float:
        """MAD scale of the pooled residuals of lines through ``p[a:k]`` and ``p[k:b]``."""
        if (a, k, b) not in self._two:
            self._two[a, k, b] = _mad_scale(np.concatenate([self.residuals(a, k),
                                                            self.residuals(k, b)]))
        return self._two[a, k, b]

    def three(self, a: int, i: int, j: int, b: int) -> float:
        """MAD scale of the pooled residuals of lines through ``p[a:i]``, ``p[i:j]``, ``p[j:b]``."""
        if (a, i, j, b) not in self._three:
            self._three[a, i, j, b] = _mad_scale(np.concatenate(
                [self.residuals(a, i), self.residuals(i, j), self.residuals(j, b)]))
        return self._three[a, i, j, b]


def _split_into_lines(p: np.ndarray, sigma: float, min_points: int,
                      scales: _PieceScales | None = None, a: int = 0,
                      b: int | None = None, steps: bool = False) -> list[tuple[int, int]]:
    """Top-down split of ordered points ``p[a:b]`` (all of ``p`` by default) into line pieces,
    as [start, end) ranges of ``p``.

    A piece is split at the breakpoint minimising the two-line TLS error while
    its single-line residuals have a robust scale (MAD) above ``2 sigma`` *and*
    the two lines at least halve that scale (``_SPLIT_GAIN``): the test adapts
    to the measured residuals, so a surface whose ranges step by a few mm
    along it (dark squares read farther, quantised or rippled real ranges)
    stays one piece, while a kink (the hinge, a mount) is split. ``scales``
    holds the pieces' line fits (shared with :func:`_merge_collinear`).

    ``steps``: when no single cut halves the scale, the best cut in three is tried
    (:func:`_step_cut`). A board held a few cm in front of a wall runs wall - board - wall
    along almost one line: any single cut leaves one range step in a piece, two cuts take the
    board out (a staircase of dark squares has many small steps, which no three lines halve).
    """
    scales = _PieceScales(p) if scales is None else scales
    b = len(p) if b is None else b
    n = b - a
    if n < 2 * min_points:
        return [(a, b)]
    scale = scales.one(a, b)
    cut: tuple[int, ...] | None = None
    if scale > 2.0 * sigma:
        sse = _tls_sse_splits(p[a:b], min_points, n - min_points + 1)
        k = a + min_points + int(np.argmin(sse))
        if scales.two(a, k, b) <= _SPLIT_GAIN * scale:
            cut = (k,)
    if cut is None and steps and n >= 3 * min_points:
        cut = _step_cut(p, sigma, min_points, scales, a, b, scale)
    if cut is None:
        return [(a, b)]
    ends = (a, *cut, b)
    return [piece for lo, hi in itertools.pairwise(ends)
            for piece in _split_into_lines(p, sigma, min_points, scales, lo, hi, steps)]


#: A range step this many range-noise sigmas between a piece and the line of its neighbours
#: makes it a surface of its own (:func:`_step_cut`).
STEP_SIGMAS = 6.0


def _step_cut(p: np.ndarray, sigma: float, min_points: int, scales: _PieceScales, a: int,
              b: int, scale: float) -> tuple[int, int] | None:
    """The best cut of ``p[a:b]`` in three (least three-line TLS error over every pair of
    breakpoints, :func:`_tls_sse_three`) when its middle piece is a surface of its own: either
    the three lines halve the robust residual scale (the test of :func:`_split_into_lines`), or
    the middle piece lies at least :data:`STEP_SIGMAS` noise sigmas off the line through the
    outer two and the three lines at least quarter the sum of squares of one (a board a few cm
    in front of a wall on a small share of the piece, which the MAD scale does not see)."""
    sse3, ii, jj = _tls_sse_three(p[a:b], min_points)
    best = int(np.argmin(sse3))
    i, j = a + int(ii[best]), a + int(jj[best])
    if scale > 2.0 * sigma and scales.three(a, i, j, b) <= _SPLIT_GAIN * scale:
        return i, j
    sse1 = float(np.sum(scales.residuals(a, b) ** 2))
    if sse3[best] > 0.25 * sse1:
        return None
    outer = fit_line_2d(np.concatenate([p[a:i], p[j:b]]))
    if abs(float(np.mean(outer.distance(p[i:j])))) < STEP_SIGMAS * sigma:
        return None
    return i, j


def _merge_collinear(p: np.ndarray, pieces: list[tuple[int, int]],
                     scales: _PieceScales | None = None) -> list[tuple[int, int]]:
    """Merge neighbouring pieces that are one line by the split test of :func:`_split_into_lines`.

    Two adjacent pieces are merged when one line through both has a robust
    residual scale below ``1 / _SPLIT_GAIN`` times that of their own two lines
    (the top-down split may cut a long staircase where neither half is straight).
    ``scales`` holds the pieces' line fits (shared with the split).
    """
    scales = _PieceScales(p) if scales is None else scales
    out = list(pieces)
    merged = True
    while merged and len(out) > 1:
        merged = False
        for i in range(len(out) - 1):
            (a, k), (_, b) = out[i], out[i + 1]
            if scales.one(a, b) * _SPLIT_GAIN < scales.two(a, k, b):
                out[i:i + 2] = [(a, b)]
                merged = True
                break
    return out


def _robust_line(p: np.ndarray, sigma: float, rng: np.random.Generator,
                 k: float = 3.5, trials: int = 100) -> tuple[Line2D, np.ndarray, float]:
    """RANSAC (threshold ``k sigma``) then iterated TLS refit, threshold ``k`` x MAD scale.

    Returns the line, the inlier mask and the robust residual scale (mm).
    (:func:`line_segments` runs the two steps, :func:`_ransac_masks` and
    :func:`_refine_line`, on all the pieces of a scan at once.)
    """
    return _refine_line(p, sigma, _ransac_masks([p], sigma, rng, k, trials)[0], k)


def _ransac_masks(pieces: list[np.ndarray], sigma: float, rng: np.random.Generator,
                  k: float = 3.5, trials: int = 100) -> list[np.ndarray]:
    """RANSAC on each piece of points (threshold ``k sigma``): the inliers of the line through
    the pair of distinct points, of ``trials`` random pairs, that has the most inliers.

    The pairs are drawn piece after piece (the same draws as one piece at a time); their
    normals and offsets are computed for all pieces at once, the inlier counts per piece (a
    hypothesis sees only its own piece's points). A piece of at most 3 points keeps them all.
    """
    drawn = [n > 3 for n in map(len, pieces)]
    if not any(drawn):
        return [np.ones(len(q), bool) for q in pieces]
    first, second, start = [], [], 0  # pair indices into the pieces' concatenated points
    for q, drew in zip(pieces, drawn):
        n = len(q)
        if drew:
            i = rng.integers(n, size=trials)
            first.append(start + i)
            second.append(start + (i + rng.integers(1, n, size=trials)) % n)
        start += n
    P = np.concatenate(pieces)
    pi = P[np.concatenate(first)]
    d = P[np.concatenate(second)] - pi
    ln = np.hypot(d[:, 0], d[:, 1])
    hyp = np.empty((len(ln), 3))  # each hypothesis line as (normal, -offset)
    with np.errstate(divide="ignore", invalid="ignore"):  # (a pair of equal points: not used)
        np.divide(d[:, ::-1] * (-1.0, 1.0), ln[:, None], out=hyp[:, :2])  # (-dy, dx) / |d|
    hyp[:, 2] = -np.einsum("ij,ij->i", pi, hyp[:, :2])
    P1 = np.column_stack([P, np.ones(len(P))])  # points as (x, y, 1)
    good = ln > 0
    n_good = np.add.reduceat(good, np.arange(0, len(good), trials), dtype=np.intp)
    count = np.uint16 if max(map(len, pieces)) < 2 ** 16 else np.intp  # (the smallest that fits)
    out, h, start = [], 0, 0
    for q, drew in zip(pieces, drawn):
        n = len(q)
        start += n
        if not drew:
            out.append(np.ones(n, bool))
            continue
        rows = slice(h, h + trials)
        g = int(n_good[h // trials])
        h += trials
        if g == 0:
            out.append(np.ones(n, bool))
            continue
        H = hyp[rows] if g == trials else hyp[rows][good[rows]]
        # (hypotheses, n) signed distances n . p - offset in one product (the same sums as
        # n . p then minus the offset), their absolute values in place
        dist = H @ P1[start - n:start].T
        inl = np.abs(dist, out=dist) <= k * sigma
        # inliers per hypothesis: a row sum of bytes (count_nonzero along an axis is slower)
        out.append(inl[int(inl.view(np.uint8).sum(axis=1, dtype=count).argmax())])
    return out


def _refine_line(p: np.ndarray, sigma: float, best: np.ndarray, k: float = 3.5,
                 fitted: tuple[Line2D, np.ndarray] | None = None
                 ) -> tuple[Line2D, np.ndarray, float]:
    """Iterated TLS refit from the RANSAC inliers ``best``, threshold ``k`` x MAD scale, then
    the levels of a staircase kept (:func:`_level_runs`): the line, its inliers, the scale.

    ``fitted``: the TLS line of all of ``p`` and its residuals, if known (the split's); used
    when RANSAC keeps every point (the first fit is then that line).
    """
    mask = best
    n_in = np.count_nonzero(mask)
    of_mask = n_in >= 2  # ``line`` is the TLS line of ``p[mask]``
    resid = None  # ``line``'s residuals, when known
    if n_in == len(p) and fitted is not None:
        line, resid = fitted
    else:  # (all points: the same fit without gathering them)
        line = fit_line_2d(p if n_in == len(p) or not of_mask else p[mask])
    scale = sigma
    for _ in range(20):
        r = np.abs(line.distance(p) if resid is None else resid)
        resid = None
        # MAD of all the piece's residuals: robust to the few outliers, and not shrunk by
        # re-estimating it from already-trimmed inliers
        scale = max(MAD_TO_SIGMA * median(r), 0.25 * sigma)
        new = r <= k * scale
        n_new = np.count_nonzero(new)
        if n_new < 2:
            break
        # the same inliers (np.array_equal): as many, and every point or the same points
        same = n_new == n_in and (n_new == len(p) or bool((new == mask).all()))
        if not (same and of_mask):  # (a refit of the same points would give this line again)
            line = fit_line_2d(p if n_new == len(p) else p[new])
        if same:
            break
        mask, of_mask, n_in = new, True, n_new
    if len(p) - n_in >= _LEVEL_RUN:  # (else no run of rejected points)
        levels = _level_runs(p, line, mask, sigma)
        if levels.any():
            mask = mask | levels
            line = fit_line_2d(p[mask])
    return line, mask, float(scale)


def _level_runs(p: np.ndarray, line: Line2D, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Rejected points that are a level of the surface, not outliers: a staircase of squares.

    A time-of-flight LiDAR reads dark squares a few mm farther than white
    ones; when that step is large against the noise the robust line keeps one
    level and rejects the other. Outliers (spurious returns, mixed pixels) are
    isolated beams; a level is a run of at least ``_LEVEL_RUN`` consecutive
    rejected points lying parallel to the line (their residuals' robust
    spread within ``3 sigma``) and offset from it by no more than the range
    step the run detection (:func:`_runs`) accepts between neighbouring beams
    on one surface (``6 sqrt(2) sigma + _TAN_MAX_INCIDENCE x`` point spacing).
    """
    out = np.zeros(len(p), bool)
    bad = np.flatnonzero(~mask)
    if len(bad) < _LEVEL_RUN:
        return out
    r = line.distance(p)
    spacing = median(np.hypot(*np.diff(p, axis=0).T))
    tau = 6 * np.sqrt(2) * sigma + _TAN_MAX_INCIDENCE * spacing
    for run in np.split(bad, np.flatnonzero(np.diff(bad) > 1) + 1):
        rr = r[run]
        if (len(run) >= _LEVEL_RUN and abs(median(rr)) <= tau
                and _mad_scale(rr) <= 3 * sigma):
            out[run] = True
    return out


@dataclass
class LineSegment:
    """One straight piece of a scan (:func:`line_segments`).

    ``beams``: beam indices of the inliers of its robust line (sorted);
    ``span``: every beam index of the piece (sorted); ``line``: the robust
    line; ``scale``: robust scale of its residuals, mm; ``points``: the
    inliers' eq. (6) points (N, 2), mm; ``run``: label of the connected run of
    returns it was cut from.
    """

    beams: np.ndarray
    span: np.ndarray
    line: Line2D
    scale: float
    points: np.ndarray
    run: int = 0


def _runs(rho: np.ndarray, valid_idx: np.ndarray, dtheta: float, sigma: float,
          max_gap: int) -> np.ndarray:
    """Connected runs of returns: beams at most ``max_gap`` apart whose range jump is small.

    The allowed jump between beams ``g`` apart is ``6 sqrt(2) sigma + 6 g rho dtheta``
    (noise plus a surface seen at up to ~80 deg incidence); depth edges are far larger.
    Skipping up to ``max_gap`` beams bridges dropouts and isolated spurious returns.
    Returns the connected-component label of each valid return (:func:`_component_labels`).
    """
    m = len(valid_idx)
    if m < 2:
        return np.zeros(m, int)
    r = rho[valid_idx]
    lags = np.arange(1, min(max_gap, m - 1) + 1)  # return i and return i + lag, lag < m
    # every lag at once, (lags, m): past the last return, no range (NaN) and no beam
    ahead = np.arange(m) + lags[:, None]
    r_ahead = np.concatenate([r, np.full(len(lags), np.nan)])[ahead]
    g = np.concatenate([valid_idx, np.full(len(lags), valid_idx[-1] + max_gap + 1)])[ahead] \
        - valid_idx
    rr = np.minimum(r_ahead, r)
    tau = 6 * np.sqrt(2) * sigma + _TAN_MAX_INCIDENCE * g * rr * dtheta
    ok = (g <= max_gap) & (np.abs(r_ahead - r) <= tau)
    return _component_labels(ok)


def _component_labels(edge: np.ndarray) -> np.ndarray:
    """Connected components of the graph on ``m`` ordered nodes with the edges ``i -> i + lag``
    where ``edge[lag - 1, i]`` (shape (lags, m)), labelled ``0, 1, ...`` in the order of each
    component's first node, as :func:`scipy.sparse.csgraph.connected_components` does.

    The edges join nodes a few places apart, so the components are almost always blocks of
    consecutive nodes, bar isolated nodes (no edge: a spurious return, bridged over): each
    node joined to an earlier one belongs to a block that starts at a node joined only to
    later ones. That is exact when no edge passes over such a starting node (it then cuts
    the order in two; the isolated nodes touch no edge); otherwise the graph is labelled by
    :func:`connected_components` (sparse graph, depth-first search).
    """
    n_lags, m = edge.shape
    back = np.zeros(m, bool)  # node joined to an earlier node
    over = np.zeros(m, bool)  # node strictly between the two ends of some edge
    for lag in range(1, n_lags + 1):
        e = edge[lag - 1, :m - lag]  # (edges from the last lag nodes would leave the graph)
        back[lag:] |= e
        for d in range(1, lag):
            over[d:m - lag + d] |= e
    fwd = edge.any(axis=0)  # node joined to a later node
    starts = fwd & ~back
    if not np.any(starts & over):
        node = np.arange(m)
        first = np.maximum.accumulate(np.where(starts, node, 0))  # the first node of its block
        alone = ~(fwd | back)
        first[alone] = node[alone]
        return (np.cumsum(starts | alone) - 1)[first]  # components by their first node
    lag, rows = np.nonzero(edge)
    graph = coo_matrix((np.ones(len(rows)), (rows, rows + lag + 1)), shape=(m, m))
    return connected_components(graph, directed=False)[1]


def line_segments(angle_deg: np.ndarray, range_mm: np.ndarray, *,
                  range_noise_mm: float | None = None, min_points: int = MIN_POINTS,
                  max_gap: int = 4, steps: bool = False) -> tuple[list[LineSegment], float]:
    """The straight pieces of one scan, in beam order, and the range noise used (mm).

    Steps (1)-(3) of :func:`lidarcal.scan.split_v`, usable for any board (a flat one too):
    (1) runs of returns connected in beam order (:func:`_runs`); (2) each run
    cut top-down into straight pieces (:func:`_split_into_lines`: a cut must
    halve the robust residual scale, so a staircase of dark squares read a few
    mm farther or quantised, rippled real ranges stay one piece) and
    neighbouring collinear pieces merged (:func:`_merge_collinear`); (3) a
    robust line per piece (:func:`_robust_line`: RANSAC, iterated TLS at 3.5 x
    the MAD scale, runs of consecutive beams at one offset kept as a level of
    the surface). Pieces with fewer than ``min_points`` inliers are dropped.

    The noise is ``range_noise_mm`` if given, else :func:`effective_range_noise`
    (second differences plus the quantisation's ``q^2 / 12``). ``steps``: also cut a piece in
    three where one surface is offset from the line of its neighbours (a board a few cm in
    front of a wall, see :func:`_split_into_lines`); the V pipeline leaves it off.
    """
    ang = np.asarray(angle_deg, dtype=float)
    pts = scan_points(ang, range_mm)
    return _line_segments(ang, pts, np.hypot(pts[:, 0], pts[:, 1]), range_noise_mm, min_points,
                          max_gap, steps)


def _line_segments(ang: np.ndarray, pts: np.ndarray, rho: np.ndarray,
                   range_noise_mm: float | None, min_points: int,
                   max_gap: int, steps: bool = False) -> tuple[list[LineSegment], float]:
    """:func:`line_segments` of a scan's beam angles (deg), eq. (6) points and ranges (mm)."""
    if np.any(np.diff(ang) <= 0):
        raise ValueError("scan angles must be strictly ascending (beam order)")
    valid_idx = np.flatnonzero(np.isfinite(rho))
    if len(valid_idx) < min_points:
        return [], float(range_noise_mm or 0.0)
    sigma = float(range_noise_mm) if range_noise_mm is not None else effective_range_noise(rho)
    r_valid = rho[valid_idx]
    if sigma < 1e-6 * r_valid.max():  # (else the floor, a millionth of the median range, is lower)
        sigma = max(sigma, 1e-6 * median(r_valid))
    dtheta = median(np.diff(np.radians(ang)))
    rng = np.random.Generator(np.random.PCG64(_SEED))  # np.random.default_rng(0)

    labels = _runs(rho, valid_idx, dtheta, sigma, max_gap)
    pieces = []  # (run label, beams of the piece, its points, its TLS line if fitted)
    for lab in np.flatnonzero(np.bincount(labels) >= min_points):  # (labels 0, 1, ...)
        beams = valid_idx[labels == lab]
        p = pts[beams]
        scales = _PieceScales(p)
        for a, b in _merge_collinear(p, _split_into_lines(p, sigma, min_points, scales,
                                                            steps=steps), scales):
            pieces.append((int(lab), beams[a:b], p[a:b], scales.fitted(a, b)))
    segments: list[LineSegment] = []
    ransac = _ransac_masks([q for _, _, q, _ in pieces], sigma, rng)
    for (lab, span, q, fitted), best in zip(pieces, ransac):
        line, mask, scale = _refine_line(q, sigma, best, fitted=fitted)
        if np.count_nonzero(mask) >= min_points:
            segments.append(LineSegment(span[mask], span, line, scale, q[mask], lab))
    segments.sort(key=lambda s: s.beams[0])
    return segments, sigma


def local_line_noise(angle_deg: np.ndarray, range_mm: np.ndarray, window: int = 15) -> float:
    """Noise (mm) about straight lines: the median over windows of ``window`` neighbouring
    returns of their TLS residual RMS (``n - 2`` degrees of freedom), at least 0.3 mm.

    Unlike second differences of ranges (:func:`effective_range_noise`), this is not fooled by
    scanners that repeat a range over neighbouring beams (the real UTM-30LX recordings repeat
    28-32 %), and it includes the integer-mm quantisation; windows across a jump or a corner are
    outvoted. With fewer than three clean windows: the second-difference estimate (>= 0.5 mm).
    """
    p = scan_points(angle_deg, range_mm)
    ok = np.isfinite(p[:, 0])
    out = []
    for s in range(0, len(p) - window + 1, max(1, window // 3)):
        if ok[s:s + window].all():
            q = p[s:s + window]
            r = fit_line_2d(q).distance(q)
            out.append(np.sqrt(np.sum(r ** 2) / (window - 2)))
    if len(out) < 3:
        try:
            return max(estimate_range_noise(range_mm), 0.5)
        except ValueError:
            return 1.0
    return float(max(np.median(out), 0.3))
