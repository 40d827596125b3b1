"""Chessboard corners refined by their point symmetry on the board plane (Datta, Kim, Kanade).

Datta, Kim, Kanade (2009), "Accurate camera calibration using iterative refinement of
control points": with the current camera and board pose, the board is looked at head-on
without lens distortion, where every corner is a point-symmetric saddle; the corners are
located there and mapped back through the pose and the lens model into the image. Here the
fronto-parallel view is never resampled into an image: pairs of points at symmetric offsets
``c + d`` and ``c - d`` around each corner ``c`` on the board plane are projected once
(eq. (1) and OpenCV's lens model, :mod:`lidarcal.lens`), and each corner is the pixel shift ``u``
that makes the image equal at both ends of every pair,

    min_u  sum_d ( I(pi(c + d) + u) - I(pi(c - d) + u) )^2,

solved by Gauss-Newton for all corners at once: one ``cv2.remap`` per iteration samples the
image and its gradient at every point of every corner (the perspective and the distortion
are in the projected pairs; over a corner's window the shift of the projection is a plain
translation to first order, so the pairs are projected only once).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .io.dataset import BoardSpec, CameraModel
from .lens import project_camera_points

#: half-width of a corner's window on the board, in squares (inside the four squares around
#: the corner, clear of the next corners' blur)
WINDOW_SQUARES = 0.8
#: sample steps along each edge to each side of the corner
ALONG_SAMPLES = 16
#: half-width (px) of the strip sampled across each edge (the edge's blur), and its steps
#: to each side
ACROSS_PX = 2.4
ACROSS_SAMPLES = 2
GOLDEN = (np.sqrt(5.0) - 1.0) / 2.0
#: Gauss-Newton iterations (the start is the detector's corner, within a tenth of a pixel)
ITERATIONS = 2


#: a corner's window must be point-symmetric to this (:func:`asymmetry`; about 1 where there
#: is no corner)
MAX_ASYMMETRY = 0.3
#: the share of corners that may fail the checks (they keep their first position)
MAX_FAILED_SHARE = 0.1


@dataclass(frozen=True)
class SymmetricCorners:
    """The refined corners (N, 2) px, each corner's :func:`asymmetry` at its solution and
    each corner's move from where it started (px)."""

    corners_px: np.ndarray
    asymmetry: np.ndarray
    moved_px: np.ndarray
    square_px: float

    def checked(self, start_px: np.ndarray) -> np.ndarray | None:
        """The refined corners where each passes the checks (its window point-symmetric to
        ``MAX_ASYMMETRY``, moved by less than a tenth of a square), ``start_px`` where it
        does not; None when more than ``MAX_FAILED_SHARE`` fail (the pose or the detection
        is off: the caller keeps its corners)."""
        bad = ~((self.asymmetry < MAX_ASYMMETRY) & (self.moved_px < 0.1 * self.square_px)
                & np.all(np.isfinite(self.corners_px), axis=1))
        if np.mean(bad) > MAX_FAILED_SHARE:
            return None
        return np.where(bad[:, None], np.asarray(start_px, float).reshape(-1, 2), self.corners_px)


def board_to_image(camera: CameraModel, R: np.ndarray, T: np.ndarray,
                   xy_mm: np.ndarray) -> np.ndarray:
    """Board points (..., 2) mm -> distorted pixels (..., 2): eq. (1) and the lens model."""
    xy = np.asarray(xy_mm, float)
    flat = xy.reshape(-1, 2)
    P = np.column_stack([flat, np.zeros(len(flat))]) @ np.asarray(R, float).T + np.asarray(T, float)
    # OpenCV's lens model without cv2.projectPoints' Jacobian (5x the projection's cost here)
    return project_camera_points(camera.K, camera.dist, P).reshape(xy.shape)


def edge_strips(corners_mm: np.ndarray, square_mm: float, mm_per_px: float,
                window_squares: float = WINDOW_SQUARES, along: int = ALONG_SAMPLES,
                across_px: float = ACROSS_PX) -> np.ndarray:
    """The ends (N, 2, 2 * along + 1, 2, 2) mm of the across-edge segments sampled around
    each corner: strip 0 along the board's x axis (the edge between the rows of squares),
    strip 1 along y; ``along`` steps to each side up to ``window_squares`` squares, each
    segment ``across_px`` pixels (``mm_per_px`` at the board) to either side of the edge,
    shifted across it by up to half its length (golden-ratio sequence, odd in the step, so the
    pairs stay symmetric: the samples meet the pixel grid at every phase, not all at the
    same one along an edge parallel to the image axes).

    Only points near an edge tell where the corner is (elsewhere the squares are flat). The
    point symmetric to step ``(i, j)`` of a strip is its step ``(-i, -j)``."""
    i = np.arange(-along, along + 1)
    a = i * (window_squares * float(square_mm) / along)
    h = across_px * float(mm_per_px)
    zero = np.sign(i) * (np.mod(np.abs(i) * GOLDEN, 1.0) - 0.5) * h
    ends = np.empty((len(corners_mm), 2, len(a), 2, 2))
    for e, sign in enumerate((-1.0, 1.0)):
        ends[:, 0, :, e] = corners_mm[:, None] + np.column_stack([a, zero + sign * h])[None]
        ends[:, 1, :, e] = corners_mm[:, None] + np.column_stack([zero + sign * h, a])[None]
    return ends


def symmetric_corners(gray: np.ndarray, camera: CameraModel, R: np.ndarray, T: np.ndarray,
                      board: BoardSpec, start_px: np.ndarray | None = None,
                      window_squares: float = WINDOW_SQUARES, along: int = ALONG_SAMPLES,
                      across_px: float = ACROSS_PX, across: int = ACROSS_SAMPLES,
                      iterations: int = ITERATIONS) -> SymmetricCorners:
    """Every inner corner of ``board`` at pose ``(R, T)`` refined by point symmetry (Datta,
    Kim, Kanade 2009; the module docstring gives the criterion).

    The pairs lie on the two edges through each corner (:func:`edge_strips`), laid out
    around the corner's projection by the pose; ``start_px`` (N, 2), the detected corners in
    OpenCV order, starts the shift from them instead. Each across-edge segment is projected
    at its two ends and sampled at ``2 * across + 1`` points between them (over a few pixels
    the lens bends a line by far less than the sampling matters). ``gray`` is sampled
    bicubically; the Gauss-Newton Jacobian is the image gradient across the edge, by finite
    differences of the same samples. Returns the corners in ``gray``'s pixels, OpenCV order.
    """
    g = np.asarray(gray)
    if g.ndim == 3:
        g = cv2.cvtColor(g, cv2.COLOR_BGR2GRAY)
    c = board.object_points()[:, :2].astype(float)
    centre = board_to_image(camera, R, T, c)
    cols, rows = board.inner_corners
    grid = centre.reshape(rows, cols, 2)
    square_px = float(np.median(np.linalg.norm(np.diff(grid, axis=1), axis=2)))
    ends = board_to_image(camera, R, T, edge_strips(c, board.square_mm,
                                                    board.square_mm / square_px,
                                                    window_squares, along, across_px))
    step = (ends[..., 1, :] - ends[..., 0, :]) / (2 * across)  # (N, 2, A, 2) px per step
    t = np.arange(2 * across + 1, dtype=float)
    px = ends[..., 0, None, :] + t[:, None] * step[..., None, :]  # (N, 2, A, S, 2)
    n_step = step / np.sum(step ** 2, axis=-1, keepdims=True)  # gradient = dI/ds * this
    u = np.zeros_like(centre) if start_px is None else np.asarray(start_px, float) - centre
    # the image in a float crop around the board
    flat = px.reshape(-1, 2)
    # each column reduced alone: numpy's min/max over axis 0 of an (n, 2) array is ~30 times
    # slower (4 ms here)
    flat_lo = np.array([flat[:, 0].min(), flat[:, 1].min()])
    flat_hi = np.array([flat[:, 0].max(), flat[:, 1].max()])
    lo = np.maximum(np.floor(flat_lo + u.min(0) - 4).astype(int), 0)
    hi = np.minimum(np.ceil(flat_hi + u.max(0) + 5).astype(int), [g.shape[1], g.shape[0]])
    crop = g[lo[1]:hi[1], lo[0]:hi[0]].astype(np.float32)
    px = (px - lo).reshape(len(c), -1, 2)
    shape = (len(c), 2, ends.shape[2], len(t))
    limit = 0.1 * square_px

    def flip(a: np.ndarray) -> np.ndarray:
        """Each sample's symmetric partner: step (i, j) -> (-i, -j) of the same strip."""
        return a[:, :, ::-1, ::-1]

    for k in range(iterations + 1):
        q = (px + u[:, None]).astype(np.float32)
        v = cv2.remap(crop, q[..., 0], q[..., 1], cv2.INTER_CUBIC,
                      borderMode=cv2.BORDER_REPLICATE).reshape(shape).astype(float)
        r = v - flip(v)
        if k == iterations:
            break
        ds = np.gradient(v, axis=3)  # dI per step across the edge
        gx, gy = ds * n_step[..., 0, None], ds * n_step[..., 1, None]
        jx = (gx - flip(gx)).reshape(len(c), -1)
        jy = (gy - flip(gy)).reshape(len(c), -1)
        r = r.reshape(len(c), -1)
        a11, a12, a22 = (jx * jx).sum(1), (jx * jy).sum(1), (jy * jy).sum(1)
        b1, b2 = -(jx * r).sum(1), -(jy * r).sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            det = a11 * a22 - a12 ** 2
            du = np.column_stack([(a22 * b1 - a12 * b2) / det, (a11 * b2 - a12 * b1) / det])
        u = u + np.clip(np.nan_to_num(du), -limit, limit)
    out = centre + u
    start = centre if start_px is None else np.asarray(start_px, float)
    return SymmetricCorners(out, asymmetry(r.reshape(len(c), -1), v.reshape(len(c), -1)),
                            np.linalg.norm(out - start, axis=1), square_px)


def asymmetry(resid: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per corner, the RMS of ``I(c + d) - I(c - d)`` over ``sqrt(2)`` times the spread of
    ``I`` in the window: 0 for a perfect centre of symmetry, about 1 where there is no corner
    (nan on a flat image)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(np.mean(resid ** 2, axis=1)) / (np.sqrt(2) * values.std(axis=1))
