"""The laser plane from lights-on colour photos of a line laser on a flat chessboard.

Photos rendered by :mod:`lidarcal.synthetic.laserphotos` with a truth plane; the
tolerances follow from the rendering: stripe centres ~0.1 px, 1 px ~ 0.6-0.9 mm at
the boards, 6 photos.
"""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.geometry import Plane
from lidarcal.io.dataset import BoardSpec, DatasetError
from lidarcal.laserplane import (
    PhotoResult,
    fit_laser_plane,
    laser_plane,
    read_camera_json,
)
from lidarcal.stripe import detect_laser_colour, laser_response, stripe_centres
from lidarcal.synthetic.laserphotos import LaserPhotoConfig, write_laser_photos

SMALL = LaserPhotoConfig(image_size=(800, 600), f_px=760.0, sheet_sigma_mm=0.8)


def _truth(folder: Path) -> dict:
    return json.loads((folder / "truth.json").read_text())


def _truth_plane(t: dict) -> Plane:
    lp = t["laser_plane"]
    n = np.asarray(lp["normal"], float)
    return Plane.from_normal_point(n, n * lp["d_mm"])


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    """6 photos of a red laser on an 8x5 board (one with the laser beside the board)."""
    out = tmp_path_factory.mktemp("laser") / "photos"
    return write_laser_photos(out, seed=5, n_photos=7, cfg=SMALL, miss=(3,))


@pytest.fixture(scope="module")
def result(photos):
    t = _truth(photos)
    return laser_plane(photos, BoardSpec(tuple(t["pattern"]), t["square_mm"]),
                       read_camera_json(photos / "camera.json"))


def test_plane_recovers_truth(photos, result) -> None:
    truth = _truth_plane(_truth(photos))
    ang = np.degrees(np.arccos(min(1.0, abs(result.plane.normal @ truth.normal))))
    assert ang < 0.5
    used = [p for p in result.photos if p.used]
    pts = np.vstack([p.points_mm for p in used])
    # the truth plane through the measured points: offset within 1.5 mm, each point close
    assert abs(np.mean(truth.distance(pts))) < 1.5
    assert np.sqrt(np.mean(truth.distance(pts) ** 2)) < 1.0
    assert result.rms_mm <= 0.25
    assert result.plane.d >= 0
    assert len(used) >= 5  # of the 6 photos with the laser on the board
    # the reported uncertainty is not absurd against the true error
    assert 0 < result.sigma_normal_deg < 0.5 and 0 < result.sigma_d_mm < 5


def test_laser_beside_the_board_is_rejected_by_name(photos, result) -> None:
    miss = [p for p in result.photos if p.name == "03.png"]
    assert miss and not miss[0].used and len(miss[0].centres_px) == 0
    assert any("03.png" in w and "not used" in w for w in result.warnings)


def test_centres_lie_on_the_true_stripe(photos, result) -> None:
    """Each used photo's stripe centres, cast onto its (estimated) board plane, lie on the
    true laser plane to well under a pixel's footprint (~0.7 mm)."""
    truth = _truth_plane(_truth(photos))
    for p in result.photos:
        if p.used:
            d = truth.distance(p.points_mm)
            assert np.sqrt(np.mean(d ** 2)) < 0.5, p.name
            assert np.max(np.abs(d)) < 1.5, p.name


def test_auto_colour_and_lit_squares(photos) -> None:
    """auto finds the red laser; in its colour excess the lit white squares are dark, while
    the brightest channel shows them as bright as the stripe."""
    img = cv2.imread(str(photos / "00.png"), cv2.IMREAD_COLOR)
    assert detect_laser_colour(img) == "red"
    assert detect_laser_colour(cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY),
                                            cv2.COLOR_GRAY2BGR)) == "gray"
    red, gray = laser_response(img, "auto"), laser_response(img, "gray")
    # bright pixels: the stripe alone in the colour excess; the white squares as well in gray
    assert (red >= 60).sum() < 0.2 * (gray >= 120).sum()
    assert (gray >= 120).sum() > 5000
    with pytest.raises(ValueError, match="laser colour must be one of"):
        laser_response(img, "purple")


def test_gray_lights_on_photo_gives_no_wrong_points(photos, result) -> None:
    """The brightest channel of a lights-on photo (white squares as bright as the stripe):
    the gates reject the stripe, or every centre found is on the true stripe."""
    truth = _truth_plane(_truth(photos))
    cam = read_camera_json(photos / "camera.json")
    from lidarcal.board import board_view
    from lidarcal.camera import backproject_to_plane
    from lidarcal.laserplane import find_board

    t = _truth(photos)
    board = BoardSpec(tuple(t["pattern"]), t["square_mm"])
    for p in result.photos:
        if not p.used:
            continue
        img = cv2.imread(str(photos / p.name), cv2.IMREAD_COLOR)
        resp = laser_response(img, "red")
        corners, spec = find_board(img, board, resp, "red", "core") or \
            find_board(img, board, resp, "red", "laser")
        view = board_view(cam, corners, spec)
        mask = np.zeros(img.shape[:2], np.uint8)
        cv2.fillPoly(mask, [np.round(view.outline_px).astype(np.int32)], 1)
        pts, info = stripe_centres(laser_response(img, "gray"), mask.astype(bool), cam,
                                   return_info=True)
        if info["problem"] is None:
            d = truth.distance(backproject_to_plane(cam, pts, view.plane_pnp))
            assert np.max(np.abs(d)) < 1.5, p.name


def _line_photo(plane: Plane, board_n: np.ndarray, board_d: float, rng, n=60) -> PhotoResult:
    """3D points of one stripe: the laser plane met with a board plane, with 0.05 mm noise."""
    u = np.cross(plane.normal, board_n)
    u /= np.linalg.norm(u)
    A = np.vstack([plane.normal, board_n, u])
    p0 = np.linalg.solve(A, [plane.d, board_d, 0.0])
    t = np.linspace(-80, 80, n)
    pts = p0 + t[:, None] * u + rng.normal(0, 0.05, (n, 3))
    return PhotoResult("x.png", np.zeros((n, 2)), pts, 0.1)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_drops_a_photo_off_the_plane(seed) -> None:
    rng = np.random.default_rng(seed)
    n = np.array([0.8, -0.3, 0.2])
    truth = Plane.from_normal_point(n / np.linalg.norm(n), np.array([0.0, 0.0, 700.0]))
    photos = []
    for k in range(6):
        bn = np.array([rng.uniform(-1.2, 1.2), rng.uniform(-1.2, 1.2), -1.0])  # stripes cross
        bn /= np.linalg.norm(bn)
        photos.append(replace(_line_photo(truth, bn, bn @ [0, 0, rng.uniform(600, 800)], rng),
                              name=f"{k}.png"))
    bad = photos[4]
    bad.points_mm = bad.points_mm + 4.0 * truth.normal  # a wrong board pose: 4 mm off
    plane, rms, s_ang, _, _ = fit_laser_plane(photos)
    assert not bad.used and "off the plane" in bad.problem
    assert all(p.used for p in photos if p is not bad)
    ang = np.degrees(np.arccos(min(1.0, abs(plane.normal @ truth.normal))))
    assert ang < 0.05 and rms < 0.08 and s_ang < 0.1


def test_parallel_stripes_do_not_determine_the_plane() -> None:
    rng = np.random.default_rng(3)
    truth = Plane.from_normal_point(np.array([1.0, 0, 0]), np.array([0.0, 0, 700]))
    bn = np.array([0.0, 0.0, -1.0])
    photos = [_line_photo(truth, bn, -700.0, rng) for k in range(4)]  # one board pose: one line
    with pytest.raises(ValueError, match="nearly\\) one line"):
        fit_laser_plane(photos)


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *args], capture_output=True,
                          text=True, timeout=300, check=False)


def test_cli_writes_the_plane(photos, tmp_path) -> None:
    """``lidarcal laser-plane``: the pattern given the other way round (5x8 for 8x5)."""
    out = tmp_path / "plane.json"
    r = _run("laser-plane", str(photos), "--pattern", "5x8", "--square-mm", "30",
             "--camera", str(photos / "camera.json"), "--out", str(out), "--laser-colour", "red")
    assert r.returncode == 0, r.stderr
    d = json.loads(out.read_text())
    assert list(d) == ["format", "normal", "d_mm", "rms_mm", "sigma", "images", "warnings"]
    assert d["format"] == "lidarcal-laser-plane/1" and set(d["sigma"]) == {"normal_deg", "d_mm"}
    assert [set(i) for i in d["images"]] == [{"name", "used", "centres", "rms_px", "centres_on"}] * 7
    truth = _truth_plane(_truth(photos))
    assert np.degrees(np.arccos(min(1.0, abs(np.dot(d["normal"], truth.normal))))) < 0.5
    assert "03.png" in r.stderr


def test_cli_bad_input_one_line(photos, tmp_path) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    r = _run("laser-plane", str(empty), "--pattern", "8x5", "--square-mm", "30",
             "--camera", str(photos / "camera.json"), "--out", str(tmp_path / "p.json"))
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        f"error: {empty}: holds no .png/.jpg/.bmp/.tif photos; give the folder that holds them"]
    r = _run("laser-plane", str(photos), "--pattern", "8x5", "--square-mm", "30",
             "--camera", str(tmp_path / "nope.json"), "--out", str(tmp_path / "p.json"))
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "nope.json: missing camera file" in r.stderr
    assert not (tmp_path / "p.json").exists()


def test_too_few_usable_photos_names_the_folder(photos, tmp_path) -> None:
    one = tmp_path / "one"
    one.mkdir()
    (one / "00.png").write_bytes((photos / "00.png").read_bytes())
    (one / "03.png").write_bytes((photos / "03.png").read_bytes())
    t = _truth(photos)
    with pytest.raises(DatasetError, match=r"one.*measured on 1 photo.*03.png"):
        laser_plane(one, BoardSpec(tuple(t["pattern"]), t["square_mm"]),
                    read_camera_json(photos / "camera.json"))


def test_residual_figure(result) -> None:
    import matplotlib

    matplotlib.use("Agg")
    from lidarcal.laserplane import residual_figure

    fig = residual_figure(result)
    lines = fig.axes[0].get_lines()
    assert len(lines) == sum(p.used for p in result.photos) + 1  # + the zero line
    assert "03.png" in fig.axes[0].get_title()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_stripe_direction_from_its_centres_undoes_a_tilted_average(seed) -> None:
    """A speckled stripe seen only in pieces (hidden every other 32 px, as between overexposed
    white squares): averaged along a direction 5 deg off (what along_stripe's search returned
    on a clean-room photo, scripts/cleanroom_oneboard.py harsh seed 1: 83.1 for 88.6 deg) its
    centres tilt within each piece; the centres' own line (centres_direction_deg) lies within
    0.2 deg of the stripe (measured 0.01-0.08), and averaged along it the centres' rms from
    the true line is below 0.6 of the tilted one's (measured 0.34-0.50 px against 0.98-1.03)."""
    from lidarcal.laser_colour import along_stripe, centres_direction_deg

    rng = np.random.default_rng(seed)
    h, w, theta = 400, 200, np.radians(86.0 + seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    nrm = np.array([-np.sin(theta), np.cos(theta)])  # the stripe's normal, image x/y
    dist = (xx - 100) * nrm[0] + (yy - 200) * nrm[1]
    field = cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 1.5) ** 2 + \
        cv2.GaussianBlur(rng.normal(size=(h, w)).astype(np.float32), (0, 0), 1.5) ** 2
    speck = field / field.mean()
    resp = 180 * np.exp(-0.5 * (dist / 2.5) ** 2) * speck
    resp[(yy // 32) % 2 == 1] = 0  # hidden pieces
    resp = np.clip(resp, 0, 255).astype(np.uint8)
    mask = np.zeros((h, w), bool)
    mask[20:h - 20, 20:w - 20] = True

    def centres_err(deg):
        avg, _ = along_stripe(resp, mask, 32, smooth_px=32, direction_deg=deg)
        c = stripe_centres(avg, mask)
        d = (c[:, 0] - 100) * nrm[0] + (c[:, 1] - 200) * nrm[1]
        return c, float(np.sqrt(np.mean(d ** 2)))

    true_deg = np.degrees(theta)
    c_off, e_off = centres_err(true_deg - 5.0)
    own = centres_direction_deg(c_off)
    assert abs((own - true_deg + 90) % 180 - 90) < 0.2
    _, e_own = centres_err(own)
    assert e_own < 0.6 * e_off, (e_own, e_off)
