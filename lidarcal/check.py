"""``lidarcal check DATASET``: is this capture usable? The detections, without the fits.

Reads everything the pipeline reads and runs, per position, the detections of
section 1 that a capture can fail on, with the pipeline's own functions: the
two chessboards in ``board.png`` (section 1.2, :func:`lidarcal.pipeline.find_boards`),
the laser-stripe centres on each board (section 1.3,
:func:`lidarcal.stripe.board_stripe_centres`) and the V in the scan (section 1.4,
:func:`lidarcal.scan.split_v`). No pose, turntable or joint fit is run.

Per position it reports the stripe centres found on each board, whether the
scan's V was found (points per side, opening angle), and the share of the
stripe's core pixels that are saturated (a clipped core biases the sub-pixel
centre). A one-page contact sheet shows every stripe image with its detections.

Exit status (the CLI): 0 usable, 1 problems (listed, one line each, naming the
file and what to do), 2 unreadable (``dataset.json``, ``positions.csv`` or
``board.png`` cannot be read; one ``error:`` line).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .io.dataset import (
    Dataset,
    DatasetError,
    Position,
    load_dataset,
    read_image,
    read_scan,
    read_stripe_image,
    write_atomic,
)

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure

    from .io.dataset import CameraModel

#: Share of the stripe's core pixels at full scale above which a position is a problem: the
#: centre of a clipped profile is biased towards the flat top's middle (lower the exposure).
MAX_SATURATED_SHARE = 0.05
#: Largest thumbnail kept per position for the contact sheet (pixels, width).
THUMB_WIDTH_PX = 320
#: Stripe centres drawn per board on a thumbnail (a subsample; the count is in the table).
DRAWN_CENTRES = 150


@dataclass
class PositionCheck:
    """The detections at one turntable position and what is wrong with them."""

    index: int
    psi_deg: float
    stripe_image: Path
    scan: Path
    centres_px: tuple[np.ndarray, np.ndarray] | None = None  # per board, raw pixels (N, 2)
    saturated_share: float | None = None  # of the stripe's core pixels, 0..1
    alpha_deg: float | None = None  # angle between the two stripe lines (section 1.3)
    v_points: tuple[int, int] | None = None  # scan returns on each side of the V
    v_opening_deg: float | None = None
    problems: list[str] = field(default_factory=list)
    # problems that cost accuracy but leave the position usable by calibrate (a saturated core)
    quality: list[str] = field(default_factory=list)
    thumbnail: np.ndarray | None = field(default=None, repr=False)
    thumb_scale: float = 1.0

    @property
    def ok(self) -> bool:
        return not self.problems and not self.quality

    @property
    def detected(self) -> bool:
        """Every detection succeeded: ``calibrate`` uses this position."""
        return not self.problems

    @property
    def n_centres(self) -> tuple[int, int] | None:
        return None if self.centres_px is None else tuple(len(c) for c in self.centres_px)


@dataclass
class CheckResult:
    """Everything :func:`check_dataset` found: dataset-level problems and notes, per position."""

    dataset: Dataset
    camera_source: str | None = None
    boards: tuple | None = None
    board_rms_px: tuple[float, float] | None = None
    positions: list[PositionCheck] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)  # dataset level
    notes: list[str] = field(default_factory=list)  # worth knowing, not blocking
    board_thumbnail: np.ndarray | None = field(default=None, repr=False)
    board_thumb_scale: float = 1.0

    @property
    def all_problems(self) -> list[str]:
        return self.problems + [p for pos in self.positions for p in pos.problems + pos.quality]

    @property
    def usable(self) -> bool:
        return not self.all_problems

    def table(self) -> pd.DataFrame:
        """One row per position: angle, centres per board, saturation, the V, problems."""
        import pandas as pd

        rows = []
        for p in self.positions:
            n = p.n_centres
            rows.append({
                "index": p.index, "psi_deg": p.psi_deg,
                "centres_board0": None if n is None else n[0],
                "centres_board1": None if n is None else n[1],
                "saturated_pct": None if p.saturated_share is None else 100 * p.saturated_share,
                "alpha_deg": p.alpha_deg,
                "scan_V": "yes" if p.v_points is not None else "NO",
                "V_points": "" if p.v_points is None else f"{p.v_points[0]}+{p.v_points[1]}",
                "V_opening_deg": p.v_opening_deg,
                "ok": "ok" if p.ok else "PROBLEM"})
        return pd.DataFrame(rows).set_index("index")


def saturated_share(image: np.ndarray, centres_px: np.ndarray) -> float:
    """Share of the stripe's core pixels at the image's full scale (255 for 8 bits).

    The core is the pixel under the stripe in every column its centres span and its
    neighbours above and below (stripes are traced column by column,
    :func:`lidarcal.stripe.stripe_centres`); columns without a centre (a clipped profile
    dropped where it crosses a square edge, :mod:`lidarcal.stripe_clipped`) are read at the
    stripe interpolated from its neighbours, so dropping clipped profiles does not hide the
    clipping. ``centres_px``: one stripe's centres, or a list of stripes (one per board).
    """
    if isinstance(centres_px, (list, tuple)):
        parts = [np.asarray(c, dtype=float).reshape(-1, 2) for c in centres_px]
        parts = [_every_column(c) for c in parts if len(c)]
        c = np.vstack(parts) if parts else np.zeros((0, 2))
    else:
        c = _every_column(np.asarray(centres_px, dtype=float).reshape(-1, 2))
    if len(c) == 0:
        return 0.0
    h, w = image.shape[:2]
    x = np.clip(np.round(c[:, 0]).astype(int), 0, w - 1)
    y = np.round(c[:, 1]).astype(int)
    ys = np.clip(np.stack([y - 1, y, y + 1]), 0, h - 1)
    full = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    return float(np.mean(image[ys, np.broadcast_to(x, ys.shape)] >= full))


def _every_column(c: np.ndarray) -> np.ndarray:
    """One stripe's centres at every integer column they span (the row interpolated between
    the neighbouring centres where a column has none); one per column where it has."""
    if len(c) < 2:
        return c
    c = c[np.argsort(c[:, 0])]
    cols = np.arange(np.round(c[0, 0]), np.round(c[-1, 0]) + 1)
    return np.column_stack([cols, np.interp(cols, c[:, 0], c[:, 1])]) if len(cols) else c


def _thumbnail(image: np.ndarray, width: int = THUMB_WIDTH_PX) -> tuple[np.ndarray, float]:
    """A small 8-bit copy, contrast-stretched so faint boards show (gamma 0.5); and its scale."""
    import cv2

    scale = min(1.0, width / image.shape[1])
    small = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) \
        if scale < 1 else image.copy()
    top = max(float(np.percentile(small, 99.9)), 1.0)
    stretched = np.sqrt(np.clip(small.astype(np.float32) / top, 0, 1))
    return (255 * stretched).astype(np.uint8), scale


def _check_position(pos: Position, camera: CameraModel | None, boards, lidar, rho) -> PositionCheck:
    """Section 1's detections at one position (no fit of a pose): stripes, then the scan's V."""
    from .board import inner_diagonal_mm
    from .scan import split_v, v_segment_limit_mm
    from .stripe import board_stripe_centres, camera_lines_from_centres

    out = PositionCheck(pos.index, pos.psi_deg, pos.stripe_image, pos.scan)
    drop = f"; check this position or drop it with --skip {pos.index}"
    alpha = None
    try:
        img = read_stripe_image(pos.stripe_image, None if camera is None else camera.image_size,
                                lidar.laser_colour)
    except DatasetError as e:
        out.problems.append(str(e))
        img = None
    if img is not None:
        out.thumbnail, out.thumb_scale = _thumbnail(img)
    if img is not None and boards is not None:
        centres, _, stripe_problems = board_stripe_centres(camera, img, boards, rho=rho)
        out.centres_px = (centres[0], centres[1])
        out.saturated_share = saturated_share(img, list(centres))
        few = [(k, p) for k, p in enumerate(stripe_problems) if p]
        for k, problem in few:
            out.problems.append(f"{pos.stripe_image}: board {k}: {problem}; is the stripe on both "
                                f"boards, bright enough, and lidar.laser_colour right?{drop}")
        if out.saturated_share > MAX_SATURATED_SHARE:
            out.quality.append(f"{pos.stripe_image}: {100 * out.saturated_share:.0f} % of the "
                                "stripe's core pixels are saturated; lower the exposure or the "
                                "gain so the stripe's peak stays below full scale")
        if not few:
            try:
                cl = camera_lines_from_centres(camera, centres, [b.plane_pnp for b in boards])
                alpha, out.alpha_deg = cl.alpha, cl.alpha_deg
            except (ValueError, np.linalg.LinAlgError) as e:
                out.problems.append(f"{pos.stripe_image}: no laser plane from the stripes ({e})"
                                    f"{drop}")
    try:
        ang, rng = read_scan(pos.scan, lidar)
    except DatasetError as e:
        out.problems.append(str(e))
        return out
    try:
        limit = None if boards is None else v_segment_limit_mm(
            [inner_diagonal_mm(camera, b) for b in boards])
        seg = split_v(ang, rng, alpha=alpha, max_segment_mm=limit)
        out.v_points = (len(seg.index1), len(seg.index2))
        out.v_opening_deg = float(seg.opening_deg)
    except ValueError as e:
        out.problems.append(f"{pos.scan}: {e}{drop}")
    return out


def check_dataset(dataset: str | os.PathLike | Dataset, progress: bool = False) -> CheckResult:
    """Read a dataset and run the per-position detections, without the fits.

    Raises :class:`DatasetError` only when the dataset cannot be read at all
    (``dataset.json``, ``positions.csv``, ``board.png``); everything else is listed in the result.
    """
    from .calibration_checks import setup_warnings
    from .pipeline import (
        MIN_POSITIONS,
        _unwrapped,
        blur_warning,
        camera_for,
        find_boards,
        matched_albedo,
        small_square_warnings,
    )
    from .workbook import summarise_dataset

    ds = dataset if isinstance(dataset, Dataset) else load_dataset(dataset)
    res = CheckResult(ds)
    camera = boards = None
    try:
        camera, intr = camera_for(ds)
        res.camera_source = camera.source if intr is None else \
            f"intrinsics/ ({len(intr.files_used)} views, RMS {camera.rms_px:.3f} px)"
    except DatasetError as e:
        res.problems.append(str(e))
    if camera is not None:
        # an unreadable board.png is fatal, as a missing one is (and as in calibrate)
        board_image = read_image(ds.board_image, camera.image_size)
        try:
            res.board_thumbnail, res.board_thumb_scale = _thumbnail(board_image)
            boards = find_boards(ds, camera, board_image)
            res.board_rms_px = tuple(float(b.reprojection_rms_px[0]) for b in boards)
        except DatasetError as e:
            res.problems.append(str(e))
    res.boards = boards
    rho, blur = None, 0.0
    if boards is not None:  # as calibrate reads them
        boards, rho, blur = matched_albedo(camera, boards, ds.positions, ds.lidar.laser_colour)
        res.boards = boards
    if blur:
        res.notes.append(blur_warning(ds, blur))
    todo = ds.positions
    if progress:
        from tqdm import tqdm

        todo = tqdm(todo, desc="positions", unit="pos", leave=False)
    res.positions = [_check_position(p, camera, boards, ds.lidar, rho) for p in todo]

    s = summarise_dataset(ds)
    # the angles as calibrate reads them: one sweep where a controller wraps at 360 deg
    swept, wrap_notes = _unwrapped(ds, list(ds.positions))
    res.notes += wrap_notes
    psi_of = {p.index: p.psi_deg for p in swept}
    psi = np.sort(list(psi_of.values()))
    steps = np.diff(psi)
    if len(steps) and steps.max() > 1.5 * steps.min():
        res.notes.append(f"the angle steps vary from {steps.min():g} to {steps.max():g} deg "
                         f"(median {s.psi_step_deg:g})")
    good = [p for p in res.positions if p.detected]
    res.notes += setup_warnings(np.array([psi_of[p.index] for p in good]) if good else psi, good)
    if boards is not None:
        res.notes += small_square_warnings(boards, ds.v_board, ds.board_image)
    if boards is not None and len(good) < MIN_POSITIONS:
        res.problems.append(f"{ds.root / 'positions.csv'}: only {len(good)} usable position(s), "
                            f"the turntable fit needs at least {MIN_POSITIONS}; capture more "
                            "positions")
    return res


# ------------------------------------------------------------------ the contact sheet


def _grid(n: int, aspect: float, width: float, height: float) -> tuple[int, int]:
    """Columns and rows of ``n`` tiles of ``aspect`` (w/h) that make the tiles largest."""
    best = (1, n, 0.0)
    for cols in range(1, n + 1):
        rows = -(-n // cols)
        size = min(width / cols / aspect, height / rows)
        if size > best[2]:
            best = (cols, rows, size)
    return best[0], best[1]


def contact_sheet(res: CheckResult) -> Figure:
    """One A4 landscape page: ``board.png`` with the boards found, then every stripe image with
    its stripe centres (one colour per board), titled index, psi and the scan's V; positions
    with a problem are framed in red."""
    from matplotlib.figure import Figure

    from .plots import BOARD_COLOURS
    from .workbook import summarise_dataset

    tiles: list[tuple[str, np.ndarray | None, float, list, bool]] = []
    if res.board_thumbnail is not None:
        outl = [] if res.boards is None else [b.outline_px for b in res.boards]
        tiles.append(("board.png" + ("" if res.boards else ": boards NOT found"),
                      res.board_thumbnail, res.board_thumb_scale,
                      [("outline", o) for o in outl], res.boards is not None))
    for p in res.positions:
        marks = [] if res.boards is None else [("outline", b.outline_px) for b in res.boards]
        if p.centres_px is not None:
            marks += [("centres", c) for c in p.centres_px]
        v = "no V" if p.v_points is None else f"V {p.v_points[0]}+{p.v_points[1]}"
        tiles.append((f"{p.index}: {p.psi_deg:g} deg, {v}", p.thumbnail, p.thumb_scale, marks,
                      p.ok))
    w_in, h_in = 11.69, 8.27
    head_in = 0.55
    w, h = res.dataset.image_size
    cols, rows = _grid(max(len(tiles), 1), w / h * 1.12, w_in, h_in - head_in)
    fig = Figure(figsize=(w_in, h_in))
    s = summarise_dataset(res.dataset)
    n_bad = sum(not p.ok for p in res.positions)
    fig.suptitle(f"lidarcal check: {s.line()}; camera from {res.camera_source or '?'}; "
                 f"{len(res.positions) - n_bad} of {len(res.positions)} positions ok"
                 + ("" if res.usable else f"; {len(res.all_problems)} problem(s)"),
                 fontsize=9, y=1 - 0.15 / h_in)
    top = 1 - head_in / h_in
    gs = fig.add_gridspec(rows, cols, left=0.01, right=0.99, bottom=0.01, top=top,
                          wspace=0.04, hspace=0.22)
    for k, (title, img, scale, marks, ok) in enumerate(tiles):
        ax = fig.add_subplot(gs[k // cols, k % cols])
        ax.set_xticks([])
        ax.set_yticks([])
        if img is not None:
            ax.imshow(img, cmap="gray", vmin=0, vmax=255, interpolation="nearest")
        else:
            ax.set_facecolor("0.85")
            ax.text(0.5, 0.5, "unreadable", ha="center", va="center", transform=ax.transAxes,
                    color="tab:red", fontsize=7)
        board = 0
        for kind, pts in marks:
            pts = np.asarray(pts, float) * scale
            if kind == "outline" and len(pts):
                ax.plot(*np.vstack([pts, pts[:1]]).T, lw=0.5, color="tab:green", alpha=0.8)
            elif kind == "centres":
                step = max(1, len(pts) // DRAWN_CENTRES)
                ax.plot(pts[::step, 0], pts[::step, 1], ".", ms=0.8,
                        color=BOARD_COLOURS[board % 2])
                board += 1
        if img is not None:
            ax.set_xlim(0, img.shape[1])
            ax.set_ylim(img.shape[0], 0)
        ax.set_title(title, fontsize=5.5, pad=1.5, color="black" if ok else "tab:red")
        for sp in ax.spines.values():
            sp.set_color("black" if ok else "tab:red")
            sp.set_linewidth(0.5 if ok else 1.5)
    return fig


def write_sheet(res: CheckResult, path: str | os.PathLike) -> Path:
    """The contact sheet as PNG or PDF (by the extension), written atomically."""
    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in ("png", "pdf"):
        raise DatasetError(path, "the contact sheet must be a .png or .pdf file; give "
                                 "--sheet NAME.png or NAME.pdf (or --no-sheet)")
    return write_atomic(path, lambda tmp: contact_sheet(res).savefig(tmp, format=fmt, dpi=200),
                        ".tmp")


# ------------------------------------------------------------------ the command


def format_report(res: CheckResult) -> str:
    """The text ``lidarcal check`` prints: the dataset, the table, notes, problems, verdict."""
    from .workbook import summarise_dataset

    s = summarise_dataset(res.dataset)
    lines = [f"dataset {res.dataset.root}",
             (f"positions {s.n_positions}; psi {s.psi_min_deg:g} to {s.psi_max_deg:g} deg "
             f"(span {s.psi_max_deg - s.psi_min_deg:g} deg, step {s.psi_step_deg:g} deg median)"),
             f"camera from {res.camera_source or 'NOT available'}",
             "boards " + ("NOT found" if res.board_rms_px is None else
                          "found, reprojection RMS " + ", ".join(f"{v:.3f}" for v in res.board_rms_px)
                          + " px"), ""]
    if res.positions:
        table = res.table()
        lines.append(table.to_string(float_format=lambda v: f"{v:.2f}", na_rep="-"))
        lines.append("")
    lines += [f"note: {n}" for n in res.notes]
    probs = res.all_problems
    if probs:
        lines.append(f"{len(probs)} problem(s):")
        lines += [f"problem: {p}" for p in probs]
        lines.append("NOT usable as it is: fix the files above or drop positions with "
                     "'lidarcal calibrate --skip N ...'")
    else:
        lines.append(f"usable: every detection succeeded at all {len(res.positions)} positions")
    return "\n".join(lines)


def run_check(dataset: str | os.PathLike, sheet: str | os.PathLike | None = "default",
              progress: bool = False) -> int:
    """``lidarcal check``: print the report, write the contact sheet; 0 usable, 1 problems.

    ``sheet="default"`` writes ``<dataset name>-check.png`` in the current folder; None none.
    An unreadable dataset raises :class:`DatasetError` (the CLI's exit status 2).
    """
    res = check_dataset(dataset, progress=progress)
    print(format_report(res))
    if sheet is not None:
        target = Path(f"{res.dataset.root.name}-check.png") if sheet == "default" else Path(sheet)
        print(f"wrote {write_sheet(res, target)}")
    return 0 if res.usable else 1
