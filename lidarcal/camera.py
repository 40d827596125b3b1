"""Camera side of section 1.2: intrinsics, undistortion, rays, back-projection onto a plane.

The paper assumes the camera is calibrated beforehand and works on undistorted
images (section 1.2). We never resample images: pixel measurements (chessboard
corners, stripe centres) are undistorted as points, which is exact up to the
distortion model and keeps the sub-pixel information.

Convention: camera frame is OpenCV's (x right, y down, z forward); normalised
image coordinates are ``(x / z, y / z)``; lengths in mm.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from .corner_symmetry import symmetric_corners
from .corners import detect_chessboard, grid_prediction_scaled, sb_accuracy_corners
from .geometry import Plane, as_points
from .intrinsics_checks import (
    DUPLICATE_RMS_PX,
    MAX_OUTLIER_SHARE,
    MIN_VIEWS_CHECKED,
    board_tilts_deg,
    conditioning_problem,
    duplicate_views,
    held_out_views,
    jackknife_sigma,
    view_outlier,
)
from .io.dataset import BoardSpec, CameraModel, DatasetError, read_image
from .lens import distort_normalised, distortion_jacobian
from .zhang import MIN_VIEWS, heldout_rms_px, view_reprojection_sq
from .zhang import zhang_fit as _calibrate

#: photos with a longer side than this (px) are searched for the board reduced to it first
#: (:func:`detect_chessboard`'s ``downscale``; corners refined at full size): OpenCV's SB
#: detector takes 3-4 s per 4000 x 3000 photo and misses boards there
SEARCH_MAX_SIDE_PX = 2560
#: With fewer usable views than this, k3 is fixed at 0 (it is poorly determined by few views).
MIN_VIEWS_FOR_K3 = 8
#: Otherwise k3 is kept only if it lowers the CROSS-VALIDATED reprojection RMS (views the
#: fit has not seen, :func:`heldout_rms_px`) by more than 3 %: a narrow lens's views cannot
#: see k3, which then takes wild values that fit the views and extrapolate badly to the
#: image corners (k3 = 57 on real photos with the in-sample rule); a wide lens needs it.
K3_GAIN = 0.97


@dataclass(frozen=True)
class IntrinsicsResult:
    """Outcome of :func:`calibrate_intrinsics`.

    ``camera`` has ``source="intrinsics"`` and ``rms_px`` set (OpenCV's overall
    reprojection RMS). ``image_points[i]`` (N, 2) and ``object_points[i]``
    (N, 3, mm) are the correspondences of ``files_used[i]``; ``flags`` are the
    ``cv2.calibrateCamera`` flags used (so the result can be reproduced).
    """

    camera: CameraModel
    per_view_rms_px: np.ndarray  # shape (n_views,)
    files_used: tuple[Path, ...]
    files_rejected: tuple[Path, ...]
    image_points: tuple[np.ndarray, ...]
    object_points: tuple[np.ndarray, ...]
    flags: int
    rvecs: tuple[np.ndarray, ...] = ()
    tvecs: tuple[np.ndarray, ...] = ()
    #: cross-validated reprojection RMS (px) without / with k3 ({flags: rms}), when compared
    heldout_rms_px: dict | None = None
    #: further views of the same camera in the fit (:func:`add_views`): (name, rms_px)
    extra_views: tuple[tuple[str, float], ...] = ()
    #: what the quality checks found (each names the photo or the folder and what to do)
    warnings: tuple[str, ...] = ()
    #: the jackknife 1-sigma of (fx, fy, cx, cy), px (:func:`lidarcal.intrinsics_checks.jackknife_sigma`)
    sigma_px: tuple[float, ...] | None = None

    def to_dict(self) -> dict:
        """``camera.json``: dataset.json's ``camera`` keys (K, dist, image_size, source,
        rms_px) plus ``views`` (each view's file and reprojection RMS, px), ``rejected``
        (files left out: unreadable, board not found, a repeat, or fitting the others' camera
        badly), ``k3`` ("fixed" or "free"), ``tangential`` ("zero" or "free"),
        ``heldout_rms_px`` (cross-validated RMS of each lens model compared: ``k1k2``,
        ``k3_fixed`` (k1, k2, p1, p2) and ``k3_free``), ``sigma_px`` (the jackknife 1-sigma of
        fx, fy, cx, cy) and ``warnings``."""
        out = self.camera.to_dict()
        out["views"] = [{"name": p.name, "rms_px": float(r)}
                        for p, r in zip(self.files_used, self.per_view_rms_px)]
        out["rejected"] = [p.name for p in self.files_rejected]
        out["k3"] = "fixed" if self.flags & cv2.CALIB_FIX_K3 else "free"
        out["tangential"] = "zero" if self.flags & cv2.CALIB_ZERO_TANGENT_DIST else "free"
        if self.extra_views:
            out["extra_views"] = [{"name": n, "rms_px": float(r)} for n, r in self.extra_views]
        if self.heldout_rms_px is not None:
            names = {cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST: "k1k2",
                     cv2.CALIB_FIX_K3: "k3_fixed", 0: "k3_free"}
            out["heldout_rms_px"] = {names[f]: float(v) for f, v in self.heldout_rms_px.items()}
        if self.sigma_px is not None:
            out["sigma_px"] = dict(zip(("fx", "fy", "cx", "cy"), self.sigma_px))
        out["warnings"] = list(self.warnings)
        return out


def calibrate_intrinsics(paths: list[Path], board: BoardSpec,
                         image_size: tuple[int, int] | None = None,
                         fix_k3: bool | None = None, sharpest: bool = True,
                         symmetric: bool | None = None) -> IntrinsicsResult:
    """Zhang's calibration of K and (k1, k2, p1, p2, k3) from chessboard views.

    Each view's corners come from :func:`detect_chessboard`; views where the
    board is not found are listed in ``files_rejected``. ``cv2.calibrateCamera``
    then estimates the model. ``fix_k3``: True keeps k3 at 0, False frees it,
    None (default) chooses the lens model on held-out views (:func:`_lens_model`:
    p1, p2 and then k3 only when they lower the cross-validated reprojection RMS by more
    than 3 %, ``K3_GAIN``; k3 only with ``MIN_VIEWS_FOR_K3`` views). Under that model a
    repeated view and views that fit the other views' camera badly are left out, each
    with a warning naming it (:func:`_checked_views`). The jackknife 1-sigma of fx, fy, cx,
    cy (``sigma_px``) is measured by leaving groups of views out; a camera the photos do
    not determine is warned about, naming what to add, or refused beyond 5 %
    (:func:`lidarcal.intrinsics_checks.conditioning_problem`).
    ``sharpest`` (default): each view then keeps the corner set its pose fits best
    (:func:`_sharpest_views`) and the model is fitted again with the same flags.
    ``symmetric`` (None: ``SYMMETRIC_PHOTOS``): each view's corners are then refined by their
    point symmetry through its pose (:func:`_sharpest_views`) and the model fitted again.

    Raises
    ------
    DatasetError
        Naming the folder, when fewer than 3 views are usable or the camera is not
        determined by them, or naming a file whose size differs from ``image_size``.
    """
    paths = [Path(p) for p in paths]
    folder = paths[0].parent if paths else Path("intrinsics")
    obj = board.object_points().astype(np.float32)
    used, rejected, img_pts, obj_pts = [], [], [], []
    size = tuple(image_size) if image_size is not None else None
    unreadable: list[tuple[Path, str]] = []  # a broken photo is left out (warned), not fatal
    found: list[tuple[Path, tuple[int, int], np.ndarray | None]] = []
    for p in paths:
        try:
            img = read_image(p, size)
        except DatasetError as e:
            unreadable.append((p, e.problem.split("; ")[0]))
            continue
        down = min(1.0, SEARCH_MAX_SIDE_PX / max(img.shape[:2]))  # large photos: reduced first
        found.append((p, (img.shape[1], img.shape[0]),
                      detect_chessboard(img, board.pattern_size, downscale=down)))
    if size is None and found:  # the photos' own size: that of most of them
        counts = Counter(s for _, s, _ in found)
        size, n = counts.most_common(1)[0]
        if 2 * n <= len(found) and len(counts) > 1:
            raise DatasetError(folder, "photos of " + ", ".join(f"{w}x{h} ({k})" for (w, h), k in
                                                               counts.most_common())
                               + " pixels, none the size of most; give one camera's photos, "
                                 "at its full resolution")
    for p, s, corners in found:
        if s != size:
            unreadable.append((p, f"image is {s[0]}x{s[1]}, the other photos {size[0]}x{size[1]}"))
        elif corners is None:
            rejected.append(p)
        else:
            used.append(p)
            img_pts.append(corners)
            obj_pts.append(obj.astype(np.float64))
    rejected = sorted(rejected + [p for p, _ in unreadable])
    notes = tuple(f"{p}: {problem}; view not used" for p, problem in unreadable)
    notes += tuple(f"{p}: the {board.inner_corners[0]}x{board.inner_corners[1]} chessboard was "
                   "not found (all its inner corners must be in the photo, in focus and not "
                   "seen too obliquely); view not used"
                   for p in rejected if p not in {q for q, _ in unreadable})
    if len(used) < MIN_VIEWS:
        raise DatasetError(folder, f"the {board.inner_corners[0]}x{board.inner_corners[1]} "
                                   f"chessboard was found in {len(used)} of {len(paths)} view(s), "
                                   f"need at least {MIN_VIEWS}"
                                   + (f" ({len(unreadable)} cannot be used, e.g. "
                                      f"{unreadable[0][0].name}: {unreadable[0][1]})"
                                      if unreadable else "")
                                   + "; add views or fix the board's pattern "
                                     "('intrinsics_board' in dataset.json, --pattern)")
    # the lens model on all views, the views checked under it, and the model chosen again
    # when views were left out (a wide lens's corner views fit a k3-fixed model badly)
    flags, heldout = _lens_model(img_pts, obj_pts, size, fix_k3)
    used, img_pts, obj_pts, left_out, folder_notes = _checked_views(used, img_pts, obj_pts,
                                                                    size, board, folder, flags)
    rejected = sorted(rejected + [p for p, _ in left_out])
    notes += tuple(w for _, w in left_out) + tuple(folder_notes)
    if left_out:
        flags, heldout = _lens_model(img_pts, obj_pts, size, fix_k3)
    res = _calibrate(img_pts, obj_pts, size, flags)
    if symmetric is None:
        symmetric = SYMMETRIC_PHOTOS
    if sharpest or symmetric:
        img_pts, n_changed = _sharpest_views(used, img_pts, obj_pts, res, board, size,
                                             sharpest, symmetric)
        if n_changed:
            res = _calibrate(img_pts, obj_pts, size, flags)
    camera, per_view, rvecs, tvecs = res
    sigma, problem = None, None
    if len(used) >= MIN_VIEWS_CHECKED:
        sigma = jackknife_sigma(held_out_views(img_pts, obj_pts, size, flags).intrinsics)
        problem = conditioning_problem(sigma, float(np.mean(np.diag(camera.K)[:2])),
                                       board_tilts_deg(rvecs), len(used))
    else:
        problem = ((f"only {len(used)} usable photos: the camera cannot be checked against "
                   f"photos it was not fitted to (at least {MIN_VIEWS_CHECKED} are needed); "
                   "add photos with the board tilted 30-45 deg towards each side of the image"),
                   False)
    if problem is not None:
        if problem[1]:
            raise DatasetError(folder, problem[0])
        notes += (f"{folder}: {problem[0]}",)
    return IntrinsicsResult(camera, per_view, tuple(used), tuple(rejected), tuple(img_pts),
                            tuple(obj_pts), flags, rvecs, tvecs, heldout, warnings=notes,
                            sigma_px=None if sigma is None else tuple(float(v) for v in sigma))


def _lens_model(img_pts: list[np.ndarray], obj_pts: list[np.ndarray], size: tuple[int, int],
                fix_k3: bool | None) -> tuple[int, dict | None]:
    """``cv2.calibrateCamera`` flags of the lens model, and the held-out RMS of each model
    compared (None when not compared). ``fix_k3`` True: k3 fixed, False: free (tangential
    terms free in both). None: model selection on views the fit has not seen
    (:func:`heldout_rms_px`): from the simplest model (k1, k2 only) on, tangential p1, p2 and
    then k3 are freed only when they lower the held-out RMS by more than 3 % (``K3_GAIN``);
    k3 only with ``MIN_VIEWS_FOR_K3`` views. Few views of a narrow lens trade the principal
    point against p1, p2: on the 7 real TAPAS views, cx 338.4 px with them free (held-out
    0.699 px), 308.1 px with them zero (0.692 px), the recordings' published 312.5 px."""
    if fix_k3 is not None:
        return (cv2.CALIB_FIX_K3 if fix_k3 else 0), None
    models = [cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST, cv2.CALIB_FIX_K3]
    if len(img_pts) >= MIN_VIEWS_FOR_K3:
        models.append(0)
    if len(img_pts) <= MIN_VIEWS:  # no view to hold out
        return cv2.CALIB_FIX_K3, None
    heldout = {f: heldout_rms_px(img_pts, obj_pts, size, f) for f in models}
    flags = models[0]
    for f in models[1:]:
        if heldout[f] < K3_GAIN * heldout[flags]:
            flags = f
    return flags, heldout


def _checked_views(used: list[Path], img_pts: list[np.ndarray], obj_pts: list[np.ndarray],
                   size: tuple[int, int], board: BoardSpec, folder: Path, flags: int
                   ) -> tuple[list[Path], list[np.ndarray], list[np.ndarray],
                              list[tuple[Path, str]], list[str]]:
    """The views without repeats (:func:`lidarcal.intrinsics_checks.duplicate_views`) and
    without views that fit the other views' camera badly
    (:func:`lidarcal.intrinsics_checks.view_outlier` under the lens model ``flags``, worst
    first, refitted after each, at most
    ``MAX_OUTLIER_SHARE`` of them); also ``(path, warning)`` of each view left out and the
    folder's warnings."""
    out: list[tuple[Path, str]] = []
    notes: list[str] = []
    for j, i in duplicate_views(img_pts):
        out.append((used[i], (f"{used[i]}: the same view as {used[j].name} (corners within "
                             f"{DUPLICATE_RMS_PX} px); view not used (it would count twice)")))
    drop = {i for _, i in duplicate_views(img_pts)}
    keep = [i for i in range(len(used)) if i not in drop]
    used, img_pts, obj_pts = ([x[i] for i in keep] for x in (used, img_pts, obj_pts))
    noise = [grid_noise_px(q, board.pattern_size) for q in img_pts]
    budget = int(MAX_OUTLIER_SHARE * len(used))
    while len(used) >= MIN_VIEWS_CHECKED:
        held = held_out_views(img_pts, obj_pts, size, flags)
        k = view_outlier(held, np.asarray(noise))
        if k is None:
            break
        med = float(np.nanmedian(held.rms_px))
        if budget == 0:
            notes.append(f"{folder}: {used[k].name} and others fit the camera of the "
                                f"other photos badly ({used[k].name}: {held.rms_px[k]:.3f} px, "
                                f"median {med:.3f} px), too many to leave out; check the "
                                "board's pattern and square size, and that one camera at one "
                                "zoom and focus took them all")
            break
        out.append((used[k], (f"{used[k]}: reprojection RMS {held.rms_px[k]:.3f} px under the "
                             f"camera fitted to the other photos (median {med:.3f} px, its "
                             f"corners' own scatter {noise[k]:.3f} px); view not used (another "
                             "camera, zoom or focus? a bent board? wrong corners?)")))
        budget -= 1
        for x in (used, img_pts, obj_pts, noise):
            del x[k]
    return used, img_pts, obj_pts, out, notes


#: whether :func:`calibrate_intrinsics` refines the photos' corners by their point symmetry
#: (:func:`_sharpest_views`) by default. Measured on the rendered wide rigs (seeds 1, 37, 39,
#: 5, 7; 18 photos each; the V refined too): the photos' corners 0.026-0.029 -> 0.010-0.013
#: px from truth, the camera's mean ray error 0.010/0.012/0.014/0.008/0.010 ->
#: 0.002/0.005/0.003/0.008/0.008 deg, the pose function's centre 0.075/0.121/0.140/0.233/0.365
#: -> 0.059/0.130/0.132/0.239/0.293 mm and its z/x axes 0.0054/0.0169 -> 0.0029/0.0132 deg on
#: average (no rig worse by more than 0.2 of its 1-sigma); no measurable CPU (the photos
#: are decoded once for both choices). On the bundled rig's 12 photos: 0.024 -> 0.007 px, ray
#: error 0.027 -> 0.007 deg. OpenCV's sample photos (640 x 480 JPEG) fail its checks and keep
#: their corners.
SYMMETRIC_PHOTOS = True


def _sharpest_views(paths: list[Path], img_pts: list[np.ndarray], obj_pts: list[np.ndarray],
                    res: tuple, board: BoardSpec, size: tuple[int, int], sharpest: bool = True,
                    symmetric: bool = False) -> tuple[list[np.ndarray], int]:
    """Per view (each photo decoded once), with the first calibration ``res``:

    ``sharpest``: :func:`detect_chessboard`'s corners or OpenCV's SB accuracy mode
    (:func:`sb_accuracy_corners`), whichever the view's pose fits best under its camera
    (:func:`view_reprojection_sq`). Measured against truth on the rendered wide rig's 18
    photos: corner rms 0.035 -> 0.028 px (seed 37), 0.027 -> 0.027 (39), 0.026 -> 0.026 (1).
    ``symmetric``: those corners then refined by their point symmetry on the board (Datta,
    Kim, Kanade 2009), sampled through the view's pose and the lens of ``res``
    (:func:`lidarcal.corner_symmetry.symmetric_corners`); kept where its checks fail.

    Returns the corners and how many views changed."""
    camera, _, rvecs, tvecs = res
    out, n = [], 0
    for p, q, o, rv, tv in zip(paths, img_pts, obj_pts, rvecs, tvecs):
        img = read_image(p, size)
        q0 = q = np.asarray(q, float).reshape(-1, 2)
        alt = sb_accuracy_corners(img, q, board.pattern_size) if sharpest else None
        try:
            if alt is not None and (view_reprojection_sq(camera, alt, o)
                                    < view_reprojection_sq(camera, q, o)):
                q = alt
        except (ValueError, cv2.error):
            pass
        if symmetric:
            sym = symmetric_corners(img, camera, cv2.Rodrigues(rv)[0],
                                    np.asarray(tv, float).ravel(), board, start_px=q).checked(q)
            q = q if sym is None else sym
        n += q is not q0
        out.append(q)
    return out, n


#: an extra view joins the fit only when its reprojection RMS under the photos' camera is
#: within this factor of its expected noise (:func:`add_views`): a view of another focus or zoom
#: (or with a wrong corner) would bend the camera model instead of sharpening it
EXTRA_VIEW_RMS_FACTOR = 3.0


def add_views(res: IntrinsicsResult, image_points: list[np.ndarray],
              object_points: list[np.ndarray], names: list[str],
              pattern_sizes: list[tuple[int, int]]) -> IntrinsicsResult:
    """Zhang's calibration (``cv2.calibrateCamera``) of the photos together with further
    chessboard views of the same camera, e.g. the two boards of the V in ``board.png``.

    Every view of a chessboard constrains K and the distortion (Zhang 2000); a board seen
    at another distance adds to the photos what fixes the focal length best, and the V's
    own poses then come from the camera that fits them. Measured on the rendered wide rig
    against truth (seeds 37, 39, 1; ``scripts/camera_truth.py``): fx error -0.12, -0.22,
    -0.09 px from the photos alone, -0.004, -0.22, -0.03 px with the V's boards; with the
    photos' first corners the V planes' offsets were 0.13/0.20, 0.16/0.20, 0.10/0.08 mm
    alone and 0.08/0.16, 0.12/0.16, 0.02/0.004 mm with them.
    The k3 choice of the photos is kept. Quality checks: an extra view whose reprojection
    RMS under the photos' camera exceeds ``EXTRA_VIEW_RMS_FACTOR`` times the larger of the
    photos' median per-view RMS and its own corners' scatter (:func:`grid_noise_px`; the
    V's bright image may be noisier than the photos) is left out (a warning names it), and the joint fit is dropped (warning)
    when it raises the photos' overall RMS by more than half.
    """
    cam0 = res.camera
    med = float(np.median(res.per_view_rms_px))
    img, obj, kept, warns = list(res.image_points), list(res.object_points), [], []
    for q, o, name in zip(image_points, object_points, names):
        q = np.asarray(q, float).reshape(-1, 2)
        try:
            rms = float(np.sqrt(view_reprojection_sq(cam0, q, o) / len(q)))
        except (ValueError, cv2.error):
            rms = np.inf
        noise = grid_noise_px(q, pattern_sizes[len(kept) + len(warns)])
        if not rms <= EXTRA_VIEW_RMS_FACTOR * max(med, noise):
            warns.append(f"{name}: reprojection RMS {rms:.3f} px under the camera of the "
                         f"intrinsics photos, its corners' own scatter {noise:.3f} px (the "
                         f"photos' median RMS {med:.3f} px); not used to refine the camera "
                         "(another focus or zoom? a wrong corner?)")
            continue
        img.append(q)
        obj.append(np.asarray(o, float))
        kept.append(name)
    if not kept:
        return replace(res, warnings=res.warnings + tuple(warns))
    cam, per_view, rvecs, tvecs = _calibrate(img, obj, cam0.image_size, res.flags)
    n = len(res.image_points)
    photos_rms = float(np.sqrt(np.mean(per_view[:n] ** 2)))
    if photos_rms > 1.5 * float(np.sqrt(np.mean(res.per_view_rms_px ** 2))):
        warns.append(f"with {', '.join(kept)} the intrinsics photos fit to {photos_rms:.3f} px "
                     f"instead of {np.sqrt(np.mean(res.per_view_rms_px ** 2)):.3f} px; the "
                     "camera is calibrated from the photos alone")
        return replace(res, warnings=res.warnings + tuple(warns))
    return replace(res, camera=cam, per_view_rms_px=per_view[:n], rvecs=rvecs[:n],
                   tvecs=tvecs[:n], extra_views=tuple(zip(kept, per_view[n:].tolist())),
                   warnings=res.warnings + tuple(warns))


def grid_noise_px(corners: np.ndarray, pattern_size: tuple[int, int]) -> float:
    """Robust RMS (px, 2-D) of the corners about their smooth grid
    (:func:`grid_prediction_scaled`, leave-one-out, residuals divided by the prediction's
    noise gain): the corners' scatter without any camera model (an upper bound: strong
    distortion adds to it). From the median: for isotropic Gaussian noise the 2-D distance
    is Rayleigh, RMS = sqrt(2 / (2 ln 2)) median = 1.201 median; one bad corner does not
    raise it."""
    pred, gain = grid_prediction_scaled(np.asarray(corners, float), pattern_size)
    r = np.linalg.norm(np.asarray(corners, float) - pred, axis=1) / gain
    return float(np.sqrt(1.0 / np.log(2.0)) * np.nanmedian(r)) if np.isfinite(r).any() else 0.0


def _newton_step(J: tuple[np.ndarray, ...], r: np.ndarray) -> np.ndarray:
    """``J^-1 r`` per point for the 2 x 2 Jacobians of :func:`lidarcal.lens.distortion_jacobian` (Cramer's
    rule), (N, 2)."""
    a, b, c, d = J
    with np.errstate(divide="ignore", invalid="ignore"):  # singular: NaN, flagged by the caller
        det = a * d - b * c
        return np.column_stack([(d * r[:, 0] - b * r[:, 1]) / det,
                                (a * r[:, 1] - c * r[:, 0]) / det])


def undistort_pixels(camera: CameraModel, px: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) -> undistorted normalised coordinates (N, 2).

    The inverse of :func:`project_points` to ~1e-10 px: OpenCV's iterative
    ``undistortPoints`` (tight criteria) as the start, then Newton steps on
    the distortion model. Points where the model cannot be inverted (far
    outside the image under strong distortion) come back as NaN.
    """
    p = as_points(px, 2)
    if len(p) == 0:
        return np.empty((0, 2))
    K = np.asarray(camera.K, dtype=float)
    dist = np.asarray(camera.dist, dtype=float)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    undist = getattr(cv2, "undistortPointsIter", None)
    src = p.reshape(-1, 1, 2).astype(np.float64)
    if undist is not None:
        xy = undist(src, K, dist, R=np.eye(3), P=np.eye(3), criteria=crit).reshape(-1, 2)
    else:
        xy = cv2.undistortPoints(src, K, dist, R=np.eye(3), P=np.eye(3),
                                 criteria=crit).reshape(-1, 2)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yn = (p[:, 1] - cy) / fy
    target = np.column_stack([(p[:, 0] - cx - skew * yn) / fx, yn])  # distorted, normalised
    xy = np.where(np.isfinite(xy), xy, target)
    for _ in range(8):
        r = distort_normalised(dist, xy) - target
        if np.max(np.abs(r)) < 1e-15:
            break
        xy = xy - _newton_step(distortion_jacobian(dist, xy), r)
    else:
        r = distort_normalised(dist, xy) - target
    bad = np.hypot(r[:, 0], r[:, 1]) * max(fx, fy) > 1e-6
    xy[bad] = np.nan
    return xy


def pixel_rays(camera: CameraModel, px: np.ndarray) -> np.ndarray:
    """Rays ``(x, y, 1)`` (N, 3) through distorted pixels, camera frame (not unit length)."""
    xy = undistort_pixels(camera, px)
    return np.column_stack([xy, np.ones(len(xy))])


def backproject_to_plane(camera: CameraModel, px: np.ndarray, plane: Plane) -> np.ndarray:
    """Camera-frame points (N, 3) where the rays of pixels meet ``plane``, mm (eqs. 1-2, 5).

    With a board's plane from eq. (3), this is the paper's recovery of object
    points from image points: the ray ``t (x, y, 1)`` with ``t`` chosen so
    that ``normal . X = d``.
    """
    return plane.intersect_rays(pixel_rays(camera, px))


def project_points(camera: CameraModel, X: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) -> distorted pixels (N, 2) (``cv2.projectPoints``)."""
    P = as_points(X)
    if len(P) == 0:
        return np.empty((0, 2))
    out, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3),
                               np.asarray(camera.K, dtype=float),
                               np.asarray(camera.dist, dtype=float))
    return out.reshape(-1, 2)


def load_intrinsics_views(folder: Path) -> list[Path]:
    """The ``*.png`` (and ``*.jpg``) chessboard views of a folder, sorted."""
    folder = Path(folder)
    return sorted([*folder.glob("*.png"), *folder.glob("*.jpg")])
