"""The LiDAR's ranging model: zero offset and dark-surface bias (beyond the paper).

Eq. (6) of the paper takes every range as exact. Real 2D LiDARs carry a
systematic zero offset (datasheets allow +-25-30 mm) and time-of-flight
sensors read weak returns, from dark surfaces, farther than bright ones. On the
V-board the scan crosses black and white squares. The model here:

    rho_measured = rho_true + offset_mm + dark_extra_mm * dark

with ``dark`` = 1 for a return from a black square of the V-board, 0 otherwise.
Both terms are estimated by the joint fit (:mod:`lidarcal.joint`) together with
the rig; which square a return hits is known from the camera: the beam's ray
(its direction from the LiDAR pose, not its biased range) is cut with the
board's plane, the hit goes into the board's own coordinates (the PnP pose of
its chessboard) and the square's colour is read from the bright image
(:func:`black_parity`, the same rule as :func:`lidarcal.board.board_blackness`).

Applying it: ``rho_true = rho_measured - offset_mm`` for any surface; the dark
term belongs to the board's black squares and is not applied to other objects
(their darkness is unknown). A range offset ``delta`` changes a diameter
measured at range ``r`` by about ``D delta / r``, so :mod:`lidarcal.measure` and
:meth:`lidarcal.api.Calibration.points` correct the ranges first.

Prior: ``dataset.json`` ``lidar.range_offset_mm`` and ``lidar.range_offset_sigma_mm``
(e.g. a datasheet's systematic error); without them a wide prior
``0 +- DEFAULT_PRIOR_SIGMA_MM``. The prior enters the fit as one more
observation, so where the data cannot separate the offset from the rig the
prior decides it and its sigma is carried into every rig sigma.

Sigma of the dark extra: beyond the fit's covariance (~0.03 mm on a 22-position
rig) it carries the returns near a square edge (share ``q``, ~0.17-0.19). They are
read with a linear ramp :data:`EDGE_BLEND_MM` wide on each side, but the
footprint's profile across an edge is not in the data: a step (spot -> 0) or a
ramp twice as wide would move the extra by +3.6 % or -8.7 % of itself (least
squares on a checkerboard, ``tests/test_ranging.py``); the term
``0.5 |extra| q / sqrt(3)`` (5.5 %) spans that. Its error is common to every rig of
one scanner, so the rig-to-rig spread of the estimates (0.02-0.03 mm) is far
below it: on six rendered rigs (offset 8 mm, extra 6 mm, 22 positions) the extra
read 5.84-5.92 mm (mean error -0.14 mm, -2.3 %) with sigma 0.26-0.32 mm, i.e. at
-0.25 to -0.57 sigma. Fitting the profile's width to the returns near the edges
would shrink it (not done).

Convention: mm; ``offset_mm`` > 0 means ranges read too far.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .io.dataset import BoardSpec, DatasetError

DEFAULT_PRIOR_SIGMA_MM = 100.0  # wide: larger than any datasheet's systematic error
#: a term is "determined by the data" when its posterior sigma is below this share of its prior's
DATA_SHARE = 0.5
#: a term is applied when the data move it this many sigmas from the prior's mean; else it is
#: held there (the pose as with exact ranges) and its sigma still enters every rig sigma
RANGING_SIGNIFICANCE = 3.0
#: a term the fit puts more than this many *prior* sigmas from the prior's mean contradicts
#: the prior: the scans did not separate it from the LiDAR's position (e.g. 20 mm range noise:
#: a 1.2 m offset, the LiDAR moved with it); it is held at the prior's mean, with a warning
PRIOR_CONFLICT = 5.0
#: returns this close to a square edge (mm) are counted partly dark (footprint, pose error)
EDGE_BLEND_MM = 1.0
MODEL_TEXT = "rho_true = rho_measured - offset_mm - dark_extra_mm * [return from a black board square]"


@dataclass(frozen=True)
class RangingPrior:
    """Prior of the ranging terms (mm); ``source`` says where it came from."""

    offset_mm: float = 0.0
    offset_sigma_mm: float = DEFAULT_PRIOR_SIGMA_MM
    dark_extra_mm: float = 0.0
    dark_extra_sigma_mm: float = DEFAULT_PRIOR_SIGMA_MM
    source: str = "default"  # "dataset.json" or "default"


def ranging_prior(raw: dict, path) -> RangingPrior:
    """:class:`RangingPrior` from a dataset.json's ``lidar`` object (``raw`` the parsed file).

    ``lidar.range_offset_mm`` (default 0) and ``lidar.range_offset_sigma_mm``
    (> 0); giving either one makes the prior the dataset's. Raises
    :class:`DatasetError` on a value that is not a finite number or a sigma <= 0.
    """
    ld = raw.get("lidar", {}) if isinstance(raw, dict) else {}
    ld = ld if isinstance(ld, dict) else {}
    if "range_offset_mm" not in ld and "range_offset_sigma_mm" not in ld:
        return RangingPrior()
    vals = {}
    for key, default in (("range_offset_mm", 0.0), ("range_offset_sigma_mm", DEFAULT_PRIOR_SIGMA_MM)):
        v = ld.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise DatasetError(path, f"'lidar.{key}' must be a finite number (mm), got {v!r}; "
                                     "fix dataset.json")
        vals[key] = float(v)
    if vals["range_offset_sigma_mm"] <= 0:
        raise DatasetError(path, f"'lidar.range_offset_sigma_mm' must be > 0 (mm), got "
                                 f"{vals['range_offset_sigma_mm']:g}; give the datasheet's "
                                 "systematic error, e.g. 30")
    return RangingPrior(vals["range_offset_mm"], vals["range_offset_sigma_mm"], source="dataset.json")


@dataclass(frozen=True)
class RangingModel:
    """Estimated ranging terms with their 1-sigma (mm); ``model`` states the formula."""

    offset_mm: float = 0.0
    offset_sigma_mm: float = 0.0
    dark_extra_mm: float = 0.0
    dark_extra_sigma_mm: float = 0.0
    model: str = MODEL_TEXT
    prior: RangingPrior | None = None
    estimated: tuple[str, ...] = ()  # the terms the joint fit estimated
    determined: tuple[str, ...] = ()  # ... and of those the ones the data determine
    held: tuple[str, ...] = ()  # not significant: held at the prior's mean (sigma still counted)

    def correct(self, range_mm: np.ndarray, dark: np.ndarray | None = None) -> np.ndarray:
        """True ranges from measured ones: ``rho - offset - dark_extra * dark``.

        Non-positive and NaN ranges (no return) are left as they are. ``dark``
        (0..1 per range) only for returns from the V-board's squares.
        """
        r = np.asarray(range_mm, dtype=float)
        delta = self.offset_mm + (0.0 if dark is None else self.dark_extra_mm * np.asarray(dark, float))
        return np.where(r > 0, r - delta, r)

    def to_dict(self) -> dict:
        """calibration.json ``ranging`` block."""
        out = {"offset_mm": float(self.offset_mm), "offset_sigma_mm": float(self.offset_sigma_mm),
               "dark_extra_mm": float(self.dark_extra_mm),
               "dark_extra_sigma_mm": float(self.dark_extra_sigma_mm), "model": self.model,
               "estimated": list(self.estimated), "determined_by_data": list(self.determined),
               "held_at_prior": list(self.held)}
        if self.prior is not None:
            out["prior"] = {"offset_mm": self.prior.offset_mm,
                            "offset_sigma_mm": self.prior.offset_sigma_mm,
                            "source": self.prior.source}
        return out

    @staticmethod
    def from_dict(d: dict | None) -> RangingModel:
        """From a calibration.json ``ranging`` block (None or absent: no correction)."""
        if not d:
            return RangingModel()
        return RangingModel(float(d.get("offset_mm", 0.0)), float(d.get("offset_sigma_mm", 0.0)),
                            float(d.get("dark_extra_mm", 0.0)),
                            float(d.get("dark_extra_sigma_mm", 0.0)), str(d.get("model", MODEL_TEXT)),
                            estimated=tuple(d.get("estimated", ())),
                            determined=tuple(d.get("determined_by_data", ())),
                            held=tuple(d.get("held_at_prior", ())))


def ranging_of(model) -> RangingModel:
    """The ranging model carried by a calibration or pose function (none: zero terms)."""
    rm = getattr(model, "ranging", None)
    if isinstance(rm, RangingModel):
        return rm
    return RangingModel.from_dict(rm if isinstance(rm, dict) else None)


def black_parity(view, camera, board: BoardSpec) -> int | None:
    """Which squares of a chessboard are black: 0 or 1 = the parity of ``i + j``.

    Square ``(i, j)`` spans ``[i, i+1] x [j, j+1]`` squares in the board frame of
    the PnP pose (origin at the first inner corner, OpenCV's order; ``i, j`` from
    -1). Read from the bright image's normalised ``view.blackness``
    (:func:`lidarcal.board.board_blackness`) at the projected square centres; None
    when the view carries no blackness map or the two parities do not differ.
    """
    from .camera import project_points

    if getattr(view, "blackness", None) is None:
        return None
    cols, rows = board.inner_corners
    sq = board.square_mm
    ii, jj = np.meshgrid(np.arange(-1, cols), np.arange(-1, rows))
    uv = np.column_stack([(ii.ravel() + 0.5) * sq, (jj.ravel() + 0.5) * sq, np.zeros(ii.size)])
    c = project_points(camera, uv @ np.asarray(view.R_pnp).T + np.asarray(view.T_pnp))
    x0, y0 = view.blackness_origin
    h, w = view.blackness.shape
    px = np.round(c - [x0, y0]).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    if inside.sum() < 4:
        return None
    val = view.blackness[px[inside, 1], px[inside, 0]]
    par = ((ii + jj).ravel() % 2)[inside]
    if (par == 0).sum() == 0 or (par == 1).sum() == 0:
        return None
    m0, m1 = float(np.median(val[par == 0])), float(np.median(val[par == 1]))
    if abs(m0 - m1) < 0.3:
        return None
    return 0 if m0 > m1 else 1


def dark_returns(origins: np.ndarray, directions: np.ndarray, board_R: np.ndarray,
                 board_T: np.ndarray, board: BoardSpec, parity: int,
                 blend_mm: float = EDGE_BLEND_MM) -> np.ndarray:
    """How much of each beam's return comes from a black square of one chessboard, 0..1.

    ``origins``, ``directions`` (M, 3): the beams in the camera frame (LiDAR
    centre and ``R [cos theta, sin theta, 0]``); the hit is the ray's cut with the
    board plane (eq. 3), so a biased range does not move it. ``board_R``,
    ``board_T``: the chessboard's pose (board frame -> camera, eq. 1; OpenCV's
    object points). ``parity`` from :func:`black_parity`. Within ``blend_mm`` of a
    square edge the share ramps linearly through 1/2 (the beam's footprint and the
    pose's error straddle the edge); away from edges it is 0 or 1; 0 off the pattern.
    """
    n = board_R[:, 2]
    d = float(n @ board_T)
    den = directions @ n
    t = (d - origins @ n) / np.where(np.abs(den) > 1e-12, den, np.nan)
    hit = origins + t[:, None] * directions
    b = (hit - board_T) @ board_R  # board coordinates (columns x, y, z)
    return np.where(np.isfinite(t), dark_share(b[:, 0], b[:, 1], board, parity, blend_mm), 0.0)


def dark_share(bx: np.ndarray, by: np.ndarray, board: BoardSpec, parity: int,
               blend_mm: float = EDGE_BLEND_MM) -> np.ndarray:
    """:func:`dark_returns` at hits given in board coordinates ``bx``, ``by`` (mm, the board
    frame of the PnP pose): the share of black square under each, ramped within
    ``blend_mm`` of a square edge, 0 off the pattern."""
    cols, rows = board.inner_corners
    sq = board.square_mm
    h = max(float(blend_mm), 1e-9)

    def wave(c: np.ndarray) -> np.ndarray:
        """+-1 by the parity of the square index, ramping to 0 at the edges."""
        q = c / sq
        i = np.floor(q)
        dist = np.minimum(q - i, i + 1 - q) * sq  # to the nearest edge, mm
        return np.where(i % 2 == 0, 1.0, -1.0) * np.clip(dist / h, 0.0, 1.0)

    checker = wave(bx) * wave(by)  # +1 on squares with i + j even
    share = 0.5 * (1 + checker) if parity == 0 else 0.5 * (1 - checker)
    # the pattern spans squares -1..cols-1 (x) and -1..rows-1 (y); white margin beyond
    inside_x = np.minimum(bx + sq, cols * sq - bx)
    inside_y = np.minimum(by + sq, rows * sq - by)
    inside = np.clip(np.minimum(inside_x, inside_y) / (2 * h) + 0.5, 0.0, 1.0)
    return share * inside


def ranging_text(ranging: dict | RangingModel | None, fmt: str = "text") -> str:
    """The ranging terms and their 1-sigma as a typst table (``fmt="typst"``) or plain text.

    ``ranging``: a :class:`RangingModel` or calibration.json's ``ranging`` block
    (None: the calibration has none, said so).
    """
    if fmt not in ("text", "typst"):
        raise ValueError(f"fmt must be 'text' or 'typst', got {fmt!r}")
    rm = ranging if isinstance(ranging, RangingModel) else RangingModel.from_dict(ranging)
    if ranging is None:
        return ("no ranging model (ranges taken as exact)" if fmt == "text"
                else "_No ranging model: ranges taken as exact._\n")
    rows = []
    for name, key, v, s in (("zero offset", "offset", rm.offset_mm, rm.offset_sigma_mm),
                            ("dark-square extra", "dark_extra", rm.dark_extra_mm, rm.dark_extra_sigma_mm)):
        if key not in rm.estimated:
            how = "not estimated"
        elif key in rm.held:
            how = "held at the prior's mean (not significant; its sigma counted)"
        elif key in rm.determined:
            how = "from the data"
        else:
            how = "prior decides (data do not separate it)"
        rows.append((name, f"{v:+.2f}", f"{s:.2f}", how))
    if fmt == "text":
        lines = [f"{n}: {v} mm +- {s} mm (1-sigma; {h})" for n, v, s, h in rows]
        return "\n".join(lines + [f"model: {rm.model}"])
    cells = ", ".join(f"[{n}], [{v}], [{s}], [{h}]" for n, v, s, h in rows)
    return ("#table(columns: 4, align: (left, right, right, left),\n"
            "  [*ranging term*], [*mm*], [*1-sigma mm*], [*source*],\n"
            f"  {cells})\n\n`{rm.model}`\n")
