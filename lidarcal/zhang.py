"""Zhang's calibration of a camera from views of a planar chessboard (Zhang 2000, "A flexible
new technique for camera calibration"), through OpenCV: the fit itself (:func:`zhang_fit`), one
view's reprojection under a given camera (:func:`view_reprojection_sq`) and the cross-validated
reprojection RMS (:func:`heldout_rms_px`). Used by :mod:`lidarcal.camera` (the photos' camera)
and :mod:`lidarcal.intrinsics_checks` (the checks of that fit). Imports only numpy, OpenCV and
:mod:`lidarcal.io.dataset`.
"""

from __future__ import annotations

import cv2
import numpy as np

from .io.dataset import CameraModel

#: fewest views Zhang's method is run on (each view gives two constraints on K)
MIN_VIEWS = 3


def heldout_rms_px(img_pts: list[np.ndarray], obj_pts: list[np.ndarray], size: tuple[int, int],
                   flags: int, folds: int = 4) -> float:
    """Cross-validated reprojection RMS (px): the views split into ``folds`` interleaved
    groups; each group's views are reprojected with the camera calibrated on the others
    (each held-out view's pose by ``cv2.solvePnP`` with that camera)."""
    n = len(img_pts)
    folds = min(folds, n)
    sq, cnt = 0.0, 0
    for f in range(folds):
        test = [i for i in range(n) if i % folds == f]
        train = [i for i in range(n) if i % folds != f]
        if len(train) < MIN_VIEWS:
            continue
        cam = zhang_fit([img_pts[i] for i in train], [obj_pts[i] for i in train], size, flags)[0]
        for i in test:
            sq += view_reprojection_sq(cam, img_pts[i], obj_pts[i])
            cnt += len(img_pts[i])
    return float(np.sqrt(sq / max(cnt, 1)))


def view_reprojection_sq(camera: CameraModel, img: np.ndarray, obj: np.ndarray) -> float:
    """Sum of squared reprojection errors (px^2) of one view, its pose by ``solvePnP``
    (IPPE start, then iterative LM) with the camera held fixed."""
    K, dist = np.asarray(camera.K, float), np.asarray(camera.dist, float)
    o = np.asarray(obj, np.float64).reshape(-1, 3)
    p = np.asarray(img, np.float64).reshape(-1, 2)
    ok, rvec, tvec = cv2.solvePnP(o, p, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if ok:
        ok, rvec, tvec = cv2.solvePnP(o, p, K, dist, rvec, tvec, useExtrinsicGuess=True,
                                      flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise ValueError("solvePnP failed on a held-out view")
    proj, _ = cv2.projectPoints(o, rvec, tvec, K, dist)
    return float(np.sum((proj.reshape(-1, 2) - p) ** 2))


def zhang_fit(img_pts: list[np.ndarray], obj_pts: list[np.ndarray], size: tuple[int, int],
              flags: int) -> tuple[CameraModel, np.ndarray, tuple, tuple]:
    """Zhang's calibration (``cv2.calibrateCameraExtended``) on one OpenCV thread.

    With several threads OpenCV sums the views' normal equations in whatever order the
    threads finish, so the same photos gave cameras differing by ~1e-12 from run to run
    (and calibration.json by ~1e-5 mm); on one thread the result is the same every run, at
    ~0.01 s more for 40 views. The caller's thread count is restored."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        rms, K, dist, rvecs, tvecs, _, _, per_view = cv2.calibrateCameraExtended(
            [o.astype(np.float32) for o in obj_pts],
            [i.reshape(-1, 1, 2).astype(np.float32) for i in img_pts],
            size, None, None, flags=flags, criteria=crit)
    finally:
        cv2.setNumThreads(threads)
    dist5 = np.zeros(5)
    d = np.asarray(dist, dtype=float).ravel()
    dist5[: min(5, d.size)] = d[:5]
    cam = CameraModel(np.asarray(K, dtype=float), dist5, (int(size[0]), int(size[1])),
                      source="intrinsics", rms_px=float(rms))
    return cam, np.asarray(per_view, dtype=float).ravel(), tuple(rvecs), tuple(tvecs)
