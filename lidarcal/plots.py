"""Figures shared by the notebooks and the PDF report.

Every function returns a :class:`matplotlib.figure.Figure` built without
``pyplot`` (nothing is shown, nothing leaks between calls; Jupyter displays
a returned figure once). Inputs are plain numpy arrays or the package's
dataclasses; the functions only draw, they compute nothing the pipeline
does not already give them.

Conventions: image coordinates in pixels (x right, y down); scan points in
the LiDAR frame (x, y), mm; 3D points in the camera frame (OpenCV), mm;
angles in degrees.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

#: One colour per board / per scan segment (board 1, board 2), used everywhere.
BOARD_COLOURS = ("tab:blue", "tab:orange")
#: Colours of the three error columns of Table 1 (centre, z axis, x axis).
ERROR_COLUMNS = (("centre_mm", "LiDAR centre (mm)"), ("z_axis_deg", "z axis (deg)"),
                 ("x_axis_deg", "x axis (deg)"))


def _figure(w: float = 6.4, h: float = 4.8) -> Figure:
    return Figure(figsize=(w, h), layout="constrained")


def _show_image(ax, image: np.ndarray) -> None:
    img = np.asarray(image)
    if img.ndim == 3:
        img = img[..., ::-1]  # BGR (OpenCV) -> RGB
        ax.imshow(img)
    else:
        ax.imshow(img, cmap="gray", vmin=0, vmax=255 if img.dtype == np.uint8 else None)
    ax.set_xlim(-0.5, img.shape[1] - 0.5)
    ax.set_ylim(img.shape[0] - 0.5, -0.5)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def plot_corners(image: np.ndarray, corners_px: Sequence[np.ndarray],
                 outlines_px: Sequence[np.ndarray] | None = None,
                 title: str = "V-board: detected chessboard corners (section 1.2)") -> Figure:
    """Detected inner corners of each board over ``board.png``.

    ``corners_px[i]`` (N, 2) in OpenCV order; the first corner of each board is
    ringed (the 180 deg order ambiguity is harmless: only the plane is used).
    ``outlines_px[i]`` (M, 2), optional, is the mask polygon of board i.
    """
    fig = _figure(7.0, 5.6)
    ax = fig.add_subplot()
    _show_image(ax, image)
    for i, c in enumerate(corners_px):
        c = np.asarray(c, dtype=float).reshape(-1, 2)
        col = BOARD_COLOURS[i % 2]
        ax.plot(c[:, 0], c[:, 1], "+", color=col, ms=4, mew=0.8, label=f"board {i + 1}: {len(c)} corners")
        ax.plot(*c[0], "o", mfc="none", mec=col, ms=10, mew=1.5)
        if outlines_px is not None and i < len(outlines_px) and outlines_px[i] is not None:
            o = np.asarray(outlines_px[i], dtype=float).reshape(-1, 2)
            o = np.vstack([o, o[:1]])
            ax.plot(o[:, 0], o[:, 1], "-", color=col, lw=1)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(title, fontsize=10)
    return fig


def plot_stripe_centres(image: np.ndarray, centres_px: Sequence[np.ndarray],
                        outlines_px: Sequence[np.ndarray] | None = None, zoom: bool = True,
                        title: str = "Laser stripe centres (section 1.3)") -> Figure:
    """Sub-pixel stripe centres of each board over a stripe image.

    ``centres_px[i]`` (N, 2) for board i. With ``zoom`` the top panel is cropped
    to the stripes and two lower panels show ~40 px windows on each stripe,
    where the pixels and the sub-pixel centre line can be seen.
    """
    img = np.asarray(image)
    if img.dtype == np.uint8 and img.ndim == 2 and img.max() < 255:
        # a dark exposure: stretch so that the stripes and faint boards show
        hi = max(float(np.percentile(img, 99.9)), 1.0)
        img = np.clip(img.astype(float) * (255.0 / hi), 0, 255).astype(np.uint8)
    cs = [np.asarray(c, dtype=float).reshape(-1, 2) for c in centres_px]
    have = zoom and sum(len(c) for c in cs) > 0
    H, W = img.shape[:2]
    if have:
        p = np.vstack(cs)
        lo, hi_ = p.min(0), p.max(0)
        m = 0.08 * (hi_ - lo).max() + 20
        x0, x1 = max(lo[0] - m, -0.5), min(hi_[0] + m, W - 0.5)
        y0, y1 = max(lo[1] - m, -0.5), min(hi_[1] + m, H - 0.5)
    else:
        x0, x1, y0, y1 = -0.5, W - 0.5, -0.5, H - 0.5
    aspect = (y1 - y0) / max(x1 - x0, 1.0)
    top_h = max(1.6, min(6.0, 7.0 * aspect + 0.8))
    fig = _figure(7.0, top_h + (2.6 if have else 0.0))
    if have:
        gs = fig.add_gridspec(2, 2, height_ratios=[top_h, 2.6])
        ax = fig.add_subplot(gs[0, :])
    else:
        ax = fig.add_subplot()
    _show_image(ax, img)
    for i, c in enumerate(cs):
        ax.plot(c[:, 0], c[:, 1], ".", color=BOARD_COLOURS[i % 2], ms=1.5,
                label=f"board {i + 1}: {len(c)} centres")
        if outlines_px is not None and i < len(outlines_px) and outlines_px[i] is not None:
            o = np.asarray(outlines_px[i], dtype=float).reshape(-1, 2)
            o = np.vstack([o, o[:1]])
            ax.plot(o[:, 0], o[:, 1], "-", color=BOARD_COLOURS[i % 2], lw=0.8, alpha=0.6)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.legend(loc="upper right", fontsize=7, markerscale=6)
    ax.set_title(title, fontsize=10)
    if have:
        for i, c in enumerate(cs[:2]):
            axz = fig.add_subplot(gs[1, i])
            if not len(c):
                axz.set_axis_off()
                continue
            cx, cy = c[len(c) // 2]
            half = 20
            axz.imshow(img, cmap="gray" if img.ndim == 2 else None, interpolation="nearest")
            sel = (np.abs(c[:, 0] - cx) < half * 1.5) & (np.abs(c[:, 1] - cy) < half)
            axz.plot(c[sel, 0], c[sel, 1], ".-", color=BOARD_COLOURS[i % 2], ms=3, lw=0.6)
            axz.set_xlim(cx - 1.5 * half, cx + 1.5 * half)
            axz.set_ylim(cy + half, cy - half)
            axz.set_title(f"board {i + 1}, around ({cx:.0f}, {cy:.0f}) px", fontsize=8)
            axz.tick_params(labelsize=7)
    return fig


def _line_segment(point: np.ndarray, direction: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """The part of a 2D line spanned by the projections of ``pts`` (2, 2)."""
    d = np.asarray(direction, dtype=float)[:2]
    d = d / np.linalg.norm(d)
    t = (pts - point[:2]) @ d
    lo, hi = min(t.min(), 0.0), max(t.max(), 0.0)
    return np.vstack([point[:2] + lo * d, point[:2] + hi * d])


def plot_scan_split(points_xy: np.ndarray, first: np.ndarray, second: np.ndarray,
                    lines: Sequence[tuple[np.ndarray, np.ndarray]] | None = None,
                    E: np.ndarray | None = None, rejected: np.ndarray | None = None,
                    zoom: bool = False,
                    title: str = "Scan split into the two boards (section 1.4)") -> Figure:
    """A scan in the LiDAR frame with its two board segments and fitted lines.

    ``points_xy`` (N, 2 or 3) all valid returns, mm; ``first``/``second``
    boolean masks or index arrays of the two segments; ``rejected`` optional
    mask/indices of points dropped from the segments (mixed pixels, outliers);
    ``lines`` = ((point, direction), (point, direction)) of L1 and L2;
    ``E`` the intersection (eq. 12). Returns a figure with the whole scan on
    the left and a zoom on the V on the right.
    """
    p = np.asarray(points_xy, dtype=float)[:, :2]
    ok = np.all(np.isfinite(p), axis=1)

    def sel(m):
        if m is None:
            return np.zeros(len(p), bool)
        m = np.asarray(m)
        if m.dtype == bool:
            return m & ok
        out = np.zeros(len(p), bool)
        out[m.astype(int)] = True
        return out & ok

    s1, s2, rej = sel(first), sel(second), sel(rejected)
    rest = ok & ~s1 & ~s2 & ~rej
    fig = _figure(9.0, 4.2)
    axes = [fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)]
    for k, ax in enumerate(axes):
        ax.plot(p[rest, 0], p[rest, 1], ".", color="0.6", ms=2, label="other returns")
        if rej.any():
            ax.plot(p[rej, 0], p[rej, 1], "x", color="tab:red", ms=4, label="rejected")
        for i, s in enumerate((s1, s2)):
            ax.plot(p[s, 0], p[s, 1], ".", color=BOARD_COLOURS[i], ms=2.5,
                    label=f"segment {i + 1} ({int(s.sum())} pts)")
        if lines is not None:
            for i, (pt, d) in enumerate(lines):
                seg_pts = p[(s1, s2)[i]] if (s1, s2)[i].any() else p[ok]
                xy = _line_segment(np.asarray(pt, float), np.asarray(d, float), seg_pts)
                ax.plot(xy[:, 0], xy[:, 1], "-", color="k" if i == 0 else "tab:green", lw=1,
                        label=f"L{i + 1} (constrained fit)")
        if E is not None:
            ax.plot(E[0], E[1], "*", color="tab:red", ms=10, label="E")
        if k == 0:
            ax.plot(0, 0, "^", color="k", ms=7)
            ax.annotate("LiDAR", (0, 0), textcoords="offset points", xytext=(4, 4), fontsize=8)
        else:
            v = p[s1 | s2] if (s1 | s2).any() else p[ok]
            if len(v):  # a square window on the V (equal spans: the equal aspect keeps the limits)
                c, half = (v.min(0) + v.max(0)) / 2, 0.6 * np.ptp(v, axis=0).max() + 5
                ax.set_xlim(c[0] - half, c[0] + half)
                ax.set_ylim(c[1] - half, c[1] + half)
        ax.set_aspect("equal", adjustable="box" if k == 1 else "datalim")
        ax.set_xlabel("x_L (mm)")
        ax.set_ylabel("y_L (mm)")
        ax.grid(alpha=0.3)
    axes[0].set_title("whole scan", fontsize=9)
    axes[1].set_title("the V", fontsize=9)
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    return fig


def plot_line_residuals(residuals_mm: Sequence[np.ndarray], labels: Sequence[str] | None = None,
                        title: str = "Fit residuals along each segment") -> Figure:
    """Residuals (mm) of points about their fitted line / plane, one panel row per set."""
    fig = _figure(7.0, 1.6 + 1.2 * len(residuals_mm))
    for i, r in enumerate(residuals_mm):
        ax = fig.add_subplot(len(residuals_mm), 1, i + 1)
        r = np.asarray(r, dtype=float)
        ax.plot(np.arange(len(r)), r, ".", ms=2, color=BOARD_COLOURS[i % 2])
        ax.axhline(0, color="k", lw=0.5)
        lab = labels[i] if labels else f"set {i + 1}"
        rms = float(np.sqrt(np.nanmean(r ** 2))) if len(r) else float("nan")
        ax.set_ylabel("mm")
        ax.set_title(f"{lab}: RMS {rms:.3f} mm", fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig


def _set_equal_3d(ax, pts: np.ndarray) -> None:
    pts = np.asarray(pts, dtype=float).reshape(-1, 3)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    if not len(pts):
        return
    c = (pts.max(0) + pts.min(0)) / 2
    r = max((pts.max(0) - pts.min(0)).max() / 2, 1e-9)
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)


def _camera_view(ax) -> None:
    """Camera frame shown upright: camera y (down) plotted as -vertical."""
    ax.set_xlabel("x_c (mm)")
    ax.set_ylabel("z_c (mm)")
    ax.set_zlabel("-y_c (mm)")
    ax.view_init(elev=20, azim=-60)


def _c2p(X: np.ndarray) -> np.ndarray:
    """Camera coordinates -> plot coordinates (x, z, -y): forward is depth, up is up."""
    X = np.asarray(X, dtype=float).reshape(-1, 3)
    return np.column_stack([X[:, 0], X[:, 2], -X[:, 1]])


def _axes_glyph(ax, origin: np.ndarray, R: np.ndarray, length: float, name: str) -> None:
    o = _c2p(origin)[0]
    for j, (col, lab) in enumerate(zip(("tab:red", "tab:green", "tab:blue"), "xyz")):
        tip = _c2p(np.asarray(origin) + length * np.asarray(R)[:, j])[0]
        ax.plot(*np.column_stack([o, tip]), color=col, lw=2)
        ax.text(*tip, f"{lab}", color=col, fontsize=7)
    ax.text(*o, f" {name}", fontsize=8)


def plot_frames_3d(poses: Sequence, boards_corners_mm: Sequence[np.ndarray] = (),
                   scan_points_cam: np.ndarray | None = None, axis: tuple | None = None,
                   axis_length: float | None = None,
                   title: str = "Camera and LiDAR frames (camera frame, mm)") -> Figure:
    """The camera frame, LiDAR frame(s) and the V-board in 3D.

    ``poses``: one or more objects with ``R`` (3, 3) and ``T`` (3,) (LiDAR in the
    camera frame); ``boards_corners_mm[i]`` (N, 3) board corners in the camera
    frame; ``scan_points_cam`` (N, 3) optional scan points mapped by eq. (28);
    ``axis`` optional (point, direction) of the turntable axis.
    """
    fig = _figure(6.4, 5.6)
    ax = fig.add_subplot(projection="3d")
    if hasattr(poses, "R"):
        poses = [poses]
    allp = [np.zeros((1, 3))]
    for i, c in enumerate(boards_corners_mm):
        c = np.asarray(c, dtype=float).reshape(-1, 3)
        q = _c2p(c)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=1, color=BOARD_COLOURS[i % 2], label=f"board {i + 1}")
        allp.append(c)
    Ts = np.array([np.asarray(p.T, float) for p in poses]) if len(poses) else np.zeros((0, 3))
    allp.append(Ts)
    span = np.ptp(np.vstack(allp), axis=0).max() if len(np.vstack(allp)) > 1 else 1000.0
    L = axis_length or 0.12 * span
    _axes_glyph(ax, np.zeros(3), np.eye(3), L, "camera")
    for k, p in enumerate(poses[:: max(1, len(poses) // 5)] if len(poses) > 5 else poses):
        _axes_glyph(ax, np.asarray(p.T, float), np.asarray(p.R, float), L,
                    "LiDAR" if k == 0 else "")
    if scan_points_cam is not None:
        s = np.asarray(scan_points_cam, float).reshape(-1, 3)
        s = s[np.all(np.isfinite(s), axis=1)]
        q = _c2p(s)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=1, color="tab:red", label="scan (eq. 28)")
    if axis is not None:
        a, d = (np.asarray(v, float) for v in axis)
        c = Ts.mean(0) if len(Ts) else a
        t0 = (c - a) @ d
        seg = _c2p(np.vstack([a + (t0 - L * 2) * d, a + (t0 + L * 2) * d]))
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], "k--", lw=1, label="turntable axis")
    _set_equal_3d(ax, _c2p(np.vstack(allp)))
    _camera_view(ax)
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(title, fontsize=10)
    return fig


def plot_trajectories(psi_deg: np.ndarray, samples: Sequence, fitted: Sequence | None = None,
                      curve: Sequence | None = None, axis: tuple | None = None,
                      tip_length_mm: float = 100.0, truth: Sequence | None = None,
                      title: str = "LiDAR centre and axis tips as the turntable turns (Fig. 4)"
                      ) -> Figure:
    """Fig. 4 of the paper: trajectories of O_L and of the z- and x-axis tips.

    ``samples`` (and optional ``fitted``/``truth``) are sequences of poses
    (``R``, ``T``) at ``psi_deg``; ``curve`` an optional dense sequence of poses
    of the pose function (drawn as lines); tips are ``T + tip_length_mm * axis``.
    Left: 3D with the turntable axis; right: each trajectory seen along the axis.
    """
    psi = np.asarray(psi_deg, dtype=float)

    def tracks(ps):
        T = np.array([np.asarray(p.T, float) for p in ps])
        Rs = np.array([np.asarray(p.R, float) for p in ps])
        return {"centre O_L": T, "z tip": T + tip_length_mm * Rs[:, :, 2],
                "x tip": T + tip_length_mm * Rs[:, :, 0]}

    cols = {"centre O_L": "k", "z tip": "tab:blue", "x tip": "tab:red"}
    fig = _figure(10.0, 4.6)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    S = tracks(samples)
    allp = [v for v in S.values()]
    for name, v in S.items():
        q = _c2p(v)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=3, color=cols[name], label=f"{name} samples")
    C = tracks(curve) if curve is not None and len(curve) else None
    if C is not None:
        for name, v in C.items():
            q = _c2p(v)
            ax.plot(q[:, 0], q[:, 1], q[:, 2], "-", color=cols[name], lw=1)
    if axis is not None:
        a, d = (np.asarray(v, float) for v in axis)
        ts = np.concatenate([(v - a) @ d for v in allp])
        pad = 0.3 * (ts.max() - ts.min()) + 10
        seg = _c2p(np.vstack([a + (ts.min() - pad) * d, a + (ts.max() + pad) * d]))
        ax.plot(seg[:, 0], seg[:, 1], seg[:, 2], "k--", lw=1, label="axis")
        allp.append(np.vstack([a + (ts.min() - pad) * d, a + (ts.max() + pad) * d]))
    _set_equal_3d(ax, _c2p(np.vstack(allp)))
    _camera_view(ax)
    ax.legend(fontsize=6, loc="upper left")

    # along the axis: each track drawn in the plane perpendicular to the axis
    ax2 = fig.add_subplot(1, 2, 2)
    if axis is not None:
        a, d = (np.asarray(v, float) for v in axis)
        d = d / np.linalg.norm(d)
    else:
        a, d = np.zeros(3), np.array([0.0, -1.0, 0.0])
    u = np.cross(d, [1.0, 0, 0] if abs(d[0]) < 0.9 else [0, 1.0, 0])
    u /= np.linalg.norm(u)
    w = np.cross(d, u)

    def flat(v):
        r = v - a
        return np.column_stack([r @ u, r @ w])

    for name, v in S.items():
        q = flat(v)
        ax2.plot(q[:, 0], q[:, 1], ".", ms=3, color=cols[name], label=f"{name}")
        if C is not None:
            qc = flat(C[name])
            ax2.plot(qc[:, 0], qc[:, 1], "-", lw=0.8, color=cols[name])
    if truth is not None and len(truth):
        for name, v in tracks(truth).items():
            q = flat(v)
            ax2.plot(q[:, 0], q[:, 1], "x", ms=3, color=cols[name], alpha=0.5)
    ax2.plot(0, 0, "k+", ms=10)
    ax2.annotate("axis", (0, 0), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel("mm (perpendicular to the axis)")
    ax2.set_ylabel("mm")
    ax2.grid(alpha=0.3)
    note = "dots: samples, lines: pose function" + (", x: truth" if truth is not None else "")
    ax2.set_title(f"seen along the axis ({note})", fontsize=8)
    ax2.legend(fontsize=7, loc="best")
    fig.suptitle(title + f", psi {psi.min():.2f} to {psi.max():.2f} deg", fontsize=10)
    return fig


def _as_columns(errors) -> dict[str, np.ndarray]:
    """A DataFrame or mapping with ``centre_mm``, ``z_axis_deg``, ``x_axis_deg`` -> arrays."""
    return {k: np.asarray(errors[k], dtype=float) for k, _ in ERROR_COLUMNS}


def plot_pose_residuals(psi_deg: np.ndarray, series: Mapping[str, object],
                        title: str = "Per-position pose differences") -> Figure:
    """Per-position residuals (centre mm, z deg, x deg) of several comparisons.

    ``series`` maps a label (e.g. "rigid vs samples") to a DataFrame/mapping
    with columns ``centre_mm``, ``z_axis_deg``, ``x_axis_deg`` aligned with
    ``psi_deg``.
    """
    psi = np.asarray(psi_deg, dtype=float)
    fig = _figure(8.0, 6.0)
    axes = [fig.add_subplot(3, 1, i + 1) for i in range(3)]
    markers = "o^sDvx"
    for k, (label, err) in enumerate(series.items()):
        cols = _as_columns(err)
        for ax, (key, name) in zip(axes, ERROR_COLUMNS):
            ax.plot(psi, cols[key], marker=markers[k % len(markers)], ms=3, lw=0.6, label=label)
            ax.set_ylabel(name, fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[-1].set_xlabel("turntable angle psi (deg)")
    h, lab = axes[0].get_legend_handles_labels()
    leg = fig.legend(h, lab, fontsize=7, ncol=min(3, max(1, len(series))),
                     loc="outside upper center", title=title, frameon=False)
    leg.get_title().set_fontsize(10)
    return fig


def plot_residual_histograms(series: Mapping[str, object],
                             title: str = "Distribution of pose differences") -> Figure:
    """Histograms of the three Table 1 columns for each comparison in ``series``."""
    fig = _figure(9.0, 3.2)
    axes = [fig.add_subplot(1, 3, i + 1) for i in range(3)]
    for label, err in series.items():
        cols = _as_columns(err)
        for ax, (key, name) in zip(axes, ERROR_COLUMNS):
            v = cols[key][np.isfinite(cols[key])]
            if len(v):
                ax.hist(v, bins=max(5, min(30, len(v) // 3)), histtype="step", lw=1.4,
                        label=label)
            ax.set_xlabel(name, fontsize=8)
    axes[0].set_ylabel("positions")
    h, lab = axes[0].get_legend_handles_labels()
    leg = fig.legend(h, lab, fontsize=7, ncol=min(3, max(1, len(series))),
                     loc="outside upper center", title=title, frameon=False)
    leg.get_title().set_fontsize(10)
    return fig


def plot_reprojection_errors(errors_px: Sequence[np.ndarray], labels: Sequence[str] | None = None,
                             title: str = "Intrinsics: reprojection errors") -> Figure:
    """Scatter of per-corner reprojection errors (du, dv) px, one colour per view."""
    fig = _figure(5.2, 4.6)
    ax = fig.add_subplot()
    allv = []
    for i, e in enumerate(errors_px):
        e = np.asarray(e, dtype=float).reshape(-1, 2)
        allv.append(e)
        ax.plot(e[:, 0], e[:, 1], ".", ms=2, label=labels[i] if labels else None)
    if allv:
        v = np.vstack(allv)
        rms = float(np.sqrt(np.mean(np.sum(v ** 2, axis=1))))
        ax.set_title(f"{title}\n{len(errors_px)} views, {len(v)} corners, RMS {rms:.3f} px",
                     fontsize=9)
    ax.axhline(0, color="k", lw=0.5)
    ax.axvline(0, color="k", lw=0.5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("du (px)")
    ax.set_ylabel("dv (px)")
    if labels and len(labels) <= 12:
        ax.legend(fontsize=6, markerscale=4)
    return fig


def plot_disc_cloud(points: np.ndarray, disc: np.ndarray | None = None,
                    rim_rejected: np.ndarray | None = None, circle: object | None = None,
                    reference_diameter_mm: float | None = None,
                    rim_estimates: np.ndarray | None = None,
                    rim_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                    title: str = "Disc point cloud (section 3.2)") -> Figure:
    """A swept cloud (eq. 28) with the disc points, rejected rim points and fitted circle.

    ``points`` (N, 3) camera frame, mm; ``disc`` / ``rim_rejected`` boolean
    masks or index arrays into ``points``, or (M, 3) arrays of their own;
    ``circle`` has ``centre``/``center_mm``, ``normal`` and ``radius`` or
    ``diameter_mm``; ``rim_estimates`` (M, 3) optional rim points the circle
    was fitted to; ``rim_bounds`` optional ((K, 3), (K, 3)): the last hit and
    the first miss bounding the rim, as rays meeting the disc plane. Left: 3D
    (rejected rim returns in red); right: the disc plane, face on.
    """
    P_all = np.asarray(points, dtype=float).reshape(-1, 3)

    def pick(m):
        if m is None:
            return np.zeros((0, 3))
        m = np.asarray(m)
        if m.ndim == 2 and m.shape[1] == 3 and m.dtype != bool:
            out = m.astype(float)
        elif m.dtype == bool:
            m = m.ravel()
            out = P_all[m] if len(m) == len(P_all) else np.zeros((0, 3))
        else:
            out = P_all[m.astype(int).ravel()]
        return out[np.all(np.isfinite(out), axis=1)]

    D, Rj = pick(disc), pick(rim_rejected)
    Ce = pick(rim_estimates)
    P = P_all[np.all(np.isfinite(P_all), axis=1)]
    centre = normal = None
    radius = None
    if circle is not None:
        centre = np.asarray(getattr(circle, "centre", getattr(circle, "center_mm", None)), float)
        normal = np.asarray(circle.normal, float)
        radius = getattr(circle, "radius", None)
        if radius is None and getattr(circle, "diameter_mm", None) is not None:
            radius = circle.diameter_mm / 2
    if centre is None and len(D):
        centre = D.mean(0)
    if normal is None and len(D) >= 3:
        _, _, vt = np.linalg.svd(D - D.mean(0))
        normal = vt[2]
    fig = _figure(10.0, 4.6)
    ax = fig.add_subplot(1, 2, 1, projection="3d")
    if centre is not None and radius is not None:
        near = np.linalg.norm(P - centre, axis=1) < 4 * radius
        Pn = P[near]
    else:
        Pn = P
    step = max(1, len(Pn) // 20000)
    q = _c2p(Pn[::step])
    ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=0.3, color="0.6", label="cloud")
    if len(D):
        q = _c2p(D)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=0.6, color="tab:blue", label="disc")
    Rj3 = Rj
    if len(Rj) and centre is not None and radius is not None:
        Rj3 = Rj[np.linalg.norm(Rj - centre, axis=1) < 3 * radius]  # near the disc only
    if len(Rj3):
        q = _c2p(Rj3)
        ax.scatter(q[:, 0], q[:, 1], q[:, 2], s=2, color="tab:red", label="rejected rim")
    _set_equal_3d(ax, _c2p(np.vstack([D, Rj3]) if len(D) else Pn))
    _camera_view(ax)
    ax.legend(fontsize=7, loc="upper left", markerscale=5)

    ax2 = fig.add_subplot(1, 2, 2)
    if centre is not None and normal is not None:
        n = normal / np.linalg.norm(normal)
        u = np.cross(n, [1.0, 0, 0] if abs(n[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        w = np.cross(n, u)

        def flat(X):
            return np.column_stack([(X - centre) @ u, (X - centre) @ w]) if len(X) else np.zeros((0, 2))

        if radius is not None:
            lim = 1.5 * radius
            nearf = flat(Pn)
            keep = np.all(np.abs(nearf) < lim, axis=1) & (np.abs((Pn - centre) @ n) < radius)
            ax2.plot(nearf[keep, 0], nearf[keep, 1], ".", ms=0.8, color="0.6", label="other returns")
        f = flat(D)
        ax2.plot(f[:, 0], f[:, 1], ".", ms=1, color="tab:blue", label="disc points")
        if rim_bounds is not None:
            for pts_, mk, lab in zip(rim_bounds, ("+", "_"), ("rim: last hit", "rim: first miss")):
                f = flat(np.asarray(pts_, float).reshape(-1, 3))
                if len(f):
                    ax2.plot(f[:, 0], f[:, 1], mk, ms=3, color="tab:red" if mk == "_" else
                             "tab:green", lw=0, label=lab)
        f = flat(Ce)
        if len(f):
            ax2.plot(f[:, 0], f[:, 1], ".", ms=2.5, color="k", label="rim estimates")
        t = np.linspace(0, 2 * np.pi, 361)
        if radius is not None:
            ax2.plot(radius * np.cos(t), radius * np.sin(t), "k-", lw=1.0,
                     label=f"fitted circle, {2 * radius:.2f} mm")
        if reference_diameter_mm:
            r0 = reference_diameter_mm / 2
            ax2.plot(r0 * np.cos(t), r0 * np.sin(t), "g--", lw=0.8,
                     label=f"reference {reference_diameter_mm:.1f} mm")
        if radius is not None:
            lim = 1.3 * radius
            ax2.set_xlim(-lim, lim)
            ax2.set_ylim(-lim, lim)
        ax2.set_aspect("equal")
        ax2.set_xlabel("mm (disc plane)")
        ax2.set_ylabel("mm")
        ax2.grid(alpha=0.3)
        ax2.legend(fontsize=6.5, loc="upper left", bbox_to_anchor=(1.02, 1.0), markerscale=2)
        ax2.set_title("face on", fontsize=9)
    fig.suptitle(title, fontsize=10)
    return fig


def plot_table2(diameters_mm: np.ndarray, reference_mm: np.ndarray | float,
                labels: Sequence[str] | None = None,
                paper_diameters_mm: np.ndarray | None = None, paper_reference_mm: float = 140.0,
                title: str = "Disc diameters (Table 2)") -> Figure:
    """Measured diameters per trial against the reference, with the paper's beside them."""
    d = np.asarray(diameters_mm, dtype=float)
    ref = np.broadcast_to(np.asarray(reference_mm, dtype=float), d.shape)
    fig = _figure(7.0, 3.4)
    ax = fig.add_subplot()
    x = np.arange(1, len(d) + 1)
    ax.plot(x, d - ref, "o", color="tab:blue", label=f"this dataset (mean {np.mean(d - ref):+.2f} mm)")
    if paper_diameters_mm is not None:
        pd_ = np.asarray(paper_diameters_mm, dtype=float)
        ax.plot(np.arange(1, len(pd_) + 1), pd_ - paper_reference_mm, "s", mfc="none",
                color="tab:gray", label=f"paper (mean {np.mean(pd_ - paper_reference_mm):+.2f} mm)")
    ax.axhline(0, color="k", lw=0.6)
    ax.set_xlabel("trial")
    ax.set_ylabel("diameter - reference (mm)")
    if labels is not None and len(labels) == len(d) and len(d) <= 12:
        ax.set_xticks(x, labels, rotation=30, fontsize=7)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(title, fontsize=10)
    return fig


def plot_angle_corrections(true_error_deg: np.ndarray, correction_deg: np.ndarray,
                           title: str = "per-position angle corrections") -> Figure:
    """The joint fit's per-position turntable angle corrections against the true angle errors
    (mean removed: the fit cannot see a common offset), with the line of equality."""
    t = np.asarray(true_error_deg, float)
    fig = _figure(4.5, 4.0)
    ax = fig.add_subplot()
    ax.scatter(t - t.mean(), np.asarray(correction_deg, float), s=14)
    lim = np.abs(t).max() * 1.2
    ax.plot([-lim, lim], [-lim, lim], "k:", lw=1)
    ax.set_xlabel("true angle error (deg, mean removed)")
    ax.set_ylabel("estimated correction (deg)")
    ax.set_title(title)
    return fig
