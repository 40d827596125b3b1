"""Both chessboards of the V and their planes in the camera frame, section 1.2, eqs. (1)-(3).

Each board defines a frame ``O_p - x~y~z~`` with the board in ``z~ = 0``;
eq. (1) maps it into the camera frame, ``X = R X~ + T``. Eq. (2): the
homography between the board plane and the (undistorted) image is
``H = K [r1 r2 T]``; we compute it against undistorted *normalised*
coordinates, so ``K = I``. ``R`` is the nearest rotation to
``[h1' h2' h1' x h2']`` (SVD), ``T`` follows by linear least squares and the
board's plane is eq. (3): ``r3 . X = r3 . T``. ``cv2.solvePnP`` (iterative
Levenberg-Marquardt on the pixel reprojection error, the maximum-likelihood
pose) is kept beside it for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .camera import backproject_to_plane, project_points, undistort_pixels
from .corner_symmetry import symmetric_corners
from .corners import detect_chessboard, saddle_corners, sb_accuracy_corners
from .geometry import MAD_TO_SIGMA, Plane, as_points, nearest_rotation
from .io.dataset import BoardSpec, CameraModel, Dataset, DatasetError, read_image


@dataclass(frozen=True)
class BoardView:
    """One chessboard of the V seen in the bright image.

    ``plane`` is eq. (3) from the homography pose (``R``, ``T``: board frame
    -> camera frame, eq. 1); ``plane_pnp`` from ``cv2.solvePnP``
    (``R_pnp``, ``T_pnp``). ``reprojection_rms_px`` = (homography, PnP).
    ``outline_px`` is a closed polygon (M, 2) around the printed pattern
    (one square beyond the outer inner corners) in the raw image, used to
    draw the board. ``stripe_outline_px`` reaches half a square further, onto the
    white border that printed chessboards carry (a stripe crossing the board
    below the pattern is still found there); the stripe search uses it, minus
    the other board's ``outline_px``. ``blackness`` is a crop of the bright
    image (origin ``blackness_origin`` = (x0, y0)) normalised to 0 on white
    and 1 on black squares by smooth white/black level fields (see
    :func:`board_blackness`); ``bright_ratio`` is the black/white ratio of
    the bright image.
    """

    corners_px: np.ndarray  # (N, 2), OpenCV order
    plane: Plane
    plane_pnp: Plane
    R: np.ndarray
    T: np.ndarray
    R_pnp: np.ndarray
    T_pnp: np.ndarray
    reprojection_rms_px: tuple[float, float]
    outline_px: np.ndarray  # (M, 2)
    blackness: np.ndarray | None = field(default=None, repr=False)
    blackness_origin: tuple[int, int] = (0, 0)
    bright_ratio: float | None = None
    stripe_outline_px: np.ndarray | None = field(default=None, repr=False)

    @property
    def centroid_px(self) -> np.ndarray:
        return self.corners_px.mean(axis=0)

    def mask(self, image_shape: tuple[int, ...]) -> np.ndarray:
        """Boolean mask (H, W) of the board's outline polygon."""
        m = np.zeros(image_shape[:2], np.uint8)
        cv2.fillPoly(m, [np.round(self.outline_px).astype(np.int32)], 1)
        return m.astype(bool)

    def blackness_map(self, image_shape: tuple[int, ...]) -> np.ndarray | None:
        """``blackness`` placed in a full image (H, W), 0 outside its crop; None if absent."""
        if self.blackness is None:
            return None
        out = np.zeros(image_shape[:2], np.float32)
        x0, y0 = self.blackness_origin
        h, w = self.blackness.shape
        H, W = out.shape
        out[y0:min(y0 + h, H), x0:min(x0 + w, W)] = self.blackness[:H - y0, :W - x0]
        return out


def pose_from_homography(camera: CameraModel, corners_px: np.ndarray,
                         object_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Board pose ``(R, T)`` (eq. 1) from the plane-to-image homography, eq. (2).

    The corners are undistorted to normalised coordinates, so eq. (2) reads
    ``t (x, y, 1)^T = [r1 r2 T] (x~, y~, 1)^T``. ``H`` is estimated by
    :func:`homography` (normalised DLT + reprojection refinement); its
    scale is ``2 / (|h1| + |h2|)`` with the sign that puts the board in front
    of the camera; ``R`` is the nearest rotation to ``[h1' h2' h1' x h2']``
    (SVD) and ``T`` solves the linear least-squares problem
    ``x (r3 . X~ + T_z) = r1 . X~ + T_x`` (and the same in y) with ``R`` fixed.

    Parameters
    ----------
    corners_px : array-like, shape (N, 2)
        Distorted pixel coordinates, N >= 4.
    object_points : array-like, shape (N, 3) or (N, 2)
        Board coordinates, mm, ``z~ = 0``.
    """
    obj = np.asarray(object_points, dtype=float)
    if obj.ndim != 2 or obj.shape[1] not in (2, 3):
        raise ValueError(f"Expected object points with shape (N, 2) or (N, 3), got {obj.shape}")
    if obj.shape[1] == 3:
        if np.max(np.abs(obj[:, 2])) > 1e-9 * max(1.0, np.max(np.abs(obj))):
            raise ValueError("Object points must lie in the board plane z = 0")
        obj = obj[:, :2]
    px = as_points(corners_px, 2)
    if len(px) != len(obj) or len(px) < 4:
        raise ValueError(f"Need >= 4 matching points, got {len(px)} image and {len(obj)} object")
    xy = undistort_pixels(camera, px)
    ok = np.all(np.isfinite(xy), axis=1)
    xy, obj = xy[ok], obj[ok]
    H = homography(obj, xy)
    h1, h2, h3 = H[:, 0], H[:, 1], H[:, 2]
    lam = 2.0 / (np.linalg.norm(h1) + np.linalg.norm(h2))
    if lam * h3[2] < 0:  # the board's origin must be in front of the camera
        lam = -lam
    r1, r2 = lam * h1, lam * h2
    R, _ = nearest_rotation(np.column_stack([r1, r2, np.cross(r1, r2)]))
    # T by linear least squares with R fixed: (R X~ + T)_xy = (x, y) (R X~ + T)_z
    P = np.column_stack([obj, np.zeros(len(obj))]) @ R.T
    A = np.zeros((2 * len(xy), 3))
    b = np.zeros(2 * len(xy))
    A[0::2, 0] = 1
    A[0::2, 2] = -xy[:, 0]
    b[0::2] = xy[:, 0] * P[:, 2] - P[:, 0]
    A[1::2, 1] = 1
    A[1::2, 2] = -xy[:, 1]
    b[1::2] = xy[:, 1] * P[:, 2] - P[:, 1]
    T, *_ = np.linalg.lstsq(A, b, rcond=None)
    return R, T


def homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Plane-to-plane homography ``dst ~ H src`` (3, 3), ``H[2, 2] = 1`` where possible.

    Hartley-normalised DLT (SVD, float64), then Levenberg-Marquardt on the
    transfer error in ``dst`` (the maximum-likelihood H when only ``dst`` is
    noisy, as for board corners). Needs >= 4 points, no three collinear.
    """
    src, dst = as_points(src, 2), as_points(dst, 2)

    def norm(p: np.ndarray) -> np.ndarray:
        c = p.mean(0)
        s = np.sqrt(2) / max(np.sqrt(((p - c) ** 2).sum(1)).mean(), 1e-300)
        return np.array([[s, 0, -s * c[0]], [0, s, -s * c[1]], [0, 0, 1]])

    Ns, Nd = norm(src), norm(dst)
    a = src @ Ns[:2, :2].T + Ns[:2, 2]
    b = dst @ Nd[:2, :2].T + Nd[:2, 2]
    n = len(a)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2], A[0::2, 2] = a, 1
    A[0::2, 6:8], A[0::2, 8] = -b[:, :1] * a, -b[:, 0]
    A[1::2, 3:5], A[1::2, 5] = a, 1
    A[1::2, 6:8], A[1::2, 8] = -b[:, 1:] * a, -b[:, 1]
    _, sv, vt = np.linalg.svd(A, full_matrices=False)
    if sv[-2] < 1e-12 * sv[0]:
        raise ValueError("Homography is undetermined (degenerate points)")
    Hn = vt[-1].reshape(3, 3)
    Hn = Hn / Hn[2, 2] if abs(Hn[2, 2]) > 1e-12 else Hn / np.linalg.norm(Hn)

    def resid(h: np.ndarray) -> np.ndarray:
        M = np.append(h, Hn.ravel()[8]).reshape(3, 3)
        q = np.column_stack([a, np.ones(n)]) @ M.T
        return (q[:, :2] / q[:, 2:] - b).ravel()

    from scipy.optimize import least_squares  # here: finding the V's boards needs no scipy

    sol = least_squares(resid, Hn.ravel()[:8], method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    Hn = np.append(sol.x, Hn.ravel()[8]).reshape(3, 3)
    H = np.linalg.inv(Nd) @ Hn @ Ns
    return H / H[2, 2] if abs(H[2, 2]) > 1e-12 else H


def plane_from_pose(R: np.ndarray, T: np.ndarray) -> Plane:
    """Eq. (3): the board plane ``r3 . X = r3 . T`` in the camera frame."""
    return Plane.from_normal_point(np.asarray(R)[:, 2], np.asarray(T))


def pose_pnp(camera: CameraModel, corners_px: np.ndarray, object_points: np.ndarray,
             R0: np.ndarray | None = None, T0: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray]:
    """Board pose by ``cv2.solvePnP`` (iterative LM on pixel reprojection error, with distortion).

    Started from ``(R0, T0)`` when given (e.g. the homography pose), otherwise
    from OpenCV's own planar initialisation (IPPE).
    """
    obj = np.asarray(object_points, dtype=float)
    if obj.shape[1] == 2:
        obj = np.column_stack([obj, np.zeros(len(obj))])
    img = as_points(corners_px, 2)
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    if R0 is None:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            raise ValueError("solvePnP (IPPE) failed")
    else:
        rvec, tvec = cv2.Rodrigues(np.asarray(R0, float))[0], np.asarray(T0, float).reshape(3, 1)
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, rvec.copy(), tvec.copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("solvePnP (iterative) failed")
    return cv2.Rodrigues(rvec)[0], tvec.ravel()


def reprojection_rms_px(camera: CameraModel, R: np.ndarray, T: np.ndarray,
                        corners_px: np.ndarray, object_points: np.ndarray) -> float:
    """RMS distance (px) between detected corners and the board corners projected by ``(R, T)``."""
    obj = np.asarray(object_points, dtype=float)
    if obj.shape[1] == 2:
        obj = np.column_stack([obj, np.zeros(len(obj))])
    proj = project_points(camera, obj @ np.asarray(R).T + np.asarray(T))
    return float(np.sqrt(np.mean(np.sum((proj - corners_px) ** 2, axis=1))))


def board_outline_px(camera: CameraModel, R: np.ndarray, T: np.ndarray, board: BoardSpec,
                     margin_squares: float = 1.0, samples_per_edge: int = 40) -> np.ndarray:
    """Polygon (M, 2) around the pattern, ``margin_squares`` beyond the outer inner corners.

    The rectangle is drawn on the board plane and projected with distortion
    (its edges are sampled so they curve as the image does).
    """
    cols, rows = board.inner_corners
    sq = board.square_mm
    x0, x1 = -margin_squares * sq, (cols - 1 + margin_squares) * sq
    y0, y1 = -margin_squares * sq, (rows - 1 + margin_squares) * sq
    t = np.linspace(0, 1, samples_per_edge, endpoint=False)
    edges = [np.column_stack([x0 + (x1 - x0) * t, np.full_like(t, y0)]),
             np.column_stack([np.full_like(t, x1), y0 + (y1 - y0) * t]),
             np.column_stack([x1 - (x1 - x0) * t, np.full_like(t, y1)]),
             np.column_stack([np.full_like(t, x0), y1 - (y1 - y0) * t])]
    xy = np.vstack(edges)
    P = np.column_stack([xy, np.zeros(len(xy))]) @ np.asarray(R).T + np.asarray(T)
    return project_points(camera, P)


def inner_diagonal_mm(camera: CameraModel, view: BoardView) -> float:
    """The board's inner-corner grid diagonal, mm: its first and last corners (opposite
    corners in OpenCV's order) cast onto the board's plane (eqs. 1-3)."""
    ends = backproject_to_plane(camera, view.corners_px[[0, -1]], view.plane)
    return float(np.linalg.norm(ends[1] - ends[0]))


STRIPE_BORDER_SQUARES = 0.5  # white border beyond the pattern searched for the stripe


def board_view(camera: CameraModel, corners_px: np.ndarray, board: BoardSpec) -> BoardView:
    """Both plane estimates (homography eq. 2-3, and solvePnP) for one detected board."""
    obj = board.object_points()
    R, T = pose_from_homography(camera, corners_px, obj)
    R_pnp, T_pnp = pose_pnp(camera, corners_px, obj, R, T)
    rms = (reprojection_rms_px(camera, R, T, corners_px, obj),
           reprojection_rms_px(camera, R_pnp, T_pnp, corners_px, obj))
    outline = board_outline_px(camera, R_pnp, T_pnp, board, margin_squares=1.0)
    stripe_outline = board_outline_px(camera, R_pnp, T_pnp, board,
                                      margin_squares=1.0 + STRIPE_BORDER_SQUARES)
    return BoardView(np.asarray(corners_px, float), plane_from_pose(R, T),
                     plane_from_pose(R_pnp, T_pnp), R, T, R_pnp, T_pnp, rms, outline,
                     stripe_outline_px=stripe_outline)


def _poly2(px: np.ndarray, scale: np.ndarray, centre: np.ndarray) -> np.ndarray:
    q = (np.asarray(px, float) - centre) / scale
    x, y = q[..., 0], q[..., 1]
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], axis=-1)


def board_blackness(image: np.ndarray, camera: CameraModel, view: BoardView, board: BoardSpec,
                    pad_px: int = 40) -> tuple[np.ndarray, tuple[int, int], float]:
    """How black each pixel of a board is in the bright image: 0 white .. 1 black.

    The image is sampled at the centres of all squares (pose from PnP); the
    darker parity is black. Smooth white and black level fields (quadratic
    in the image, robustly fitted) turn the image into
    ``(W - I) / (W - B)``, clipped to [0, 1], over the outline's bounding
    box plus ``pad_px``. The edges keep the image's own blur, which is also
    the blur the stripe image has. Returns (crop, (x0, y0), black/white ratio).
    """
    img = np.asarray(image)
    H, W = img.shape[:2]
    cols, rows = board.inner_corners
    sq = board.square_mm
    ii, jj = np.meshgrid(np.arange(-1, cols), np.arange(-1, rows))
    uv = np.column_stack([(ii.ravel() + 0.5) * sq, (jj.ravel() + 0.5) * sq])
    P = np.column_stack([uv, np.zeros(len(uv))]) @ view.R_pnp.T + view.T_pnp
    c = project_points(camera, P)
    parity = ((ii + jj).ravel() % 2).astype(bool)
    inside = (c[:, 0] >= 2) & (c[:, 0] < W - 2) & (c[:, 1] >= 2) & (c[:, 1] < H - 2)
    r = max(1, int(0.15 * _mean_square_px(view.corners_px, board)))
    vals = _box_means(img, np.round(c).astype(int), r)
    a, b = parity & inside, ~parity & inside
    if np.median(vals[a]) < np.median(vals[b]):
        a, b = b, a  # a = white
    centre = c[inside].mean(0)
    scale = np.maximum(np.ptp(c[inside], axis=0), 1.0)

    def fit(sel: np.ndarray) -> np.ndarray:
        A, y = _poly2(c[sel], scale, centre), vals[sel]
        keep = np.ones(len(y), bool)
        for _ in range(3):
            coef, *_ = np.linalg.lstsq(A[keep], y[keep], rcond=None)
            res = y - A @ coef
            s = MAD_TO_SIGMA * np.median(np.abs(res[keep])) + 1e-6
            keep = np.abs(res) <= 3.5 * s
        return coef

    cw, cb = fit(a), fit(b)
    xs, ys = view.outline_px[:, 0], view.outline_px[:, 1]
    x0, y0 = int(max(np.floor(xs.min()) - pad_px, 0)), int(max(np.floor(ys.min()) - pad_px, 0))
    x1, y1 = int(min(np.ceil(xs.max()) + pad_px + 1, W)), int(min(np.ceil(ys.max()) + pad_px + 1, H))
    # the two quadratic level fields on the crop's grid (separable: no (h, w, 6) design matrix)
    qx = ((np.arange(x0, x1) - centre[0]) / scale[0])[None, :]
    qy = ((np.arange(y0, y1) - centre[1]) / scale[1])[:, None]

    def field(cf: np.ndarray) -> np.ndarray:
        return (cf[0] + cf[1] * qx + cf[3] * qx * qx) + qy * (cf[2] + cf[4] * qx) + cf[5] * qy * qy

    Wl, Bl = field(cw), field(cb)
    # (W - I) / max(W - B, 1e-3), clipped to [0, 1]; in place: the crop is ~1 million pixels
    span = np.maximum(np.subtract(Wl, Bl, out=Bl), 1e-3, out=Bl)
    blk = np.subtract(Wl, img[y0:y1, x0:x1].astype(np.float32), out=Wl)
    with np.errstate(invalid="ignore", divide="ignore"):
        np.divide(blk, span, out=blk)
    ratio = float(np.median(vals[b]) / max(np.median(vals[a]), 1e-6))
    blk = np.clip(np.nan_to_num(blk, copy=False), 0.0, 1.0, out=blk)
    return blk.astype(np.float32), (x0, y0), ratio


def _box_means(image: np.ndarray, at_px: np.ndarray, r: int) -> np.ndarray:
    """Mean of ``image`` over the (2r+1)^2 box around each pixel ``at_px`` (n, 2) (x, y;
    clipped into the image), as ``cv2.blur`` of the float image (edges reflected) gives it.
    Only the bounding box of the points plus ``r`` is blurred: a box mean reads nothing
    further, and the sums of integer grey levels are exact, so the values are the same."""
    H, W = image.shape[:2]
    x = at_px[:, 0].clip(0, W - 1)
    y = at_px[:, 1].clip(0, H - 1)
    x0, y0 = max(int(x.min()) - r, 0), max(int(y.min()) - r, 0)
    x1, y1 = min(int(x.max()) + r + 1, W), min(int(y.max()) + r + 1, H)
    crop = np.asarray(image[y0:y1, x0:x1], np.float32)
    return cv2.blur(crop, (2 * r + 1, 2 * r + 1))[y - y0, x - x0]


def _fill_board(gray: np.ndarray, outline_px: np.ndarray, grow_px: int) -> np.ndarray:
    """Paint a detected board's area with the local white so the detector cannot see it again."""
    mask = np.zeros(gray.shape, np.uint8)
    cv2.fillPoly(mask, [np.round(outline_px).astype(np.int32)], 255)
    if grow_px > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))
        mask = cv2.dilate(mask, k)
    inside = gray[mask > 0]
    white = np.percentile(inside, 90) if inside.size else 255
    out = gray.copy()
    out[mask > 0] = np.uint8(white)
    return out


def find_v_boards(image: np.ndarray, board: BoardSpec,
                  camera: CameraModel) -> tuple[BoardView, BoardView]:
    """Both chessboards of the V in one bright image, sorted left to right (section 1.2).

    Detect one board, paint its pattern area over with its own white, detect
    the second; each gets the homography plane (eqs. 2-3) and the solvePnP
    plane. The classic detector and ``CALIB_CB_EXHAUSTIVE`` are tried when the
    first attempt fails. Board 0 is the one whose corner centroid is further
    left in the image. The 180 deg corner-order ambiguity of a chessboard
    does not change its plane.

    Raises
    ------
    ValueError
        When fewer than two distinct boards are found (the caller names the file).
    """
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    views: list[BoardView] = []
    work = img
    for k in range(2):
        corners = detect_chessboard(work, board.pattern_size, downscale=0.5)
        if corners is None:
            corners = detect_chessboard(work, board.pattern_size, exhaustive=True)
        if corners is None:
            raise ValueError(f"found {k} of the 2 chessboards of the V "
                             f"({board.inner_corners[0]}x{board.inner_corners[1]} inner "
                             "corners); " + (_small_squares_hint(views[0], board) if views else "")
                             + "check v_board.inner_corners in dataset.json, lighting and focus")
        view = board_view(camera, sharpest_corners(work, corners, board, camera), board)
        if k == 0:
            # painted over so the detector finds the other board next (the fill grows by
            # a tenth of a square beyond the pattern's outline)
            side = _mean_square_px(view.corners_px, board)
            work = _fill_board(img, view.outline_px, grow_px=max(1, round(0.1 * side)))
        else:
            _check_distinct(views[0], view, board)
        views.append(view)
    views.sort(key=lambda v: v.centroid_px[0])
    out = []
    for v in views:
        blk, origin, ratio = board_blackness(img, camera, v, board)
        out.append(replace(v, blackness=blk, blackness_origin=origin, bright_ratio=ratio))
    return out[0], out[1]


def sharpest_corners(gray: np.ndarray, corners: np.ndarray, board: BoardSpec,
                     camera: CameraModel) -> np.ndarray:
    """Of :func:`lidarcal.corners.detect_chessboard`'s corners (``cv2.cornerSubPix``), the
    saddle points of the smoothed image (:func:`lidarcal.corners.saddle_corners`) and OpenCV's
    SB detector in its accuracy mode (:func:`lidarcal.corners.sb_accuracy_corners`), the set
    the board's pose fits best: the smaller ``cv2.solvePnP`` reprojection RMS with the camera
    (the same board and camera for all, so the RMS compares the corners' noise). SB's search
    (~0.25 s per board) is only run when the saddles do not beat the detector's corners.

    Measured against truth on board.png (true projections, rms px, boards 0 / 1;
    cornerSubPix, SB accuracy, saddles): bundled paper rig 0.082 / 0.060, 0.034 / 0.033,
    0.019 / 0.022; paper seed 11 0.042 / 0.038, 0.030 / 0.025, 0.017 / 0.014; wide seed 37
    0.071 / 0.057, 0.050 / 0.036, 0.039 / 0.028: the saddles were taken on every simulated
    board. On the bundled real TAPAS views the saddles fit the pose worse than the detector's
    corners on all seven (0.34 against 0.24 px on 00.png) and SB's were taken on two.

    The set kept is then refined by its point symmetry on the board plane
    (:func:`symmetric_refinement`, Datta, Kim, Kanade 2009; ``SYMMETRIC_REFINEMENT``) and the
    refined set taken when its PnP RMS is lower still. Measured (``scripts/symmetry_truth.py``)
    against the detector/SB choice on board.png of 11 simulated rigs (wide seeds 1, 37, 39, 5,
    7; paper 11, 12, 13 and the bundled rig; harsh 61, 62): corner RMS against truth 0.040 ->
    0.020 px on average (better on all 22 boards), the PnP normals with the true camera
    0.0043 -> 0.0029 deg; 0.04 s CPU per board.png on the bundled rig."""
    obj = board.object_points()

    def rms(c: np.ndarray) -> float:
        try:
            R, T = pose_pnp(camera, c, obj)
        except (ValueError, cv2.error):
            return np.inf
        return reprojection_rms_px(camera, R, T, c, obj)

    best, best_rms = corners, rms(corners)
    saddle = saddle_corners(gray, corners, board.pattern_size)
    saddle_rms = np.inf if saddle is None else rms(saddle)
    if saddle_rms < best_rms:
        best, best_rms = saddle, saddle_rms
    else:
        sb = sb_accuracy_corners(gray, corners, board.pattern_size)
        if sb is not None and rms(sb) < best_rms:
            best, best_rms = sb, rms(sb)
    if not SYMMETRIC_REFINEMENT:
        return best
    sym = symmetric_refinement(gray, best, board, camera)
    return sym if sym is not None and rms(sym) < best_rms else best


#: whether :func:`sharpest_corners` refines the corners it keeps by their point symmetry
SYMMETRIC_REFINEMENT = True


def symmetric_refinement(gray: np.ndarray, corners: np.ndarray, board: BoardSpec,
                         camera: CameraModel) -> np.ndarray | None:
    """``corners`` refined by their point symmetry on the board plane (Datta, Kim, Kanade
    2009, :func:`lidarcal.corner_symmetry.symmetric_corners`), sampled through the
    ``cv2.solvePnP`` pose of ``corners`` and the lens model. A corner whose window is not
    point-symmetric or that moves by a tenth of a square keeps its position; None (the
    caller keeps ``corners``) when the pose cannot be had or too many corners fail
    (:meth:`lidarcal.corner_symmetry.SymmetricCorners.checked`)."""
    c = np.asarray(corners, float).reshape(-1, 2)
    try:
        R, T = pose_pnp(camera, c, board.object_points())
    except (ValueError, cv2.error):
        return None
    return symmetric_corners(gray, camera, R, T, board, start_px=c).checked(c)


#: squares (px) below which the chessboard detector was seen to lose a board of the V: on
#: rendered wide rigs (``scripts/rig_sweep.py``) 8 px squares found both boards, 5 px one
SMALL_SQUARE_PX = 8.0


def _small_squares_hint(found: BoardView, board: BoardSpec) -> str:
    """What to do when the V's second board is lost and the first one's squares are small."""
    side = _mean_square_px(found.corners_px, board)
    if side >= SMALL_SQUARE_PX:
        return ""
    return (f"the board found has squares of only {side:.1f} px (the detector needs about "
            f"{SMALL_SQUARE_PX:.0f} px or more): move the camera nearer the V, use a longer "
            "lens or a board with bigger squares; else ")


#: squares (px) below which the board planes from board.png are weak: on rendered wide rigs
#: (``scripts/rig_sweep.py``, true errors) the solvePnP planes' normals were 0.005 deg off
#: with 45 px squares, 0.04 deg with 8 px and 0.04-0.1 deg with 6 px (the homography planes
#: of eqs. 2-3: 0.4-1 deg); the joint fit's centre error 1.5-57 mm (a 2-deg sweep)
WEAK_SQUARE_PX = 10.0


def small_square_warnings(boards: tuple[BoardView, BoardView], board: BoardSpec,
                          path) -> list[str]:
    """A warning naming ``path`` (board.png) when a board's squares are smaller than
    ``WEAK_SQUARE_PX`` in the image: its corners, so its plane (eqs. 1-3), are weak."""
    sides = [_mean_square_px(b.corners_px, board) for b in boards]
    if min(sides) >= WEAK_SQUARE_PX:
        return []
    return [(f"{path}: the V's squares are only {min(sides):.1f} px wide in the image (under "
            f"{WEAK_SQUARE_PX:.0f} px the board planes are weak: on rendered rigs their normals "
            "were 10-20 times further off than with 45 px squares); move the camera nearer the "
            "V, use a longer lens or a board with bigger squares")]


def _mean_square_px(corners: np.ndarray, board: BoardSpec) -> float:
    g = corners.reshape(board.inner_corners[1], board.inner_corners[0], 2)
    return float(np.mean(np.linalg.norm(np.diff(g, axis=1), axis=2)))


def _check_distinct(a: BoardView, b: BoardView, board: BoardSpec) -> None:
    """The second detection must be another board, not the first found again."""
    side = _mean_square_px(a.corners_px, board)
    inside = cv2.pointPolygonTest(a.outline_px.astype(np.float32).reshape(-1, 1, 2),
                                  tuple(float(v) for v in b.centroid_px), False)
    if np.linalg.norm(a.centroid_px - b.centroid_px) < 2 * side or inside > 0:
        raise ValueError("the second chessboard found is the first one again; "
                         "the two boards of the V must both be fully visible")


def find_boards(ds: Dataset, camera: CameraModel, image: np.ndarray | None = None
                ) -> tuple[BoardView, BoardView]:
    """Both chessboards of the V in ``board.png`` (section 1.2); ``image``: that file
    already decoded (:func:`lidarcal.io.dataset.read_image`), else it is read here.
    A board not found is a :class:`~lidarcal.io.dataset.DatasetError` naming ``board.png``."""
    img = read_image(ds.board_image, camera.image_size) if image is None else image
    try:
        return find_v_boards(img, ds.v_board, camera)
    except ValueError as e:
        raise DatasetError(ds.board_image, f"{e}; both boards must be fully "
                                           "in view, nothing in front of them, without "
                                           "glare") from None
