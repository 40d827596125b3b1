"""The stripe centre's numerical kernels (section 1.3) against their definitions: the window
centroid, the saturated-core centres, the incremental column passes and the closed-form
TLS directions give what the plain formulas give (issue 15: they were rewritten for speed)."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal import stripe_profile as sp
from lidarcal.geometry import median
from lidarcal.laser_colour import SATURATED_DN
from lidarcal.scan import fit_line_2d


def _centroid_reference(prof: np.ndarray, start: np.ndarray, half: float, iters: int = 6,
                        tol: float = 1e-4) -> np.ndarray:
    """The window centroid as documented: weights = overlap of [c - half, c + half] with
    each sample's cell, iterated per profile until it moves by at most ``tol``."""
    out = np.empty(len(prof))
    j = np.arange(prof.shape[1])
    for r, row in enumerate(np.clip(prof, 0, None)):
        c = float(start[r])
        for _ in range(iters):
            w = np.clip(np.minimum(c + half, j + 0.5) - np.maximum(c - half, j - 0.5), 0, 1)
            m = (w * row).sum()
            new = (w * row * j).sum() / m if m > 0 else np.nan
            done = not abs(new - c) > tol
            c = new
            if done:
                break
        out[r] = c
    return out


@pytest.mark.parametrize("seed", range(3))
def test_window_centroid_is_the_overlap_weighted_centroid(seed) -> None:
    rng = np.random.default_rng(seed)
    n_rows, n = 60, 41
    j = np.arange(n)
    centre = rng.uniform(8, n - 9, n_rows)
    prof = 100 * np.exp(-0.5 * ((j - centre[:, None]) / rng.uniform(1, 3)) ** 2)
    prof += rng.normal(0, 2, prof.shape)
    prof[:3] = 0.0  # no signal: NaN
    start = np.clip(np.round(centre + rng.normal(0, 1.5, n_rows)), 0, n - 1)
    half = float(rng.uniform(2, 7))
    got, _ = sp._window_centroid(prof, start, half)
    ref = _centroid_reference(prof, start, half)
    assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.isnan(got[:3]).all()
    assert np.nanmax(np.abs(got - ref)) < 1e-9


def _saturated_reference(prof, s, cen, peak):
    out, pk = cen.copy(), peak.copy()
    n = s.shape[1]
    for i in range(len(prof)):
        top = prof[i].max()
        if top < SATURATED_DN or not np.isfinite(cen[i]):
            continue
        flat = prof[i] >= top - 1
        best, end, run = 0, 0, 0
        for j in range(n):  # the longest run of flat samples (the first of equal ones)
            run = run + 1 if flat[j] else 0
            if run > best:
                best, end = run, j
        if best < 3:
            continue
        row = s[i]
        p0, p1 = end - best + 1, end
        head = min(row[p0], row[p1])
        h = 0.5 * head
        a = p0
        while a > 0 and row[a - 1] >= h:
            a -= 1
        b = p1
        while b < n - 1 and row[b + 1] >= h:
            b += 1
        if head <= 0 or a == 0 or b == n - 1:
            continue
        left = a - (row[a] - h) / max(row[a] - row[a - 1], 1e-6)
        right = b + (row[b] - h) / max(row[b] - row[b + 1], 1e-6)
        out[i] = 0.5 * (left + right)
        pk[i] = head * np.sqrt(best)
    return out, pk


def test_saturated_centres_match_the_run_definition() -> None:
    rng = np.random.default_rng(4)
    j = np.arange(45)
    c = rng.uniform(5, 40, 200)
    prof = np.clip(600 * np.exp(-0.5 * ((j - c[:, None]) / 2.0) ** 2) + rng.normal(0, 2, (200, 45)),
                   0, 255).round()
    prof[::7] *= 0.3  # unsaturated rows keep their centroid
    prof[3, 2] = 255.0  # a hot pixel beside a clipped core: not its plateau
    s = prof - 3.0
    cen = c + rng.normal(0, 0.3, 200)
    cen[5] = np.nan
    peak = s.max(axis=1)
    got, pk = sp._saturated_centres(prof, s, cen, peak, np.zeros_like(s), noise=2.0)
    ref, pk_ref = _saturated_reference(prof, s, cen, peak)
    assert np.array_equal(np.isnan(got), np.isnan(ref))
    assert np.nanmax(np.abs(got - ref)) < 1e-12 and np.max(np.abs(pk - pk_ref)) < 1e-9
    assert np.sum(got != cen) > 50  # the clipped rows were re-centred
    assert np.abs(got - c)[pk > peak].max() < 0.1  # on the truth (to the flanks' interpolation)
    # without a blackness map: the run through the centroid, the peaks as they were
    got, pk = sp._saturated_centres(prof, s, cen, peak)
    ref = _run_reference(prof, s, cen)
    assert np.array_equal(np.isnan(got), np.isnan(ref)) and np.nanmax(np.abs(got - ref)) < 1e-12
    assert np.array_equal(pk, peak)


def _run_reference(prof, s, cen):
    out = cen.copy()
    n = s.shape[1]
    for i in range(len(prof)):
        top = prof[i].max()
        if (prof[i] >= top - 1).sum() < 3 or top < SATURATED_DN or not np.isfinite(cen[i]):
            continue
        row = s[i]
        k = int(np.clip(np.rint(cen[i]), 0, n - 1))
        half = 0.5 * row.max()
        if row[k] < half:
            continue
        a = k
        while a > 0 and row[a - 1] >= half:
            a -= 1
        b = k
        while b < n - 1 and row[b + 1] >= half:
            b += 1
        if a == 0 or b == n - 1:
            continue
        left = a - (row[a] - half) / max(row[a] - row[a - 1], 1e-6)
        right = b + (row[b] - half) / max(row[b] - row[b + 1], 1e-6)
        out[i] = 0.5 * (left + right)
    return out


def test_incremental_passes_equal_full_passes(monkeypatch) -> None:
    """Recomputing only the columns whose window moved gives the centres of recomputing all."""
    rng = np.random.default_rng(5)
    H, W = 160, 300
    y, x = np.mgrid[0:H, 0:W].astype(float)
    blk = (((x // 25) + (y // 25)) % 2).astype(np.float32)  # squares: 1 on black
    f = 80.3 + 0.12 * (x - W / 2) + 4e-4 * (x - W / 2) ** 2
    img = (1 - 0.7 * blk) * (200 * np.exp(-0.5 * ((y - f) / 1.8) ** 2) + 6)
    img = np.clip(np.rint(img + rng.normal(0, 2, img.shape)), 0, 255).astype(np.uint8)
    mask = np.zeros((H, W), bool)
    mask[10:-10, 10:-10] = True
    args = (img, mask, np.array([W / 2, 80.3]), 0.12, 2.0, 8.0, blk, 0.3, False)
    fast = sp._centres_by_column(*args)
    full_pass = sp._column_pass
    calls = []

    def every_column(img_, blk_, cols, top, *rest):
        calls.append(len(cols))
        return full_pass(img_, blk_, cols, top, *rest)

    monkeypatch.setattr(sp, "_column_pass", every_column)
    sp._centres_by_column(*args)
    assert len(calls) >= 2 and min(calls) < max(calls)  # later passes: the moved columns
    monkeypatch.undo()

    # reference: all columns every pass (windows from the previous pass's centres)
    cols = np.flatnonzero(mask.any(axis=0))
    y_cur = 80.3 + 0.12 * (cols - W / 2)
    width = sp._fwhm(sp._profiles(img, cols, y_cur, 30)[0], 2.0)
    L = int(min(max(np.ceil(4 * width) + 6, 10), (H - 1) // 2))
    half = max(1.5 * width, 2.0)
    for _ in range(4):
        top = sp._profile_top(y_cur, L, H)
        _, _, _, _, peak, cen = full_pass(img, blk, cols, top, L, max(width / 2.355, 0.8),
                                          0.3, half)
        ok = np.isfinite(cen) & (peak >= 8.0 * 2.0)
        y_cur = np.where(ok, top + cen, y_cur)
    pts = fast[0]
    ref = dict(zip(cols.tolist(), y_cur))
    assert len(pts) > 200
    assert max(abs(yy - ref[int(xx)]) for xx, yy in pts) < 1e-9
    assert np.abs(pts[:, 1] - (80.3 + 0.12 * (pts[:, 0] - W / 2)
                               + 4e-4 * (pts[:, 0] - W / 2) ** 2)).max() < 0.3


@pytest.mark.parametrize("seed", range(4))
def test_closed_form_directions_match_the_svd(seed) -> None:
    rng = np.random.default_rng(seed)
    t = np.array([np.cos(seed), np.sin(seed)])
    p = rng.normal(0, 30, (50, 1)) * t + rng.normal(0, 0.5, (50, 2)) + [400.0, -90.0]
    _, _, vt = np.linalg.svd(p - p.mean(0), full_matrices=False)
    d = sp._principal_direction(p - p.mean(0))
    assert abs(abs(d @ vt[0]) - 1) < 1e-12
    line = fit_line_2d(p)
    assert abs(abs(line.normal @ vt[1]) - 1) < 1e-12
    assert np.allclose(np.abs(line.distance(p)), np.abs((p - p.mean(0)) @ vt[1]), atol=1e-9)


@pytest.mark.parametrize("sigma", sorted(sp._UINT8_BLUR_KSIZE))
def test_uint8_blur_kernel_sizes_give_opencvs_own_result(sigma) -> None:
    """The smaller uint8 kernels of ``_gaussian_blur`` change no pixel: on full-range noise
    (every tap shows) and on an impulse, the result equals OpenCV's size from sigma."""
    rng = np.random.default_rng(7)
    noise = rng.integers(0, 256, (157, 211)).astype(np.uint8)
    impulse = np.zeros((31, 31), np.uint8)
    impulse[15, 15] = 255
    for img in (noise, impulse):
        assert np.array_equal(sp._gaussian_blur(img, sigma),
                              sp.cv2.GaussianBlur(img, (0, 0), sigma))
    # a smaller kernel still would not be the same blur: the sizes are the smallest ones
    k = sp._UINT8_BLUR_KSIZE[sigma] - 2
    assert not np.array_equal(sp.cv2.GaussianBlur(noise, (k, k), sigma),
                              sp.cv2.GaussianBlur(noise, (0, 0), sigma))


# --- issue 15 (stripe side): exact shortcuts against the plain numpy/OpenCV calls they replace,
# on a real photo (data/real_tapas) and a simulated stripe image (data/paper_rig)

_IMAGES = ("data/real_tapas/00.png", "data/paper_rig/stripes/0000.png")


def _gray(path: str) -> np.ndarray:
    from pathlib import Path

    import cv2

    img = cv2.imread(str(Path(__file__).resolve().parents[1] / path), cv2.IMREAD_GRAYSCALE)
    assert img is not None, path
    return img


def _polygon_mask(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    import cv2

    H, W = shape
    poly = np.column_stack([rng.uniform(0, W, 5), rng.uniform(0, H, 5)]).astype(np.int32)
    m = np.zeros(shape, np.uint8)
    cv2.fillConvexPoly(m, cv2.convexHull(poly), 1)
    return m.astype(bool)


@pytest.mark.parametrize("path", _IMAGES)
def test_masked_histogram_is_opencvs_masked_calchist(path) -> None:
    import cv2

    img = _gray(path)
    rng = np.random.default_rng(3)
    masks = [_polygon_mask(img.shape, rng) for _ in range(3)]
    masks += [np.ones(img.shape, bool), rng.random(img.shape) < 0.5, np.zeros(img.shape, bool)]
    for mask in masks:
        ref = cv2.calcHist([img], [0], mask.view(np.uint8), [256], [0, 256]).ravel()
        got = sp._masked_hist(img, mask)
        assert got.dtype == np.int64 and np.array_equal(got, ref.astype(np.int64))
        assert got.sum() == np.count_nonzero(mask)
        ro = mask.copy()
        ro.flags.writeable = False  # the cached path (read-only board masks)
        assert np.array_equal(sp._masked_hist(img, ro), got)
        assert np.array_equal(sp._masked_hist(img, ro), got)


def _fwhm_reference(prof: np.ndarray, noise: float) -> float:
    """The stripe width as it was written before: row-wise numpy on (M, W) profiles."""
    s = prof - np.median(prof, axis=1)[:, None]
    pk = s.max(axis=1)
    good = pk > 8 * noise
    if good.sum() < 3:
        return 3.0
    widths = np.count_nonzero(s[good] > 0.5 * pk[good, None], axis=1)
    return float(np.clip(np.median(widths), 1.0, 30.0))


@pytest.mark.parametrize("path", _IMAGES)
def test_profile_reductions_match_the_row_wise_numpy(path) -> None:
    """Column profiles of a real and a simulated stripe image: the stripe width, the
    per-profile maximum and the row medians (odd and even widths, one row and many) are
    the ones numpy's row-wise calls give, to the bit."""
    img = _gray(path)
    H, W = img.shape
    rng = np.random.default_rng(5)
    row, _ = np.unravel_index(np.argmax(sp._gaussian_blur(img, 1.5)), img.shape)
    cols = np.arange(W)
    for y0 in (np.full(W, float(row)), rng.uniform(0, H - 1, W)):
        for L in (8, 26, 30):
            prof, _ = sp._profiles(img, cols, y0, L)
            assert sp._fwhm(prof, 2.0) == _fwhm_reference(prof, 2.0)
            assert np.array_equal(sp._row_max(prof), prof.max(axis=1))
            for n in (17, 18, 61):
                part = np.ascontiguousarray(prof[:, :min(n, prof.shape[1])])
                assert np.array_equal(sp._row_median(part), np.median(part, axis=1))
                assert median(part[0]) == float(np.median(part[0]))


def _background_reference(prof: np.ndarray, bprof: np.ndarray | None) -> np.ndarray:
    """The background as documented: a straight line through the medians of the two outer
    thirds for every profile, replaced by ``b0 + b1 * blackness`` where the thirds'
    blackness medians differ by more than 0.3."""
    n = prof.shape[1]
    third = max(n // 3, 2)
    left, right = np.median(prof[:, :third], axis=1), np.median(prof[:, -third:], axis=1)
    xl, xr = (third - 1) / 2.0, n - 1 - (third - 1) / 2.0
    bg = left[:, None] + (right - left)[:, None] * ((np.arange(n)[None, :] - xl) / (xr - xl))
    if bprof is None:
        return bg
    bl, br = np.median(bprof[:, :third], axis=1), np.median(bprof[:, -third:], axis=1)
    for r in np.flatnonzero(np.abs(br - bl) > 0.3):
        bg[r] = left[r] + (right[r] - left[r]) / (br[r] - bl[r]) * (bprof[r] - bl[r])
    return bg


@pytest.mark.parametrize("seed", range(4))
def test_background_rows_by_their_own_model(seed) -> None:
    """Background per profile (rows with and without a blackness step, none, all): the
    line or the blackness model of each row, bit for bit as the row-by-row reference."""
    rng = np.random.default_rng(seed)
    m, n = 200, int(rng.integers(20, 62))
    prof = rng.normal(20, 5, (m, n)).astype(np.float32)
    edge = rng.integers(0, n, m)[:, None]
    for bprof in (None, (np.arange(n)[None, :] >= edge).astype(np.float32),
                  np.zeros((m, n), np.float32), np.tile(np.arange(n) >= n // 2, (m, 1))
                  .astype(np.float32)):
        got, ref = sp._background(prof, bprof), _background_reference(prof, bprof)
        assert got.dtype == ref.dtype and np.array_equal(got, ref)
