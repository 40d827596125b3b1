"""Edge zones of the V's scan segments, found from the residual profile pooled over positions
(beyond the paper).

A LiDAR's spot has a size: a beam whose spot straddles two surfaces reads a range between
them (a mixed or partial return). At the V's hinge (a concave corner) such returns read short,
at a board's outer edge (the wall or nothing behind) they read long or off the board's line.
With a spot about one beam spacing wide that touches one or two returns per end, which
:func:`lidarcal.scan.split_v` trims by their residuals; a spot several beam spacings wide
(large divergence or exit window) biases several returns per end by less than the range
noise each, invisible in one scan but systematic: the joint fit's range offset
(:mod:`lidarcal.ranging`) is separated from the LiDAR's position mainly by the returns at
the boards' ends, so a 1 mm bias over five returns per end moved it by ~3 mm.

The zone is read from the data, not from a rig constant: every segment's residuals to its
own line (eqs. 7-12, signed, + = farther from the LiDAR) are stacked by their rank from the
outer end and from the hinge end; a rank whose mean residual over all positions lies more
than ``z`` standard errors from zero (the noise from the segments' interior, MAD) is in the
zone; the zone extends over the next ranks while their mean exceeds ``Z_FADE`` standard errors,
plus one rank (the bias fades over the spot; what is left below detection still moved the
range offset), and every segment drops the returns of the zone at that end. No rank
significant: nothing dropped (a spot about a beam spacing wide: the rigs as before).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import MAD_TO_SIGMA, median
from .scan_segments import Line2D

#: at most this share of a segment's returns is searched from each end
MAX_SHARE = 0.2
#: significance of a rank's mean residual (standard errors); 60 ranks tested: false alarm ~0.4 %
Z_EDGE = 4.0
#: once a zone is found, it extends over the following ranks whose mean is still this
#: significant, plus one rank (the fading bias below detection)
Z_FADE = 1.5


@dataclass(frozen=True)
class EdgeZones:
    """Returns to drop at the outer end and at the hinge end of every segment, with the pooled
    profiles (mean signed residual per rank, mm) and the noise (mm) they were judged against."""

    outer: int
    hinge: int
    outer_profile: np.ndarray
    hinge_profile: np.ndarray
    noise_mm: float


def _signed_residuals(points: np.ndarray, line: Line2D) -> np.ndarray:
    """Orthogonal residuals to ``line``, + = beyond the line as seen from the LiDAR."""
    s = 1.0 if line.offset >= 0 else -1.0
    return s * line.distance(points)


def edge_zones(segments: list[tuple[np.ndarray, Line2D, bool]], z: float = Z_EDGE) -> EdgeZones:
    """The edge zones of a dataset's segments (module docstring).

    Parameters
    ----------
    segments : list of (points (M, 2), line, hinge_last)
        Every board segment of every position, its points in beam order, its fitted line,
        and whether the hinge is at its last point (segment 1 of :func:`lidarcal.scan.split_v`)
        or its first (segment 2).
    """
    lens = [len(p) for p, _, _ in segments]
    depth = int(MAX_SHARE * min(lens)) if lens else 0
    empty = np.zeros(0)
    if depth < 2 or len(segments) < 3:
        return EdgeZones(0, 0, empty, empty, float("nan"))
    outer, hinge, inner = [], [], []
    for pts, line, hinge_last in segments:
        r = _signed_residuals(pts, line)
        start, end = r[:depth], r[::-1][:depth]        # ranked from the first / last return
        (outer if hinge_last else hinge).append(start)
        (hinge if hinge_last else outer).append(end)
        inner.append(r[depth:len(r) - depth])
    inner_all = np.concatenate(inner)
    noise = MAD_TO_SIGMA * median(np.abs(inner_all - median(inner_all)))
    out = []
    for prof in (np.array(outer), np.array(hinge)):
        mean = prof.mean(axis=0)
        se = noise / np.sqrt(len(prof))
        zs = np.abs(mean) / se if se > 0 else np.zeros(depth)
        sig = np.flatnonzero(zs > z)
        k = int(sig.max()) + 1 if len(sig) else 0
        if k:  # the bias fades over the spot: extend while it still shows (> Z_FADE), one more
            while k < depth and zs[k] > Z_FADE:
                k += 1
            k = min(k + 1, depth)
        out.append((k, mean))
    (k_out, m_out), (k_hin, m_hin) = out
    return EdgeZones(k_out, k_hin, m_out, m_hin, noise)


def trim_edges(points: np.ndarray, hinge_last: bool, zones: EdgeZones) -> np.ndarray:
    """``points`` (beam order) without the edge zones: ``zones.outer`` returns dropped at the
    outer end and ``zones.hinge`` at the hinge end (never more than leaves half of them)."""
    n = len(points)
    a, b = (zones.outer, zones.hinge) if hinge_last else (zones.hinge, zones.outer)
    if a + b > n // 2:
        return points
    return points[a:n - b]
