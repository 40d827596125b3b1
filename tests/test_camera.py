"""Camera model: undistortion round trips, back-projection, intrinsics on real and simulated views."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidarcal.camera import (
    backproject_to_plane,
    calibrate_intrinsics,
    pixel_rays,
    project_points,
    undistort_pixels,
)
from lidarcal.corners import detect_chessboard
from lidarcal.geometry import Plane
from lidarcal.io.dataset import BoardSpec, CameraModel, DatasetError

PAPER_CAM = CameraModel(np.array([[2757.4, 0, 831.6], [0, 2758.6, 638.9], [0, 0, 1.0]]),
                        np.array([-0.076, 0.371, 0, 0, 0]), (1624, 1234))
WIDE_CAM = CameraModel(np.array([[1187.0, 0, 968.5], [0, 1189.5, 597.0], [0, 0, 1.0]]),
                       np.array([-0.30, 0.12, 0.0008, -0.0006, -0.02]), (1920, 1200))


def _points_in_view(cam: CameraModel, rng: np.random.Generator, n: int) -> np.ndarray:
    """Random camera-frame points whose images fall inside the image (checked via projection)."""
    w, h = cam.image_size
    K = cam.K
    u = rng.uniform(0, w, n)
    v = rng.uniform(0, h, n)
    z = rng.uniform(500, 3000, n)
    x = (u - K[0, 2]) / K[0, 0] * z
    y = (v - K[1, 2]) / K[1, 1] * z
    return np.column_stack([x, y, z])


@pytest.mark.parametrize("cam", [PAPER_CAM, WIDE_CAM], ids=["paper", "wide"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_undistort_inverts_projection(cam: CameraModel, seed: int) -> None:
    rng = np.random.default_rng(seed)
    X = _points_in_view(cam, rng, 2000)
    px = project_points(cam, X)
    xy = undistort_pixels(cam, px)
    assert np.all(np.isfinite(xy))
    # normalised error below 1e-12 (about 1e-9 px)
    assert np.max(np.abs(xy - X[:, :2] / X[:, 2:])) < 1e-12


def test_undistort_beats_default_opencv() -> None:
    """The default cv2.undistortPoints (5 iterations) is off by up to ~1 px at the wide rig's corners."""
    rng = np.random.default_rng(3)
    X = _points_in_view(WIDE_CAM, rng, 500)
    px = project_points(WIDE_CAM, X)
    ours = undistort_pixels(WIDE_CAM, px)
    theirs = cv2.undistortPoints(px.reshape(-1, 1, 2), WIDE_CAM.K, WIDE_CAM.dist).reshape(-1, 2)
    truth = X[:, :2] / X[:, 2:]
    assert np.max(np.abs(theirs - truth)) * WIDE_CAM.K[0, 0] > 1e-3
    assert np.max(np.abs(ours - truth)) * WIDE_CAM.K[0, 0] < 1e-8


@settings(max_examples=60, deadline=None)
@given(k1=st.floats(-0.4, 0.2), k2=st.floats(-0.2, 0.5), p1=st.floats(-2e-3, 2e-3),
       p2=st.floats(-2e-3, 2e-3), k3=st.floats(-0.1, 0.1), seed=st.integers(0, 2**31 - 1))
def test_undistort_project_round_trip_property(k1, k2, p1, p2, k3, seed) -> None:
    """project(undistort(px)) == px for any plausible lens, points inside the image circle."""
    cam = CameraModel(WIDE_CAM.K, np.array([k1, k2, p1, p2, k3]), WIDE_CAM.image_size)
    rng = np.random.default_rng(seed)
    # normalised points within a radius where this lens model is monotonic
    r = rng.uniform(0, 0.55, 200)
    phi = rng.uniform(0, 2 * np.pi, 200)
    X = np.column_stack([r * np.cos(phi), r * np.sin(phi), np.ones(200)]) * 1000.0
    px = project_points(cam, X)
    xy = undistort_pixels(cam, px)
    assert np.all(np.isfinite(xy))
    back = project_points(cam, np.column_stack([xy, np.ones(len(xy))]))
    assert np.max(np.abs(back - px)) < 1e-6
    assert np.max(np.abs(xy - X[:, :2] / X[:, 2:])) < 1e-9


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_backproject_to_plane_recovers_points(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n = np.array([rng.normal(0, 0.5), rng.normal(0, 0.5), -1.0])
    plane = Plane.from_normal_point(n, [0, 0, rng.uniform(800, 2000)])
    X = plane.intersect_rays(np.column_stack([rng.uniform(-0.3, 0.3, (300, 2)), np.ones(300)]))
    px = project_points(WIDE_CAM, X)
    back = backproject_to_plane(WIDE_CAM, px, plane)
    assert np.max(np.linalg.norm(back - X, axis=1)) < 1e-6
    rays = pixel_rays(WIDE_CAM, px)
    assert np.allclose(rays[:, 2], 1.0)
    assert np.allclose(np.cross(rays, X), 0, atol=1e-6)


def test_empty_inputs() -> None:
    assert undistort_pixels(PAPER_CAM, np.empty((0, 2))).shape == (0, 2)
    assert project_points(PAPER_CAM, np.empty((0, 3))).shape == (0, 2)


# --- intrinsics on real photos: OpenCV's sample set (see tests/data/opencv_left/README.md) ---

@pytest.fixture(scope="module")
def opencv_result(opencv_photos):
    return calibrate_intrinsics(opencv_photos, BoardSpec((9, 6), 1.0))


def test_real_photos_calibrate(opencv_result, opencv_photos) -> None:
    r = opencv_result
    assert len(r.files_used) == len(opencv_photos) and not r.files_rejected
    assert r.camera.source == "intrinsics" and r.camera.image_size == (640, 480)
    assert r.camera.rms_px < 0.5
    assert len(r.per_view_rms_px) == len(r.files_used)
    assert np.all(r.per_view_rms_px < 0.6)
    # published values for this set (OpenCV tutorial): fx ~ fy ~ 533 px, principal point ~ (342, 234)
    K = r.camera.K
    assert 525 < K[0, 0] < 540 and 525 < K[1, 1] < 540
    assert 330 < K[0, 2] < 355 and 220 < K[1, 2] < 245
    assert -0.35 < r.camera.dist[0] < -0.2  # barrel distortion


def test_real_photos_match_plain_opencv(opencv_result) -> None:
    """Same corners, same flags: identical to cv2.calibrateCamera to 0.2 % in fx, fy."""
    r = opencv_result
    _, K, _, _, _ = cv2.calibrateCamera([o.astype(np.float32) for o in r.object_points],
                                        [i.astype(np.float32).reshape(-1, 1, 2)
                                         for i in r.image_points], (640, 480), None, None,
                                        flags=r.flags)
    assert abs(r.camera.K[0, 0] / K[0, 0] - 1) < 2e-3
    assert abs(r.camera.K[1, 1] / K[1, 1] - 1) < 2e-3


def test_real_photos_match_tutorial_detector(opencv_result, opencv_photos) -> None:
    """The tutorial's own recipe (classic detector + cornerSubPix, 5x5 window) agrees to 0.5 % in fx, fy."""
    obj, img = [], []
    objp = BoardSpec((9, 6), 1.0).object_points().astype(np.float32)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    for p in opencv_photos:
        g = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6), None)
        if ok:
            img.append(cv2.cornerSubPix(g, c, (5, 5), (-1, -1), crit))
            obj.append(objp)
    assert len(img) >= 10
    _, K, _, _, _ = cv2.calibrateCamera(obj, img, (640, 480), None, None,
                                        flags=opencv_result.flags)
    assert abs(opencv_result.camera.K[0, 0] / K[0, 0] - 1) < 5e-3
    assert abs(opencv_result.camera.K[1, 1] / K[1, 1] - 1) < 5e-3


def test_too_few_views_names_the_folder(opencv_photos, tmp_path) -> None:
    folder = tmp_path / "intrinsics"
    folder.mkdir()
    for p in opencv_photos[:2]:
        shutil.copy(p, folder / p.name)
    blank = folder / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    with pytest.raises(DatasetError, match="intrinsics.*found in 2 of 3 view"):
        calibrate_intrinsics(sorted(folder.iterdir()), BoardSpec((9, 6), 1.0))


def test_rejected_views_are_listed(opencv_photos, tmp_path) -> None:
    blank = tmp_path / "blank.png"
    cv2.imwrite(str(blank), np.full((480, 640), 128, np.uint8))
    r = calibrate_intrinsics([*opencv_photos[:5], blank], BoardSpec((9, 6), 1.0))
    assert r.files_rejected == (blank,)
    assert len(r.files_used) == 5
    assert r.flags & cv2.CALIB_FIX_K3  # few views: k3 fixed
    assert r.camera.dist[4] == 0.0


def test_wrong_image_size_is_reported(opencv_photos) -> None:
    with pytest.raises(DatasetError, match="expected 800x600"):
        calibrate_intrinsics(opencv_photos[:3], BoardSpec((9, 6), 1.0), image_size=(800, 600))


def test_detect_chessboard_none_on_blank() -> None:
    assert detect_chessboard(np.full((200, 300), 200, np.uint8), (9, 6)) is None


# --- intrinsics on simulated views with known truth -------------------------------------

BUNDLED = Path(__file__).resolve().parents[1] / "data" / "paper_rig"


def test_simulated_views_recover_truth() -> None:
    """The bundled paper-rig views: fx, fy to 0.05 %, principal point to 2 px, vs truth.json."""
    from lidarcal.io.dataset import load_dataset
    ds = load_dataset(BUNDLED)
    Kt = np.array(ds.truth()["camera"]["K"])
    r = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board, ds.image_size)
    K = r.camera.K
    assert not r.files_rejected
    assert r.camera.rms_px < 0.1
    assert abs(K[0, 0] / Kt[0, 0] - 1) < 5e-4 and abs(K[1, 1] / Kt[1, 1] - 1) < 5e-4
    assert np.hypot(K[0, 2] - Kt[0, 2], K[1, 2] - Kt[1, 2]) < 2.0
    # k3 is not seen by a 12 mm lens's views: model selection keeps it at 0
    assert r.camera.dist[4] == 0.0 and r.flags & cv2.CALIB_FIX_K3
    # the estimated model maps the truth's rays to within 1.5 px everywhere in the image
    # (what remains is mostly a principal-point offset of ~0.7 px)
    cam_t = CameraModel(Kt, np.array(ds.truth()["camera"]["dist"], float), ds.image_size)
    w, h = ds.image_size
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, 30), np.linspace(0, h - 1, 20)), -1)
    g = g.reshape(-1, 2)
    xy_t = undistort_pixels(cam_t, g)
    px = project_points(r.camera, np.column_stack([xy_t, np.ones(len(g))]))
    assert np.max(np.linalg.norm(px - g, axis=1)) < 1.5


def test_zhang_calibration_is_the_same_every_run() -> None:
    """40 noisy simulated views of a 9 x 6 board through the wide lens: the same camera, bit
    for bit, from five runs (OpenCV's threaded sums made it differ by ~1e-12 from run to
    run), and the caller's OpenCV thread count is left as it was."""
    from lidarcal.camera import _calibrate
    rng = np.random.default_rng(7)
    obj = np.zeros((54, 3))
    obj[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 30.0
    img_pts, obj_pts = [], []
    while len(img_pts) < 40:
        rvec = rng.normal(0, 0.35, 3)
        tvec = np.array([rng.uniform(-200, 50), rng.uniform(-150, 50), rng.uniform(450, 900)])
        px, _ = cv2.projectPoints(obj, rvec, tvec, WIDE_CAM.K, WIDE_CAM.dist)
        px = px.reshape(-1, 2) + rng.normal(0, 0.1, (54, 2))
        if np.all((px > 0) & (px < np.array(WIDE_CAM.image_size) - 1)):
            img_pts.append(px)
            obj_pts.append(obj)
    threads = cv2.getNumThreads()
    runs = [_calibrate(img_pts, obj_pts, WIDE_CAM.image_size, 0)[0] for _ in range(5)]
    assert cv2.getNumThreads() == threads
    for cam in runs[1:]:
        assert np.array_equal(cam.K, runs[0].K) and np.array_equal(cam.dist, runs[0].dist)
    assert abs(runs[0].K[0, 0] / WIDE_CAM.K[0, 0] - 1) < 2e-3  # and it is the lens simulated
