"""Checks of Zhang's calibration from chessboard photos (:func:`lidarcal.camera.calibrate_intrinsics`).

Each check is measured on the photos themselves, without the true camera:

- :func:`duplicate_views`: the same photo (or the same view) given twice;
- :func:`held_out_views`: every photo reprojected under the camera fitted WITHOUT it (grouped
  leave-out, Zhang's fit through :func:`lidarcal.zhang.zhang_fit`): a photo of another camera,
  zoom or focus, or with wrong corners, fits the others' camera badly
  (:func:`view_outlier`) and is left out instead of pulling the estimate;
- :func:`jackknife_sigma`: the spread of fx, fy, cx, cy over those leave-out fits, the
  delete-a-group jackknife's standard error (Efron and Tibshirani 1993, ch. 11). Unlike OpenCV's
  ``stdDeviationsIntrinsics`` (the fit's Jacobian, which assumes the lens model is right) it
  also sees a model that trades the principal point against tangential distortion on few
  views: on the 7 real TAPAS views OpenCV gives cx +-3.6 px where the estimate is 26 px from
  the recordings' published camera, the jackknife +-14 px;
- :func:`conditioning_problem`: a camera the photos do not determine (too few photos, all
  nearly fronto-parallel, the board never near the image's edges), named with what to add.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .zhang import MIN_VIEWS, view_reprojection_sq, zhang_fit

#: two views whose corners agree to this RMS (px) are the same view (a photo copied twice, or
#: a burst from a tripod): one is left out, since it would count that pose twice and leak into
#: the held-out checks (the copy predicts its twin perfectly). Measured on OpenCV's left03.jpg:
#: re-saved as JPEG at quality 95/90/75 0.002/0.005/0.007 px, with 2 DN of new sensor noise
#: 0.012 px (a second exposure of the same pose: left out too, the pose counted once); the
#: closest two different photos of the set 16.7 px.
DUPLICATE_RMS_PX = 0.02
#: leave-out groups for :func:`held_out_views` (one view each up to this many views)
MAX_GROUPS = 12
#: a view whose held-out RMS exceeds this factor times the larger of the views' median
#: held-out RMS and its own corners' scatter is left out (:func:`view_outlier`)
VIEW_OUTLIER_FACTOR = 3.0
#: at most this share of the views may be left out as outliers: beyond it the photos disagree
#: as a whole (a wrong board size, a lens the model cannot fit) and the check stops (warned)
MAX_OUTLIER_SHARE = 0.25
#: fewest views for the leave-out checks (each fit then still has MIN_VIEWS + 1 views)
MIN_VIEWS_CHECKED = MIN_VIEWS + 2
#: the camera is poorly determined (warning) when the jackknife 1-sigma of fx or fy exceeds
#: this share of the focal length (a board's distance is then uncertain by as much: 0.2 % is
#: 3 mm at 1.5 m). Measured: 12 rendered views of the paper rig tilted up to 40 deg: 0.01 %;
#: tilted up to 6 deg: 0.30 % (fx 4.6 px = 0.17 % off); the 13 real OpenCV photos: 0.12 %; the
#: 7 real TAPAS views: 1.0 %
POOR_FOCAL_SHARE = 0.002
#: ... or that of cx or cy exceeds this share of the focal length (0.5 %: 0.29 deg of ray
#: direction). Measured: paper rig 40 deg: 0.004 %, 6 deg: 0.02 %; OpenCV photos: 0.28 %;
#: TAPAS: 1.2 %
POOR_CENTRE_SHARE = 0.005
#: ... and undetermined (error) when either exceeds this share (5 %: of no use for measuring)
UNDETERMINED_SIGMA_SHARE = 0.05
#: boards tilted less than this from fronto-parallel add little to the focal length (Zhang
#: 2000, section 3.3: parallel planes give no new constraint); named in the warning
FRONTAL_TILT_DEG = 20.0


def duplicate_views(img_pts: list[np.ndarray]) -> list[tuple[int, int]]:
    """Pairs ``(j, i)``, ``i > j``, of views whose corners agree within
    ``DUPLICATE_RMS_PX`` (RMS over the corners, px): ``i`` repeats ``j``."""
    out, seen = [], []
    for i, q in enumerate(img_pts):
        q = np.asarray(q, float).reshape(-1, 2)
        for j in seen:
            p = np.asarray(img_pts[j], float).reshape(-1, 2)
            if p.shape == q.shape and np.sqrt(np.mean(np.sum((p - q) ** 2, 1))) < DUPLICATE_RMS_PX:
                out.append((j, i))
                break
        else:
            seen.append(i)
    return out


@dataclass(frozen=True)
class HeldOutViews:
    """Outcome of :func:`held_out_views`: per view, its reprojection RMS (px) under the camera
    fitted without its group (``rms_px``, NaN where its pose could not be solved); per group,
    that camera's ``(fx, fy, cx, cy)`` (``intrinsics``, (g, 4))."""

    rms_px: np.ndarray
    intrinsics: np.ndarray


def held_out_views(img_pts: list[np.ndarray], obj_pts: list[np.ndarray],
                   size: tuple[int, int], flags: int,
                   max_groups: int = MAX_GROUPS) -> HeldOutViews:
    """Grouped leave-out of Zhang's fit: the views split into ``min(n, max_groups)``
    interleaved groups; each group's views are reprojected (pose by ``solvePnP``) under the
    camera fitted to all other views with ``flags``."""
    n = len(img_pts)
    g = min(n, max_groups)
    rms = np.full(n, np.nan)
    K = np.full((g, 4), np.nan)
    for k in range(g):
        train = [i for i in range(n) if i % g != k]
        cam = zhang_fit([img_pts[i] for i in train], [obj_pts[i] for i in train], size, flags)[0]
        K[k] = cam.K[[0, 1, 0, 1], [0, 1, 2, 2]]
        for i in range(k, n, g):
            try:
                sq = view_reprojection_sq(cam, img_pts[i], obj_pts[i])
                rms[i] = np.sqrt(sq / len(np.asarray(img_pts[i]).reshape(-1, 2)))
            except (ValueError, cv2.error):
                pass
    return HeldOutViews(rms, K)


def jackknife_sigma(intrinsics: np.ndarray) -> np.ndarray:
    """The delete-a-group jackknife's standard error of each column of ``intrinsics`` (the
    leave-out fits' ``fx, fy, cx, cy``, (g, 4)): ``sqrt((g - 1) / g * sum (t_k - mean)^2)``."""
    t = np.asarray(intrinsics, float)
    g = len(t)
    if g < 2:
        return np.full(t.shape[1], np.inf)
    return np.sqrt((g - 1) / g * np.sum((t - t.mean(0)) ** 2, axis=0))


def view_outlier(held: HeldOutViews, noise_px: np.ndarray) -> int | None:
    """The view to leave out, or None: the worst whose held-out RMS exceeds
    ``VIEW_OUTLIER_FACTOR`` times the larger of the median held-out RMS and its own corners'
    scatter ``noise_px`` (a blurred photo's corners scatter more without being wrong); a view
    whose pose cannot be solved under the others' camera counts as the worst."""
    r = np.where(np.isfinite(held.rms_px), held.rms_px, np.inf)
    med = float(np.median(r[np.isfinite(r)])) if np.isfinite(r).any() else np.inf
    ratio = r / np.maximum(med, np.asarray(noise_px, float))
    k = int(np.argmax(ratio))
    return k if ratio[k] > VIEW_OUTLIER_FACTOR else None


def board_tilts_deg(rvecs: tuple[np.ndarray, ...] | list[np.ndarray]) -> np.ndarray:
    """Each view's board tilt from fronto-parallel (deg): the angle between the board's
    normal and the camera's optical axis."""
    return np.array([np.degrees(np.arccos(min(1.0, abs(cv2.Rodrigues(np.asarray(rv, float))[0][2, 2]))))
                     for rv in rvecs])


def conditioning_problem(sigma: np.ndarray, focal_px: float, tilts_deg: np.ndarray,
                         n_views: int) -> tuple[str, bool] | None:
    """``(what is wrong and what to add, fatal)`` when the jackknife 1-sigma ``sigma`` of
    ``(fx, fy, cx, cy)`` exceeds ``POOR_FOCAL_SHARE`` (fx, fy) or ``POOR_CENTRE_SHARE`` (cx, cy)
    of ``focal_px``, or every board is within ``FRONTAL_TILT_DEG`` of fronto-parallel; fatal
    beyond ``UNDETERMINED_SIGMA_SHARE``. Else None. Names the spread, the boards' tilts and
    the photos to add."""
    s = np.asarray(sigma, float) / focal_px
    frontal = float(np.max(tilts_deg)) < FRONTAL_TILT_DEG
    poor = not (s[:2].max() <= POOR_FOCAL_SHARE and s[2:].max() <= POOR_CENTRE_SHARE)
    if not (poor or frontal):
        return None
    fatal = not s.max() <= UNDETERMINED_SIGMA_SHARE
    px = np.asarray(sigma, float)
    tilt = (f"every board within {np.max(tilts_deg):.0f} deg of fronto-parallel, which leaves "
            "the focal length open" if frontal else
            f"board tilts {np.min(tilts_deg):.0f}-{np.max(tilts_deg):.0f} deg")
    what = (f"the camera is {'not' if fatal else 'poorly'} determined by these {n_views} "
            f"photos (leave-out spread, 1-sigma: fx {px[0]:.2f}, fy {px[1]:.2f}, cx {px[2]:.2f}, "
            f"cy {px[3]:.2f} px, up to {100 * s[:2].max():.2f} % of the focal length in fx, fy; "
            f"{tilt}); add photos with the board tilted 30-45 deg towards each side of the "
            "image and reaching into its corners")
    return what, fatal
