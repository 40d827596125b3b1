"""The faster scan side (issue 15) gives what the plain algorithms give, to the bit.

Each replaced step is run next to the plain one it replaced (kept here as the reference:
scipy's connected components, one RANSAC per piece with its own pair loop, the scalar V-pair
loop, np.unique, brute-force split costs) on simulated V scans (tests/vscan_truth.py: boards,
wall, post, spurious returns, mixed pixels, dropouts), the bundled rig's scans and the real
UTM-30LX scans of data/real_tapas.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from vscan_truth import make_truth, simulate_scan

from lidarcal.geometry import MAD_TO_SIGMA, median, unit
from lidarcal.io.dataset import load_dataset, read_scan
from lidarcal.io.pairs import read_view_pairs
from lidarcal.pose import pose_from_line_pairs, single_shot_pose
from lidarcal.scan import _v_pairs, fit_v_lines, split_v
from lidarcal.scan_segments import (
    _TAN_MAX_INCIDENCE,
    _component_labels,
    _level_runs,
    _merge_collinear,
    _robust_line,
    _runs,
    _split_into_lines,
    _tls_sse_splits,
    effective_range_noise,
    estimate_range_quantum,
    fit_line_2d,
    line_segments,
    scan_points,
)

REPO = Path(__file__).resolve().parents[1]


def _scans() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, angle_deg, range_mm): simulated V scans, 12 of the bundled rig, the real ones."""
    out = []
    for seed in range(6):
        rng = np.random.default_rng(seed)
        ang, rho, _ = simulate_scan(make_truth(rng, upright=seed % 2 == 0), rng,
                                    sigma_mm=(0.5, 1.0, 3.0)[seed % 3], spurious=0.03)
        out.append((f"sim{seed}", ang, rho))
    ds = load_dataset(REPO / "data" / "paper_rig")
    for pos in ds.positions[::8]:
        out.append((pos.scan.name, *read_scan(pos.scan, ds.lidar)))
    for pr in read_view_pairs(REPO / "data" / "real_tapas"):
        out.append((pr.name, pr.angle_deg, pr.range_mm))
    return out


SCANS = _scans()


# --- runs of connected returns: block labelling vs scipy's connected components ----------

def _scipy_labels(edge: np.ndarray) -> np.ndarray:
    lag, rows = np.nonzero(edge)
    m = edge.shape[1]
    graph = coo_matrix((np.ones(len(rows)), (rows, rows + lag + 1)), shape=(m, m))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("seed", range(40))
def test_component_labels_are_scipys_on_random_graphs(seed):
    """Random edge tables with up to 4 lags, sparse to dense: isolated nodes, edges over
    block starts (scipy's fallback) and plain blocks all label as scipy labels them."""
    rng = np.random.default_rng(seed)
    m = int(rng.integers(1, 60))
    density = rng.uniform(0.05, 0.95)
    n_lags = int(rng.integers(0, 5))
    edge = rng.random((n_lags, m)) < density
    for lag in range(1, n_lags + 1):
        edge[lag - 1, max(m - lag, 0):] = False  # no edge past the last node
    assert np.array_equal(_component_labels(edge), _scipy_labels(edge))


def _runs_v0(rho, valid_idx, dtheta, sigma, max_gap):
    """The plain _runs: one edge list per lag, scipy's connected components."""
    m = len(valid_idx)
    rows, cols = [], []
    r = rho[valid_idx]
    for lag in range(1, max_gap + 1):
        if lag >= m:
            break
        g = valid_idx[lag:] - valid_idx[:-lag]
        rr = np.minimum(r[lag:], r[:-lag])
        tau = 6 * np.sqrt(2) * sigma + _TAN_MAX_INCIDENCE * g * rr * dtheta
        ok = (g <= max_gap) & (np.abs(r[lag:] - r[:-lag]) <= tau)
        i = np.flatnonzero(ok)
        rows.append(i)
        cols.append(i + lag)
    rows = np.concatenate(rows) if rows else np.zeros(0, int)
    cols = np.concatenate(cols) if cols else np.zeros(0, int)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(m, m))
    return connected_components(graph, directed=False)[1]


@pytest.mark.parametrize("name, ang, rng_mm", SCANS, ids=[s[0] for s in SCANS])
def test_runs_are_the_plain_runs(name, ang, rng_mm):
    pts = scan_points(ang, rng_mm)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    valid = np.flatnonzero(np.isfinite(rho))
    sigma = effective_range_noise(rho)
    dtheta = median(np.diff(np.radians(ang)))
    for max_gap in (1, 4):
        assert np.array_equal(_runs(rho, valid, dtheta, sigma, max_gap),
                              _runs_v0(rho, valid, dtheta, sigma, max_gap))


# --- robust lines: all pieces at once vs one RANSAC per piece ------------------------------

def _robust_line_v0(p, sigma, rng, k=3.5, trials=100):
    """The plain robust line: RANSAC over (points, hypotheses), then the iterated TLS refit."""
    n = len(p)
    best = np.ones(n, bool)
    if n > 3:
        i = rng.integers(n, size=trials)
        j = (i + rng.integers(1, n, size=trials)) % n
        d = p[j] - p[i]
        ln = np.hypot(d[:, 0], d[:, 1])
        good = ln > 0
        if good.any():
            if not good.all():
                i, d, ln = i[good], d[good], ln[good]
            nrm = np.column_stack([-d[:, 1], d[:, 0]]) / ln[:, None]
            off = np.einsum("ij,ij->i", p[i], nrm)
            inl = np.abs(p @ nrm.T - off) <= k * sigma
            best = inl[:, int(np.argmax(np.count_nonzero(inl, axis=0)))]
    mask = best
    of_mask = np.count_nonzero(mask) >= 2
    line = fit_line_2d(p[mask]) if of_mask else fit_line_2d(p)
    scale = sigma
    for _ in range(20):
        r = np.abs(line.distance(p))
        scale = max(MAD_TO_SIGMA * np.median(r), 0.25 * sigma)
        new = r <= k * scale
        if np.count_nonzero(new) < 2:
            break
        same = np.array_equal(new, mask)
        if not (same and of_mask):
            line = fit_line_2d(p[new])
        if same:
            break
        mask, of_mask = new, True
    levels = _level_runs(p, line, mask, sigma)
    if levels.any():
        mask = mask | levels
        line = fit_line_2d(p[mask])
    return line, mask, float(scale)


def _line_segments_v0(ang, rng_mm, min_points=8, max_gap=4):
    """The plain segmentation: runs, split, merge, then one robust line per piece in turn."""
    pts = scan_points(ang, rng_mm)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    valid = np.flatnonzero(np.isfinite(rho))
    sigma = effective_range_noise(rho)
    sigma = max(sigma, 1e-6 * float(np.median(rho[valid])))
    dtheta = float(np.median(np.diff(np.radians(ang))))
    rng = np.random.default_rng(0)
    labels = _runs_v0(rho, valid, dtheta, sigma, max_gap)
    out = []
    for lab in np.unique(labels):
        beams = valid[labels == lab]
        if len(beams) < min_points:
            continue
        p = pts[beams]
        # (no shared fits: the split and the merge each fit every piece they test)
        for a, b in _merge_collinear(p, _split_into_lines(p, sigma, min_points)):
            span = beams[a:b]
            line, mask, scale = _robust_line_v0(pts[span], sigma, rng)
            if mask.sum() >= min_points:
                out.append((span[mask], span, line, scale, int(lab)))
    out.sort(key=lambda s: s[0][0])
    return out, sigma


@pytest.mark.parametrize("name, ang, rng_mm", SCANS, ids=[s[0] for s in SCANS])
def test_line_segments_are_the_plain_segmentation(name, ang, rng_mm):
    """Beams, spans, lines, scales and runs of every segment, bit for bit."""
    segs, sigma = line_segments(ang, rng_mm)
    ref, sigma0 = _line_segments_v0(ang, rng_mm)
    assert sigma == sigma0
    assert len(segs) == len(ref) >= 1
    for s, (beams, span, line, scale, run) in zip(segs, ref):
        assert np.array_equal(s.beams, beams) and np.array_equal(s.span, span)
        assert np.array_equal(s.line.normal, line.normal) and s.line.offset == line.offset
        assert s.scale == scale and s.run == run
        assert np.array_equal(s.points, scan_points(ang, rng_mm)[beams])


def test_robust_line_is_the_plain_one_on_every_piece():
    """_robust_line (RANSAC of :func:`_ransac_masks`, then :func:`_refine_line`) against the
    plain loop, piece by piece, on the same random draws."""
    n_pieces = 0
    for _, ang, rng_mm in SCANS:
        for s in line_segments(ang, rng_mm)[0]:
            p = scan_points(ang, rng_mm)[s.span]
            sigma = max(s.scale, 0.3)
            for seed in range(3):
                a = _robust_line(p, sigma, np.random.default_rng(seed))
                b = _robust_line_v0(p, sigma, np.random.default_rng(seed))
                assert np.array_equal(a[0].normal, b[0].normal) and a[0].offset == b[0].offset
                assert np.array_equal(a[1], b[1]) and a[2] == b[2]
            n_pieces += 1
    assert n_pieces > 50


# --- the V's pair test: arrays over all pairs vs the scalar loop ----------------------------

def _v_pairs_v0(segments, pts, rho, lo, hi, alpha, alpha_tol_deg):
    """The plain pair loop of split_v (before issue 15)."""
    cands = []
    ends = []
    for sg in segments:
        nx, ny = (float(v) for v in sg.line.normal)
        c = float(sg.line.offset)
        feet = []
        for b in (sg.beams[0], sg.beams[-1]):
            x, y = float(pts[b, 0]), float(pts[b, 1])
            r = x * nx + y * ny - c
            feet.append((x - r * nx, y - r * ny))
        ends.append(((nx, ny), c, feet[0], feet[1],
                     float(np.hypot(*(pts[sg.beams[-1]] - pts[sg.beams[0]])))))
    for i in range(len(segments)):
        for j in range(i + 1, min(i + 4, len(segments))):
            (n1, c1, f1, g1, len1), (n2, c2, h2, f2, len2) = ends[i], ends[j]
            det = n1[0] * n2[1] - n1[1] * n2[0]
            if abs(det) < 1e-9:
                continue
            E = ((c1 * n2[1] - n1[1] * c2) / det, (n1[0] * c2 - c1 * n2[0]) / det)
            d1 = (f1[0] - E[0], f1[1] - E[1])
            d2 = (f2[0] - E[0], f2[1] - E[1])
            m1, m2 = np.hypot(*d1), np.hypot(*d2)
            if m1 == 0 or m2 == 0:
                continue
            l1, l2 = (d1[0] / m1, d1[1] / m1), (d2[0] / m2, d2[1] / m2)
            cross = l1[0] * l2[1] - l1[1] * l2[0]
            opening = float(np.arctan2(abs(cross), l1[0] * l2[0] + l1[1] * l2[1]))
            if not (cross < 0 and lo <= opening <= hi):
                continue
            gap1 = (g1[0] - E[0]) * l1[0] + (g1[1] - E[1]) * l1[1]
            gap2 = (h2[0] - E[0]) * l2[0] + (h2[1] - E[1]) * l2[1]
            if not ((-0.1 * len1 <= gap1 <= 0.25 * len1) and (-0.1 * len2 <= gap2 <= 0.25 * len2)):
                continue
            if alpha is not None and abs(opening - alpha) > np.radians(alpha_tol_deg):
                continue
            rE = np.hypot(*E)
            if not all(float(np.median(rho[segments[b].beams])) > rE for b in range(i + 1, j)):
                continue
            cands.append((len(segments[i].beams) + len(segments[j].beams), i, j, opening))
    return cands


@pytest.mark.parametrize("name, ang, rng_mm", SCANS, ids=[s[0] for s in SCANS])
def test_v_pairs_are_the_scalar_loop(name, ang, rng_mm):
    segs = line_segments(ang, rng_mm)[0]
    if len(segs) < 2:
        pytest.skip("one segment: no pair to test")
    pts = scan_points(ang, rng_mm)
    rho = np.hypot(pts[:, 0], pts[:, 1])
    n_found = 0
    for alpha, (lo, hi) in ((None, (90.0, 170.0)), (np.radians(120.0), (105.0, 135.0)),
                            (None, (1.0, 179.0))):
        got = _v_pairs(segs, pts, rho, np.radians(lo), np.radians(hi), alpha, 15.0)
        ref = _v_pairs_v0(segs, pts, rho, np.radians(lo), np.radians(hi), alpha, 15.0)
        at = {id(sg): k for k, sg in enumerate(segs)}
        assert [(c[0], at[id(c[1])], at[id(c[2])], c[3]) for c in got] == ref
        n_found += len(ref)
    if name.startswith("sim") or name.endswith(".csv"):  # V scans: the V is among the pairs
        assert n_found > 0


# --- the rest: split costs, quantum, the single-shot pose ----------------------------------

@pytest.mark.parametrize("seed", range(5))
def test_split_costs_are_the_two_lines_sse(seed):
    """_tls_sse_splits (prefix moments, both sides in one pass) is the brute-force sum of
    squared TLS residuals of the two lines at every split, to float rounding."""
    rng = np.random.default_rng(seed)
    n = 40
    t = np.sort(rng.uniform(0, 500, n))
    p = np.column_stack([t, np.where(t < 250, 0.3 * t, 75 - 0.5 * (t - 250))])
    p = p + rng.normal(0, 2.0, p.shape) + [1000.0, 2000.0]
    ref = []
    for k in range(3, n - 2):
        ref.append(sum(float(np.sum(fit_line_2d(q).distance(q) ** 2)) for q in (p[:k], p[k:])))
    np.testing.assert_allclose(_tls_sse_splits(p, 3, n - 2), ref, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("q", [1.0, 0.1, 0.0])
def test_range_quantum_from_one_sort_is_uniques(q):
    rng = np.random.default_rng(3)
    r = rng.uniform(500, 4000, 800)
    if q:
        r = np.round(r / q) * q
    r[rng.random(800) < 0.05] = np.nan
    u = np.unique(r[np.isfinite(r) & (r > 0)])
    ref = float(np.min(np.diff(u)))
    k = r[np.isfinite(r)] / ref
    ref = ref if np.mean(np.abs(k - np.round(k)) <= 1e-6) >= 0.99 else 0.0
    assert estimate_range_quantum(r) == ref
    assert (ref > 0) == (q > 0)
    assert estimate_range_quantum(np.array([1000.0, 1000.0, 1001.0, np.nan])) == 0.0


def test_single_shot_candidates_are_both_pairings():
    """single_shot_pose computes the shared part once: its two candidates are
    pose_from_line_pairs of both pairings, to the bit."""
    rng = np.random.default_rng(5)
    ang, rho, _ = simulate_scan(make_truth(rng), rng)
    seg = split_v(ang, rho)
    alpha = np.radians(seg.opening_deg)
    ll = fit_v_lines(seg.points1, seg.points2, alpha)
    u = np.array([0.6, 0.1, 0.8]) / np.linalg.norm([0.6, 0.1, 0.8])
    w = np.cross(u, [0.0, 1.0, 0.0])
    w /= np.linalg.norm(w)
    l_cam = np.array([u, np.cos(alpha) * u + np.sin(alpha) * np.cross(w, u)])  # at alpha
    E_cam = np.array([20.0, -30.0, 900.0])
    pose = single_shot_pose(l_cam, E_cam, alpha, ll, (0.0, -1.0, 0.0))
    for name, l_lidar in (("direct", ll.l_lidar), ("swapped", ll.l_lidar[::-1])):
        ref = pose_from_line_pairs(l_cam, l_lidar, E_cam, ll.E_lidar)
        got = pose.info["candidates"][name]
        assert np.array_equal(got.R, ref.R) and np.array_equal(got.T, ref.T)
        assert got.residual == ref.residual
        for key in ("raw_R", "angle_cam", "angle_lidar"):
            assert np.array_equal(got.info[key], ref.info[key])


@pytest.mark.parametrize("shape", [(3,), (2, 3), (500, 3), (40, 2)])
def test_unit_is_division_by_numpys_norm(shape):
    """geometry.unit (its norm's sum without np.linalg.norm's wrapper) to the bit."""
    rng = np.random.default_rng(len(shape))
    v = rng.normal(size=shape) * 10.0 ** rng.uniform(-3, 4, shape[:-1] + (1,))
    assert np.array_equal(unit(v), v / np.linalg.norm(v, axis=-1, keepdims=True))
    with pytest.raises(ValueError, match="zero vector"):
        unit(np.zeros(shape))
