"""The plane of a line laser from photos of it on a flat chessboard (section 1.3 on its own).

The structured-light step: in each lights-on photo the chessboard gives the
board's plane (eqs. 1-3), the laser stripe on it gives sub-pixel centres
(section 1.3: on the laser's colour response averaged along the stripe,
:func:`lidarcal.laser_colour.along_stripe`, kept off overexposed areas, its saturated
core filled up to a width scaled with the squares; the centroid centres of
:func:`lidarcal.stripe.stripe_centres` guide Steger's line detector,
:func:`lidarcal.stripe_steger.steger_stripe`; on a colour photo,
the same detector also runs on the full-resolution luma with the lit board modelled and
removed, :func:`lidarcal.stripe_luma.luma_stripe`, at the luma stripe's own width, whose
centres are used when they pass the same gates and scatter less about their line, unless an
overexposed square lies within a square of the stripe), their rays meet
the board plane (eq. 5) and all the photos' 3D
stripe points are fitted by one plane (eq. 4, total least squares: geometric
distances, not the paper's algebraic ``ax + by + cz = 1``). Photos whose
chessboard or stripe fails its checks, or whose stripe line lies off the
common plane, are left out with a warning naming them; sigma comes from a
bootstrap over the photos used. Real photos: a JPEG tagged with an EXIF rotation is
read in the camera's orientation (:func:`read_photo`), large photos are searched for the
board reduced, a stray chessboard corner is replaced (:func:`board_view_robust`) and the
board's fit is judged per focal length (:func:`max_board_rms_px`).

The centres are correlated along the stripe (the response is averaged over a square's
side along it, and Steger's Gaussian over its scale): ``rms_mm``, the rms distance of the
used centres' 3D points to the plane, measures their scatter, not an error of independent
points; the plane's sigma comes from resampling whole photos, which keeps each photo's
correlated centres together.

Output (``lidarcal-laser-plane/1``): ``normal . X = d_mm`` in the camera frame
(OpenCV's), ``d_mm >= 0``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .board import BoardView, board_view, pose_pnp
from .camera import backproject_to_plane, project_points
from .corners import detect_chessboard
from .geometry import Plane, fit_plane
from .io.camera_files import read_camera_file
from .io.dataset import (
    BoardSpec,
    CameraModel,
    DatasetError,
    decode_image,
    write_json_atomic,
)
from .laser_colour import (
    _CHANNEL,
    ALONG_STEP_DEG,
    CORE_MAX_PX,
    SATURATED_DN,
    along_stripe,
    centres_direction_deg,
    clipped_areas,
    detect_laser_colour,
    laser_response,
)
from .stripe import stripe_centres
from .stripe_luma import luma_stripe
from .stripe_quality import quality_problem
from .stripe_steger import steger_stripe

FORMAT = "lidarcal-laser-plane/1"
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
#: a photo whose stripe points lie further (rms) than this many times the rms of the other
#: photos about their own plane, and than MIN_OUTLIER_MM, is an outlier (a wrong board pose,
#: a reflection)
OUTLIER_K = 4.0
MIN_OUTLIER_MM = 0.3
MIN_PHOTOS = 2
#: a board whose corners fit its pose worse than this (rms, px) is not used
MAX_BOARD_RMS_PX = 1.0
#: stripe profiles keep this share of a square's side away from overexposed areas
CLIPPED_GUARD_SQUARES = 0.125
#: the board is searched in photos larger than this (px, longer side) reduced to it first
BOARD_SEARCH_PX = 1600
#: colour photos: the stripe's centres also found on the full-resolution luma with the lit
#: board modelled and removed (:mod:`lidarcal.stripe_luma`), used where they scatter less
LUMA_REFINE = True
#: ... but not when an overexposed area of the board lies within this many squares' sides of
#: the stripe (measured on the semi-real photos: the luma's centres of a stripe 7-24 px from
#: one were biased by up to 0.8 mm, of one 79 px or more away as good as on a board that
#: does not clip; a square is 38-50 px there)
LUMA_CLIP_SQUARES = 1.0
#: below this ratio of the 2nd to the 1st singular value of the points the stripes are
#: (nearly) parallel and the plane is not determined
MIN_SPREAD = 0.02


@dataclass
class PhotoResult:
    """One photo: its stripe centres (px), 3D points (mm) and why it was not used."""

    name: str
    centres_px: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    points_mm: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    rms_px: float | None = None
    board_plane: Plane | None = None
    problem: str | None = None
    #: the photo's size (w, h) when it is not the camera's (it was then not measured)
    other_size: tuple[int, int] | None = None
    #: the image the centres were found in: "colour" (the laser's colour response, or a
    #: gray image) or "luma" (:mod:`lidarcal.stripe_luma`)
    centres_on: str = "colour"

    @property
    def used(self) -> bool:
        return self.problem is None


@dataclass
class LaserPlaneResult:
    plane: Plane
    rms_mm: float
    sigma_normal_deg: float
    sigma_d_mm: float
    photos: list[PhotoResult]
    warnings: list[str]

    def to_dict(self) -> dict:
        return {"format": FORMAT, "normal": self.plane.normal.tolist(), "d_mm": float(self.plane.d),
                "rms_mm": _num(self.rms_mm),
                "sigma": {"normal_deg": _num(self.sigma_normal_deg), "d_mm": _num(self.sigma_d_mm)},
                "images": [{"name": p.name, "used": p.used, "centres": len(p.centres_px),
                            "rms_px": _num(p.rms_px), "centres_on": p.centres_on}
                           for p in self.photos],
                "warnings": list(self.warnings)}


def _num(v: float | None) -> float | None:
    """JSON has no NaN: None where a number is not known."""
    return None if v is None or not np.isfinite(v) else float(v)


def read_camera_json(path: str | Path) -> CameraModel:
    """The ``--camera`` file: camera.json (the keys of dataset.json's ``camera`` block: K, dist,
    image_size), an OpenCV calibration YAML/XML or a ROS camera_info YAML
    (:func:`lidarcal.io.camera_files.read_camera_file`)."""
    return read_camera_file(path)


def board_gray(image: np.ndarray, colour: str, response: np.ndarray,
               paint: str = "laser") -> np.ndarray:
    """The photo as the chessboard detector should see it: without the laser.

    For a coloured laser, the mean of the two other channels (they see little of it);
    for a gray (NIR, white) laser, luminance. What is left of the laser there (a
    saturated core clips every channel) is painted out from its surroundings.
    """
    if image.ndim == 2:
        gray = image
    elif colour in ("red", "green", "blue"):
        k = {"blue": 0, "green": 1, "red": 2}[colour]
        o = [c for c in range(3) if c != k]
        gray = ((image[..., o[0]].astype(np.uint16) + image[..., o[1]]) // 2).astype(np.uint8)
    else:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    thr = max(25.0, 0.25 * float(np.percentile(response, 99.9)))
    m = response > thr  # the laser where it is clear (overexposed white squares are not)
    if paint == "core" and image.ndim == 3:
        m &= image[..., :3].min(axis=2) >= SATURATED_DN  # only its white (clipped) core
    if not m.any():
        return gray
    m = cv2.dilate(m.astype(np.uint8), np.ones((5, 5), np.uint8))
    return cv2.inpaint(gray, m, 3, cv2.INPAINT_TELEA)


def find_board(image: np.ndarray, board: BoardSpec, response: np.ndarray,
               colour: str = "gray", paint: str = "laser") -> tuple[np.ndarray, BoardSpec] | None:
    """Chessboard corners in a lights-on photo that also shows the laser, or None.

    The detector and the corner refinement see the photo without the laser
    (:func:`board_gray` with ``paint``; it breaks the detector and pulls corners); the
    pattern is tried as given and swapped (8x5 = 5x8), the detector's exhaustive mode
    next, and last with a few stray corners put at their grid prediction (the laser's
    core across a corner; ``detect_chessboard(predict_strays=True)``); a photo larger than ``BOARD_SEARCH_PX`` is searched reduced to it first (the
    corners refined at full size). Returns the corners and the board spec they match.
    """
    clean = board_gray(image, colour, response, paint)
    down = min(1.0, BOARD_SEARCH_PX / max(clean.shape[:2]))  # large photos: searched reduced
    c, r = board.inner_corners
    specs = (board, BoardSpec((r, c), board.square_mm)) if c != r else (board,)
    # last, a few corners that no refinement can place (the laser's core across them) put
    # at their grid prediction: board_view_robust then checks them against the pose
    for exhaustive, strays in ((False, False), (True, False), (False, True)):
        for spec in specs:
            corners = detect_chessboard(clean, spec.pattern_size, exhaustive=exhaustive,
                                        downscale=down, predict_strays=strays)
            if corners is not None:
                return corners, spec
    return None


#: a corner whose reprojection residual exceeds this many times the median of the others
#: (and the board limit) is a stray corner (:func:`board_view_robust`)
STRAY_CORNER_K = 5.0


def board_view_robust(camera: CameraModel, corners_px: np.ndarray, board: BoardSpec
                      ) -> tuple[BoardView, int]:
    """:func:`lidarcal.board.board_view` with stray corners replaced: (view, how many).

    Robust PnP by leaving the worst corner out: while the corner furthest from the pose's
    reprojection lies ``STRAY_CORNER_K`` times the median residual and the board limit
    (:func:`max_board_rms_px`) away, the pose is solved without it (``cv2.solvePnP``) and
    the corner replaced by its projection; at most a tenth of the corners (at least one).
    The chessboard detector can put an outer corner on a fiducial ring beside the board
    (seen on the real TAPAS views enlarged to 2000 x 1500: 30 px off, the rest ~1 px).
    """
    c = np.asarray(corners_px, float).copy()
    obj = board.object_points()
    view = board_view(camera, c, board)
    out = np.zeros(len(c), bool)
    for _ in range(max(1, len(c) // 10)):
        res = np.linalg.norm(project_points(camera, obj @ view.R_pnp.T + view.T_pnp) - c, axis=1)
        res[out] = 0.0
        k = int(np.argmax(res))
        if res[k] <= max(STRAY_CORNER_K * float(np.median(res[~out])), max_board_rms_px(camera)):
            break
        keep = np.ones(len(c), bool)
        keep[k] = False
        keep &= ~out
        R, T = pose_pnp(camera, c[keep], obj[keep], view.R_pnp, view.T_pnp)
        c[k] = project_points(camera, obj[k:k + 1] @ R.T + T)[0]
        out[k] = True
        view = board_view(camera, c, board)
    return view, int(out.sum())


#: coloured things thicker than this share of a square's side are not a stripe
WIDE_OBJECT_SQUARES = 0.25


def wide_objects(response: np.ndarray, mask: np.ndarray, side_px: float) -> np.ndarray:
    """Where the laser's colour covers something thicker than ``WIDE_OBJECT_SQUARES`` of a
    square (uint8 0/1): red labels and dots beside the board, not a stripe (thin).

    The response above half its 99.9th percentile inside ``mask`` is opened by a square of
    that size (what survives is thick) and grown by the same size, for its blurred rim."""
    vals = response[mask.astype(bool)]
    if vals.size == 0:
        return np.zeros(response.shape, np.uint8)
    thr = max(float(np.percentile(vals, 99.9)) / 2, 1.0)
    hot = (response > thr).astype(np.uint8)
    k = 2 * int(side_px * WIDE_OBJECT_SQUARES / 2) + 1
    se = cv2.getStructuringElement(cv2.MORPH_RECT, (k, k))
    return cv2.dilate(cv2.morphologyEx(hot, cv2.MORPH_OPEN, se), se)


def max_board_rms_px(camera: CameraModel) -> float:
    """The largest corner reprojection rms (px) of a usable board: ``MAX_BOARD_RMS_PX`` per
    1000 px of focal length, at least ``MAX_BOARD_RMS_PX`` (an angle, ~1 mrad: the same
    board misfit in a 12 MP photo spans six times the pixels of a VGA one)."""
    return MAX_BOARD_RMS_PX * max(1.0, float(camera.K[0][0]) / 1000.0)


def read_photo(path: Path, image_size: tuple[int, int]) -> tuple[np.ndarray | None, str | None]:
    """The photo (BGR) in the camera's orientation, or its problem (a photo of another size
    comes back with its problem, to be named).

    OpenCV turns a JPEG by its EXIF orientation tag; a phone held upright stores the
    sensor's (landscape) pixels and tags them "rotate 90": turned, the photo no longer
    has the camera's size. The photo is read turned (as ``lidarcal intrinsics`` reads
    its photos) and, when that does not fit the camera but the sensor's own orientation
    (``cv2.IMREAD_IGNORE_ORIENTATION``) does, as stored.
    """
    try:
        img = decode_image(path, cv2.IMREAD_COLOR)
    except DatasetError as e:
        return None, e.problem.split("; ")[0]
    size = tuple(int(v) for v in image_size)
    if (img.shape[1], img.shape[0]) != size:
        raw = cv2.imread(str(path), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if raw is not None and (raw.shape[1], raw.shape[0]) == size:
            return raw, None
        return img, (f"image is {img.shape[1]}x{img.shape[0]}, the camera's is "
                     f"{size[0]}x{size[1]}")
    return img, None


def square_side_and_edges(corners_px: np.ndarray, board: BoardSpec
                          ) -> tuple[float, tuple[float, float]]:
    """A square's side (px, median of neighbouring corners' distances) and the image
    directions (deg, 0-180) of the board's rows and columns of corners."""
    c, r = board.inner_corners
    g = np.asarray(corners_px, float).reshape(r, c, 2)
    dx, dy = np.diff(g, axis=1).reshape(-1, 2), np.diff(g, axis=0).reshape(-1, 2)
    side = float(np.median(np.hypot(*np.vstack([dx, dy]).T)))
    ang = tuple(float(np.degrees(np.arctan2(v[1], v[0])) % 180)
                for v in (dx.mean(0), dy.mean(0)))
    return side, ang


def _refilled(img: np.ndarray, colour: str, core_px: int, outline_px: np.ndarray,
              margin: int) -> np.ndarray:
    """:func:`lidarcal.laser_colour.laser_response` with saturated cores filled up to
    ``core_px`` wide, computed on the board's box grown by ``margin`` px (the fill and the
    clipped-area test reach ``core_px``; the along-stripe average a square beyond the
    board), zero outside it."""
    H, W = img.shape[:2]
    x0, y0 = (max(int(np.floor(v)) - margin, 0) for v in outline_px.min(axis=0))
    x1 = min(int(np.ceil(outline_px[:, 0].max())) + margin + 1, W)
    y1 = min(int(np.ceil(outline_px[:, 1].max())) + margin + 1, H)
    out = np.zeros((H, W), np.uint8)
    out[y0:y1, x0:x1] = laser_response(img[y0:y1, x0:x1], colour, core_max_px=core_px)
    return out


def measure_photo(path: Path, camera: CameraModel, board: BoardSpec,
                  laser_colour: str = "auto") -> PhotoResult:
    """Stripe centres and 3D stripe points (eq. 5) of one photo, or its problem."""
    res = PhotoResult(path.name)
    img, problem = read_photo(path, camera.image_size)
    if problem:
        res.problem = problem
        if img is not None:
            res.other_size = (img.shape[1], img.shape[0])
        return res
    colour = detect_laser_colour(img) if laser_colour == "auto" else laser_colour
    response = laser_response(img, colour)
    # only the laser's clipped core painted out first (corners under the stripe keep their
    # own pixels), then the whole visible laser: the board pose that fits its corners best
    view, found_spec = None, board
    for paint in ("core", "laser"):
        found = find_board(img, board, response, colour, paint)
        if found is not None:
            v, _ = board_view_robust(camera, found[0], found[1])
            if view is None or v.reprojection_rms_px[1] < view.reprojection_rms_px[1]:
                view, found_spec = v, found[1]
            if view.reprojection_rms_px[1] <= max_board_rms_px(camera) / 2:
                break
    if view is None:
        res.problem = (f"the {board.inner_corners[0]}x{board.inner_corners[1]} chessboard "
                       "was not found")
        return res
    if view.reprojection_rms_px[1] > max_board_rms_px(camera):
        res.problem = (f"the chessboard corners do not fit one board pose (reprojection "
                       f"{view.reprojection_rms_px[1]:.2f} px)")
        return res
    mask = np.zeros(img.shape[:2], np.uint8)
    cv2.fillPoly(mask, [np.round(view.outline_px).astype(np.int32)], 1)
    if colour in ("red", "green", "blue"):
        side, edges = square_side_and_edges(view.corners_px, found_spec)
        # profiles off overexposed squares: the laser is not seen there, and a profile that
        # reaches one is cut on that side
        # (a core is narrower than a quarter of a square: on large photos wider than 15 px)
        core = max(CORE_MAX_PX, 2 * int(side * WIDE_OBJECT_SQUARES / 2) + 1)
        if core > CORE_MAX_PX:  # a large photo: its saturated core filled up to that width
            response = _refilled(img, colour, core, view.outline_px, core + int(side))
        k = 2 * int(np.ceil(side * CLIPPED_GUARD_SQUARES)) + 1
        clipped = cv2.dilate(clipped_areas(img, colour, core).view(np.uint8),
                             np.ones((k, k), np.uint8))
        board_clipped = clipped & mask  # overexposed squares on the board
        mask &= 1 - clipped
        mask &= 1 - wide_objects(response, mask, side)
        raw = response
        response, along_deg = along_stripe(raw, mask.astype(bool), side, edges, smooth_px=side)
        pts, info = stripe_centres(response, mask.astype(bool), camera, return_info=True)
        # the direction of the centres' own line, when it differs from the searched one by
        # more than the search's resolution: the average redone along it, kept when its
        # centres scatter less about their line (measured in scripts/cleanroom_oneboard.py)
        own = centres_direction_deg(pts)
        if own is not None and abs((own - along_deg + 90) % 180 - 90) > ALONG_STEP_DEG / 10:
            r2, d2 = along_stripe(raw, mask.astype(bool), side, edges, smooth_px=side,
                                  direction_deg=own)
            p2, i2 = stripe_centres(r2, mask.astype(bool), camera, return_info=True)
            if len(p2) >= 5 and i2.get("fit_rms_px", np.inf) < info.get("fit_rms_px", np.inf):
                response, along_deg, pts, info = r2, d2, p2, i2
    else:
        board_clipped, side = None, float("nan")
        pts, info = stripe_centres(response, mask.astype(bool), camera, return_info=True)
    if len(pts) >= 5 and "width_px" in info:  # the centroid centres guide Steger's detector
        sat = None if img.ndim != 3 or colour not in _CHANNEL else \
            img[..., _CHANNEL[colour]] >= SATURATED_DN
        guide, ginfo = pts, info
        pts, info = steger_stripe(response, mask.astype(bool), camera, pts, info, sat)
        if LUMA_REFINE and colour in _CHANNEL and len(pts) >= 5 and info["problem"] is None \
                and not clipped_near(board_clipped, pts, LUMA_CLIP_SQUARES * side):
            # the same stripe on the full-resolution luma, the lit board removed: used when
            # it passes the same gates and its centres scatter less about their line (not
            # beside an overexposed square: the luma has no headroom left for the laser on
            # the white squares there, the stripe's luma is cut)
            p2, i2 = luma_stripe(img, camera, view, found_spec, pts, guide, ginfo,
                                 mask.astype(bool), side, along_deg, sat)
            if i2.get("problem") is None and i2["fit_rms_px"] <= info["fit_rms_px"]:
                pts, info = p2, i2
                res.centres_on = "luma"
    res.rms_px = None if not np.isfinite(info.get("fit_rms_px", np.nan)) else \
        float(info["fit_rms_px"])
    problem = info.get("problem") if "quality" not in info else quality_problem(info["quality"])
    if problem:
        res.problem = f"laser stripe on the board: {problem}"
        return res
    res.centres_px = pts
    res.board_plane = view.plane_pnp  # the ML pose: better than the homography's plane
    res.points_mm = backproject_to_plane(camera, pts, view.plane_pnp)
    return res


def clipped_near(clipped: np.ndarray | None, centres_px: np.ndarray, reach_px: float) -> bool:
    """Whether a pixel of ``clipped`` (uint8 or bool, the image's shape; None: none) lies
    within ``reach_px`` of a centre (N, 2): ``cv2.distanceTransform`` of the rest."""
    if clipped is None or not np.any(clipped) or len(centres_px) == 0:
        return False
    dist = cv2.distanceTransform((np.asarray(clipped) == 0).astype(np.uint8), cv2.DIST_L2, 5)
    H, W = dist.shape
    ip = np.rint(np.asarray(centres_px, float)).astype(int)
    ip = np.clip(ip, 0, [W - 1, H - 1])
    return bool((dist[ip[:, 1], ip[:, 0]] <= reach_px).any())


def _rms_to_plane(photo: PhotoResult, plane: Plane) -> float:
    return float(np.sqrt(np.mean(plane.distance(photo.points_mm) ** 2)))


def _oriented(plane: Plane) -> Plane:
    return plane if plane.d >= 0 else Plane(-plane.normal, -plane.d)


def fit_laser_plane(photos: list[PhotoResult], n_boot: int = 200, seed: int = 0
                    ) -> tuple[Plane, float, float, float, list[str]]:
    """Eq. (4) by total least squares over every used photo's 3D stripe points, robustly.

    Each photo's stripe is one line; leaving each photo out in turn, the one whose
    removal fits the others best is dropped when its points lie further (rms) off the
    others' plane than ``OUTLIER_K`` times their own rms and ``MIN_OUTLIER_MM``; then
    again on the rest. Each photo weighs by its points.
    Sigma: bootstrap over the photos (``n_boot`` resamples): the rms angle of the
    resampled normals to the estimate, and the std of ``d`` (mm).
    Returns (plane, rms_mm, sigma_normal_deg, sigma_d_mm, warnings).
    """
    warnings: list[str] = []
    used = [p for p in photos if p.used]
    while len(used) > MIN_PHOTOS + 1:
        # leave one out: the photo whose removal fits the rest best is the suspect; it is an
        # outlier when its stripe lies far off the plane of the others
        loo, rest = [], []
        for p in used:
            others = [q for q in used if q is not p]
            pl = fit_plane(np.vstack([q.points_mm for q in others]))
            loo.append(_rms_to_plane(p, pl))
            rest.append(float(np.sqrt(np.mean(pl.distance(np.vstack([q.points_mm
                                                                      for q in others])) ** 2))))
        k = int(np.argmin(rest))
        if loo[k] <= max(OUTLIER_K * rest[k], MIN_OUTLIER_MM):
            break
        used[k].problem = (f"its stripe lies {loo[k]:.2f} mm rms off the plane of the other "
                           f"photos (their rms {rest[k]:.2f} mm): a wrong board pose or a "
                           "reflection")
        used = [p for p in used if p.used]
    if len(used) < MIN_PHOTOS:
        raise ValueError(f"the laser stripe was measured on {len(used)} photo(s), need at least "
                         f"{MIN_PHOTOS} with the board in different poses")
    allp = np.vstack([p.points_mm for p in used])
    plane = _oriented(fit_plane(allp))
    sv = np.linalg.svd(allp - allp.mean(0), compute_uv=False)
    if sv[1] < MIN_SPREAD * sv[0]:
        raise ValueError("the stripes of all photos lie on (nearly) one line: the plane is not "
                         "determined; tilt and move the board between photos")
    rms = float(np.sqrt(np.mean(plane.distance(allp) ** 2)))
    rng = np.random.default_rng(seed)
    angs, ds = [], []
    for _ in range(n_boot if len(used) >= 3 else 0):
        pick = rng.integers(0, len(used), len(used))
        P = np.vstack([used[i].points_mm for i in pick])
        if np.linalg.svd(P - P.mean(0), compute_uv=False)[1] < MIN_SPREAD * sv[0]:
            continue
        b = fit_plane(P)
        if b.normal @ plane.normal < 0:
            b = Plane(-b.normal, -b.d)
        angs.append(np.degrees(np.arccos(np.clip(b.normal @ plane.normal, -1, 1))))
        ds.append(b.d)
    if len(angs) >= 20:
        s_ang = float(np.sqrt(np.mean(np.square(angs))))
        s_d = float(np.std(ds))
    else:
        s_ang, s_d = float("nan"), float("nan")
        warnings.append(f"only {len(used)} photos used: no bootstrap uncertainty; add photos")
    if len(used) < 4:
        warnings.append(f"only {len(used)} photos used: the plane has little redundancy")
    return plane, rms, s_ang, s_d, warnings


def laser_plane(folder: str | Path, board: BoardSpec, camera: CameraModel,
                laser_colour: str = "auto") -> LaserPlaneResult:
    """The laser plane from the photos of a folder (see the module docstring).

    Raises
    ------
    DatasetError
        Naming the folder when it holds no photos or too few usable ones.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "not a folder of laser photos; give the folder that holds "
                                 "them")
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not paths:
        raise DatasetError(folder, "holds no .png/.jpg/.bmp/.tif photos; give the folder that "
                                 "holds them")
    photos = [measure_photo(p, camera, board, laser_colour) for p in paths]
    sizes = {p.other_size for p in photos}
    if len(sizes) == 1 and None not in sizes:  # every photo of one other size
        w, h = sizes.pop()
        raise DatasetError(Path(camera.source), f"image_size is {camera.image_size[0]}x"
                                                f"{camera.image_size[1]} but every photo is "
                                                f"{w}x{h}; give the camera.json of the camera "
                                                "that took them")
    try:
        plane, rms, s_ang, s_d, warn = fit_laser_plane(photos)
    except ValueError as e:
        reasons = "; ".join(f"{p.name}: {p.problem}" for p in photos if p.problem)
        raise DatasetError(folder, f"{e}" + (f" ({reasons})" if reasons else "")) from None
    warnings = [f"{folder / p.name}: not used: {p.problem}" for p in photos if p.problem]
    return LaserPlaneResult(plane, rms, s_ang, s_d, photos, warnings + warn)


def write_laser_plane(result: LaserPlaneResult, path: str | Path) -> Path:
    """``plane.json`` (``lidarcal-laser-plane/1``), written atomically."""
    path = Path(path)
    write_json_atomic(path, result.to_dict())
    return path


def residual_figure(result: LaserPlaneResult):
    """A matplotlib Figure for a report: each used photo's stripe points, their distance to
    the fitted plane (mm) along the stripe, one colour per photo; unused photos listed."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.2), layout="constrained")
    for p in result.photos:
        if not p.used:
            continue
        P = p.points_mm
        t = (P - P.mean(0)) @ np.linalg.svd(P - P.mean(0), full_matrices=False)[2][0]
        o = np.argsort(t)
        ax.plot(t[o], result.plane.distance(P)[o], lw=0.8, label=p.name)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("along the stripe (mm)")
    ax.set_ylabel("distance to the laser plane (mm)")
    unused = [p.name for p in result.photos if not p.used]
    ax.set_title(f"laser plane: rms {result.rms_mm:.3f} mm, {len(result.photos) - len(unused)} "
                 f"photos used" + (f"; not used: {', '.join(unused)}" if unused else ""),
                 fontsize=9)
    if len(result.photos) <= 16:
        ax.legend(fontsize=6, ncol=2)
    return fig
