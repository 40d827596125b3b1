"""Laser stripes on the V: centre lines, 3D stripe points, laser plane, E, l1, l2, alpha (section 1.3).

The LiDAR's scan plane ``Pi_L`` cuts each board of the V in a straight line
(``L1``, ``L2``). Its red laser is visible to the camera: the stripe centres
are extracted with sub-pixel precision inside each board's outline
(:mod:`lidarcal.stripe_profile`), cast as rays and met with that board's plane
(eqs. 3, 5), and ``Pi_L`` is fitted to the 3D points of both stripes (eq. 4). ``E`` is the common point of
``Pi_1, Pi_2, Pi_L``; ``l_k = n_k x n_L`` (oriented towards stripe ``k``),
``alpha = arccos(l1 . l2)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from .board import BoardView
from .camera import backproject_to_plane
from .geometry import Plane, cross3, fit_plane, fit_plane_algebraic, intersect_planes, unit
from .io.dataset import CameraModel
from .laser_colour import (  # noqa: F401  (re-exported: the stripe's public API)
    LASER_COLOURS,
    SATURATED_DN,
    detect_laser_colour,
    laser_response,
)
from .stripe_profile import (  # noqa: F401  (re-exported: stripe_centres is the stripe's API)
    _CROP_PAD,
    _centres_in_crop,
    _empty,
    reflectance_ratio,
    stripe_centres,
)
from .stripe_quality import (  # noqa: F401  (re-exported)
    DEFAULT_GATES,
    StripeGates,
    quality_problem,
    stripe_quality,
)


def stripe_points_3d(camera: CameraModel, centres_px: np.ndarray, plane: Plane) -> np.ndarray:
    """3D stripe points (N, 3), mm: rays through the centres meet that board's plane (eq. 5)."""
    return backproject_to_plane(camera, centres_px, plane)


@dataclass(frozen=True)
class CameraLines:
    """The camera side of one position (section 1.3).

    ``laser_plane`` is the total-least-squares fit of eq. (4) to both boards'
    stripe points; ``laser_plane_algebraic`` the paper's ``ax + by + cz = 1``
    least squares, for comparison; ``laser_plane_lines`` the plane through
    the two stripe lines fitted in their board planes (beyond the paper); these
    two are computed from ``points_3d`` when first asked for (the calibration
    does not use them).
    ``E`` (3,) = Pi_1 ^ Pi_2 ^ Pi_L, mm. ``l[k]`` is the unit direction of
    the stripe on board ``k`` (``n_k x n_L``), oriented from ``E`` towards
    that stripe's points; ``alpha = arccos(l0 . l1)``, rad.
    ``residual_rms_mm`` is the rms distance of the stripe points to
    ``laser_plane``; ``rho`` the stripe's black/white reflectance ratio used
    to correct the centres (None: no correction).
    """

    laser_plane: Plane
    E: np.ndarray
    l: np.ndarray  # (2, 3)
    alpha: float
    centres_px: tuple[np.ndarray, np.ndarray]
    points_3d: tuple[np.ndarray, np.ndarray]
    residual_rms_mm: float
    board_planes: tuple[Plane, Plane]
    rho: float | None = None

    @property
    def alpha_deg(self) -> float:
        return float(np.degrees(self.alpha))

    @cached_property
    def laser_plane_algebraic(self) -> Plane:
        """The paper's algebraic fit of eq. (4) to both boards' stripe points."""
        return fit_plane_algebraic(np.vstack(self.points_3d))

    @cached_property
    def laser_plane_lines(self) -> Plane:
        """The plane through the two stripe lines (:func:`laser_plane_from_lines`)."""
        return laser_plane_from_lines(self.points_3d, self.board_planes)


def laser_plane_from_lines(points: tuple[np.ndarray, np.ndarray],
                           planes: tuple[Plane, Plane]) -> Plane:
    """Laser plane through the two 3D stripe lines (beyond the paper).

    Each stripe is fitted as a line inside its own board plane (TLS on the
    points projected onto the plane); the laser plane is then the TLS plane
    of the two fitted lines, each sampled over the extent of its points and
    weighted by its point count.
    """
    samples, weights = [], []
    for P, pl in zip(points, planes):
        Q = pl.project(P)
        c = Q.mean(0)
        _, V = np.linalg.eigh((Q - c).T @ (Q - c))  # the scatter's principal axis
        d = V[:, -1]
        t = (Q - c) @ d
        ts = np.linspace(t.min(), t.max(), 9)
        samples.append(c + ts[:, None] * d)
        weights.append(np.full(9, len(P) / 9.0))
    return fit_plane(np.vstack(samples), np.concatenate(weights))


_CROP_CACHE: list = []  # [(board, other board, (shape, albedo), geometry)]: the same boards serve every image


def _board_crop(img: np.ndarray, board: BoardView, albedo: bool, other: BoardView | None = None):
    """The crop of ``img`` around one board's outline that :func:`stripe_centres` would use
    with the full mask ``board.mask``: (image crop, mask crop, blackness crop or None, origin).

    Only the crop is rasterised and sliced (no full-size mask or blackness map); the
    mask and blackness crops depend on the boards alone and are kept for the next image.
    The mask is ``board.stripe_outline_px`` (the pattern and half a square of its white
    border; ``outline_px`` when absent) minus the ``other`` board's ``outline_px``.
    """
    key = (img.shape[:2], albedo)
    for b, o, k, geo in _CROP_CACHE:
        if b is board and o is other and k == key:
            break
    else:
        geo = _board_crop_geometry(img.shape[:2], board, albedo, other)
        _CROP_CACHE.insert(0, (board, other, key, geo))
        del _CROP_CACHE[4:]
    if geo is None:
        return None
    msub, bsub, (x_lo, y_lo) = geo
    h, w = msub.shape
    return img[y_lo:y_lo + h, x_lo:x_lo + w], msub, bsub, (x_lo, y_lo)


def _board_crop_geometry(shape: tuple[int, int], board: BoardView, albedo: bool,
                         other: BoardView | None = None):
    """Mask crop, blackness crop (finite, float32) or None, and origin for :func:`_board_crop`."""
    H, W = shape
    outline = getattr(board, "stripe_outline_px", None)
    poly = np.round(board.outline_px if outline is None else outline).astype(np.int32)
    bx0, by0 = np.clip(poly.min(0), 0, [W - 1, H - 1])
    bx1, by1 = np.clip(poly.max(0) + 1, 1, [W, H])
    small = np.zeros((by1 - by0, bx1 - bx0), np.uint8)
    cv2.fillPoly(small, [poly], 1, offset=(-int(bx0), -int(by0)))
    if other is not None and outline is not None:
        cv2.fillPoly(small, [np.round(other.outline_px).astype(np.int32)], 0,
                     offset=(-int(bx0), -int(by0)))
    small = small.astype(bool)
    if not small.any():
        return None
    ys, xs = np.flatnonzero(small.any(axis=1)), np.flatnonzero(small.any(axis=0))
    y_lo, y_hi = max(by0 + ys[0] - _CROP_PAD, 0), min(by0 + ys[-1] + 1 + _CROP_PAD, H)
    x_lo, x_hi = max(bx0 + xs[0] - _CROP_PAD, 0), min(bx0 + xs[-1] + 1 + _CROP_PAD, W)
    msub = np.zeros((y_hi - y_lo, x_hi - x_lo), bool)
    msub[by0 - y_lo:by1 - y_lo, bx0 - x_lo:bx1 - x_lo] = small
    bsub = None
    if albedo and board.blackness is not None:
        bsub = np.zeros(msub.shape, np.float32)  # as blackness_map: 0 outside the stored crop
        ox, oy = board.blackness_origin
        h, w = board.blackness.shape
        h, w = min(h, H - oy), min(w, W - ox)
        sx0, sy0 = max(x_lo, ox), max(y_lo, oy)
        sx1, sy1 = min(x_hi, ox + w), min(y_hi, oy + h)
        if sx1 > sx0 and sy1 > sy0:
            bsub[sy0 - y_lo:sy1 - y_lo, sx0 - x_lo:sx1 - x_lo] = \
                board.blackness[sy0 - oy:sy1 - oy, sx0 - ox:sx1 - ox]
        bsub = np.nan_to_num(bsub, nan=0.0)
        bsub.flags.writeable = False  # shared by every image: never modified
    msub.flags.writeable = False
    return msub, bsub, (int(x_lo), int(y_lo))


def _board_inputs(img: np.ndarray, boards: tuple[BoardView, BoardView], albedo: bool):
    return [_board_crop(img, b, albedo, boards[1 - k]) for k, b in enumerate(boards)]


def _crop_centres(crop, camera: CameraModel, min_snr: float, rho: float | None,
                  return_info: bool = False, want_samples: bool | None = None,
                  samples_only: bool = False):
    if crop is None:
        return _empty(return_info)
    sub, msub, bsub, origin = crop
    return _centres_in_crop(sub, msub, bsub, origin, camera, min_snr, rho, return_info,
                            return_info if want_samples is None else want_samples, clean=True,
                            samples_only=samples_only)


def estimate_reflectance_ratio(camera: CameraModel, stripe_images: list[np.ndarray],
                               boards: tuple[BoardView, BoardView],
                               min_snr: float = 8.0) -> float | None:
    """The stripe's black/white reflectance ratio from several stripe images at once.

    A property of the board and the laser, the same at every position: pooling
    positions sees the stripe on pure white and pure black squares even when
    at some position it runs along a square edge. None without blackness maps
    or contrast.
    """
    samples = []
    for img in stripe_images:
        got = reflectance_samples(camera, img, boards, min_snr)
        if got is None:
            return None
        samples += got
    return reflectance_ratio(samples)


def reflectance_samples(camera: CameraModel, stripe_image: np.ndarray,
                        boards: tuple[BoardView, BoardView], min_snr: float = 8.0
                        ) -> list | None:
    """One image's share of :func:`estimate_reflectance_ratio`: the ``samples`` of its two
    stripes for :func:`reflectance_ratio` (None when the boards carry no blackness maps)."""
    img = np.asarray(stripe_image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    crops = _board_inputs(img, boards, True)
    if any(crop is not None and crop[2] is None for crop in crops):
        return None
    return _crops_samples(crops, camera, min_snr)


def _crops_samples(crops, camera: CameraModel, min_snr: float) -> list:
    """The :func:`reflectance_ratio` samples of the stripes in ``crops`` (centres found
    with ``rho = 1``: no albedo division)."""
    out = []
    for crop in crops:
        _, info = _crop_centres(crop, camera, min_snr, 1.0, return_info=True, samples_only=True)
        if info.get("samples") is not None:
            out.append(info["samples"])
    return out


#: Fewer stripe centres than this on a board: no usable stripe there (section 1.3).
MIN_STRIPE_CENTRES = 10


def board_stripe_centres(camera: CameraModel, stripe_image: np.ndarray,
                         boards: tuple[BoardView, BoardView], min_snr: float = 8.0,
                         rho: float | None = None, albedo_correction: bool = True,
                         laser_colour: str = "auto"
                         ) -> tuple[list[np.ndarray], float | None, list[str | None]]:
    """Sub-pixel laser-stripe centres (raw pixels, (N, 2) per board) on each board of the V,
    the detection step of section 1.3 before any fit, the reflectance ratio used, and per
    board the quality problem (None when the stripe passes the gates of :class:`StripeGates`
    and has at least :data:`MIN_STRIPE_CENTRES` centres).

    With ``albedo_correction`` (and boards found by :func:`lidarcal.board.find_v_boards`,
    which carry blackness maps) the centres are corrected for the squares' reflectance
    (:func:`stripe_centres`); ``rho`` is the stripe's black/white reflectance ratio,
    estimated from this image's two stripes when not given (better: once per dataset with
    :func:`estimate_reflectance_ratio`). A colour image is turned into the laser's response
    by ``laser_colour`` (:func:`laser_response`).
    """
    centres, rho, infos = _board_stripe_centres(camera, stripe_image, boards, min_snr, rho,
                                                albedo_correction, laser_colour)
    return centres, rho, [_problem(c, info) for c, info in zip(centres, infos)]


def _problem(centres: np.ndarray, info: dict) -> str | None:
    """One board's stripe problem for :func:`board_stripe_centres` (None: usable)."""
    return info.get("problem") or (
        None if len(centres) >= MIN_STRIPE_CENTRES
        else f"{len(centres)} stripe centres found, need at least {MIN_STRIPE_CENTRES}")


def _board_stripe_centres(camera: CameraModel, stripe_image: np.ndarray,
                          boards: tuple[BoardView, BoardView], min_snr: float, rho: float | None,
                          albedo_correction: bool, laser_colour: str
                          ) -> tuple[list[np.ndarray], float | None, list[dict]]:
    """:func:`board_stripe_centres` with each board's ``info`` of :func:`stripe_centres`
    instead of its problem."""
    img = np.asarray(stripe_image)
    if img.ndim == 3:
        img = laser_response(img, laser_colour)
    crops = _board_inputs(img, boards, albedo_correction)
    use_albedo = albedo_correction and all(b.blackness is not None for b in boards)
    if not use_albedo:
        crops = [None if c is None else (c[0], c[1], None, c[3]) for c in crops]
        rho = None
    elif rho is None:
        rho = reflectance_ratio(_crops_samples(crops, camera, min_snr))
        if rho is None:
            rho = 1.0  # not seen in this image: no division (background still uses blackness)
    centres, infos = [], []
    for k in range(2):
        c, info = _crop_centres(crops[k], camera, min_snr, rho, return_info=True,
                                want_samples=False)
        centres.append(c)
        infos.append(info)
    return centres, rho, infos


def camera_lines(camera: CameraModel, stripe_image: np.ndarray,
                 boards: tuple[BoardView, BoardView], use_pnp: bool = True,
                 min_snr: float = 8.0, rho: float | None = None,
                 albedo_correction: bool = True, laser_colour: str = "auto") -> CameraLines:
    """Laser plane (eq. 4), E, l1, l2 and alpha from one stripe image (section 1.3).

    ``use_pnp`` (default) takes the board planes from ``cv2.solvePnP`` (the
    maximum-likelihood pose, started from the homography's) instead of the
    homography alone (eqs. 2-3). Measured on the rendered wide rig (seed 37, true
    camera): board-plane offset 0.01-0.04 mm with PnP against 0.14-0.32 mm with the
    homography (normals 0.016-0.030 against 0.021-0.066 deg). The stripe centres are
    :func:`board_stripe_centres` (``rho``, ``albedo_correction``, ``laser_colour`` as there).

    Raises
    ------
    ValueError
        When a board's stripe fails the quality gates (:class:`StripeGates`: too few
        centres, not one smooth curve, too little of the board crossed, too faint); the
        caller names the file. Never wrong points instead.
    """
    planes = tuple(b.plane_pnp if use_pnp else b.plane for b in boards)
    centres, rho, infos = _board_stripe_centres(camera, stripe_image, boards, min_snr, rho,
                                                albedo_correction, laser_colour)
    for k, (c, info) in enumerate(zip(centres, infos)):
        problem = _problem(c, info)
        if problem:
            raise ValueError(f"board {k}: {problem}; is the stripe on both boards, bright "
                             "enough, and lidar.laser_colour right?")
    return camera_lines_from_centres(camera, centres, planes, rho,
                                     normalised=[info.get("normalised") for info in infos])


def camera_lines_from_centres(camera: CameraModel, centres: Sequence[np.ndarray],
                              planes: Sequence[Plane], rho: float | None = None,
                              normalised: Sequence[np.ndarray | None] | None = None
                              ) -> CameraLines:
    """Section 1.3 after centre extraction: eq. (4), E, l1, l2, alpha.

    Rays through each board's stripe centres meet that board's plane (eq. 5);
    the laser plane is the TLS fit of both boards' points (the paper's algebraic
    ``ax + by + cz = 1`` fit is kept for comparison); ``E = Pi_1 ^ Pi_2 ^ Pi_L``;
    ``l_k = n_k x n_L`` oriented from E towards stripe ``k``. ``normalised``: the
    centres already undistorted (``info["normalised"]`` of :func:`stripe_centres`), per
    board or None, so the rays need not be computed again.
    """
    xy = [None, None] if normalised is None else list(normalised)
    pts = [stripe_points_3d(camera, c, pl) if n is None or len(n) != len(c)
           else pl.intersect_rays(np.column_stack([n, np.ones(len(n))]))
           for c, pl, n in zip(centres, planes, xy)]
    allp = np.vstack(pts)
    laser = fit_plane(allp)
    E = intersect_planes(planes[0], planes[1], laser)
    ls = []
    for k in range(2):
        lk = unit(cross3(planes[k].normal, laser.normal))
        if (pts[k].mean(0) - E) @ lk < 0:
            lk = -lk
        ls.append(lk)
    l = np.vstack(ls)
    alpha = float(np.arccos(np.clip(l[0] @ l[1], -1.0, 1.0)))
    rms = float(np.sqrt(np.mean(laser.distance(allp) ** 2)))
    return CameraLines(laser, E, l, alpha, (centres[0], centres[1]), (pts[0], pts[1]), rms,
                       (planes[0], planes[1]), rho)
