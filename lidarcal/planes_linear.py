"""Consensus on the board segment and the linear solution of the one-board calibration
(Zhang & Pless 2004, eq. 5: ``n_i^T H (x, y, 1)^T = d_i``, ``H = [r1 r2 T]``), used by
:mod:`lidarcal.planes` (steps 2-3 of its docstring).

Convention: ``X_cam = R X_lidar + T``, camera frame OpenCV's; mm at the edges, metres inside
the linear systems (conditioning).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .degeneracy import MIN_VIEWS, PARALLEL_LIMIT
from .geometry import Plane, nearest_rotation, skew
from .scan_segments import LineSegment


def _design(points_m: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Rows ``kron((x, y, 1), n)`` of the linear constraint ``n^T H (x, y, 1) = d`` (vec(H)
    column-major), points in metres (conditioning)."""
    ph = np.column_stack([points_m, np.ones(len(points_m))])
    return np.einsum("ij,k->ijk", ph, normal).reshape(len(ph), 9)


@dataclass(frozen=True)
class _Moments:
    """Sums over one candidate's points under one view's plane (metres): ``N``, ``b``, ``dd`` of
    the normal equations of ``H``, and ``flat`` = (N, b, C1, C2, C3, v) flattened, where
    ``C1 = c n n^T``, ``C2 = (sum x) n n^T``, ``C3 = (sum y) n n^T``, ``v = c d n`` (``c`` the
    count) give ``T`` for a fixed ``R``: ``C1 T = v - C2 r1 - C3 r2``. Sums of ``flat`` over
    candidates are the moments of their union."""

    N: np.ndarray  # (9, 9)
    b: np.ndarray  # (9,)
    dd: float
    n: int
    flat: np.ndarray  # (120,)


def _moments(points_mm: np.ndarray, plane: Plane) -> _Moments:
    pm = points_mm / 1000.0
    A = _design(pm, plane.normal)
    d = np.full(len(A), plane.d / 1000.0)
    nn = np.outer(plane.normal, plane.normal)
    c = float(len(pm))
    sx, sy = pm.sum(0)
    N, b = A.T @ A, A.T @ d
    flat = np.concatenate([N.ravel(), b, (c * nn).ravel(), (sx * nn).ravel(), (sy * nn).ravel(),
                           c * plane.d / 1000.0 * plane.normal])
    return _Moments(N, b, float(d @ d), len(A), flat)


def _hypotheses(flat: np.ndarray) -> np.ndarray:
    """Rigid ``vec(H)`` (K, 9) from summed moments (K, 120): the linear ``H`` (Zhang-Pless),
    ``R`` the nearest rotation to ``[h1 h2 h1 x h2]`` (batched SVD), ``T`` re-solved with
    ``R`` fixed, then both fitted rigidly to the hypothesis' own moments (:func:`_rigid_fit`). A wrong set of segments can fit the nine free entries of ``H``; it rarely
    fits a rotation. (Keeping ``h3`` as ``T`` is not enough: with few views the free ``H``
    trades its rotation part against ``h3``.)"""
    K = len(flat)
    N = flat[:, :81].reshape(K, 9, 9)
    b = flat[:, 81:90]
    C1, C2, C3 = (flat[:, 90 + 9 * j: 99 + 9 * j].reshape(K, 3, 3) for j in range(3))
    v = flat[:, 117:120]
    h = _solve_h(N, b)
    Hm = h.reshape(-1, 3, 3).transpose(0, 2, 1)  # columns h1, h2, h3
    M = np.stack([Hm[:, :, 0], Hm[:, :, 1], np.cross(Hm[:, :, 0], Hm[:, :, 1])], axis=2)
    U, _, Vt = np.linalg.svd(M)
    D = np.ones((K, 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R = (U * D[:, None, :]) @ Vt
    r1, r2 = R[:, :, 0], R[:, :, 1]
    rhs = v - np.einsum("kij,kj->ki", C2, r1) - np.einsum("kij,kj->ki", C3, r2)
    T = _psolve(C1, rhs)
    return _rigid_fit(R, T, N, b)


def _rigid_fit(R: np.ndarray, T: np.ndarray, N: np.ndarray, b: np.ndarray,
               iterations: int = 6) -> np.ndarray:
    """Rigid ``vec(H) = (r1, r2, T)`` (K, 9) minimising each hypothesis' own point-on-plane sum
    of squares ``h^T N h - 2 b^T h`` (Zhang-Pless's linear cost, with ``H`` kept rigid), by
    batched Gauss-Newton from ``(R, T)``: ``R <- exp(w) R``, so ``d r_j = -[r_j]_x w``.

    The nearest rotation to a free ``H`` is not the best rigid one: from exactly five views
    the free ``H`` is barely overdetermined (ten constraints, nine unknowns) and follows the
    noise, and its projection sat 24-37 mm RMS off the very segments it came from on rendered
    views (2-4 mm for the free ``H``, 2.0-2.8 mm for this fit), so five right views failed
    their own gate and the consensus chose nothing."""
    K = len(R)
    eye = np.broadcast_to(np.eye(3), (K, 3, 3))
    scale = np.trace(N, axis1=1, axis2=2)[:, None, None]
    for _ in range(iterations):
        h = np.concatenate([R[:, :, 0], R[:, :, 1], T], axis=1)
        J = np.zeros((K, 9, 6))
        J[:, 0:3, 0:3] = -skew(R[:, :, 0])
        J[:, 3:6, 0:3] = -skew(R[:, :, 1])
        J[:, 6:9, 3:6] = eye
        g = np.einsum("kia,kij,kj->ka", J, N, h) - np.einsum("kia,ki->ka", J, b)
        A = np.einsum("kia,kij,kjb->kab", J, N, J) + 1e-12 * scale * np.eye(6)
        step = -np.linalg.solve(A, g[..., None])[..., 0]
        R = Rotation.from_rotvec(step[:, :3]).as_matrix() @ R
        T = T + step[:, 3:]
    return np.concatenate([R[:, :, 0], R[:, :, 1], T], axis=1)


def _solve_h(N: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Least-squares ``vec(H)`` from summed moments (batched; a tiny ridge keeps rank-deficient
    sets, e.g. parallel boards, solvable: their null space is left at zero)."""
    return _psolve(N, b)


#: Relative eigenvalue below which a direction of the hypotheses' normal equations counts as
#: unobserved and is left at zero (board normals from real corners scatter by ~1e-3 rad, so an
#: unobserved direction shows up at ~1e-6 relative).
_RCOND = 1e-5


def _psolve(N: np.ndarray, b: np.ndarray, rcond: float = _RCOND) -> np.ndarray:
    """Minimum-norm solution of symmetric ``N x = b`` (batched), eigenvalues below ``rcond``
    of the largest dropped."""
    lam, V = np.linalg.eigh(N)
    keep = lam > rcond * lam[..., -1:]
    inv = np.where(keep, 1.0 / np.where(keep, lam, 1.0), 0.0)
    return np.einsum("...ij,...j,...kj,...k->...i", V, inv, V, b)


def _rms_under(h: np.ndarray, m: _Moments) -> np.ndarray:
    """RMS (mm) of ``n^T H p - d`` over a candidate's points, for hypotheses ``h`` (K, 9)."""
    sse = np.einsum("ki,ij,kj->k", h, m.N, h) - 2 * h @ m.b + m.dd
    return 1000.0 * np.sqrt(np.maximum(sse, 0.0) / m.n)


def _outside_board(h: np.ndarray, centre_mm: np.ndarray, board: tuple) -> np.ndarray:
    """How far (mm) a candidate's centroid, mapped into the camera by hypotheses ``h`` (K, 9),
    lies in the board's plane outside its printed pattern grown by ``grow`` on every side;
    ``board = (R_b, T_b, lo, hi, grow)``: board frame -> camera (eq. 1), the pattern's corners
    ``lo``, ``hi`` in the board frame (mm)."""
    Rb, Tb, lo, hi, grow = board
    X = h[:, 0:3] * centre_mm[0] + h[:, 3:6] * centre_mm[1] + 1000.0 * h[:, 6:9]  # X = H (x, y, 1)
    u = (X - Tb) @ Rb[:, :2]
    mid, half = (lo + hi) / 2, (hi - lo) / 2 + grow
    return np.linalg.norm(np.maximum(np.abs(u - mid) - half, 0.0), axis=1)


def _too_long(segment: LineSegment, board: tuple | None) -> bool:
    """Whether a candidate segment is longer end to end than the board's longest chord (the
    diagonal of its printed pattern grown by ``grow`` on every side, as
    :func:`lidarcal.planes_wall.max_chord_mm`; ``board`` as for
    :func:`_outside_board`, None: never), so that it cannot be all board."""
    if board is None:
        return False
    _, _, lo, hi, grow = board
    p = segment.points
    return bool(np.linalg.norm(p[-1] - p[0]) > np.linalg.norm(hi - lo + 2 * np.asarray(grow)))


def select_board_segments(candidates: list[list[LineSegment]], planes: list[Plane],
                          gates_mm: list[float], rng: np.random.Generator,
                          hypotheses: int = 10000, max_candidates: int = 4,
                          boards: list[tuple] | None = None) -> list[int | None]:
    """Which candidate segment of each view is the board: consensus of linear hypotheses.

    A hypothesis is the least-squares ``H`` of ``min(5, n)`` views with one candidate each
    (five views give the ten constraints nine unknowns need; every such choice when there are
    at most ``hypotheses``, else random ones), made rigid (:func:`_hypotheses`); every
    candidate of every view is scored by the RMS of its points to the board plane
    ``H`` predicts; the hypothesis with the least sum over views of
    ``min(rms / gate, 1)^2`` wins (MSAC: a wrong segment that fits loosely costs more than a
    view left out); views whose best candidate is beyond their gate get ``None``. Each view offers its ``max_candidates`` segments with the most
    returns (a calibration board is a large, near surface); nothing else is assumed about
    which segment is the board. With ``boards`` a second offer is tried too, where a segment
    longer end to end than the board's longest chord (:func:`_too_long`: not all board; a
    room's wall that no range step cut to a board piece, which a 270-degree scan offers several
    times over, or a board in line with a wall) comes after every segment that could be all
    board; the offer whose best hypothesis costs less wins (the first on a tie). In a
    clean-room room (``scripts/cleanroom_oneboard.py``) such walls had pushed the board out of
    5 of 10 views' first offers.

    ``boards`` (per view ``(R_b, T_b, lo, hi, grow)``, see :func:`_outside_board`): a candidate
    whose centroid the hypothesis maps outside the board's printed pattern grown by ``grow``
    does not count for it. A wall a few cm behind every board is itself a consistent set of
    planes (those of a pose shifted by the offset) and, without the board's noise, fits them
    better; beside the board it is not on the board.
    """
    n = len(planes)
    by_count = [sorted(range(len(c)), key=lambda k: -len(c[k].beams))[:max_candidates]
                for c in candidates]
    best = _consensus(candidates, planes, gates_mm, rng, hypotheses, boards, by_count)
    if boards is not None:
        fits = [sorted(range(len(c)), key=lambda k: (_too_long(c[k], boards[i]), -len(c[k].beams)))
                [:max_candidates] for i, c in enumerate(candidates)]
        if fits != by_count:
            other = _consensus(candidates, planes, gates_mm, rng, hypotheses, boards, fits)
            if other[0] < best[0]:
                best = other
    return best[1] if best[1] is not None else [None] * n


def _consensus(candidates: list[list[LineSegment]], planes: list[Plane], gates_mm: list[float],
               rng: np.random.Generator, hypotheses: int, boards: list[tuple] | None,
               keep: list[list[int]]) -> tuple[float, list[int | None] | None]:
    """:func:`select_board_segments` for one offer ``keep`` (per view, the candidates' indices):
    the best hypothesis's MSAC cost and its choice (``(inf, None)`` with too few views)."""
    n = len(planes)
    mom = [[_moments(candidates[i][k].points, planes[i]) for k in keep[i]] for i in range(n)]
    views = [i for i in range(n) if mom[i]]
    if len(views) < MIN_VIEWS:
        return np.inf, None
    k = min(5, len(views))
    import itertools

    subsets = list(itertools.combinations(views, k))
    total = sum(int(np.prod([len(mom[i]) for i in sub])) for sub in subsets)
    if total <= hypotheses:  # small problems: every k views with every choice of candidates
        flat = np.stack([sum(mom[i][c].flat for i, c in zip(sub, cb)) for sub in subsets
                         for cb in itertools.product(*[range(len(mom[i])) for i in sub])])
    else:
        flat = np.empty((hypotheses, 120))
        for h in range(hypotheses):
            pick = rng.choice(views, size=k, replace=False)
            flat[h] = sum(mom[i][rng.integers(len(mom[i]))].flat for i in pick)
    H = _hypotheses(flat)
    cost = np.zeros(len(H))
    choice = np.full((len(H), n), -1)
    for i in views:
        rms = np.stack([_rms_under(H, m) for m in mom[i]], axis=1)  # (K, candidates)
        if boards is not None and boards[i] is not None:
            for c, k in enumerate(keep[i]):
                far = _outside_board(H, candidates[i][k].points.mean(0), boards[i]) > 0
                rms[far, c] = np.inf
        j = np.argmin(rms, axis=1)
        r = rms[np.arange(len(H)), j] / gates_mm[i]
        cost += np.minimum(r, 1.0) ** 2  # MSAC: truncated quadratic, not an inlier count
        choice[:, i] = np.where(r <= 1.0, j, -1)
    h = int(np.argmin(cost))
    return float(cost[h]), [keep[i][int(c)] if c >= 0 else None for i, c in enumerate(choice[h])]


def linear_extrinsics(points_mm: list[np.ndarray], planes: list[Plane]
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zhang & Pless's linear solution: ``H`` by least squares over every point-on-plane
    constraint ``n_i^T H (x, y, 1)^T = d_i``, ``R`` = nearest rotation to
    ``[h1 h2 h1 x h2]`` (SVD), then ``T`` by least squares with ``R`` fixed (better than
    ``h3`` when few views leave ``H`` loosely determined). Returns ``(R, T_mm, singular values of the
    design)``; small singular values flag an undetermined ``H``."""
    A = np.vstack([_design(p / 1000.0, pl.normal) for p, pl in zip(points_mm, planes)])
    d = np.concatenate([np.full(len(p), pl.d / 1000.0) for p, pl in zip(points_mm, planes)])
    h = _psolve(A.T @ A, A.T @ d)
    s = np.linalg.svd(A, compute_uv=False)
    Hm = h.reshape(3, 3, order="F")
    h1, h2 = Hm[:, 0], Hm[:, 1]
    if np.linalg.norm(h1) < 1e-6 or np.linalg.norm(h2) < 1e-6:
        R = np.eye(3)
    else:
        R, _ = nearest_rotation(np.column_stack([h1, h2, np.cross(h1, h2)]))
    # T again with R fixed: n_i . T = d_i - n_i . R p (the free H trades h3 against h1, h2)
    An = np.vstack([np.tile(pl.normal, (len(p), 1)) for p, pl in zip(points_mm, planes)])
    P3 = np.vstack([np.column_stack([p, np.zeros(len(p))]) for p in points_mm])
    rhs = 1000.0 * d - np.einsum("ij,ij->i", An, P3 @ R.T)
    T = _psolve(An.T @ An, An.T @ rhs, rcond=PARALLEL_LIMIT ** 2)  # unseen along a common board
    # direction (e.g. every board vertical): left at its minimum norm, see unobservable_directions
    return R, T, s
