"""The physical board's margins beyond its printed pattern, measured in the photos.

Every view photographs the same board, so each side of the pattern (left, right, top, bottom in
the board frame of eq. 1: ``u`` along the inner corners' rows, ``v`` along their columns) has one
margin in mm shared by all views. Per view the photo is resampled on the board plane (the board
pose of :func:`lidarcal.planes.board_plane` projected through the lens model, ``cv2.remap``);
beyond each side of the printed pattern the gradient across that side is taken and its median
along the side (a straight edge parallel to the side spans the whole strip; a fiducial ring or a
hand beside the board does not) gives a profile whose strongest peak is the board's edge. The
views are combined robustly: the margin is their median, its uncertainty the median absolute
deviation scaled to a sigma (at least the resampling step); a side is accepted only when most
views agree within :data:`AGREE_MM` and the edge stands clear of the profile's noise
(:data:`MIN_CONTRAST`); else it is unknown (``None``) and callers keep the assumed margin of
:func:`lidarcal.planes_wall.pattern_extent`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .geometry import MAD_TO_SIGMA
from .io.dataset import BoardSpec, CameraModel
from .planes_wall import pattern_extent

if TYPE_CHECKING:
    from .planes import ViewData

#: Board-plane resampling step (mm per pixel of the warped strips).
STEP_MM = 1.0
#: Views agree on a side when within this of their median (mm).
AGREE_MM = 5.0
#: An edge is clear when its gradient peak is this many robust sigmas of the profile's noise.
MIN_CONTRAST = 10.0
#: Margins are sought from this far beyond the pattern (mm; clear of the outer squares' own edge
#: blurred by the resampling) out to half the pattern's shorter side (the assumed margin).
SKIP_MM = 12.0
SIDES = ("left", "right", "top", "bottom")


@dataclass(frozen=True)
class SideEdge:
    """One view's edge beyond one side: the margin (mm from the pattern) and its contrast (peak
    over the robust sigma of the gradient profile)."""

    margin_mm: float
    contrast: float


@dataclass(frozen=True)
class BoardMargins:
    """Per side: the margin shared by the views (mm, None if not accepted), its 1-sigma spread,
    and each view's edges (for the report)."""

    margin_mm: dict[str, float | None]
    sigma_mm: dict[str, float | None]
    per_view: list[dict[str, SideEdge]]
    #: the same pooled per axis of the board frame (``u``: left and right, ``v``: top and
    #: bottom), which is what the scan's gating uses: a pattern found turned by 180 degrees
    #: exchanges left and right, so a side's name is not the same physical side in every view
    axis_margin_mm: dict[str, float | None] = None  # type: ignore[assignment]
    axis_sigma_mm: dict[str, float | None] = None  # type: ignore[assignment]
    #: the pattern's inner corners as found in the first view (``u`` along the first number)
    ref_corners: tuple[int, int] | None = None

    def grow_mm(self, assumed_mm: float, transposed: bool = False) -> np.ndarray | None:
        """Per board axis ``(u, v)`` the extent beyond the pattern in which the board's edge lies
        (the pooled margin plus three sigmas; ``assumed_mm`` on an axis not measured); None if
        neither axis is measured. ``transposed``: for a view whose pattern was found the other
        way round (its ``u`` is this one's ``v``)."""
        m, s = self.axis_margin_mm or {}, self.axis_sigma_mm or {}
        if all(m.get(a) is None for a in "uv"):
            return None
        g = np.array([assumed_mm if m.get(a) is None else m[a] + 3.0 * s[a] for a in "uv"])
        return g[::-1].copy() if transposed else g

    def grown(self, side: str, assumed_mm: float) -> float:
        """The extent beyond ``side`` in which the board's edge lies: the measured margin plus
        three sigmas where accepted, else ``assumed_mm``."""
        m = self.margin_mm.get(side)
        return assumed_mm if m is None else m + 3.0 * float(self.sigma_mm[side])

    def record(self, pattern: tuple[int, int], assumed_mm: float, photos: int) -> dict:
        """The ``board_margins`` block of ``extrinsics.json`` (docs/dataset-format.md): per axis
        of the pattern as given (``u`` along its first number of inner corners) the margin and
        its sigma (mm, null where not measured), how many views' edges agree on it, the extent
        beyond the pattern the scan's cut takes (mm), and ``fallback`` naming the axes that keep
        the ``assumed_mm`` margin (null when both are measured)."""
        swap = self.ref_corners is not None and tuple(self.ref_corners) != tuple(pattern)
        ax = {"u": "v", "v": "u"} if swap else {"u": "u", "v": "v"}
        sides = {"u": ("left", "right"), "v": ("top", "bottom")}
        m, s = self.axis_margin_mm or {}, self.axis_sigma_mm or {}
        out: dict = {"photos": int(photos), "assumed_mm": float(assumed_mm)}
        for a in "uv":
            b = ax[a]
            mb = m.get(b)
            seen = [e[x].margin_mm for e in self.per_view for x in sides[b]
                    if x in e and e[x].contrast >= MIN_CONTRAST]
            out[f"{a}_mm"] = mb
            out[f"sigma_{a}_mm"] = s.get(b)
            out[f"views_{a}"] = 0 if mb is None else int(np.sum(np.abs(np.array(seen) - mb)
                                                                <= AGREE_MM))
            out[f"grown_{a}_mm"] = float(assumed_mm if mb is None else round(mb + 3.0 * s[b], 2))
        missing = [a for a in "uv" if out[f"{a}_mm"] is None]
        out["fallback"] = None if not missing else (
            f"margin along {' and '.join(missing)} not measured (fewer than three views' photos "
            f"agree on the board's edge): the assumed {assumed_mm:g} mm (half the pattern's "
            "shorter side) is used")
        return out

    def to_dict(self) -> dict:
        return {"margin_mm": self.margin_mm, "sigma_mm": self.sigma_mm,
                "axis_margin_mm": self.axis_margin_mm, "axis_sigma_mm": self.axis_sigma_mm,
                "per_view": [{s: [round(e.margin_mm, 1), round(e.contrast, 1)]
                              for s, e in d.items()} for d in self.per_view]}


def _pattern_box(board: BoardSpec) -> tuple[np.ndarray, np.ndarray]:
    c, r = board.inner_corners
    sq = board.square_mm
    return np.array([-sq, -sq]), np.array([c * sq, r * sq])


def board_strip(image: np.ndarray, camera: CameraModel, R: np.ndarray, T: np.ndarray,
                u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The photo resampled on the board plane at the board-frame grid ``u`` x ``v`` (mm): each
    board point ``R @ (u, v, 0) + T`` (eq. 1) projected through the lens (``cv2.projectPoints``)
    and read by ``cv2.remap`` (bilinear); NaN outside the photo. Rows follow ``v``."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    U, V = np.meshgrid(u, v)
    obj = np.column_stack([U.ravel(), V.ravel(), np.zeros(U.size)])
    px = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], np.asarray(T, float).reshape(3, 1),
                           np.asarray(camera.K, float), np.asarray(camera.dist, float))[0]
    mx, my = (px.reshape(-1, 2).T.reshape(2, *U.shape)).astype(np.float32)
    out = cv2.remap(gray.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
    h, w = gray.shape[:2]
    out[(mx < 0) | (my < 0) | (mx > w - 1) | (my > h - 1)] = np.nan
    return out


def side_edges(image: np.ndarray, camera: CameraModel, R: np.ndarray, T: np.ndarray,
               board: BoardSpec) -> dict[str, SideEdge]:
    """One view's board edge beyond each side of the printed pattern (module docstring): the
    distance from the pattern where the median along the side of the gradient across it has its
    nearest clear peak (the board's own edge; beyond it lie the stand and the room).
    Sides whose strip leaves the photo are omitted."""
    lo, hi = _pattern_box(board)
    reach = 0.5 * float(np.min(hi - lo))  # the assumed margin of planes_wall.pattern_extent
    d = np.arange(0.0, reach, STEP_MM)  # distance beyond the side
    out = {}
    for side in SIDES:
        axis, sign = (0, -1) if side == "left" else (0, 1) if side == "right" else (
            1, -1) if side == "top" else (1, 1)
        edge = lo[axis] if sign < 0 else hi[axis]
        across = edge + sign * d
        # along the side, its middle part (clear of the corners, where the other sides' margins are)
        a0, a1 = lo[1 - axis], hi[1 - axis]
        along = np.arange(a0 + 0.1 * (a1 - a0), a1 - 0.1 * (a1 - a0), STEP_MM)
        strip = (board_strip(image, camera, R, T, across, along) if axis == 0 else
                 board_strip(image, camera, R, T, along, across).T)  # rows: along, cols: d
        seen = np.mean(np.isfinite(strip), axis=0) >= 0.9  # per distance: in the photo
        n_in = len(d) if np.all(seen) else int(np.argmin(seen))
        if n_in * STEP_MM < 0.5 * reach:  # the strip leaves the photo before half the reach
            continue
        strip = strip[:, :n_in]
        g = np.gradient(cv2.GaussianBlur(np.nan_to_num(strip, nan=np.nanmedian(strip)),
                                         (0, 0), 1.5), axis=1)
        prof = np.abs(np.nanmedian(np.where(np.isfinite(strip), g, np.nan), axis=0))
        k = d[:n_in] >= SKIP_MM
        noise = MAD_TO_SIGMA * np.median(np.abs(prof[k] - np.median(prof[k]))) + 1e-9
        z = (prof - np.median(prof[k])) / noise
        peak = np.zeros(len(prof), bool)
        peak[1:-1] = (prof[1:-1] > prof[:-2]) & (prof[1:-1] >= prof[2:])
        clear = np.flatnonzero(k & peak & (z >= MIN_CONTRAST))
        if len(clear):  # the nearest clear edge: the board's own (beyond it, what is behind)
            i = int(clear[0])
        else:
            i = int(np.flatnonzero(k)[np.argmax(prof[k])])
        # sub-sample peak (parabola through the neighbours)
        if 0 < i < len(prof) - 1:
            y0, y1, y2 = prof[i - 1:i + 2]
            den = y0 - 2 * y1 + y2
            off = 0.5 * (y0 - y2) / den if den < 0 else 0.0
        else:
            off = 0.0
        out[side] = SideEdge(float(d[i] + off * STEP_MM),
                             float((prof[i] - np.median(prof[k])) / noise))
    return out


def combine_margins(per_view: list[dict[str, SideEdge]],
                    ref_corners: tuple[int, int] | None = None) -> BoardMargins:
    """The margin per side shared by the views (module docstring): median of the views' clear
    edges, 1.4826 MAD as its sigma (at least :data:`STEP_MM`); accepted when more than half of
    all views that see the side have a clear edge within :data:`AGREE_MM` of it."""
    margin: dict[str, float | None] = {}
    sigma: dict[str, float | None] = {}
    groups = {s: (s,) for s in SIDES} | {"u": ("left", "right"), "v": ("top", "bottom")}
    for name, sides in groups.items():
        seen = [e[side] for e in per_view for side in sides if side in e]
        margin[name], sigma[name] = _consensus(seen)
    return BoardMargins({s: margin[s] for s in SIDES}, {s: sigma[s] for s in SIDES}, per_view,
                        {a: margin[a] for a in "uv"}, {a: sigma[a] for a in "uv"}, ref_corners)


def _consensus(seen: list[SideEdge]) -> tuple[float | None, float | None]:
    """Median and robust sigma of the clear edges among ``seen``, or ``(None, None)`` unless
    three are clear and more than half of ``seen`` agree within :data:`AGREE_MM`."""
    clear = np.array([e.margin_mm for e in seen if e.contrast >= MIN_CONTRAST])
    if len(seen) < 3 or len(clear) < 3:
        return None, None
    m = float(np.median(clear))
    agree = np.abs(clear - m) <= AGREE_MM
    if np.count_nonzero(agree) * 2 <= len(seen):
        return None, None
    s = max(MAD_TO_SIGMA * float(np.median(np.abs(clear[agree] - m))), STEP_MM)
    return round(m, 2), round(s, 2)


def measure_margins(images: list[np.ndarray], camera: CameraModel, poses: list[tuple],
                    boards: list[BoardSpec]) -> BoardMargins:
    """:func:`side_edges` of every view (photo, board pose ``(R, T)``, pattern as found) combined
    by :func:`combine_margins`. Patterns found the other way round (5x8 for 8x5) are read in
    their own frame and their sides mapped to the first view's (u <-> v swap)."""
    ref = boards[0].inner_corners
    per_view = []
    for img, (R, T), b in zip(images, poses, boards):
        e = side_edges(img, camera, R, T, b)
        if b.inner_corners != ref:  # transposed pattern: u and v exchanged
            swap = {"left": "top", "top": "left", "right": "bottom", "bottom": "right"}
            e = {swap[s]: x for s, x in e.items()}
        per_view.append(e)
    return combine_margins(per_view, tuple(ref))


def no_margins_record(pattern_board: BoardSpec, photos: int) -> dict:
    """The ``board_margins`` block when fewer than three views have a photo with the board: nothing
    measured, the assumed margin of :func:`lidarcal.planes_wall.pattern_extent` on both axes."""
    m = BoardMargins(dict.fromkeys(SIDES), dict.fromkeys(SIDES), [], {"u": None, "v": None},
                     {"u": None, "v": None})
    return m.record(pattern_board.inner_corners, float(pattern_extent(pattern_board)[2]), photos)


def apply_board_margins(views: list[ViewData], images: list, camera: CameraModel
                        ) -> BoardMargins | None:
    """The board's margins measured in the views' photos (:func:`measure_margins`) set on every
    view's board (``BoardPlane.grow_mm``: the extent beyond the pattern in which the scan's cut,
    :func:`lidarcal.planes_wall.cut_run`, looks for the board's edge; an axis not measured keeps
    the assumed margin); returns the :class:`BoardMargins` (None if fewer than three views have a
    board and a photo). Called by :func:`lidarcal.planes.run_planes` unless
    ``assumed_margin``."""
    have = [(v, im) for v, im in zip(views, images) if v.board is not None and im is not None]
    if len(have) < 3:
        return None
    m = measure_margins([im for _, im in have], camera, [(v.board.R, v.board.T) for v, _ in have],
                        [v.board.board for v, _ in have])
    for v, _ in have:
        grow = pattern_extent(v.board.board)[2]
        g = m.grow_mm(grow, transposed=v.board.board.inner_corners != m.ref_corners)
        if g is not None:
            v.board = replace(v.board, grow_mm=g)
    return m
