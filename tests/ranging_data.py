"""Test data with LiDAR ranging errors, made by post-processing a simulated dataset's scans.

Until the simulator models them (issue 16), a dataset written by ``lidarcal simulate``
gets a range offset (every valid range ``offset_mm`` farther) and a dark-square bias
(returns whose camera-frame hit lies on a black square of a V-board chessboard read
``dark_extra_mm`` farther), computed from ``truth.json``: the true LiDAR pose of each
position, the board rectangles (``chessboard_outline_mm``, ``u_axis``, ``v_axis``) and the
simulator's colour rule (square (0, 0) at the chessboard outline's first corner is black,
:meth:`lidarcal.synthetic.scene.Rect.material`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np


def dark_hits(truth: dict, square_mm: float, inner: tuple[int, int], X: np.ndarray,
              tol_mm: float = 5.0) -> np.ndarray:
    """True where camera-frame points ``X`` (N, 3) lie on a black square of a V-board."""
    out = np.zeros(len(X), bool)
    for b in truth["boards"]:
        n, d = np.asarray(b["normal"], float), float(b["d_mm"])
        on = np.abs(X @ n - d) < tol_mm
        o = np.asarray(b["chessboard_outline_mm"], float)[0]
        u, v = np.asarray(b["u_axis"], float), np.asarray(b["v_axis"], float)
        i = np.floor((X - o) @ u / square_mm)
        j = np.floor((X - o) @ v / square_mm)
        inside = (i >= 0) & (i <= inner[0]) & (j >= 0) & (j <= inner[1])
        out |= on & inside & ((i + j) % 2 == 0)
    return out


def add_ranging_errors(src: str | os.PathLike, dst: str | os.PathLike, offset_mm: float = 0.0,
                       dark_extra_mm: float = 0.0, range_offset_prior: tuple[float, float] | None = None
                       ) -> Path:
    """Copy dataset ``src`` to ``dst`` (images linked, not copied) with biased scans.

    ``range_offset_prior``: optional ``(mean, sigma)`` written as dataset.json
    ``lidar.range_offset_mm`` / ``lidar.range_offset_sigma_mm``.
    """
    src, dst = Path(src), Path(dst)
    dst.mkdir(parents=True)
    for item in src.iterdir():
        if item.name in ("scans", "dataset.json"):
            continue
        (dst / item.name).symlink_to(item.resolve(), target_is_directory=item.is_dir())
    meta = json.loads((src / "dataset.json").read_text())
    if range_offset_prior is not None:
        meta["lidar"]["range_offset_mm"] = float(range_offset_prior[0])
        meta["lidar"]["range_offset_sigma_mm"] = float(range_offset_prior[1])
    (dst / "dataset.json").write_text(json.dumps(meta, indent=2))
    truth = json.loads((src / "truth.json").read_text())
    sq = float(meta["v_board"]["square_mm"])
    inner = tuple(int(v) for v in meta["v_board"]["inner_corners"])
    poses = {int(p["index"]): p for p in truth["poses"]}
    index_of = {}
    for line in (src / "positions.csv").read_text().splitlines()[1:]:
        f = line.split(",")
        if len(f) >= 4:
            index_of[f[3].strip()] = int(f[0])
    (dst / "scans").mkdir()
    for scan in sorted((src / "scans").glob("*.csv")):
        ang, rng = np.loadtxt(scan, delimiter=",", skiprows=1, unpack=True, ndmin=2)
        idx = index_of.get(f"scans/{scan.name}", int(scan.stem))
        p = poses[idx]
        R, T = np.asarray(p["R"], float), np.asarray(p["T_mm"], float)
        ok = np.isfinite(rng) & (rng > 0)
        th = np.radians(ang)
        X = (np.column_stack([rng * np.cos(th), rng * np.sin(th), np.zeros_like(th)]) @ R.T) + T
        extra = np.where(ok, offset_mm, 0.0) + np.where(ok & dark_hits(truth, sq, inner, X),
                                                        dark_extra_mm, 0.0)
        out = np.column_stack([ang, np.where(ok, rng + extra, 0.0)])
        np.savetxt(dst / "scans" / scan.name, out, delimiter=",", fmt=["%.6f", "%.1f"],
                   header="angle_deg,range_mm", comments="")
    return dst
