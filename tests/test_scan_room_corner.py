"""Section 1.4 in a room: a wide-angle scanner sees the room's 90 deg corners beside the V.

Found by scripts/cleanroom_rig.py (coarse_lidar, a V of 100 deg): the V was the pair of
segments with the most returns, so a room corner (two walls, metres long, opening 90 deg,
inside the alpha window of 100 +- 15 deg) won at every position and `calibrate` put the
LiDAR 1.7 m from the truth with exit status 0. A board segment is now at most a few of
the pattern's diagonals long (`max_segment_mm`, measured from board.png).
"""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal.scan import split_v, v_segment_limit_mm


def _cast(segments: list[tuple[np.ndarray, np.ndarray]], theta: np.ndarray) -> np.ndarray:
    """Range of the first segment hit along each beam from the origin (inf: none)."""
    d = np.column_stack([np.cos(theta), np.sin(theta)])
    best = np.full(len(theta), np.inf)
    for a, b in segments:
        e = b - a
        den = d[:, 0] * (-e[1]) - d[:, 1] * (-e[0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (a[0] * (-e[1]) - a[1] * (-e[0])) / den
            s = (d[:, 0] * a[1] - d[:, 1] * a[0]) / den
        ok = (t > 0) & (s >= 0) & (s <= 1)
        best = np.where(ok & (t < best), t, best)
    return best


def _room_scan(v_deg: float, seed: int, step_deg: float = 0.36):
    """A 240 deg scan of a V (hinge 1.15 m ahead, boards 300 mm wide) in a 5 x 6 m room.

    Returns the beam angles, ranges (NaN: no return), and the true hinge point."""
    rng = np.random.default_rng(seed)
    hinge = np.array([1150.0, rng.uniform(-60, 60)])
    bis = np.array([-1.0, 0.0])  # the V opens towards the scanner
    half = np.radians(v_deg) / 2
    width = 300.0
    ends = [hinge + width * np.array([np.cos(np.pi + s * half), np.sin(np.pi + s * half)])
            for s in (1, -1)]
    assert np.allclose(bis @ (ends[0] - hinge), width * np.cos(half))
    x0, x1, y0, y1 = -1800.0, 2400.0 + rng.uniform(0, 300), -2900.0, 2600.0
    walls = [(np.array([x0, y0]), np.array([x1, y0])), (np.array([x1, y0]), np.array([x1, y1])),
             (np.array([x1, y1]), np.array([x0, y1])), (np.array([x0, y1]), np.array([x0, y0]))]
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))  # the room turned 10 deg
    rot = np.array([[c, -s], [s, c]])
    walls = [(rot @ a, rot @ b) for a, b in walls]
    boards = [(hinge, ends[0]), (hinge, ends[1])]
    ang = np.arange(-120.0, 120.0 + 1e-9, step_deg)
    r = _cast(boards + walls, np.radians(ang))
    r = np.round(r + rng.normal(0, 3.0, len(r)), 0)
    r[~np.isfinite(r)] = np.nan
    return ang, r, hinge


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("v_deg", [100.0, 104.0])
def test_room_corner_is_not_the_v(v_deg, seed):
    ang, r, hinge = _room_scan(v_deg, seed)
    alpha = np.radians(v_deg)
    # without the length limit a room corner (90 deg, hundreds of returns) wins
    loose = split_v(ang, r, alpha=alpha)
    assert len(loose.index1) + len(loose.index2) > 200
    assert abs(loose.opening_deg - 90.0) < 2.0
    # with it, the V: both segments on the boards (within 3 noise sigmas of them) and
    # its opening the truth's
    limit = v_segment_limit_mm([np.hypot(7, 10) * 30.0])  # the boards' 8 x 11 grid, 30 mm
    seg = split_v(ang, r, alpha=alpha, max_segment_mm=limit)
    assert abs(seg.opening_deg - v_deg) < 1.5
    for pts in (seg.points1, seg.points2):
        assert 20 <= len(pts) <= 60
        assert np.linalg.norm(pts - hinge, axis=1).max() < 320.0


def test_length_limit_names_itself_when_nothing_fits():
    ang, r, _ = _room_scan(100.0, 0)
    with pytest.raises(ValueError, match="each at most 100 mm long"):
        split_v(ang, r, alpha=np.radians(100.0), max_segment_mm=100.0)
