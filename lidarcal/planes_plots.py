"""Figures of the one-board calibration (``lidarcal planes``): the scan on each photo, the board
segments in each scan, the per-view residuals. Each returns a matplotlib Figure (no pyplot).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .planes import PlanesResult, plane_residuals_mm
from .scan import scan_points


def projection_figure(res: PlanesResult, k: int, image: np.ndarray | None = None):
    """View ``k``'s scan drawn on its photo with the calibration (board returns ringed, the
    pattern's outline one square beyond the outer corners in yellow)."""
    from .board import board_outline_px
    from .io.dataset import read_image
    from .overlay import lidar_on_image

    v = res.views[k]
    pair = res.pairs[k]  # type: ignore[attr-defined]
    img = image
    if img is None:
        img = cv2.imread(str(pair.image_path), cv2.IMREAD_COLOR)  # colour photo (BGR)
        if img is None:
            img = read_image(pair.image_path)
    outline = None
    if v.board is not None:
        outline = board_outline_px(res.camera, v.board.R, v.board.T, v.board.board)  # type: ignore[attr-defined]
    return lidar_on_image(img, res.camera, res.R, res.T, v.angle_deg, v.range_mm,  # type: ignore[attr-defined]
                          highlight=v.beams if res.used[k] else None, outline_px=outline,
                          title=f"{v.name}: scan on the photo")


def write_projections(res: PlanesResult, out: str | Path) -> list[Path]:
    """``OUT/projection_NAME.png`` for every view (see :func:`projection_figure`)."""
    from .overlay import save_figure

    paths = []
    for k, v in enumerate(res.views):
        paths.append(save_figure(projection_figure(res, k), Path(out) / f"projection_{v.name}.png"))
    return paths


def plot_board_segments(res: PlanesResult, cols: int = 4):
    """Every scan in the LiDAR frame: all returns grey, the candidate segments thin, the
    board's returns (used in the fit) bold, with the board plane's trace predicted by the
    calibration."""
    from .plots import _figure

    n = len(res.views)
    rows = int(np.ceil(n / cols))
    fig = _figure(3.2 * cols, 3.0 * rows)
    for k, v in enumerate(res.views):
        ax = fig.add_subplot(rows, cols, k + 1)
        p = scan_points(v.angle_deg, v.range_mm)
        ax.plot(p[:, 0], p[:, 1], ".", ms=1, color="0.7")
        for s in v.candidates:
            ax.plot(s.points[:, 0], s.points[:, 1], "-", lw=0.6, color="tab:blue", alpha=0.5)
        if res.used[k]:
            b = v.points_mm
            ax.plot(b[:, 0], b[:, 1], ".", ms=2, color="tab:red")
            # trace of the board plane in the scan plane: {p : n.(R p + T) = d}
            n = res.R.T @ v.board.plane.normal
            c = v.board.plane.d - v.board.plane.normal @ res.T
            t = np.array([-n[1], n[0]]) / np.hypot(n[0], n[1])
            p0 = n[:2] * c / (n[0] ** 2 + n[1] ** 2)
            s = (b - p0) @ t
            e = p0 + np.outer([s.min() - 200, s.max() + 200], t)
            ax.plot(e[:, 0], e[:, 1], "--", color="k", lw=0.8)
            lim = np.r_[b.min(0) - 600, b.max(0) + 600]
            ax.set_xlim(lim[0], lim[2])
            ax.set_ylim(lim[1], lim[3])
        ax.plot(0, 0, "k+")
        ax.set_aspect("equal")
        ax.set_title(f"{v.name}: " + (f"{len(v.beams)} returns, {res.rms_mm[k]:.1f} mm RMS"
                                      if res.used[k] else "not used"), fontsize=8)
        ax.tick_params(labelsize=6)
    return fig


def plot_view_residuals(res: PlanesResult):
    """Point-to-plane residuals (mm) of every used view against the beam index."""
    from .plots import _figure

    fig = _figure(7.0, 3.6)
    ax = fig.add_subplot()
    for k, v in enumerate(res.views):
        if res.used[k]:
            ax.plot(v.beams, plane_residuals_mm(v, res.R, res.T), ".", ms=2,
                    label=f"{v.name} ({res.rms_mm[k]:.1f} mm)")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("beam index")
    ax.set_ylabel("point-to-plane residual (mm)")
    ax.legend(fontsize=7, ncols=4)
    return fig


def board_return_share(res: PlanesResult, margin_squares: float = 1.0) -> dict[str, float]:
    """Per view (by name), the share of its board returns that the calibration ``R, T`` projects
    inside the board's outline in its photo (``margin_squares`` beyond the outer corners, the
    board's plane from its corners): the check of the projection figures in numbers. Views with
    no board or no board returns are left out."""
    from .board import board_outline_px
    from .overlay import project_returns

    share = {}
    for v in res.views:
        if v.board is None or len(v.beams) == 0:
            continue
        px, _, _ = project_returns(res.camera, res.R, res.T, v.angle_deg, v.range_mm)  # type: ignore[attr-defined]
        outline = board_outline_px(res.camera, v.board.R, v.board.T, v.board.board,  # type: ignore[attr-defined]
                                   margin_squares=margin_squares).astype(np.float32)
        share[v.name] = float(np.mean([cv2.pointPolygonTest(outline, (float(x), float(y)), False) >= 0
                                       for x, y in px[v.beams]]))
    return share
