"""Board planes, eqs. (1)-(3): homography pose on exact and noisy corners, both boards of a rendered V."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.special import erf

from lidarcal.board import (
    board_outline_px,
    find_v_boards,
    homography,
    plane_from_pose,
    pose_from_homography,
    pose_pnp,
)
from lidarcal.camera import pixel_rays, project_points
from lidarcal.geometry import angle_between_deg
from lidarcal.io.dataset import BoardSpec, CameraModel

CAM = CameraModel(np.array([[1400.0, 0, 505.0], [0, 1402.0, 396.0], [0, 0, 1]]),
                  np.array([-0.12, 0.15, 0.0005, -0.0003, 0.0]), (1000, 800))
PAPER_CAM = CameraModel(np.array([[2757.4, 0, 831.6], [0, 2758.6, 638.9], [0, 0, 1.0]]),
                        np.array([-0.076, 0.371, 0, 0, 0]), (1624, 1234))
BOARD = BoardSpec((9, 7), 30.0)


def _random_pose(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    R = Rotation.from_rotvec(rng.normal(0, 0.45, 3)).as_matrix()
    T = np.array([rng.uniform(-350, -50), rng.uniform(-250, 0), rng.uniform(1200, 2200)])
    return R, T


@pytest.mark.parametrize("seed", range(6))
def test_homography_pose_exact(seed: int) -> None:
    """Exactly projected corners (with distortion): R, T to 1e-6 (eq. 2 and the SVD step)."""
    rng = np.random.default_rng(seed)
    R, T = _random_pose(rng)
    board = BoardSpec((14, 20), 20.0)
    obj = board.object_points()
    px = project_points(PAPER_CAM, obj @ R.T + T)
    R1, T1 = pose_from_homography(PAPER_CAM, px, obj)
    assert np.max(np.abs(R1 - R)) < 1e-6
    assert np.max(np.abs(T1 - T)) < 1e-6 * np.linalg.norm(T)
    plane = plane_from_pose(R1, T1)
    assert np.max(np.abs(plane.distance(obj @ R.T + T))) < 1e-6


def test_homography_maps_points() -> None:
    rng = np.random.default_rng(7)
    H = np.array([[1.2, 0.1, 30], [-0.05, 0.9, -12], [1e-4, -2e-4, 1]])
    src = rng.uniform(-100, 100, (20, 2))
    q = np.column_stack([src, np.ones(20)]) @ H.T
    dst = q[:, :2] / q[:, 2:]
    assert np.allclose(homography(src, dst), H, atol=1e-9)
    with pytest.raises(ValueError, match="degenerate"):
        homography(np.column_stack([np.arange(6.0), np.arange(6.0)]), dst[:6])


@pytest.mark.parametrize("seed", range(4))
def test_homography_pose_noisy_corners(seed: int) -> None:
    """Corner noise 0.1 px: plane normal and distance errors stay within a few noise-propagated sigma.

    For an N-corner board at distance Z seen with focal f, the plane's depth is
    known to about sigma * Z^2 / (f * extent * sqrt(N)) ... we bound loosely
    by 0.1 deg and 0.5 mm and require the PnP estimate to be as good.
    """
    rng = np.random.default_rng(100 + seed)
    R, T = _random_pose(rng)
    board = BoardSpec((14, 20), 20.0)
    obj = board.object_points()
    Xc = obj @ R.T + T
    px = project_points(PAPER_CAM, Xc) + rng.normal(0, 0.1, (len(obj), 2))
    R1, T1 = pose_from_homography(PAPER_CAM, px, obj)
    R2, T2 = pose_pnp(PAPER_CAM, px, obj, R1, T1)
    for Ra, Ta in ((R1, T1), (R2, T2)):
        pl = plane_from_pose(Ra, Ta)
        assert angle_between_deg(pl.normal, R[:, 2] * np.sign(R[:, 2] @ pl.normal)) < 0.1
        assert np.max(np.abs(pl.distance(Xc))) < 0.5


def test_pose_rejects_bad_object_points() -> None:
    obj = BOARD.object_points()
    with pytest.raises(ValueError, match="z = 0"):
        pose_from_homography(CAM, np.zeros((len(obj), 2)), obj + [0, 0, 1.0])
    with pytest.raises(ValueError, match=">= 4"):
        pose_from_homography(CAM, np.zeros((3, 2)), obj[:3])


# --- a rendered V -------------------------------------------------------------------------

def v_board_poses(opening_deg: float = 120.0, hinge_z: float = 1000.0, yaw_deg: float = 0.0,
                  gap_mm: float = 5.0, board: BoardSpec = BOARD):
    """Poses (R, T) of the left and right chessboards of a V whose hinge is vertical.

    Board frame: x along the corner rows (towards the hinge for the left
    board, away from it for the right one), y down, origin at the first inner
    corner. The printed pattern has one square of white margin.
    """
    half = np.radians((180.0 - opening_deg) / 2.0)
    yaw = Rotation.from_euler("y", yaw_deg, degrees=True).as_matrix()
    cols, rows = board.inner_corners
    sq = board.square_mm
    width = (cols + 1) * sq  # pattern width incl. one square beyond the inner corners each side
    height = (rows - 1) * sq
    hinge = np.array([0.0, -height / 2, hinge_z])
    poses = []
    for side in (-1, 1):
        # left board: x towards the hinge, right board: x away from it; the hinge is farthest
        u = yaw @ np.array([np.cos(half), 0.0, -side * np.sin(half)])
        v = np.array([0.0, 1.0, 0.0])
        R = np.column_stack([u, v, np.cross(u, v)])
        if side == -1:  # first inner corner is (width - sq + gap) before the hinge
            T = hinge - u * (width - sq + gap_mm)
        else:
            T = hinge + u * (sq + gap_mm)
        poses.append((R, T))
    return poses


def _smooth_step(d_px: np.ndarray, sigma_px: float) -> np.ndarray:
    """A unit step at 0 seen through a Gaussian PSF: 0 .. 1."""
    return 0.5 * (1 + erf(d_px / (np.sqrt(2) * sigma_px)))


def render_boards(cam: CameraModel, poses, board: BoardSpec, seed: int = 0,
                  white: float = 200.0, black: float = 36.0, background: float = 70.0,
                  noise: float = 1.5, psf_px: float = 0.75) -> np.ndarray:
    """Chessboards (pattern + 1 square white margin) seen by a distorted camera.

    Anti-aliased analytically: every edge is a step blurred by a Gaussian PSF
    of ``psf_px`` (pixel footprint included), using the distance of each pixel
    centre to the edge in pixels (board coordinates / their image gradient).
    Locally the pattern is point-symmetric about every inner corner, so the
    corners' true positions are exactly the projections of the board's
    corners (supersampling would put a 1/ss px quantisation on every edge).
    """
    w, h = cam.image_size
    ys, xs = np.mgrid[0:h, 0:w]
    rays = pixel_rays(cam, np.column_stack([xs.ravel(), ys.ravel()]))
    cols, rows = board.inner_corners
    sq = board.square_mm
    best_t = np.full(len(rays), np.inf)
    val = np.full(len(rays), background)
    for R, T in poses:
        n = R[:, 2]
        t = (n @ T) / (rays @ n)
        uv = ((rays * t[:, None] - T) @ R[:, :2]).reshape(h, w, 2)  # mm; inner corners k * sq
        # mm per pixel along each board axis, to turn distances in mm into pixels
        scale = [np.hypot(*np.gradient(uv[:, :, k])) for k in (0, 1)]
        q = [uv[:, :, k] / sq for k in (0, 1)]
        base = [np.floor(qk) for qk in q]
        # membership of squares base-1 .. base+1 along each axis, smooth (sums to 1)
        memb = []
        for k in (0, 1):
            m = []
            for di in (-1, 0, 1):
                lo = (q[k] - (base[k] + di)) * sq / scale[k]
                hi = (base[k] + di + 1 - q[k]) * sq / scale[k]
                m.append(_smooth_step(lo, psf_px) + _smooth_step(hi, psf_px) - 1)
            memb.append(m)
        blackness = np.zeros((h, w))
        for a, di in enumerate((-1, 0, 1)):
            for b, dj in enumerate((-1, 0, 1)):
                i, j = base[0] + di, base[1] + dj  # square (i, j) spans [i, i+1] x [j, j+1] sq
                is_black = (i >= -1) & (i < cols) & (j >= -1) & (j < rows) & ((i + j) % 2 == 0)
                blackness += is_black * memb[0][a] * memb[1][b]
        colour = (white - (white - black) * blackness).ravel()
        u, v = uv[:, :, 0].ravel(), uv[:, :, 1].ravel()
        on_board = (u > -2 * sq) & (u < (cols + 1) * sq) & (v > -2 * sq) & (v < (rows + 1) * sq)
        hit = on_board & (t > 0) & (t < best_t)
        val[hit] = colour[hit]
        best_t[hit] = t[hit]
    img = val.reshape(h, w) + np.random.default_rng(seed).normal(0, noise, (h, w))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def v_image():
    poses = v_board_poses(yaw_deg=8.0)
    return render_boards(CAM, poses, BOARD), poses


def test_find_v_boards_planes(v_image) -> None:
    img, poses = v_image
    b0, b1 = find_v_boards(img, BOARD, CAM)
    assert b0.centroid_px[0] < b1.centroid_px[0]
    for view, (R, T) in zip((b0, b1), poses):
        obj = BOARD.object_points()
        Xc = obj @ R.T + T
        for pl in (view.plane, view.plane_pnp):
            ang = angle_between_deg(pl.normal, R[:, 2])
            assert min(ang, 180 - ang) < 0.05
            assert np.max(np.abs(pl.distance(Xc))) < 0.1
        assert max(view.reprojection_rms_px) < 0.05
        # corners are the truth's up to the 180 deg order ambiguity
        truth_px = project_points(CAM, Xc)
        err = min(np.abs(view.corners_px - truth_px).max(),
                  np.abs(view.corners_px[::-1] - truth_px).max())
        assert err < 0.1
        # outline encloses every corner
        outline = board_outline_px(CAM, view.R_pnp, view.T_pnp, BOARD)
        m = view.mask(img.shape)
        assert m[np.round(view.corners_px[:, 1]).astype(int),
                 np.round(view.corners_px[:, 0]).astype(int)].all()
        assert outline.shape[1] == 2


def test_find_v_boards_one_board_only(v_image) -> None:
    _, poses = v_image
    img = render_boards(CAM, poses[:1], BOARD)
    with pytest.raises(ValueError, match="found 1 of the 2 chessboards"):
        find_v_boards(img, BOARD, CAM)


def test_find_v_boards_no_board() -> None:
    with pytest.raises(ValueError, match="found 0 of the 2"):
        find_v_boards(np.full((800, 1000), 90, np.uint8), BOARD, CAM)


def _truth_for(corners: np.ndarray, poses) -> np.ndarray:
    """The true corner pixels of the rendered board ``corners`` belong to, in their order."""
    truths = [project_points(CAM, BOARD.object_points() @ R.T + T) for R, T in poses]
    t = min(truths, key=lambda q: np.linalg.norm(q.mean(0) - corners.mean(0)))
    return t if np.linalg.norm(corners[0] - t[0]) < np.linalg.norm(corners[0] - t[-1]) else t[::-1]


def _rms(c: np.ndarray, truth_px: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((c - truth_px) ** 2, axis=1))))


@pytest.mark.parametrize("opening, yaw, noise", [(120.0, 8.0, 1.5), (85.0, 0.0, 1.5),
                                                 (100.0, -10.0, 3.0)])
def test_saddle_corners_against_truth(opening: float, yaw: float, noise: float) -> None:
    """The saddle points of the smoothed image (Lucchese-Mitra) on rendered V boards (an
    80-90 deg V too): nearer the truth than the detector's cornerSubPix corners and OpenCV's
    SB accuracy mode, and within a noise-scaled bound (measured 0.009 px at 1.5 DN, 0.017 px at
    3 DN: the fit averages about a square's worth of pixels)."""
    from lidarcal.corners import detect_chessboard, saddle_corners, sb_accuracy_corners

    poses = v_board_poses(opening_deg=opening, yaw_deg=yaw)
    img = render_boards(CAM, poses, BOARD, noise=noise)
    det = detect_chessboard(img, BOARD.pattern_size)
    truth_px = _truth_for(det, poses)
    sad = saddle_corners(img, det, BOARD.pattern_size)
    assert sad is not None
    assert _rms(sad, truth_px) < min(_rms(det, truth_px), 0.01 * noise)
    sb = sb_accuracy_corners(img, det, BOARD.pattern_size)
    assert sb is None or _rms(sad, truth_px) < _rms(sb, truth_px)
    # from corners 0.3 px off (the classic detector's class of error) to the same saddles
    noisy = det + np.random.default_rng(5).normal(0, 0.3, det.shape)
    again = saddle_corners(img, noisy, BOARD.pattern_size)
    assert again is not None and np.max(np.abs(again - sad)) < 0.01


def test_saddle_corners_keeps_dragged_corners_and_refuses_blank(v_image) -> None:
    """A dark blob in the white square beside one corner (a fiducial ring, a marker) spoils
    that corner's smoothed saddle (no saddle, off the grid or dragged): the corner keeps the
    given position, the corners far from it their saddles; no corners in the image: None."""
    from lidarcal.corners import detect_chessboard, local_square_px, saddle_corners

    img, _ = v_image
    det = detect_chessboard(img, BOARD.pattern_size)
    clean = saddle_corners(img, det, BOARD.pattern_size)
    k = BOARD.inner_corners[0] + 3  # an interior corner
    side = float(local_square_px(det, BOARD.pattern_size)[k])
    marked = img.copy()
    centre = det[k] + [0.3 * side, 0.15 * side]  # inside one square, near the corner
    cv2.circle(marked, tuple(np.round(centre).astype(int).tolist()), int(0.15 * side), 0, -1)
    out = saddle_corners(marked, det, BOARD.pattern_size)
    assert out is not None
    assert np.array_equal(out[k], det[k])
    others = np.arange(len(det)) != k
    far = np.linalg.norm(det - det[k], axis=1) > 1.5 * side
    assert np.max(np.abs(out[far & others] - clean[far & others])) < 1e-3
    assert saddle_corners(np.full_like(img, 120), det, BOARD.pattern_size) is None


def test_sharpest_corners_against_truth(v_image, monkeypatch) -> None:
    """Of the detector's corners, the saddles and SB's accuracy mode, the set the PnP pose fits
    best is kept: on the rendered V (1.5 DN noise) the saddles (0.009 px from truth, the
    detector's 0.013 px, SB's 0.022 px, measured), then refined by point symmetry (0.005 px,
    closer than all three); when the detector's corners carry 0.3 px extra noise, still a set
    within 0.05 px."""
    from lidarcal import board as board_module
    from lidarcal.board import sharpest_corners
    from lidarcal.corners import detect_chessboard, saddle_corners, sb_accuracy_corners

    img, poses = v_image
    det = detect_chessboard(img, BOARD.pattern_size)
    truth_px = _truth_for(det, poses)
    sb = sb_accuracy_corners(img, det, BOARD.pattern_size)
    sad = saddle_corners(img, det, BOARD.pattern_size)
    assert sb is not None and _rms(sb, truth_px) < 0.05
    with monkeypatch.context() as m:  # the choice alone, before the symmetric refinement
        m.setattr(board_module, "SYMMETRIC_REFINEMENT", False)
        assert np.array_equal(sharpest_corners(img, det, BOARD, CAM), sad)
    chosen = sharpest_corners(img, det, BOARD, CAM)  # then refined by point symmetry
    assert _rms(chosen, truth_px) <= min(_rms(det, truth_px), _rms(sb, truth_px),
                                         _rms(sad, truth_px)) + 1e-12
    noisy = det + np.random.default_rng(3).normal(0, 0.3, det.shape)
    assert _rms(noisy, truth_px) > 0.3 and _rms(sharpest_corners(img, noisy, BOARD, CAM),
                                                 truth_px) < 0.05
    # neither the saddles nor SB found on a blank image: the given corners come back unchanged
    blank = np.full_like(img, 120)
    assert np.array_equal(sharpest_corners(blank, det, BOARD, CAM), det)


def test_sharpest_corners_on_the_real_tapas_views() -> None:
    """The bundled real views (fiducial rings beside the board's outer corners) with the
    recording's intrinsics: the chosen corners never fit the board's pose worse than the
    detector's, and stay within 1.5 px of them (SB is refused where a ring drags it; it
    was taken on 2 of the 7 views, measured 0.318 -> 0.253 px and 0.239 -> 0.226 px)."""
    import json
    from pathlib import Path

    import cv2

    from lidarcal.board import board_view, sharpest_corners
    from lidarcal.corners import detect_chessboard
    from lidarcal.io.dataset import parse_camera

    tapas = Path(__file__).resolve().parents[1] / "data" / "real_tapas"
    cam = parse_camera(json.loads((tapas / "camera.json").read_text()), tapas / "camera.json")
    board = BoardSpec((8, 5), 100.0)
    taken = 0
    for p in sorted(tapas.glob("*.png")):
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        c = detect_chessboard(g, board.pattern_size)
        if c is None:
            continue
        s = sharpest_corners(g, c, board, cam)
        rms = [board_view(cam, q, board).reprojection_rms_px[1] for q in (c, s)]
        assert rms[1] <= rms[0] + 1e-12, p.name
        assert np.max(np.linalg.norm(s - c, axis=1)) < 1.5, p.name
        taken += not np.array_equal(s, c)
    assert taken >= 1


def test_bilinear_patches_match_scipy() -> None:
    """The saddle fit's patch sampler is bilinear interpolation with the image's edge
    repeated (``scipy.ndimage.map_coordinates``, order 1, mode "nearest"), to float32 precision,
    centres near the border included."""
    from scipy.ndimage import map_coordinates

    from lidarcal.corners import _bilinear_patches

    rng = np.random.default_rng(0)
    img = rng.uniform(0, 255, (120, 160)).astype(np.float32)
    centres = np.vstack([rng.uniform(0, [159, 119], (40, 2)), [[0.2, 0.7], [158.9, 118.6]]])
    w = 6
    yy, xx = np.mgrid[-w:w + 1, -w:w + 1].astype(float)
    ref = map_coordinates(img, [centres[:, 1, None, None] + yy, centres[:, 0, None, None] + xx],
                          order=1, mode="nearest")
    assert np.max(np.abs(_bilinear_patches(img, centres, w) - ref)) < 1e-4


@pytest.mark.parametrize("r", [1, 4, 9])
def test_box_means_match_the_blurred_image(r: int) -> None:
    """The blackness map's square samples (box means blurred only around the points) equal
    ``cv2.blur`` of the whole float image at those pixels, points at and beyond the image's
    edges included (clipped, edges reflected as OpenCV does)."""
    from lidarcal.board import _box_means

    rng = np.random.default_rng(r)
    img = rng.integers(0, 256, (90, 130), dtype=np.uint8)
    at = np.vstack([rng.integers(0, [130, 90], (50, 2)), [[0, 0], [129, 89], [-3, 95], [140, 2]]])
    full = cv2.blur(img.astype(np.float32), (2 * r + 1, 2 * r + 1))
    ref = full[at[:, 1].clip(0, 89), at[:, 0].clip(0, 129)]
    assert np.array_equal(_box_means(img, at, r), ref)


@pytest.mark.parametrize("at_edges", [False, True])
def test_bilinear_patches_equal_the_four_corner_formula(at_edges: bool) -> None:
    """Patches cut from the strided windows (all inside the image) or indexed pixel by pixel
    (some beyond its edges, which repeat), interpolated along x on every row once and then
    along y: the four-corner bilinear formula's numbers exactly (the same products and sums)."""
    from lidarcal.corners import _bilinear_patches

    rng = np.random.default_rng(1)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (100, 140)).astype(np.float32), (0, 0), 1.5)
    centres = rng.uniform(6, [133, 93], (30, 2))
    if at_edges:
        centres = np.vstack([centres, [[0.3, 0.1], [138.7, 98.9]]])
    w = 5
    base = np.floor(centres).astype(int)
    f = (centres - base)[:, :, None, None]
    r = np.arange(-w, w + 2)
    rows = np.clip(base[:, 1, None] + r, 0, 99)
    cols = np.clip(base[:, 0, None] + r, 0, 139)
    P = img[rows[:, :, None], cols[:, None, :]].astype(np.float64)
    fx, fy = f[:, 0], f[:, 1]
    ref = ((1 - fy) * ((1 - fx) * P[:, :-1, :-1] + fx * P[:, :-1, 1:])
           + fy * ((1 - fx) * P[:, 1:, :-1] + fx * P[:, 1:, 1:]))
    assert np.array_equal(_bilinear_patches(img, centres, w), ref)
