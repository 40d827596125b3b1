"""The classic one-board calibration of a 2D LiDAR against a camera (Zhang & Pless 2004).

Each view shows one flat chessboard to the camera (its plane ``n_i . X = d_i``
in the camera frame, from the corners) and to the LiDAR (a line of returns
in the scan plane). A LiDAR point ``p = (x, y, 0)`` on the board satisfies
the point-on-plane constraint (Zhang & Pless, eq. 5)::

    n_i . (R p + T) = d_i,   i.e.   n_i^T H (x, y, 1)^T = d_i,   H = [r1 r2 T]

which is linear in the nine entries of ``H``. Steps:

1. board plane per view with its 3x3 covariance from the corner noise
   (:func:`board_plane`, ``cv2.solvePnP`` + the projection Jacobian; of the package's
   corners, or OpenCV's accuracy-mode corners where they fit the board clearly better:
   :func:`choose_corner_set`);
2. straight segments of each scan (:func:`lidarcal.scan_segments.line_segments`, the V
   pipeline's segmenter, with the noise about lines of :func:`local_line_noise`: quantised
   and repeated ranges allowed for; a segment longer than the board replaced by its board piece
   and every gated run cut at the board's edges, :mod:`lidarcal.planes_wall`, its margins
   measured in the photos, :mod:`lidarcal.board_margin`) and the board segment chosen by
   consensus: rigid hypotheses from the linear solution of five random views, every view's
   candidates scored against the board plane they predict (:func:`select_board_segments`);
3. linear initialisation (:func:`linear_extrinsics`: ``H`` by least squares,
   ``R`` the nearest rotation to ``[h1 h2 h1 x h2]``, ``T`` by least squares with
   ``R`` fixed);
4. the robust maximum-likelihood refinement (:func:`refine_extrinsics`): point-to-plane
   residuals over the range noise projected on the plane normal, each board plane a
   nuisance parameter with its prior from the corners, ``least_squares`` with a
   ``soft_l1`` loss; then every return within 4 sigma of the predicted board plane
   (the board's width is not needed) and refine again;
5. the covariance and its eigen-analysis (:mod:`lidarcal.degeneracy`): a
   direction the views do not determine (e.g. every board vertical and the
   scan plane horizontal: the height along the boards and the tilt of the
   scan plane) is named in the warnings and its sigma is ``null``; the sigmas
   are scaled by the views' disagreement beyond the noise (view-level chi-square).

Convention: ``X_cam = R X_lidar + T``, camera frame OpenCV's, mm; angles in
degrees at the edges, radians inside.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from .board_margin import apply_board_margins, no_margins_record
from .degeneracy import (
    AMBIGUITY_CHI2,
    MIN_VIEWS,
    PARALLEL_LIMIT,
    UNDETERMINED_MM,
    Uncertainty,
    describe_ambiguity,
    describe_degeneracy,
    pose_difference,
    pose_uncertainty,
    unobservable_directions,
    view_level_chi2,
)
from .geometry import Plane, plane_basis
from .io.dataset import BoardSpec, CameraModel, DatasetError, write_json_atomic
from .planes_checks import FLAT_STEP, direction_words, flat_valley, other_minima
from .planes_linear import linear_extrinsics, select_board_segments
from .planes_wall import MIN_STEP_SIGMAS, cut_candidates, cut_run, pattern_extent
from .scan import scan_points
from .scan_segments import MIN_POINTS, LineSegment, line_segments, local_line_noise

EXTRINSICS_FORMAT = "lidarcal-extrinsics/1"
#: Views needed to cross-check the board segments (the linear H has nine unknowns, each view
#: gives two constraints).
MIN_VIEWS_CONSENSUS = 5


# ---------------------------------------------------------------------------
# 1. board planes with their uncertainty

@dataclass(frozen=True)
class BoardPlane:
    """One view's board plane ``n . X = d`` (camera frame, mm) and its uncertainty.

    ``cov`` (3, 3) is the covariance of ``(b1 . dn, b2 . dn, dd)``, with ``basis`` =
    ``[b1 b2]`` (3, 2) spanning the plane's tangent directions: the first-order
    propagation of the corner noise (``sigma_px``, from the reprojection residuals)
    through ``cv2.solvePnP``'s pose. ``R``, ``T`` map board coordinates (mm) into the
    camera frame (eq. 1); ``board`` is the pattern as found (either way round).
    """

    plane: Plane
    cov: np.ndarray
    basis: np.ndarray
    R: np.ndarray
    T: np.ndarray
    corners_px: np.ndarray
    sigma_px: float
    board: BoardSpec
    #: per board axis (u, v) how far beyond the pattern the board's edge may lie, from the margins
    #: measured in the photos (:mod:`lidarcal.board_margin`); None: the assumed margin
    grow_mm: np.ndarray | None = None


def find_board(image: np.ndarray, board: BoardSpec) -> list[tuple[np.ndarray, BoardSpec]]:
    """Chessboard corner sets (N, 2) with the pattern either way round (8x5 = 5x8): the
    package's finder (:func:`lidarcal.corners.detect_chessboard`) and OpenCV's
    ``findChessboardCornersSB`` in its accuracy mode (``CALIB_CB_ACCURACY``, no
    ``cornerSubPix``). On the real TAPAS photos, whose boards carry fiducial rings beside
    the pattern, the package's corners fit the board model with 0.17-0.32 px in five views
    and 0.68 / 1.03 px in the two the rings pull (the accuracy mode's: 0.17-0.50 px, 0.36 /
    0.34 px there);
    :func:`prepare_views` keeps, per view, :func:`choose_corner_set`'s. Empty if neither
    finds the board."""
    from .corners import _gray, detect_chessboard

    gray = _gray(image)
    c, r = board.inner_corners
    for size in ((c, r), (r, c)) if c != r else ((c, r),):
        found = []
        corners = detect_chessboard(gray, size)
        if corners is not None:
            found.append((corners, BoardSpec(size, board.square_mm)))
        ok, sb = cv2.findChessboardCornersSB(gray, size, flags=cv2.CALIB_CB_ACCURACY
                                             | cv2.CALIB_CB_EXHAUSTIVE)
        if ok and sb is not None:
            found.append((sb.reshape(-1, 2).astype(np.float64), BoardSpec(size, board.square_mm)))
        if found:
            return found
    return []


def board_plane(camera: CameraModel, corners_px: np.ndarray, board: BoardSpec) -> BoardPlane:
    """Board plane (eq. 3 of the paper: ``r3 . X = r3 . T``) with its covariance.

    The pose is ``cv2.solvePnP`` (iterative, the maximum-likelihood pose under
    i.i.d. corner noise) started from the homography pose; the corner noise
    ``sigma_px`` is the residual RMS with ``2N - 6`` degrees of freedom; the pose
    covariance is ``sigma_px^2 (J^T J)^-1`` with ``J`` from ``cv2.projectPoints``,
    propagated to the plane parameters by their Jacobian.
    """
    from .board import pose_from_homography, pose_pnp

    obj = board.object_points()
    R0, T0 = pose_from_homography(camera, corners_px, obj)
    R, T = pose_pnp(camera, corners_px, obj, R0, T0)
    rvec = cv2.Rodrigues(R)[0]
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    proj, jac = cv2.projectPoints(obj, rvec, T.reshape(3, 1), K, dist)
    res = proj.reshape(-1, 2) - corners_px
    n_obs = res.size
    sigma_px = float(np.sqrt(np.sum(res ** 2) / max(n_obs - 6, 1)))
    J = jac[:, :6]
    cov_pose = sigma_px ** 2 * np.linalg.inv(J.T @ J)
    plane = Plane.from_normal_point(R[:, 2], T)
    basis = plane_basis(plane.normal).T  # (3, 2)

    def params(x: np.ndarray) -> np.ndarray:
        Rx = cv2.Rodrigues(x[:3])[0]
        n = Rx[:, 2]
        return np.array([basis[:, 0] @ n, basis[:, 1] @ n, n @ x[3:]])

    x0 = np.concatenate([rvec.ravel(), T])
    G = np.empty((3, 6))
    for k in range(6):
        h = 1e-6 if k < 3 else 1e-3
        e = np.zeros(6)
        e[k] = h
        G[:, k] = (params(x0 + e) - params(x0 - e)) / (2 * h)
    return BoardPlane(plane, G @ cov_pose @ G.T, basis, R, T, np.asarray(corners_px, float),
                      sigma_px, board)


#: OpenCV's accuracy-mode corners replace the package's only when they fit the board better by
#: more than this (px RMS). Their smooth corner model fits clean boards with a lower residual
#: (0.02-0.06 px against 0.02-0.08 px on the rendered one-board views, differences <= 0.04 px)
#: but carries pattern-scale errors the residual cannot show (a common scale moves the pose, not
#: the residuals): 0.2-0.9 per mille, up to 5 mm of plane distance at 1.1-2 m, Mahalanobis
#: distances up to 8 from the plane's covariance, mostly of one sign, so they do not average
#: out over the views.
#: Where the package's corners fail (TAPAS's fiducial rings: 0.86 and 1.04 px against 0.35 px)
#: the difference is 0.5-0.7 px.
ACCURACY_MODE_GAIN_PX = 0.1


def choose_corner_set(fits: list[BoardPlane]) -> BoardPlane:
    """The board plane of the package's corners (``fits[0]``, ``cornerSubPix``-refined; the only
    set when one detector found the board), unless OpenCV's accuracy-mode set fits the board
    better by more than :data:`ACCURACY_MODE_GAIN_PX` (Zhang & Pless's plane, eq. 3, from the
    corners that are closer to the truth, not merely smoother)."""
    best = min(fits, key=lambda bp: bp.sigma_px)
    return best if best.sigma_px < fits[0].sigma_px - ACCURACY_MODE_GAIN_PX else fits[0]


# ---------------------------------------------------------------------------
# 4. gating and the robust maximum-likelihood refinement

def gate_board_points(angle_deg: np.ndarray, range_mm: np.ndarray, plane: Plane, R: np.ndarray,
                      T: np.ndarray, tol_mm: float, seed_beams: np.ndarray | None = None,
                      trim: int = 1) -> np.ndarray:
    """Beam indices of the board's returns: the contiguous run (gaps of one beam allowed)
    of returns within ``tol_mm`` of the board plane predicted by ``(R, T)`` that holds
    the most ``seed_beams`` (or the longest run); ``trim`` beams are dropped at each
    end (mixed returns on the board's edges). The board's width is not needed."""
    p = scan_points(angle_deg, range_mm)
    X = np.column_stack([p, np.zeros(len(p))]) @ R.T + T
    with np.errstate(invalid="ignore"):
        near = np.abs(plane.distance(X)) <= tol_mm
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return idx
    cuts = np.flatnonzero(np.diff(idx) > 2) + 1
    runs = np.split(idx, cuts)
    if seed_beams is not None and len(seed_beams):
        score = [np.intersect1d(rn, seed_beams).size for rn in runs]
    else:
        score = [len(rn) for rn in runs]
    run = runs[int(np.argmax(score))]
    if len(run) > 2 * trim + MIN_POINTS:
        run = run[trim:len(run) - trim]
    return run


@dataclass
class ViewData:
    """One view as the refinement uses it: board plane, the board's returns, noise."""

    name: str
    board: BoardPlane | None
    angle_deg: np.ndarray
    range_mm: np.ndarray
    sigma_range_mm: float
    beams: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    candidates: list[LineSegment] = field(default_factory=list)
    note: str = ""
    beside: float = 0.0  # share of the gated returns beyond the board, no step found (_gate_view)

    @property
    def points_mm(self) -> np.ndarray:
        return scan_points(self.angle_deg[self.beams], self.range_mm[self.beams])


def _pose(x: np.ndarray, R0: np.ndarray, T0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return Rotation.from_rotvec(x[:3]).as_matrix() @ R0, T0 + x[3:6]


def _point_sigma(v: ViewData, R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Range noise projected on the plane normal: ``sigma_r |n . R u|`` (u the beam direction),
    floored at a quarter of ``sigma_r`` (grazing beams)."""
    u = p / np.linalg.norm(p, axis=1, keepdims=True)
    c = np.abs((np.column_stack([u, np.zeros(len(u))]) @ R.T) @ v.board.plane.normal)
    return v.sigma_range_mm * np.maximum(c, 0.25)


@dataclass(frozen=True)
class Refined:
    """Outcome of :func:`refine_extrinsics`: pose, the 6x6 information of ``(omega, T)``
    (rotation vector rad, left-multiplied, camera frame; T mm) after marginalising the
    board planes, and the noise scale (sqrt of the robust reduced chi-square)."""

    R: np.ndarray
    T: np.ndarray
    information: np.ndarray
    noise_scale: float
    cost: float
    converged: bool = True  # False: ``max_nfev`` ran out before a tolerance was met


def _quadratic_under(r: np.ndarray, loss: str, f_scale: float) -> np.ndarray:
    """Prior residuals that stay Gaussian under ``least_squares``' robust loss (which applies to
    every residual): for ``soft_l1``, ``r sqrt(1 + r^2 / (4 f^2))`` has ``f^2 rho(r'^2/f^2) = r^2``
    exactly. Without this a robust loss would cap the board-plane priors and let the planes
    drift to fit the scan."""
    if loss == "linear":
        return r
    if loss != "soft_l1":
        raise ValueError(f"loss must be 'soft_l1' or 'linear', got {loss!r}")
    return r * np.sqrt(1.0 + r * r / (4.0 * f_scale ** 2))


#: Weak priors on the pose's change from its start (rad, mm): they only keep directions the
#: views cannot see bounded; such directions come out with a 1-sigma near these values, far
#: above :data:`UNDETERMINED_MM`, and are reported as undetermined.
WEAK_PRIOR = (0.1, 500.0)


def refine_extrinsics(views: list[ViewData], R0: np.ndarray, T0: np.ndarray,
                      loss: str = "soft_l1", f_scale: float = 3.0,
                      anchor: tuple[np.ndarray, np.ndarray] | None = None,
                      fixed: list[np.ndarray] = (), lever_mm: float = 1000.0,
                      max_nfev: int | None = None) -> Refined:
    """Robust maximum likelihood over the pose and every board plane (Zhang & Pless's
    non-linear step, with the camera's plane noise): residuals
    ``(n_i' . (R p + T) - d_i') / sigma_k`` for every return (``sigma_k`` from
    :func:`_point_sigma`; robust ``loss``) and the Gaussian prior ``L_i^-1 delta_i`` (kept
    quadratic, :func:`_quadratic_under`) of each board plane's
    perturbation ``delta_i = (b1 . dn, b2 . dn, dd)`` (``L_i L_i^T = cov_i``);
    ``least_squares`` with ``loss`` (scale ``f_scale`` sigmas). The information of the
    pose is ``J^T J`` with the planes marginalised (Schur complement). A weak prior
    (:data:`WEAK_PRIOR`) ties the pose to ``anchor`` (default: the start), so directions the
    views do not see stay there instead of drifting with the noise. ``fixed`` pose directions
    (6-vectors of ``(omega, dT)``, e.g. :func:`unobservable_directions`) are held at the start:
    the pose moves only in their complement (orthogonal with rotations scaled by
    ``lever_mm``), and the returned information is zero along them. ``max_nfev`` caps the
    residual evaluations (``Refined.converged`` says whether a tolerance was met first)."""
    S = np.diag([lever_mm] * 3 + [1.0] * 3)
    if len(fixed):
        Q, _ = np.linalg.qr(np.array([S @ f for f in fixed]).T)
        U, _, _ = np.linalg.svd(np.eye(6) - Q @ Q.T)
        Bc = U[:, :6 - Q.shape[1]]
    else:
        Bc = np.eye(6)
    kp = Bc.shape[1]
    Si = np.linalg.inv(S)

    def pose6(x: np.ndarray) -> np.ndarray:
        return Si @ (Bc @ x[:kp])

    used = [v for v in views if v.board is not None and len(v.beams) >= MIN_POINTS]
    pts = [v.points_mm for v in used]
    sig = [_point_sigma(v, R0, p) for v, p in zip(used, pts)]
    # per view: the inverse Cholesky factor of its plane's covariance (the prior's whitening)
    chol_inv = [np.linalg.inv(np.linalg.cholesky(v.board.cov + 1e-12 * np.eye(3))) for v in used]
    normals = [v.board.plane.normal for v in used]
    bases = [v.board.basis for v in used]
    ds = [v.board.plane.d for v in used]
    m = len(used)
    Ra, Ta = (R0, T0) if anchor is None else anchor
    start_from_anchor = Rotation.from_matrix(R0 @ Ra.T)  # R Ra^T = Rot(omega) (R0 Ra^T)
    prior_sd = np.repeat(WEAK_PRIOR, 3)

    def residuals(x: np.ndarray) -> np.ndarray:
        y = pose6(x)
        turn = Rotation.from_rotvec(y[:3])
        R, T = turn.as_matrix() @ R0, T0 + y[3:6]
        R2 = R[:, :2]  # scan points have z = 0 in the LiDAR frame
        out = []
        for k in range(m):
            dlt = x[kp + 3 * k: kp + 3 + 3 * k]
            n = normals[k] + bases[k] @ dlt[:2]
            nn = np.linalg.norm(n)
            n = n / nn
            d = (ds[k] + dlt[2]) / nn
            # n . (R p + T) - d for every return p (eq. of the board plane in the camera frame)
            out.append((pts[k] @ (R2.T @ n) + (T @ n - d)) / sig[k])
            out.append(_quadratic_under(chol_inv[k] @ dlt, loss, f_scale))
        dev = np.concatenate([(turn * start_from_anchor).as_rotvec(), T - Ta])
        out.append(_quadratic_under(dev / prior_sd, loss, f_scale))
        return np.concatenate(out)

    if m == 0:
        raise ValueError("no view with board returns to refine on")
    x0 = np.zeros(kp + 3 * m)
    res = least_squares(residuals, x0, loss=loss, f_scale=f_scale, x_scale="jac", method="trf",
                        tr_solver="lsmr", max_nfev=max_nfev)
    R, T = _pose(pose6(res.x), R0, T0)
    J = res.jac
    info = J.T @ J
    A, B, C = info[:kp, :kp], info[:kp, kp:], info[kp:, kp:]
    marg_z = A - B @ np.linalg.solve(C, B.T)
    marg = S @ Bc @ marg_z @ Bc.T @ S  # information of (omega, T): y = S x = Bc z
    n_obs = sum(len(p) for p in pts)
    dof = max(n_obs - 6, 1)
    scale = float(np.sqrt(max(1.0, 2.0 * res.cost / dof)))
    return Refined(R, T, 0.5 * (marg + marg.T), scale, float(res.cost), bool(res.status > 0))


# ---------------------------------------------------------------------------
# the whole calibration

@dataclass
class PlanesResult:
    """Outcome of :func:`calibrate_planes`."""

    R: np.ndarray
    T: np.ndarray
    views: list[ViewData]
    used: list[bool]
    rms_mm: list[float | None]
    uncertainty: Uncertainty
    refined: Refined
    warnings: list[str]
    R_linear: np.ndarray
    T_linear: np.ndarray
    #: the board's margins measured in the photos (:meth:`lidarcal.board_margin.BoardMargins.record`;
    #: None: not measured, the assumed margin)
    board_margins: dict | None = None

    @property
    def total_rms_mm(self) -> float:
        res = [plane_residuals_mm(v, self.R, self.T) for v, u in zip(self.views, self.used) if u]
        allr = np.concatenate(res) if res else np.zeros(0)
        return float(np.sqrt(np.mean(allr ** 2))) if len(allr) else float("nan")

    def to_dict(self) -> dict:
        """The ``lidarcal-extrinsics/1`` document (see :func:`write_extrinsics`)."""
        unc = self.uncertainty
        return {
            "format": EXTRINSICS_FORMAT,
            "R": self.R.tolist(),
            "T_mm": self.T.tolist(),
            "sigma": {"rotation_deg": unc.rotation_deg, "translation_mm": unc.translation_mm},
            "views": [{"name": v.name, "used": bool(u), "points": len(v.beams) if u else 0,
                       "rms_mm": None if r is None else float(r),
                       "range_noise_mm": float(v.sigma_range_mm),
                       "board_plane": None if v.board is None else v.board.plane.to_dict(),
                       "corner_noise_px": None if v.board is None else v.board.sigma_px,
                       "beams": [int(b) for b in v.beams] if u else [],
                       **({"note": v.note} if v.note else {})}
                      for v, u, r in zip(self.views, self.used, self.rms_mm)],
            "rms_mm": self.total_rms_mm,
            "warnings": list(self.warnings),
            "covariance": {"parameters": ["rot_x_rad", "rot_y_rad", "rot_z_rad", "T_x_mm",
                                          "T_y_mm", "T_z_mm"],
                           "matrix": unc.covariance.tolist(),
                           "note": "rotation as a small rotation vector left-multiplying R, "
                                   "camera frame; undetermined directions excluded"},
            "undetermined": [{"kind": d.kind, "direction_cam": d.direction_cam.tolist(),
                              "sigma_mm": None if not np.isfinite(d.sigma_mm) else d.sigma_mm}
                             for d in unc.undetermined],
            "noise_scale": self.refined.noise_scale,
            "view_chi2": dict(zip(("chi2", "dof"), view_level_chi2(
                [v for v, u in zip(self.views, self.used) if u], self.R, self.T))),
            "linear": {"R": self.R_linear.tolist(), "T_mm": self.T_linear.tolist()},
            "board_margins": self.board_margins,
        }


def _board_extent(bp: BoardPlane) -> tuple:
    """``(R_b, T_b, lo, hi, grow)`` for the consensus (:func:`select_board_segments`): the printed
    pattern's corners in the board frame (one square beyond the outer inner corners) and, for
    the board's unknown margin, half the pattern's shorter side (the real TAPAS boards reach
    1.6 squares beyond their pattern)."""
    return bp.R, bp.T, *pattern_extent(bp.board)  # the consensus only picks the segment


def _share_off_board(view: ViewData, R: np.ndarray, T: np.ndarray) -> float:
    """Share of a view's board returns that ``(R, T)`` maps outside the board's printed pattern
    grown by the margin of :func:`_board_extent` (in the board frame of eq. 1)."""
    Rb, Tb, lo, hi, grow = _board_extent(view.board)
    p = view.points_mm
    u = (np.column_stack([p, np.zeros(len(p))]) @ R.T + T - Tb) @ Rb[:, :2]
    out = np.any((u < lo - grow) | (u > hi + grow), axis=1)
    return float(np.mean(out)) if len(out) else 0.0


def _lies_along_plane(view: ViewData, R: np.ndarray, T: np.ndarray, sigma_mm: float) -> bool:
    """A late view's gated returns are its board only if they run along the predicted plane:
    RMS within ``3 sigma + 1 mm`` and no trend across the run beyond ``3 sigma`` (a scan line
    that merely crosses the predicted plane leaves a short run with a steep trend)."""
    r = plane_residuals_mm(view, R, T)
    if np.sqrt(np.mean(r ** 2)) > 3.0 * sigma_mm + 1.0:
        return False
    p = view.points_mm
    s = (p - p.mean(0)) @ (p[-1] - p[0]) / max(np.linalg.norm(p[-1] - p[0]), 1e-9)
    b = np.polyfit(s, r, 1)[0] if np.ptp(s) > 0 else 0.0
    return abs(b) * np.ptp(s) <= 3.0 * sigma_mm


def _beams_on_pattern(v: ViewData, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Beams whose returns, mapped by ``(R, T)``, fall within the board's printed pattern (board
    frame of eq. 1, :func:`lidarcal.planes_wall.pattern_extent`) whatever their distance from
    its plane."""
    with np.errstate(invalid="ignore"):
        p = scan_points(v.angle_deg, v.range_mm)
        u = (np.column_stack([p, np.zeros(len(p))]) @ R.T + T - v.board.T) @ v.board.R[:, :2]
        lo, hi, _ = pattern_extent(v.board.board)
        return np.flatnonzero(np.all((u >= lo) & (u <= hi), axis=1))


def _gate_view(v: ViewData, R: np.ndarray, T: np.ndarray, tol_mm: float,
               seed_beams: np.ndarray | None = None) -> np.ndarray:
    """:func:`gate_board_points` of a view, then the board cut out of a wall in line with it
    (:func:`lidarcal.planes_wall.cut_run`: the edges between the printed pattern and its grown
    extent, mapped by ``(R, T)`` and the camera's board pose). The run gated is the one with
    most returns on the printed pattern (else the one with most ``seed_beams``). The cut is sought on the run gated
    at three times ``tol_mm`` (a wall's returns gated at ``tol_mm`` are those its noise pulls
    nearer: their step would be biased low); where it is significant, the board's returns are
    those between the steps at that wider gate (a patch of the board read a few mm off, a dark
    square, no longer breaks the run); where it is not and the board's margin was measured
    (``BoardPlane.grow_mm``), those between the edges found within ``tol_mm`` of the plane. Sets
    ``v.beside``: the share of the gated run beyond the board that no significant step separates
    from it (then dropped)."""
    inside = _beams_on_pattern(v, R, T)
    if len(inside) >= MIN_POINTS:  # the run the camera's board is on (not a wall piece beside it)
        seed_beams = inside
    run = gate_board_points(v.angle_deg, v.range_mm, v.board.plane, R, T, tol_mm, seed_beams)
    v.beside = 0.0
    if len(run) < MIN_POINTS:
        return run
    wide = gate_board_points(v.angle_deg, v.range_mm, v.board.plane, R, T, 3.0 * tol_mm, run)
    p = scan_points(v.angle_deg[wide], v.range_mm[wide])
    X = np.column_stack([p, np.zeros(len(p))]) @ R.T + T
    u = (X - v.board.T) @ v.board.R[:, :2]
    i, j, loose, cut = cut_run(p, u, v.board.board, MIN_POINTS, v.board.grow_mm)
    if (i, j) == (0, len(wide)):
        return run
    if cut is not None and cut.significant:  # the board between the steps, at the wide gate
        v.beside = loose
        if j - i > 2 + MIN_POINTS:
            i, j = i + (i > 0), j - (j < len(wide))  # mixed returns at a cut edge
        return wide[i:j]
    keep = run[(run >= wide[i]) & (run <= wide[j - 1])]
    if v.board.grow_mm is not None:
        # the board's measured extent bounds its returns, so they need not be one run at
        # ``tol_mm``: every return between the edges within ``tol_mm`` of the plane is the board's
        # (two adjacent returns a few mm off at a black-white edge, with noise beyond the gate,
        # split TAPAS view 03's run and left out 18 % of its board, scripts/margin_beams.py)
        keep = wide[i:j][np.abs(v.board.plane.distance(X[i:j])) <= tol_mm]
    # those dropped beyond a measured margin are surely not the board (cut_run's share in doubt)
    v.beside = loose if v.board.grow_mm is not None else 1.0 - len(keep) / len(run)
    return keep


def plane_residuals_mm(view: ViewData, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Signed distances (mm) of a view's board returns, mapped by ``(R, T)``, to the board
    plane measured by the camera."""
    p = view.points_mm
    X = np.column_stack([p, np.zeros(len(p))]) @ R.T + T
    return view.board.plane.distance(X)


def prepare_views(pairs, camera: CameraModel, board: BoardSpec, min_points: int = MIN_POINTS,
                  photos: list | None = None) -> list[ViewData]:
    """Board plane (with covariance) and candidate scan segments of every view pair; each view's
    photo (None where it could not be read) is appended to ``photos`` if given (for
    :func:`lidarcal.board_margin.apply_board_margins`)."""
    from .io.dataset import read_image

    views = []
    for pr in pairs:
        try:
            img, problem = read_image(pr.image_path, camera.image_size), ""
        except DatasetError as e:  # a broken photo leaves its view out, like a missed board
            img, problem = None, e.problem.split("; ")[0]
        found = find_board(img, board) if img is not None else []
        if np.count_nonzero(np.isfinite(pr.range_mm)) < MIN_POINTS:
            raise DatasetError(pr.scan_path, f"fewer than {MIN_POINTS} returns; check the file")
        sig = local_line_noise(pr.angle_deg, pr.range_mm)
        v = ViewData(pr.name, None, pr.angle_deg, pr.range_mm, max(sig, 0.3))
        if problem:
            v.note = f"photo {pr.image_path.name}: {problem}"
        elif not found:
            v.note = (f"no {board.inner_corners[0]}x{board.inner_corners[1]} chessboard found in "
                      f"{pr.image_path.name}")
        else:  # the package's corners, or the accuracy-mode set where clearly better
            v.board = choose_corner_set([board_plane(camera, c, b) for c, b in found])
            v.candidates = line_segments(pr.angle_deg, pr.range_mm, range_noise_mm=sig,
                                         min_points=min_points, steps=True)[0]
        views.append(v)
        if photos is not None:
            photos.append(img)
    return views


def calibrate_planes(views: list[ViewData], seed: int = 0, limit_mm: float = UNDETERMINED_MM,
                     where: str | Path = ".") -> PlanesResult:
    """Zhang & Pless calibration of prepared views (see the module docstring for the steps).

    Raises :class:`DatasetError` (naming ``where``) when fewer than three views have a board
    and a board segment.
    """
    rng = np.random.default_rng(seed)
    warnings: list[str] = []
    with_board = [i for i, v in enumerate(views) if v.board is not None]
    for v in views:
        if v.board is None:
            warnings.append(f"{v.name}: {v.note}; view not used")
        elif v.board.sigma_px > 1.0:
            warnings.append(f"{v.name}: chessboard corners fit their board with {v.board.sigma_px:.2f}"
                            " px RMS (> 1 px); check the photo (blur, wrong pattern, bent board)")
    if len(with_board) < MIN_VIEWS:
        raise DatasetError(where, f"only {len(with_board)} view(s) show the chessboard; at least "
                                  f"{MIN_VIEWS} views with differently tilted boards are needed")
    sub = [views[i] for i in with_board]
    sv = np.linalg.svd(np.array([v.board.plane.normal for v in sub]), compute_uv=False)
    if sv[1] < PARALLEL_LIMIT * sv[0]:
        raise DatasetError(where, "every board is parallel to the others (normals within "
                                  f"{np.degrees(np.arcsin(min(1.0, sv[1] / sv[0]))):.1f} deg): "
                                  "the LiDAR's position in the boards' plane and its rotation about "
                                  "their normal are undetermined; tilt the board differently in "
                                  "some views")
    tot = [float(np.hypot(v.sigma_range_mm, np.sqrt(v.board.cov[2, 2]))) for v in sub]
    gates = [max(5.0 * t, 5.0) for t in tot]  # a rigid hypothesis from five right views: ~1-2 t
    cands = [cut_candidates(v.candidates, v.board.board, MIN_POINTS) for v in sub]
    if len(sub) >= MIN_VIEWS_CONSENSUS:
        choice = select_board_segments(cands, [v.board.plane for v in sub],
                                       gates, rng, boards=[_board_extent(v.board) for v in sub])
    else:  # too few views to cross-check: the segment with most returns in each scan
        choice = [max(range(len(c)), key=lambda k: len(c[k].beams)) if c else None
                  for c in cands]
        warnings.append(f"only {len(sub)} views: too few to cross-check which scan segment is the "
                        f"board (>= {MIN_VIEWS_CONSENSUS} needed), so the segment with most returns "
                        "was taken in each scan, and the linear start is underdetermined; check "
                        "the projections, and add views")
    chosen = [(v, cs[c]) for v, cs, c in zip(sub, cands, choice) if c is not None]
    if len(chosen) < MIN_VIEWS:
        raise DatasetError(where, f"the scans of only {len(chosen)} view(s) agree on a board "
                                  "segment; check that the scan plane crosses the board in every "
                                  "view (and the pattern size), or add views")
    R0, T0, _ = linear_extrinsics([s.points for _, s in chosen], [v.board.plane for v, _ in chosen])
    R, T = R0, T0
    seeds = {id(v): s.beams for v, s in chosen}
    for v in sub:
        v.beams = seeds.get(id(v), np.zeros(0, int))
    ref = refine_extrinsics(sub, R0, T0)  # on the consensus segments alone
    R, T = ref.R, ref.T
    for factor in (6.0, 4.0):  # gate on the predicted plane and refine; then once more, tighter
        for v, t in zip(sub, tot):
            if id(v) in seeds:  # seeded by the last gate's board (the consensus piece may be
                # a wall beside it, which the cut of the gated run has since left out)
                last = v.beams if len(v.beams) >= MIN_POINTS else seeds[id(v)]
                v.beams = _gate_view(v, R, T, factor * t, last)
        ref = refine_extrinsics(sub, R, T, anchor=(R0, T0))
        R, T = ref.R, ref.T
    # views outside the first consensus: gated on the final prediction, kept if they agree
    for v, t in zip(sub, tot):
        if id(v) not in seeds:
            v.beams = _gate_view(v, R, T, 4.0 * t)
            if len(v.beams) >= MIN_POINTS and not _lies_along_plane(v, R, T, t):
                v.beams = np.zeros(0, int)
    used, rms = [], []
    for v in views:
        ok = v.board is not None and len(v.beams) >= MIN_POINTS
        r = float(np.sqrt(np.mean(plane_residuals_mm(v, R, T) ** 2))) if ok else None
        used.append(ok)
        rms.append(r)
    if sum(used) < MIN_VIEWS:
        raise DatasetError(where, f"only {sum(used)} view(s) have board returns that agree with "
                                  "their board plane; check that the scan plane crosses the board "
                                  "in every view, or add views")
    if any(u and id(v) not in seeds for v, u in zip(views, used)):
        ref = refine_extrinsics([v for v, u in zip(views, used) if u], R, T,
                                anchor=(R0, T0))
        R, T = ref.R, ref.T
    for k, v in enumerate(views):
        if v.board is not None and not used[k]:
            warnings.append(f"{v.name}: no board segment in the scan agrees with the board "
                            "plane; view not used (does the scan plane cross the board?)")
        if used[k]:
            rms[k] = float(np.sqrt(np.mean(plane_residuals_mm(v, R, T) ** 2)))
            expect = float(np.hypot(v.sigma_range_mm, np.sqrt(v.board.cov[2, 2])))
            if rms[k] > 3.0 * expect + 1.0:
                warnings.append(f"{v.name}: board returns are {rms[k]:.1f} mm RMS from the board "
                                f"plane, > 3x the expected {expect:.1f} mm; check this view")
    for k, v in enumerate(views):
        if used[k]:
            off = _share_off_board(v, R, T)
            if off > 0.1:
                warnings.append(f"{v.name}: {100 * off:.0f} % of the returns taken as the board lie "
                                "beside the board the camera sees, on a surface in line with it: "
                                "the board cannot be told from the surface behind it (a range "
                                "step below the noise); hold the board farther from the wall")
            elif v.beside > 0.1:
                warnings.append(f"{v.name}: the scan runs on beside the board along a surface in "
                                f"line with it and no range step (>= {MIN_STEP_SIGMAS:g} noise "
                                "sigmas) marks the board's edge within its margin "
                                f"({100 * v.beside:.0f} % of the returns near the board in doubt; "
                                "those beyond the board's grown extent dropped): the board cannot "
                                "be told from the surface behind it; hold the board farther from "
                                "the wall")
    if ref.noise_scale > 3.0:
        warnings.append(f"residuals are {ref.noise_scale:.1f}x the noise model (range noise and "
                        "corner noise); the sigmas are scaled by it, but check for a bent board "
                        "or a time offset between photo and scan")
    pts = np.vstack([v.points_mm for v, u in zip(views, used) if u])
    lever = float(np.sqrt(np.mean(np.sum(pts ** 2, axis=1))))
    normals = np.array([v.board.plane.normal for v, u in zip(views, used) if u])
    held = unobservable_directions(normals, R, T)
    if held:  # refit with them held at the linear start (which leaves them at their minimum norm)
        ref = refine_extrinsics([v for v, u in zip(views, used) if u], R0, T0,
                                fixed=unobservable_directions(normals, R0, T0), lever_mm=lever)
        R, T = ref.R, ref.T
        warnings.append("the pose is given with its undetermined directions held at the linear "
                        "solution's minimum-norm values; the determined part is conditional on "
                        "them")
        for k, v in enumerate(views):
            if used[k]:
                rms[k] = float(np.sqrt(np.mean(plane_residuals_mm(v, R, T) ** 2)))
    uv = [v for v, u in zip(views, used) if u]
    second: list[np.ndarray] = []
    if not held:  # restarts: a better valley (adopted), or an equally good one far away (named)
        best, others, scale = other_minima(uv, ref, lever, refine_extrinsics)
        if best[1] is not ref:
            warnings.append(f"the refinement from the linear start stopped in a local minimum "
                            f"(robust chi-square {others[0][0]:.0f}); a restart found one with "
                            f"{best[0]:.0f}, used")
            gate = {id(v): t for v, t in zip(sub, tot)}
            for v in uv:
                v.beams = _gate_view(v, best[1].R, best[1].T, 4.0 * gate[id(v)], v.beams)
            ref = refine_extrinsics([v for v in uv if len(v.beams) >= MIN_POINTS], best[1].R,
                                    best[1].T)
            R, T = ref.R, ref.T
            for k, v in enumerate(views):
                if used[k]:
                    rms[k] = float(np.sqrt(np.mean(plane_residuals_mm(v, R, T) ** 2)))
        for c2, r in others:
            if c2 - best[0] < AMBIGUITY_CHI2 * scale ** 2:
                d6 = pose_difference(r.R, r.T, R, T)
                second.append(d6)
                warnings.append(describe_ambiguity(d6, best[0], c2, scale, lever))
    chi2, dof = view_level_chi2(uv, R, T)
    if dof > 0:
        birge = float(np.sqrt(max(1.0, chi2 / dof)))
        if birge > ref.noise_scale:
            ref = replace(ref, noise_scale=birge)
        if birge > 2.0:
            warnings.append(f"the views disagree with each other beyond the corner and range noise "
                            f"(view-level chi2 {chi2:.0f} for {dof} degrees of freedom); the sigmas "
                            f"are scaled by {birge:.1f} (likely causes: a bent board, a range bias "
                            "on the black squares, corner bias near markers)")
    else:
        warnings.append(f"{sum(used)} views fix the six pose parameters exactly: nothing checks "
                        "them; add views")
    if not held and not second:
        flat = flat_valley(uv, ref, lever, refine_extrinsics)
        if flat is not None:
            second.append(flat[0])
            warnings.append(f"the fit's valley is far flatter than its curvature says along "
                            f"{direction_words(flat[0])}: {FLAT_STEP:.0f} sigma along it the "
                            f"cost rises by {100 * flat[1]:.0f} % of the quadratic prediction, so "
                            "the pose is undetermined along it and its sigma is null there (boards "
                            "nearly perpendicular to the scan plane); add views with the board "
                            "tilted forwards/backwards against the scan plane")
    unc = pose_uncertainty(ref.information, ref.noise_scale, lever, limit_mm, held + second)
    warnings += describe_degeneracy([v.board.plane for v, u in zip(views, used) if u], unc)
    return PlanesResult(R, T, views, used, rms, unc, ref, warnings, R0, T0)


def run_planes(folder: str | Path, camera_json: str | Path, board: BoardSpec,
               seed: int = 0, limit_mm: float = UNDETERMINED_MM,
               assumed_margin: bool = False) -> PlanesResult:
    """``lidarcal planes``: read the view pairs and the camera, measure the board's margins in
    the photos (:func:`lidarcal.board_margin.apply_board_margins`; ``assumed_margin``: keep the
    assumed half of the pattern's shorter side, as before the measurement), calibrate.
    ``PlanesResult.board_margins`` is the ``extrinsics.json`` block (None with
    ``assumed_margin``)."""
    from .io.camera_files import read_camera_file
    from .io.pairs import read_view_pairs

    cpath = Path(camera_json)
    cam = read_camera_file(cpath)
    pairs = read_view_pairs(folder)
    photos: list = []
    views = prepare_views(pairs, cam, board, photos=photos)
    sizes = {v.note.partition(": image is ")[2].partition(",")[0] for v in views}
    if all(": image is " in v.note for v in views) and len(sizes) == 1:
        raise DatasetError(cpath, f"image_size is {cam.image_size[0]}x{cam.image_size[1]} but "
                                  f"every photo is {sizes.pop()}; give the camera.json of the "
                                  "camera that took them")
    record = None
    if not assumed_margin:
        m = apply_board_margins(views, photos, cam)
        n = sum(v.board is not None and im is not None for v, im in zip(views, photos))
        record = (no_margins_record(board, n) if m is None else
                  m.record(board.inner_corners, float(pattern_extent(board)[2]), n))
    res = calibrate_planes(views, seed=seed, limit_mm=limit_mm, where=folder)
    res.board_margins = record
    res.camera = cam  # type: ignore[attr-defined]
    res.pairs = pairs  # type: ignore[attr-defined]
    return res


def write_extrinsics(res: PlanesResult, out: str | Path, command: str | None = None) -> Path:
    """Write ``OUT/extrinsics.json`` atomically; returns its path."""
    out = Path(out)
    doc = res.to_dict()
    if command:
        doc["provenance"] = {"command": command}
    path = out / "extrinsics.json"
    write_json_atomic(path, doc)
    return path


def leave_one_out(views: list[ViewData], result: PlanesResult, seed: int = 0,
                  names: list[str] | None = None) -> list[dict]:
    """Calibrate on every used view but one; the held-out view's board returns (as chosen by
    the full fit) are scored against its camera plane: ``{"name", "rms_mm", "in_sample_rms_mm",
    "determined"}`` per held-out view (all used views, or those in ``names``); ``determined`` is
    False when the other views leave a pose direction undetermined (the prediction then tests
    nothing: the pose is free along that direction)."""
    import copy

    out = []
    used = [k for k, u in enumerate(result.used) if u]
    for k in used:
        if names is not None and views[k].name not in names:
            continue
        others = [copy.copy(views[j]) for j in used if j != k]
        for o in others:
            o.beams = np.zeros(0, int)
        r = calibrate_planes(others, seed=seed)
        held = views[k]
        res = plane_residuals_mm(held, r.R, r.T)
        out.append({"name": held.name, "rms_mm": float(np.sqrt(np.mean(res ** 2))),
                    "in_sample_rms_mm": result.rms_mm[k],
                    "determined": not r.uncertainty.undetermined})
    return out
