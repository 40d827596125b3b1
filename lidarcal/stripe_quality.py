"""Per-stripe quality gates (section 1.3 on real images): a stripe that is not found is a
skip or an error, never wrong points."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import median


@dataclass(frozen=True)
class StripeGates:
    """Per-image quality gates of a stripe (section 1.3 on real images).

    The centres must form one smooth curve: their RMS about it at most
    ``max_rms_width`` times the stripe width (FWHM) or ``min_rms_px``, whichever is
    larger; at least ``min_inlier_share`` of the columns' centres on it; crossing at
    least ``min_coverage`` of the board along the stripe; a median peak of at least
    ``min_median_snr`` noise sigmas; at least ``min_points`` centres.
    """

    max_rms_width: float = 0.25
    min_rms_px: float = 0.5
    min_inlier_share: float = 0.6
    min_coverage: float = 0.3
    min_median_snr: float = 10.0
    min_points: int = 10


DEFAULT_GATES = StripeGates()


def stripe_quality(pts: np.ndarray, n_rejected: int, fit_rms_px: float, width_px: float,
                   snr: np.ndarray, mask: np.ndarray, origin: tuple[int, int] = (0, 0)
                   ) -> dict:
    """The numbers the gates of :class:`StripeGates` judge one stripe by.

    ``coverage``: the share of the mask crossed along the stripe: the mask's pixels
    within 2 px of the centres' line, binned every 4 px along it, and the share of
    those bins that hold a centre. ``mask`` is given with its ``origin`` (x0, y0) in
    the image.
    """
    n = len(pts)
    q = {"points": n, "rms_px": float(fit_rms_px), "width_px": float(width_px),
         "inlier_share": n / max(n + n_rejected, 1),
         "median_snr": median(snr) if n else 0.0, "coverage": 0.0}
    if n < 3:
        return q
    c = pts.mean(0)
    _, _, vt = np.linalg.svd(pts - c, full_matrices=False)
    q["coverage"] = _coverage(pts - c, _band_candidates(mask, origin, c, vt[1]), vt[0], vt[1])
    return q


def _coverage(pts_c: np.ndarray, P: np.ndarray, t_dir: np.ndarray, n_dir: np.ndarray,
              half: float = 2.0, bin_px: float = 4.0) -> float:
    """Share of the board crossed along the stripe: of the ``bin_px`` bins along ``t_dir``
    that hold a mask pixel within ``half`` px of the centres' line, the share that also
    hold a centre. ``pts_c`` (N, 2) the centres and ``P`` (M, 2) the candidate mask
    pixels, both minus the centres' mean; ``t_dir``, ``n_dir`` the line's unit direction
    and normal."""
    band = np.abs(P @ n_dir) <= half
    if not band.any():
        return 0.0
    tm = P[band] @ t_dir
    lo = tm.min()
    nb = int((tm.max() - lo) // bin_px) + 1
    board_bins = np.zeros(nb, bool)
    board_bins[((tm - lo) // bin_px).astype(int)] = True
    tc = (pts_c @ t_dir - lo) // bin_px
    hit = np.zeros(nb, bool)
    hit[tc[(tc >= 0) & (tc < nb)].astype(int)] = True
    return float((hit & board_bins).sum() / max(board_bins.sum(), 1))


def _band_candidates(mask: np.ndarray, origin: tuple[int, int], c: np.ndarray,
                     n_dir: np.ndarray, half: float = 2.0) -> np.ndarray:
    """Image coordinates minus ``c`` (M, 2) of the mask's pixels near the line through ``c``
    with unit normal ``n_dir``: a superset of those within ``half`` px of it.

    Gathered along the line's dominant axis (a few pixels per column, or per row), not by
    scanning the whole mask: the band is ``|(p - c) . n| <= half``, so at each column ``x``
    it spans ``2 half / |n_y|`` rows about the line; one more row each side covers rounding.
    """
    x0, y0 = origin
    H, W = mask.shape
    along = 0 if abs(n_dir[1]) >= abs(n_dir[0]) else 1  # 0: one run of rows per column
    na, nc = (n_dir[0], n_dir[1]) if along == 0 else (n_dir[1], n_dir[0])
    ca, cc = (c[0] - x0, c[1] - y0) if along == 0 else (c[1] - y0, c[0] - x0)
    n_along, n_cross = (W, H) if along == 0 else (H, W)
    a = np.arange(n_along)
    mid = cc - (a - ca) * na / nc  # the line's cross coordinate at each a
    r = int(np.ceil(half / abs(nc))) + 1
    b = np.floor(mid)[:, None].astype(int) + np.arange(-r, r + 2)[None, :]
    a = np.broadcast_to(a[:, None], b.shape)
    inside = (b >= 0) & (b < n_cross)
    a, b = a[inside], b[inside]
    xs, ys = (a, b) if along == 0 else (b, a)
    sel = mask[ys, xs]
    xs, ys = xs[sel], ys[sel]
    P = np.empty((len(xs), 2))
    P[:, 0], P[:, 1] = xs + x0, ys + y0
    return P - c


def quality_problem(q: dict, gates: StripeGates = DEFAULT_GATES) -> str | None:
    """Why a stripe fails :class:`StripeGates` (one phrase), or None when it passes."""
    if q["points"] < gates.min_points:
        return f"{q['points']} stripe centres found, need at least {gates.min_points}"
    limit = max(gates.max_rms_width * q["width_px"], gates.min_rms_px)
    if not np.isfinite(q["rms_px"]) or q["rms_px"] > limit:
        return (f"the stripe centres do not form one smooth curve (rms {q['rms_px']:.2f} px, "
                f"limit {limit:.2f} px)")
    if q["inlier_share"] < gates.min_inlier_share:
        return (f"only {100 * q['inlier_share']:.0f} % of the stripe centres lie on one curve "
                f"(need {100 * gates.min_inlier_share:.0f} %)")
    if q["coverage"] < gates.min_coverage:
        return (f"the stripe crosses only {100 * q['coverage']:.0f} % of the board "
                f"(need {100 * gates.min_coverage:.0f} %)")
    if q["median_snr"] < gates.min_median_snr:
        return f"the stripe is faint (median peak {q['median_snr']:.1f} noise sigmas)"
    return None


