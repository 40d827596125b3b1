"""A board held in front of a wall: its returns cut out of a scan line that runs on along the wall.

The scan then reads wall - board - wall along almost one line, with a range step at the board's
edges that may be only a few noise sigmas (a wall 10 mm behind, 3 mm range noise). One step is
lost in the noise of one beam, but the whole board sits off the wall's line: the best cut of the
ordered points in three straight pieces (wall, board, wall) against one line is a likelihood
ratio test, decided by the Bayesian information criterion with the noise estimated from the
pieces' own residuals (Schwarz 1978: ``n ln(SSE_1 / SSE_3) > k ln n``; no range-noise model, so
quantised real ranges, whose neighbours repeat, cannot make it over-confident). What is known of
the board bounds where the cut may fall:

* without a pose (:func:`cut_candidates`): a straight segment longer than the board's longest
  chord (the diagonal of its printed pattern grown by the unknown margin) cannot be all board;
  the board is a piece at most that long;
* with a pose guess (:func:`cut_run`): the board frame of every return is known (the camera's
  board pose, eq. 1), so the board's edges fall between the printed pattern and the pattern
  grown by the margin; returns beyond that are the wall and fix its line.

Where the cut is not significant the returns beyond the board's extent are dropped and their share
reported, so the caller can say the board cannot be told from the surface behind it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .io.dataset import BoardSpec
from .scan_segments import LineSegment, _mad_scale, fit_line_2d


def pattern_extent(board: BoardSpec, grow_mm: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, float | np.ndarray]:
    """``(lo, hi, grow)``: the printed pattern's corners in the board frame (mm; one square beyond
    the outer inner corners) and how far beyond them the board's edge may lie: ``grow_mm`` per
    board axis ``(u, v)`` where the photos measured the margin
    (:meth:`lidarcal.board_margin.BoardMargins.grow_mm`), else the margin assumed, half the
    pattern's shorter side (the real TAPAS boards reach 1.6 squares beyond their pattern)."""
    c, r = board.inner_corners
    sq = board.square_mm
    lo, hi = np.array([-sq, -sq]), np.array([c * sq, r * sq])
    if grow_mm is not None:
        return lo, hi, np.asarray(grow_mm, float)
    return lo, hi, 0.5 * float(np.min(hi - lo))


def max_chord_mm(board: BoardSpec, grow_mm: np.ndarray | None = None) -> float:
    """The longest straight line across the board: the diagonal of its pattern grown by the margin
    of :func:`pattern_extent` on every side (mm)."""
    lo, hi, grow = pattern_extent(board, grow_mm)
    return float(np.linalg.norm(hi - lo + 2 * grow))


#: An outer piece must lie this many residual sigmas behind the board's line to be a wall (a
#: board's own margin, bent or read with a small bias, stays within about one sigma of it).
MIN_STEP_SIGMAS = 2.0


@dataclass(frozen=True)
class BoardCut:
    """The board piece ``[start, stop)`` of ordered points and the test that found it.

    ``gain`` is ``n ln(SSE_1 / SSE_cut)`` (twice the log likelihood ratio with the noise at its
    maximum-likelihood value), ``penalty`` BIC's ``k ln n`` (``k``: 3 per outer piece, a line and
    its breakpoint); ``step_sigmas``: how far the outer pieces lie behind the board piece's line
    beside it (the nearer of the two, :func:`_behind_sigmas`) in units of the cut model's
    residual sigma (inf when there is no outer piece)."""

    start: int
    stop: int
    gain: float
    penalty: float
    step_sigmas: float

    @property
    def significant(self) -> bool:
        """BIC prefers the cut, and every outer piece lies behind the board (a wall)."""
        return self.gain > self.penalty and self.step_sigmas >= MIN_STEP_SIGMAS


def _sse(cs: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """TLS sum of squared orthogonal residuals of the pieces ``[lo, hi)`` from prefix sums ``cs``
    (5, n + 1) of ``x, y, xx, xy, yy``; 0 for pieces of fewer than three points."""
    c = np.maximum(hi - lo, 1).astype(float)
    sx, sy, sxx, sxy, syy = cs[:, hi] - cs[:, lo]
    mx, my = sx / c, sy / c
    a, b, d = sxx - c * mx * mx, sxy - c * mx * my, syy - c * my * my
    out = np.maximum(0.5 * (a + d) - np.sqrt(0.25 * (a - d) ** 2 + b * b), 0.0)
    return np.where(hi - lo >= 3, out, 0.0)


def _behind_sigmas(p: np.ndarray, i: int, j: int, sse: float) -> float:
    """How far the outer pieces ``p[:i]``, ``p[j:]`` lie behind the TLS line of ``p[i:j]`` (the
    nearer of the two; mean distance along the line's normal pointing away from the LiDAR at the
    origin, over the outer returns within half the board's count of it: a long wall is not
    judged by the board's line extrapolated metres away), in units of the residual sigma of the
    three-line fit (``sse``); inf if neither."""
    line = fit_line_2d(p[i:j])
    away = 1.0 if line.offset >= 0 else -1.0  # normal . p = offset > 0 on the far side
    sigma = np.sqrt(sse / max(len(p) - 3 * ((i > 0) + (j < len(p)) + 1), 1))
    k = max((j - i) // 2, 3)  # beside the board only: its line extrapolated no farther
    steps = [away * float(np.mean(line.distance(q))) for q in (p[max(i - k, 0):i], p[j:j + k])
             if len(q)]
    return min(steps) / max(sigma, 1e-12) if steps else np.inf


def best_cut(p: np.ndarray, starts: np.ndarray, stops: np.ndarray,
             max_chord: float = np.inf) -> BoardCut | None:
    """The board piece ``p[i:j]`` of ordered points ``p`` (N, 2) with ``i`` in ``starts`` and
    ``j`` in ``stops`` (``i = 0`` / ``j = N``: no wall on that side), its chord at most
    ``max_chord`` mm: for each shape (a wall on the left, the right or both sides) the pair whose
    three-line fit (``p[:i]``, ``p[i:j]``, ``p[j:]``, each its own TLS line) leaves the least
    squared residual; of those, the significant one (:attr:`BoardCut.significant`: BIC against
    one line through all of ``p``, the walls behind the board) with the largest ``gain - penalty``,
    else the one with the largest. None if no pair is allowed."""
    n = len(p)
    q = p - p.mean(0)
    x, y = q[:, 0], q[:, 1]
    cs = np.zeros((5, n + 1))
    np.cumsum(np.array([x, y, x * x, x * y, y * y]), axis=1, out=cs[:, 1:])
    i, j = np.meshgrid(np.asarray(starts, int), np.asarray(stops, int), indexing="ij")
    i, j = i.ravel(), j.ravel()
    ok = (j - i >= 3) & (np.linalg.norm(p[np.maximum(j - 1, 0)] - p[i], axis=1) <= max_chord)
    ok &= (i > 0) | (j < n)  # one outer piece at least
    if not np.any(ok):
        return None
    i, j = i[ok], j[ok]
    sse = (_sse(cs, np.zeros_like(i), i) + _sse(cs, i, j) + _sse(cs, j, np.full_like(j, n)))
    sse1 = max(float(_sse(cs, np.array([0]), np.array([n]))[0]), 1e-300)
    cuts = []
    for shape in ((i > 0) & (j < n), (i > 0) & (j == n), (i == 0) & (j < n)):
        if not np.any(shape):
            continue
        b = np.flatnonzero(shape)[int(np.argmin(sse[shape]))]
        i0, j0 = int(i[b]), int(j[b])
        s = min(max(float(sse[b]), 1e-12 * sse1), sse1)
        cuts.append(BoardCut(i0, j0, n * float(np.log(sse1 / s)),
                             3 * ((i0 > 0) + (j0 < n)) * float(np.log(n)),
                             _behind_sigmas(p, i0, j0, s)))
    return max(cuts, key=lambda c: (c.significant, c.gain - c.penalty))


def cut_candidates(candidates: list[LineSegment], board: BoardSpec,
                   min_points: int, grow_mm: np.ndarray | None = None) -> list[LineSegment]:
    """The scan's candidate segments with every one longer than the board's longest chord
    (:func:`max_chord_mm`: it cannot be all board) replaced by its board piece (:func:`best_cut`,
    at most that long, ``min_points`` in every piece) when the three-line model is significant;
    others are kept as they are."""
    chord = max_chord_mm(board, grow_mm)
    out = []
    for s in candidates:
        p = s.points
        n = len(p)
        if n < 3 * min_points or np.linalg.norm(p[-1] - p[0]) <= chord:
            out.append(s)
            continue
        inner = np.arange(min_points, n - min_points + 1)
        cut = best_cut(p, np.concatenate([[0], inner]), np.concatenate([inner, [n]]), chord)
        if cut is None or not cut.significant or cut.stop - cut.start < min_points:
            out.append(s)
            continue
        q = p[cut.start:cut.stop]
        line = fit_line_2d(q)
        out.append(LineSegment(s.beams[cut.start:cut.stop], s.beams[cut.start:cut.stop], line,
                               _mad_scale(line.distance(q)), q, s.run))
    return out


def cut_run(p: np.ndarray, u: np.ndarray, board: BoardSpec, min_points: int,
            grow_mm: np.ndarray | None = None) -> tuple[int, int, float, BoardCut | None]:
    """The board's returns in a gated run of ordered scan points ``p`` (N, 2) whose board-frame
    coordinates (the pose guess and the camera's board pose, eq. 1) are ``u`` (N, 2), mm.

    Returns ``(start, stop, beside, cut)``: the board piece ``p[start:stop]``, the share of the
    run beyond the board's extent (:func:`pattern_extent`) that no significant step separates from
    it (0 when the run stays on the board; when the cut falls at the grown extent itself, the
    board piece's share between the pattern and that cut), and the test (None if not run). The
    breakpoints may fall only between the printed pattern and its grown extent (the board's
    unknown margin); returns beyond the extent are outer pieces (the wall's line). A run with
    fewer than ``min_points`` returns beside the pattern on both sides is left whole. With the
    margin measured in the photos (``grow_mm``, :func:`pattern_extent`) the returns beyond the
    grown extent (the margin plus three sigmas) are surely not the board's: with no significant
    step they are dropped without doubt (``beside`` counts only those beyond an assumed extent),
    and a cut at the grown extent is the board's edge found."""
    lo, hi, grow = pattern_extent(board, grow_mm)
    measured = np.asarray(grow) < pattern_extent(board)[2]  # per axis: the photos pinned the edge
    n = len(p)
    out = (u < lo - grow) | (u > hi + grow)
    beyond = np.any(out, axis=1)
    in_doubt = np.any(out & ~measured, axis=1)  # beyond an assumed extent: maybe the board's
    inside = np.all((u >= lo) & (u <= hi), axis=1)
    if not np.any(inside):
        return 0, n, 0.0, None
    a, b = int(np.argmax(inside)), n - int(np.argmax(inside[::-1]))  # the pattern's returns
    if a < min_points and b > n - min_points:  # nothing but the pattern's own returns
        return 0, n, 0.0, None
    left, right = beyond[:a], beyond[b:]
    i_lo = int(np.flatnonzero(left)[-1]) + 1 if np.any(left) else 0
    j_hi = b + int(np.flatnonzero(right)[0]) if np.any(right) else n
    starts = np.arange(max(i_lo, min_points), a + 1) if i_lo > 0 else np.concatenate(
        [[0], np.arange(min_points, a + 1)])
    stops = np.arange(b, min(j_hi, n - min_points) + 1) if j_hi < n else np.concatenate(
        [np.arange(b, n - min_points + 1), [n]])
    cut = best_cut(p, starts, stops)
    if cut is not None and cut.significant:
        # a step at the grown extent is no board edge found: the returns between the pattern and
        # it may be the wall's (a board's margin is well inside the grown extent)
        near = max(3, n // 50)  # returns: "at" the extent, give or take its noisy mapping
        loose = (cut.start - a if 0 < i_lo and cut.start <= i_lo + near else 0) + (
            cut.stop - b if j_hi < n and cut.stop >= j_hi - near else 0)
        loose = 0 if np.all(measured) else loose
        return cut.start, cut.stop, loose / (cut.stop - cut.start), cut
    return i_lo, j_hi, float(np.mean(in_doubt)), cut
