"""Scan lines in the LiDAR frame: V segmentation, constrained lines (eqs. 7-12).

The points (eq. 6), range noise and straight pieces of a scan are in
:mod:`lidarcal.scan_segments` (re-exported here: ``from lidarcal.scan import line_segments``).

Convention: the LiDAR frame is the scanner's (beam angle 0 = x axis, 90 deg =
y axis, z = x cross y); scan points lie in its z = 0 plane. Lengths in mm,
angles in radians inside (``_deg`` names at the edges). Beams are in
ascending angle order, i.e. counter-clockwise about the LiDAR z axis.

Which way L2 turns from L1 (the trap of eq. 8)
----------------------------------------------
Let ``l1`` be the ray from the vertex E towards segment 1 (the lower beam
angles) and ``l2`` the ray towards segment 2 (eq. 12). The V-board is
*concave* seen from the scanner (its hinge is the far point), and beams sweep
counter-clockwise, so segment 1 lies clockwise of segment 2 as seen from the
origin while E lies beyond both. Then ``l2`` is ``l1`` turned *clockwise* by
alpha: ``l2 = Rot(-alpha) l1``, ``z . (l1 x l2) = -sin(alpha) < 0``. As lines
(directions modulo pi) that is the paper's ``tan(beta - alpha)`` of eq. (8).
Example: E = (1000, 0), l1 at 240 deg, l2 at 120 deg. A convex V (hinge
towards the scanner) or beams in clockwise order would flip it to
``beta + alpha``. :func:`fit_v_lines` reads the turn sign from the free fit
(``sign`` in :class:`LidarLines`, -1 for the concave V), and the tests confirm
it on ray-cast scans.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from .geometry import median
from .scan_segments import (  # noqa: F401  (re-exported: the segmentation lives there)
    Line2D,
    LineSegment,
    _line_segments,
    effective_range_noise,
    estimate_range_noise,
    estimate_range_quantum,
    fit_line_2d,
    line_segments,
    local_line_noise,
    scan_points,
)

# ---------------------------------------------------------------------------
# small 2D line helpers (the TLS line itself: :func:`fit_line_2d`)

def intersect_lines_2d(a: Line2D, b: Line2D) -> np.ndarray:
    """The common point of two lines (2 x 2 linear system)."""
    A = np.array([a.normal, b.normal])
    if abs(np.linalg.det(A)) < 1e-9:
        raise ValueError("lines are parallel: no vertex")
    return np.linalg.solve(A, np.array([a.offset, b.offset]))


def _rot2(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s], [s, c]])


def _cross2(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def _unit2(v: np.ndarray) -> np.ndarray:
    n = math.sqrt(float(v @ v))  # np.linalg.norm(v), as it computes it
    if n == 0:
        raise ValueError("degenerate V: a segment end coincides with the vertex")
    return v / n


# ---------------------------------------------------------------------------
# V segmentation

def _segment_ends(segments: list[LineSegment], pts: np.ndarray) -> np.ndarray:
    """Every segment's line (normal ``nx, ny``, offset ``c``), the feet of its first and last
    points on it (``fx, fy`` and ``gx, gy``) and the distance between those two points
    (``length``): rows ``nx, ny, c, fx, fy, gx, gy, length`` over the segments (columns),
    for :func:`_v_pairs`."""
    nx, ny = np.array([sg.line.normal for sg in segments]).T
    c = np.array([sg.line.offset for sg in segments], dtype=float)
    ends = pts[[sg.beams[0] for sg in segments] + [sg.beams[-1] for sg in segments]]
    x, y = ends.T  # first points, then last points
    n2x, n2y, c2 = np.tile(nx, 2), np.tile(ny, 2), np.tile(c, 2)
    r = x * n2x + y * n2y - c2
    fx, fy = x - r * n2x, y - r * n2y
    S = len(segments)
    return np.array([nx, ny, c, fx[:S], fy[:S], fx[S:], fy[S:],
                     np.hypot(x[S:] - x[:S], y[S:] - y[:S])])


def _v_pairs(segments: list[LineSegment], pts: np.ndarray, rho: np.ndarray, lo: float,
             hi: float, alpha: float | None, alpha_tol_deg: float,
             max_segment_mm: float | None = None) -> list[tuple]:
    """Step (4) of :func:`split_v`: the pairs of segments that form the V, as ``(points,
    segment 1, segment 2, opening)`` in beam order of segment 1, then of segment 2.

    Every pair of segments at most 3 apart in beam order is tested at once (arrays over the
    pairs): the lines' vertex E, the eq. (12) rays l1 (E to the foot of segment 1's first
    point) and l2 (E to the foot of segment 2's last point), a concave turn (``z . (l1 x l2)
    < 0``) with an opening in ``[lo, hi]`` rad (and within ``alpha_tol_deg`` of ``alpha``),
    the vertex at the inner ends (at most 10 % beyond them into a segment, 25 % short of
    them), each segment at most ``max_segment_mm`` long (when given: a board is not a
    wall); segments between the two in beam order must lie farther than E (seen through a
    gap at the hinge).
    """
    ii, jj = [], []
    for i in range(len(segments)):
        for j in range(i + 1, min(i + 4, len(segments))):
            ii.append(i)
            jj.append(j)
    i, j = np.array(ii, dtype=int), np.array(jj, dtype=int)
    e = _segment_ends(segments, pts)
    # f1: foot of segment 1's first point, g1: of its last (inner end); h2: foot of
    # segment 2's first point (inner end), f2: of its last
    n1x, n1y, c1, f1x, f1y, g1x, g1y, len1 = e[:, i]
    n2x, n2y, c2, h2x, h2y, f2x, f2y, len2 = e[:, j]
    with np.errstate(divide="ignore", invalid="ignore"):
        det = n1x * n2y - n1y * n2x
        Ex, Ey = (c1 * n2y - n1y * c2) / det, (n1x * c2 - c1 * n2x) / det
        d1x, d1y = f1x - Ex, f1y - Ey
        d2x, d2y = f2x - Ex, f2y - Ey
        m1, m2 = np.hypot(d1x, d1y), np.hypot(d2x, d2y)
        l1x, l1y, l2x, l2y = d1x / m1, d1y / m1, d2x / m2, d2y / m2
        cross = l1x * l2y - l1y * l2x
        opening = np.arctan2(np.abs(cross), l1x * l2x + l1y * l2y)
        gap1 = (g1x - Ex) * l1x + (g1y - Ey) * l1y  # inner end of 1, along l1
        gap2 = (h2x - Ex) * l2x + (h2y - Ey) * l2y
        ok = ((np.abs(det) >= 1e-9) & (m1 != 0) & (m2 != 0)  # a vertex, not at a segment end
              & (cross < 0) & (lo <= opening) & (opening <= hi)  # concave, opening in range
              & (-0.1 * len1 <= gap1) & (gap1 <= 0.25 * len1)
              & (-0.1 * len2 <= gap2) & (gap2 <= 0.25 * len2))
        if alpha is not None:
            ok &= ~(np.abs(opening - alpha) > np.radians(alpha_tol_deg))
        if max_segment_mm is not None:
            ok &= (len1 <= max_segment_mm) & (len2 <= max_segment_mm)
    med_rho: dict[int, float] = {}

    def median_range(m: int) -> float:  # a segment's median range, when asked
        if m not in med_rho:
            med_rho[m] = median(rho[segments[m].beams])
        return med_rho[m]

    candidates = []
    for k in np.flatnonzero(ok):
        a, b = int(i[k]), int(j[k])
        rE = np.hypot(Ex[k], Ey[k])
        if not all(median_range(m) > rE for m in range(a + 1, b)):
            continue
        candidates.append((len(segments[a].beams) + len(segments[b].beams), segments[a],
                           segments[b], float(opening[k])))
    return candidates


@dataclass(frozen=True)
class VSegments:
    """The two board segments of one scan (section 1.4), in beam-angle order.

    ``index1`` / ``index2`` are the beams (indices into the scan arrays) kept
    on board 1 (lower beam angles) and board 2; ``points1`` / ``points2`` their
    eq. (6) points. ``rejected1`` / ``rejected2`` are returns inside each
    segment's beam span that were left out (off the line: spurious returns,
    mixed pixels at the outer edges). ``noise_mm`` is the range noise used for
    the thresholds, ``scale1_mm`` / ``scale2_mm`` the robust (MAD) scale of
    the orthogonal residuals, ``opening_deg`` the free-fit angle between the
    segments, measured as in eq. (12).
    """

    index1: np.ndarray
    index2: np.ndarray
    points1: np.ndarray
    points2: np.ndarray
    rejected1: np.ndarray
    rejected2: np.ndarray
    noise_mm: float
    scale1_mm: float
    scale2_mm: float
    opening_deg: float
    info: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def first(self) -> np.ndarray:
        """Alias of ``index1`` (beams of segment 1, the lower beam angles)."""
        return self.index1

    @property
    def second(self) -> np.ndarray:
        """Alias of ``index2``."""
        return self.index2


def _trim_outer(beams: np.ndarray, resid: np.ndarray, scale: float, from_start: bool,
                max_trim: int) -> np.ndarray:
    """Drop up to ``max_trim`` outermost points while their residual exceeds ``2.5 scale``."""
    keep = np.ones(len(beams), bool)
    order = range(len(beams)) if from_start else range(len(beams) - 1, -1, -1)
    for t, i in enumerate(order):
        if t >= max_trim or abs(resid[i]) <= 2.5 * scale:
            break
        keep[i] = False
    return keep


def full_circle_cut(angle_deg: np.ndarray, range_mm: np.ndarray) -> int:
    """Where to start a 360 deg scan so that the V is not cut by its first and last beams:
    the middle of its longest run of beams without a return (else of its largest range
    jump); 0 for a scan that does not close the circle or has no return at its first or last
    beam (nothing straddles the seam)."""
    ang = np.asarray(angle_deg, dtype=float)
    n = len(ang)
    if n < 3:
        return 0
    step = (ang[-1] - ang[0]) / (n - 1)
    if ang[-1] - ang[0] + 1.5 * step < 360.0:
        return 0
    r = np.asarray(range_mm, dtype=float)
    none = ~np.isfinite(r) | (r <= 0)
    if none[0] or none[-1]:  # no return at the seam: nothing straddles it
        return 0
    if none.any():
        # longest circular run of no-returns: start it after a return
        k0 = int(np.flatnonzero(~none)[-1]) + 1
        runs = np.roll(none, -k0)
        best, best_len, start, length = 0, 0, 0, 0
        for i, v in enumerate(runs):
            if v:
                start, length = (i, length + 1) if length == 0 else (start, length + 1)
                if length > best_len:
                    best, best_len = start, length
            else:
                length = 0
        return int((k0 + best + best_len // 2) % n)
    jumps = np.abs(np.diff(np.concatenate([r, r[:1]])))
    return int((np.argmax(jumps) + 1) % n)


V_SEGMENT_DIAGONALS = 2.5  # longest board segment, in inner-corner diagonals of the pattern


def v_segment_limit_mm(diagonals_mm: list[float]) -> float:
    """Longest scan segment that can lie on a board of the V, mm (section 1.4).

    A scan line crosses a board at most along its diagonal; the inner-corner grid's
    diagonal (:func:`lidarcal.board.inner_diagonal_mm`, measured in board.png) times
    ``V_SEGMENT_DIAGONALS`` leaves room for a white border of about half the pattern on
    every side and a slanted crossing, while a room's walls (metres) stay out.
    """
    return V_SEGMENT_DIAGONALS * max(diagonals_mm)


def split_v(angle_deg: np.ndarray, range_mm: np.ndarray, *, range_noise_mm: float | None = None,
            alpha: float | None = None, alpha_tol_deg: float = 15.0,
            opening_deg: tuple[float, float] | None = None, min_points: int = 8,
            max_gap: int = 4, max_trim: int = 3,
            max_segment_mm: float | None = None) -> VSegments:
    """Find the two board segments of the V in one scan (section 1.4).

    The scan also holds background, mounts, spurious returns, dropped beams and
    mixed pixels at depth edges. Steps (1)-(3) are :func:`line_segments`:
    (1) runs of returns connected in beam order (a range jump large against
    noise and beam spacing breaks a run); (2) each run is split top-down into
    straight pieces (a staircase of squares at different ranges, quantised
    ranges stay whole); (3) each piece gets a robust line (RANSAC + iterated
    TLS, threshold 3.5 x MAD scale); (4) of the
    pieces adjacent in beam order (or separated only by pieces farther than the
    vertex, seen through a gap at the hinge), the pair forming a concave V
    (vertex away from the scanner, ``z . (l1 x l2) < 0``, see module docstring)
    with an opening in ``opening_deg`` and a vertex at the pieces' inner ends
    is kept, the one with most points winning; the hinge split between them is
    re-chosen to fit the two lines best; (5) up to ``max_trim`` points at each
    outer end whose residual still exceeds 2.5 x scale are dropped (mixed pixels).

    Parameters
    ----------
    angle_deg, range_mm : arrays, shape (N,)
        The scan, ascending angles; NaN range = no return.
    range_noise_mm : float, optional
        Range noise sigma; estimated robustly (:func:`effective_range_noise`:
        second differences plus quantisation) if None.
    alpha : float, optional
        The camera's V angle (rad): when given, only pairs whose free opening is
        within ``alpha_tol_deg`` of it qualify.
    opening_deg : (float, float), optional
        Accepted opening range of the V, degrees. Default: ``alpha`` +-
        ``alpha_tol_deg`` when ``alpha`` is given (a V-board may open at any
        angle: the camera says which), else 90-170 deg.
    min_points : int
        Fewest points of a board segment.
    max_segment_mm : float, optional
        Longest board segment, mm (:func:`v_segment_limit_mm`: a few of the pattern's
        diagonals). Without it a room's corner (two walls at 90 deg, metres long, many
        more returns than the boards) seen by a wide-angle scanner can win over a V of
        100 deg.

    Raises
    ------
    ValueError
        When fewer than two line segments are found, or no pair forms the V.
    """
    ang = np.asarray(angle_deg, dtype=float)
    cut = full_circle_cut(ang, range_mm)
    if cut:  # a 360 deg scan: the V may straddle the first and last beams; split where nothing is
        n = len(ang)
        rolled = np.concatenate([ang[cut:], ang[:cut] + 360.0])
        seg = split_v(rolled, np.roll(np.asarray(range_mm, dtype=float), -cut),
                      range_noise_mm=range_noise_mm, alpha=alpha, alpha_tol_deg=alpha_tol_deg,
                      opening_deg=opening_deg, min_points=min_points, max_gap=max_gap,
                      max_trim=max_trim, max_segment_mm=max_segment_mm)
        back = {k: (getattr(seg, k) + cut) % n for k in ("index1", "index2", "rejected1", "rejected2")}
        return replace(seg, **back, info={**seg.info, "full_circle_cut": cut})
    pts = scan_points(ang, range_mm)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    n_valid = int(np.isfinite(rho).sum())
    if n_valid < 2 * min_points:
        raise ValueError(f"scan has {n_valid} returns; need at least {2 * min_points} "
                         "to find the two board segments")
    segments, sigma = _line_segments(ang, pts, rho, range_noise_mm, min_points, max_gap)

    if len(segments) < 2:
        raise ValueError(f"found {len(segments)} board segment{'s' if len(segments) != 1 else ''}, "
                         "expected 2 (the scan plane must cross both boards of the V)")

    if opening_deg is None:
        opening_deg = ((max(1.0, np.degrees(alpha) - alpha_tol_deg), min(179.0, np.degrees(alpha) + alpha_tol_deg))
                       if alpha is not None else (90.0, 170.0))
    lo, hi = np.radians(opening_deg)
    candidates = _v_pairs(segments, pts, rho, lo, hi, alpha, alpha_tol_deg, max_segment_mm)
    if not candidates:
        raise ValueError(f"found {len(segments)} line segments but no pair forms the V "
                         f"(adjacent, concave, opening {opening_deg[0]:.0f}-{opening_deg[1]:.0f} deg"
                         + (f", within {alpha_tol_deg:g} deg of alpha" if alpha is not None else "")
                         + (f", each at most {max_segment_mm:.0f} mm long"
                            if max_segment_mm is not None else "")
                         + "); the scan plane must cross both boards")
    candidates.sort(key=lambda c: -c[0])
    _, s1, s2, opening = candidates[0]

    # hinge: the split between the two segments in beam order that fits the two lines best
    both = np.concatenate([s1.beams, s2.beams])
    p_both = pts[both]
    r1 = s1.line.distance(p_both) ** 2
    r2 = s2.line.distance(p_both) ** 2
    cost = np.concatenate([[0.0], np.cumsum(r1)]) + np.concatenate([np.cumsum(r2[::-1])[::-1], [0.0]])
    k = int(np.argmin(cost))
    if min_points <= k <= len(both) - min_points:
        s1.beams, s2.beams = both[:k], both[k:]
    else:
        k = len(s1.beams)
    out = []
    for s, p_s, from_start in ((s1, p_both[:k], True), (s2, p_both[k:], False)):
        resid = s.line.distance(p_s)  # (p_s: the points of s.beams)
        keep = _trim_outer(s.beams, resid, s.scale, from_start, max_trim)
        beams = s.beams[keep]
        span = np.arange(min(s.span[0], beams[0]), max(s.span[-1], beams[-1]) + 1)
        off_line = np.isfinite(rho[span])  # the returns in the span, less the kept beams
        off_line[beams - span[0]] = False
        rejected = span[off_line]
        out.append((beams, p_s[keep], rejected, s.scale))
    (b1, p1, r1, sc1), (b2, p2, r2, sc2) = out
    return VSegments(b1, b2, p1, p2, r1, r2, sigma, sc1, sc2, float(np.degrees(opening)),
                     info={"n_segments": len(segments), "n_candidates": len(candidates),
                           "segments": [(int(s.beams[0]), int(s.beams[-1])) for s in segments]})


# ---------------------------------------------------------------------------
# lines: free and constrained (eqs. 7-12)

@dataclass(frozen=True)
class LidarLines:
    """The two scan lines of the V in the LiDAR plane (eqs. 7-12).

    ``E`` is their vertex (mm), ``l1`` / ``l2`` unit rays from E towards
    segment 1 / segment 2 (eq. 12: to the foot of the first point of L1 and of
    the last point of L2), ``alpha`` the angle between them (rad; equal to the
    given alpha for a constrained fit). ``sign`` is the turn from l1 to l2:
    ``l2 = Rot(sign * alpha) l1``, -1 for a concave V in ascending beam order
    (the paper's ``beta - alpha``). ``E_cov`` is the 2 x 2 covariance of E
    from the fit (Gauss-Newton, residual variance), mm^2. ``free`` holds the
    unconstrained fit for comparison.
    """

    E: np.ndarray
    l1: np.ndarray
    l2: np.ndarray
    alpha: float
    residual_rms_mm: float
    n1: int
    n2: int
    line1: Line2D
    line2: Line2D
    sign: int
    method: str
    E_cov: np.ndarray | None = None
    free: LidarLines | None = None
    info: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def E_lidar(self) -> np.ndarray:
        """E as a 3D LiDAR-frame point (z = 0), for eq. (14)."""
        return np.array([self.E[0], self.E[1], 0.0])

    @property
    def l_lidar(self) -> np.ndarray:
        """``[l1; l2]`` as 3D LiDAR-frame directions (2, 3), z = 0, for eq. (13)."""
        return np.array([[self.l1[0], self.l1[1], 0.0], [self.l2[0], self.l2[1], 0.0]])


def _check_points(p: np.ndarray, name: str) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) < 2 or not np.isfinite(p).all():
        raise ValueError(f"{name} must be finite points with shape (N >= 2, 2), got {p.shape}")
    return p


def _rays(line1: Line2D, line2: Line2D, p1: np.ndarray, p2: np.ndarray):
    """E and the eq. (12) rays: E -> foot of P_1 on L1, E -> foot of Q_N2 on L2."""
    E = intersect_lines_2d(line1, line2)
    return E, _unit2(line1.foot(p1[0]) - E), _unit2(line2.foot(p2[-1]) - E)


def _residual_rms(line1: Line2D, line2: Line2D, p1: np.ndarray, p2: np.ndarray) -> float:
    r = np.concatenate([line1.distance(p1), line2.distance(p2)])
    return math.sqrt(np.add.reduce(r ** 2) / len(r))  # (np.mean's sum and division)


def fit_v_lines_free(points1: np.ndarray, points2: np.ndarray) -> LidarLines:
    """Two independent total-least-squares lines and their vertex (eq. 12 rays).

    The unconstrained fit: the angle between the rays is whatever the data say,
    so eq. (13) would not give a rotation. Used to initialise and to compare.
    """
    return _fit_free(_check_points(points1, "points1"), _check_points(points2, "points2"))


def _fit_free(p1: np.ndarray, p2: np.ndarray) -> LidarLines:
    """:func:`fit_v_lines_free` of checked points."""
    L1, L2 = fit_line_2d(p1), fit_line_2d(p2)
    E, l1, l2 = _rays(L1, L2, p1, p2)
    ang = float(np.arctan2(abs(_cross2(l1, l2)), l1 @ l2))
    return LidarLines(E, l1, l2, ang, _residual_rms(L1, L2, p1, p2), len(p1), len(p2), L1, L2,
                      int(np.sign(_cross2(l1, l2)) or -1), "free TLS")


#: weightings of :func:`fit_v_lines`
WEIGHTINGS = ("range", "orthogonal")
#: ``weighting="range"`` falls back to "orthogonal" when a return's beam meets its board at
#: more than arccos(this) = 88.9 deg incidence (its range is then ill-conditioned)
MIN_RANGE_COS = 0.02


def fit_v_lines(points1: np.ndarray, points2: np.ndarray, alpha: float,
                sign: int | None = None, weighting: str = "range") -> LidarLines:
    """Both lines fitted jointly so that they meet at exactly ``alpha``, eqs. (7)-(12).

    Line 1 is ``n . p = c1`` and line 2 ``(Q n) . p = c2`` with ``Q = Rot(sign * alpha)``,
    ``n = (cos phi, sin phi)``: three parameters ``(phi, c1, c2)``.

    ``weighting="orthogonal"`` minimises the sum of squared *orthogonal* distances of the
    points to their lines. For a fixed ``n`` the offsets are the centroid projections, so
    the cost is ``n^T (S1 + Q^T S2 Q) n`` (``S`` = scatter matrices of the centred points),
    minimised exactly by the eigenvector of the smallest eigenvalue: a closed-form global
    optimum, not an iteration. (The paper's linearised iteration in ``(lambda, eta1,
    eta2)`` is :func:`fit_v_lines_paper`; it minimises vertical residuals normalised with
    the previous slope and needs lines not parallel to the LiDAR y axis.)

    ``weighting="range"`` (default) is the maximum-likelihood fit for a LiDAR's noise, which
    lies along each beam: range ``r_i = c_k / (n_k . u_i) + e_i`` (``u_i = p_i / |p_i|``, the
    beam direction; ``e_i ~ N(0, s^2)``), i.e. the orthogonal residual ``n_k . p_i - c_k``
    has standard deviation ``s |n_k . u_i|``. It minimises ``sum (r_i - c_k / (n_k .
    u_i))^2`` by Gauss-Newton from the orthogonal optimum (converged in 2-4 steps), and
    reaches the Cramer-Rao bound of :func:`lidarcal.evaluate.v_fit_crlb`. The orthogonal
    fit weighs every return alike, so it under-weighs the board seen more obliquely,
    whose returns lie closer to its line: for a V facing the LiDAR the two agree within
    1 % (the rendered wide rigs: 0.2-0.5 % in the bound, samples within 2 %), for a V of 90 deg turned 30 deg away (one
    board at 67-75 deg incidence) the orthogonal fit's centre error is 1.4-1.5 times the
    bound, turned 40 deg 2.5-2.8 times (Monte Carlo and first order; issue 13).

    Parameters
    ----------
    points1, points2 : arrays, shape (N1, 2), (N2, 2)
        Segment points in ascending beam order (eq. 6).
    alpha : float
        Angle between the stripe rays l1, l2 from the camera (rad), in (0, pi).
    sign : {-1, +1}, optional
        Turn from l1 to l2 (``l2 = Rot(sign alpha) l1``); read from the free fit
        if None (-1 for a concave V; see the module docstring).
    weighting : {"range", "orthogonal"}
        The noise model (above).

    Returns
    -------
    LidarLines
        ``E_cov`` is the Gauss-Newton covariance of E with the residual variance (of the
        ranges for "range", of the orthogonal distances for "orthogonal");
        ``residual_rms_mm`` the orthogonal rms either way; ``info`` holds ``phi_std_rad``,
        ``sse`` (orthogonal), ``weighting`` and, for "range", ``range_rms_mm`` and
        ``iterations``.
    """
    p1, p2 = _check_points(points1, "points1"), _check_points(points2, "points2")
    if not 0 < alpha < np.pi:
        raise ValueError(f"alpha must be in (0, pi) rad, got {alpha!r}")
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {WEIGHTINGS}, got {weighting!r}")
    free = _fit_free(p1, p2)
    s = free.sign if sign is None else int(np.sign(sign))
    if s not in (-1, 1):
        raise ValueError(f"sign must be -1 or +1, got {sign!r}")
    Q = _rot2(s * alpha)
    m1, m2 = np.add.reduce(p1) / len(p1), np.add.reduce(p2) / len(p2)  # (as p.mean(0))
    d1, d2 = p1 - m1, p2 - m2
    S1, S2 = d1.T @ d1, d2.T @ d2
    _, V = np.linalg.eigh(S1 + Q.T @ S2 @ Q)
    n1 = V[:, 0]
    theta = np.array([math.atan2(n1[1], n1[0]), float(n1 @ m1), float((Q @ n1) @ m2)])
    info: dict = {"weighting": weighting}
    if weighting == "range":
        nu = np.concatenate([p1 @ n1 / np.hypot(p1[:, 0], p1[:, 1]),
                             p2 @ (Q @ n1) / np.hypot(p2[:, 0], p2[:, 1])])
        if np.abs(nu).min() < MIN_RANGE_COS:  # a beam almost along its board: ranges ill-posed
            weighting = "orthogonal"
            info["weighting"] = (f"orthogonal (a return at {np.degrees(np.arccos(np.abs(nu).min())):.1f}"
                                 " deg incidence: the range model is ill-posed)")
        else:
            theta, J, e, it = _range_ml(p1, p2, Q, theta)
            info.update(iterations=it)
    n1 = np.array([math.cos(theta[0]), math.sin(theta[0])])
    n2 = Q @ n1
    L1, L2 = Line2D(n1, float(theta[1])), Line2D(n2, float(theta[2]))
    E, l1, l2 = _rays(L1, L2, p1, p2)
    ray_angle = float(np.arctan2(abs(_cross2(l1, l2)), l1 @ l2))
    if abs(ray_angle - alpha) > 1e-6:
        # lines meet at alpha but the segments lie on the wrong sides of E
        raise ValueError(f"the segments do not form a V at the fitted vertex (rays at "
                         f"{np.degrees(ray_angle):.2f} deg, lines at {np.degrees(alpha):.2f} deg); "
                         "check the segmentation and the sign")
    N = len(p1) + len(p2)
    sse = float(np.add.reduce(L1.distance(p1) ** 2) + np.add.reduce(L2.distance(p2) ** 2))
    # covariance of (phi, c1, c2) -> E (Gauss-Newton, residual variance)
    dn1 = np.array([-n1[1], n1[0]])
    dn2 = Q @ dn1
    if weighting == "orthogonal":  # (also the fallback of "range")
        J = np.zeros((N, 3))
        J[: len(p1), 0] = p1 @ dn1
        J[: len(p1), 1] = -1.0
        J[len(p1):, 0] = p2 @ dn2
        J[len(p1):, 2] = -1.0
        var = sse / max(N - 3, 1)
    else:
        var = float(e @ e) / max(N - 3, 1)
        info["range_rms_mm"] = float(np.sqrt(e @ e / N))
    try:
        cov_p = var * np.linalg.inv(J.T @ J)
        A_inv = np.linalg.inv(np.array([n1, n2]))
        dE = np.column_stack([-A_inv @ np.array([dn1 @ E, dn2 @ E]), A_inv[:, 0], A_inv[:, 1]])
        E_cov = dE @ cov_p @ dE.T
    except np.linalg.LinAlgError:
        E_cov = None
    info.update(phi_std_rad=float(np.sqrt(cov_p[0, 0])) if E_cov is not None else float("nan"),
                sse=sse)
    method = ("constrained ML, range noise along the beams (Gauss-Newton)" if weighting == "range"
              else "constrained orthogonal (closed form)")
    return LidarLines(E, l1, l2, float(alpha), float(np.sqrt(sse / N)), len(p1), len(p2), L1, L2,
                      s, method, E_cov, free, info=info)


def _range_residuals(p: list[np.ndarray], Q: np.ndarray, theta: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Range residuals ``r_i - c_k / (n_k . u_i)`` of both segments and their Jacobian in
    ``(phi, c1, c2)`` (:func:`fit_v_lines`, ``weighting="range"``)."""
    n1 = np.array([math.cos(theta[0]), math.sin(theta[0])])
    res, rows = [], []
    for k, (pk, nk) in enumerate(zip(p, (n1, Q @ n1))):
        r = np.hypot(pk[:, 0], pk[:, 1])
        u = pk / r[:, None]
        nu = u @ nk
        c = theta[1 + k]
        res.append(r - c / nu)
        J = np.zeros((len(pk), 3))
        J[:, 0] = c * (u @ np.array([-nk[1], nk[0]])) / nu ** 2
        J[:, 1 + k] = -1.0 / nu
        rows.append(J)
    return np.concatenate(res), np.vstack(rows)


def _range_ml(p1: np.ndarray, p2: np.ndarray, Q: np.ndarray, theta: np.ndarray,
              max_iter: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Gauss-Newton on the range residuals (:func:`_range_residuals`) from ``theta``; the
    parameters, the Jacobian and residuals there, and the steps taken. A step that does not
    lower the cost is halved (a return nearly parallel to its board could overshoot)."""
    p = [p1, p2]
    e, J = _range_residuals(p, Q, theta)
    cost = float(e @ e)
    # residuals at rounding level (noise-free returns): the closed form is already exact, and
    # a step would only follow the rounding along a poorly conditioned direction
    floor = len(e) * (1e-11 * max(float(np.abs(p1).max()), float(np.abs(p2).max()))) ** 2
    it = 0
    for it in range(1, max_iter + 1):
        if cost <= floor:
            break
        step = np.linalg.lstsq(J, -e, rcond=None)[0]
        for _ in range(30):
            t_new = theta + step
            e_new, J_new = _range_residuals(p, Q, t_new)
            c_new = float(e_new @ e_new)
            if np.isfinite(c_new) and c_new <= cost:
                break
            step = step / 2
        else:
            break
        done = cost - c_new <= 1e-10 * cost  # converged: the cost no longer drops
        theta, e, J, cost = t_new, e_new, J_new, c_new
        if done:
            break
    return theta, J, e, it


def fit_v_lines_paper(points1: np.ndarray, points2: np.ndarray, alpha: float,
                      sign: int | None = None, iterations: int = 50) -> LidarLines:
    """The paper's linearised constrained fit, eqs. (7)-(11), iterated from the free fit.

    L1: ``y = lambda x + eta1`` (eq. 7); L2: ``y = tan(beta + sign alpha) x + eta2``
    (eq. 8, the paper's ``beta - alpha`` is ``sign = -1``). With the slope
    ``lambda0`` of the previous step in the denominators and normalisers,
    eqs. (10)-(11) are linear in ``(lambda, eta1, eta2)`` and solved by least
    squares; ``lambda0`` starts from the least-squares fit of L1 (eq. 9) and is
    updated until it stops changing (``iterations=1`` is the single linear solve
    as printed). Kept as the documented reference. The angle is always exactly
    alpha, but the result is *not* the least-squares optimum: eq. (11) uses
    ``cos a / (cos a + sin a lambda0)`` as the derivative of L2's slope with
    respect to lambda where the true derivative is ``1 / (cos a + sin a
    lambda0)^2``, so the fixed point is biased (E off by ~2x the optimum's
    error for a symmetric V, tens of mm once a line nears the LiDAR y axis,
    where the slope form of eq. (7) degenerates, as the paper assumes away).
    Use :func:`fit_v_lines`.
    """
    p1, p2 = _check_points(points1, "points1"), _check_points(points2, "points2")
    free = fit_v_lines_free(p1, p2)
    s = free.sign if sign is None else int(np.sign(sign))
    ca, sa = np.cos(alpha), s * np.sin(alpha)
    lam0 = float(np.polyfit(p1[:, 0], p1[:, 1], 1)[0])  # eq. (9): LS fit of L1
    x1, y1, x2, y2 = p1[:, 0], p1[:, 1], p2[:, 0], p2[:, 1]
    it = 0
    for it in range(1, iterations + 1):
        den = ca - sa * lam0  # tan(beta + s alpha) = (ca lam + sa) / (ca - sa lam)
        w1 = 1.0 / np.sqrt(1 + lam0 ** 2)
        phi = np.sqrt(1 + ((ca * lam0 + sa) / den) ** 2)
        # eq. (10): w1 x lam + w1 eta1 = w1 y
        A1 = np.column_stack([w1 * x1, np.full_like(x1, w1), np.zeros_like(x1)])
        b1 = w1 * y1
        # eq. (11): (ca/den) x lam / phi + eta2 / phi = y / phi - (sa/den) x / phi
        A2 = np.column_stack([(ca / den) * x2 / phi, np.zeros_like(x2), np.full_like(x2, 1 / phi)])
        b2 = (y2 - (sa / den) * x2) / phi
        (lam, eta1, eta2), *_ = np.linalg.lstsq(np.vstack([A1, A2]), np.concatenate([b1, b2]),
                                                rcond=None)
        done = abs(lam - lam0) <= 1e-13 * max(1.0, abs(lam))
        lam0 = float(lam)
        if done:
            break
    lam2 = (ca * lam0 + sa) / (ca - sa * lam0)  # eq. (8)
    n1 = np.array([-lam0, 1.0]) / np.hypot(lam0, 1.0)
    n2 = np.array([-lam2, 1.0]) / np.hypot(lam2, 1.0)
    L1 = Line2D(n1, float(eta1 / np.hypot(lam0, 1.0)))
    L2 = Line2D(n2, float(eta2 / np.hypot(lam2, 1.0)))
    E, l1, l2 = _rays(L1, L2, p1, p2)
    ang = float(np.arctan2(abs(_cross2(l1, l2)), l1 @ l2))
    return LidarLines(E, l1, l2, ang, _residual_rms(L1, L2, p1, p2), len(p1), len(p2), L1, L2, s,
                      "paper linearised eqs. (7)-(11)", None, free, info={"iterations": it})
