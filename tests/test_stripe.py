"""Laser stripes, section 1.3: sub-pixel centres on rendered profiles, laser plane / E / alpha on the simulator."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from lidarcal.geometry import Plane, angle_between_deg, intersect_planes, unit
from lidarcal.io.dataset import CameraModel
from lidarcal.stripe import reflectance_ratio, stripe_centres

H, W = 240, 420


def render_stripe(centre, sigma=1.6, peak=180.0, noise=3.0, ambient=4.0, seed=0,
                  albedo=None, speckle=0.0, psf=0.7, vertical=False):
    """A stripe whose centre line is ``y = centre(x)`` (or ``x = centre(y)``), Gaussian profile.

    ``albedo`` (H, W) multiplies stripe and ambient light (dark and bright squares).
    The profile is measured perpendicular to the line; saturation at 255.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(float)
    if vertical:
        x, y = y, x
    c = centre(x)
    dc = (centre(x + 0.5) - centre(x - 0.5))
    d = (y - c) / np.sqrt(1 + dc**2)  # perpendicular distance
    alb = np.ones((H, W)) if albedo is None else albedo
    sig = peak * np.exp(-0.5 * (d / sigma) ** 2)
    if speckle > 0:
        f = cv2.GaussianBlur(rng.standard_normal((H, W)), (0, 0), 1.5)
        sig = sig * np.exp(speckle * f / f.std() - 0.5 * speckle**2)
    img = cv2.GaussianBlur(alb * (sig + ambient), (0, 0), psf) + 2.0
    img = img + rng.normal(0, noise, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def full_mask(margin=20):
    m = np.zeros((H, W), bool)
    m[margin:H - margin, margin:W - margin] = True
    return m


def line(a, b, x0=W / 2):
    return lambda x: a + b * (x - x0)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("slope", [0.0, 0.17, -0.4])
def test_centres_of_straight_stripe(seed, slope) -> None:
    """3 DN noise, 180 DN peak: centres unbiased (< 0.02 px mean) and scattered < 0.06 px."""
    f = line(118.37, slope)
    img = render_stripe(f, seed=seed)
    c, info = stripe_centres(img, full_mask(), return_info=True)
    err = (c[:, 1] - f(c[:, 0])) / np.sqrt(1 + slope**2)
    assert len(c) > 0.9 * (W - 40)
    assert abs(err.mean()) < 0.02
    assert err.std() < 0.06
    assert 2.5 < info["width_px"] < 6
    assert 2.0 < info["noise_dn"] < 4.0


def test_saturated_stripe_is_unbiased() -> None:
    f = line(101.7, 0.05)
    img = render_stripe(f, peak=900.0, sigma=2.0)
    assert (img == 255).mean() > 0.01
    c = stripe_centres(img, full_mask())
    err = c[:, 1] - f(c[:, 0])
    assert abs(err.mean()) < 0.02 and np.abs(err).max() < 0.15


def test_vertical_stripe() -> None:
    f = line(200.4, 0.1, x0=H / 2)  # x = f(y)
    img = render_stripe(f, vertical=True)
    c = stripe_centres(img, full_mask())
    err = c[:, 0] - f(c[:, 1])
    assert len(c) > 0.9 * (H - 40)
    assert abs(err.mean()) < 0.02 and err.std() < 0.06


def test_curved_stripe_with_camera() -> None:
    """A straight line on a board seen through strong distortion: outlier rejection keeps it."""
    cam = CameraModel(np.array([[500.0, 0, W / 2], [0, 500.0, H / 2], [0, 0, 1]]),
                      np.array([-0.35, 0.15, 0, 0, 0]), (W, H))
    xs = np.linspace(-0.6, 0.6, 4000)
    X = np.column_stack([xs, -0.12 + 0.1 * xs, np.ones_like(xs)])
    from lidarcal.camera import project_points
    px = project_points(cam, X)
    order = np.argsort(px[:, 0])
    f = lambda x: np.interp(x, px[order, 0], px[order, 1])
    img = render_stripe(f, seed=4)
    c, info = stripe_centres(img, full_mask(), camera=cam, return_info=True)
    err = c[:, 1] - f(c[:, 0])
    assert len(c) > 0.9 * (W - 40) and info["n_rejected"] < 0.05 * len(c)
    assert abs(err.mean()) < 0.03 and err.std() < 0.08


def test_planted_glints_are_rejected() -> None:
    f = line(120.2, 0.08)
    img = render_stripe(f, seed=5).astype(float)
    rng = np.random.default_rng(9)
    xs = rng.integers(30, W - 30, 25)
    for x in xs:  # bright blobs a few widths off the stripe, inside the profile windows
        y = int(f(x) + rng.choice([-7, 7]))
        img[y - 1:y + 2, x - 1:x + 2] = 250
    c = stripe_centres(img.astype(np.uint8), full_mask())
    err = c[:, 1] - f(c[:, 0])
    assert np.abs(err).max() < 0.3
    assert abs(err.mean()) < 0.02


def test_speckle_and_ambient() -> None:
    """Harsh: log-normal speckle (contrast 0.45), ambient 25 DN, noise 3 DN."""
    f = line(121.0, -0.12)
    img = render_stripe(f, speckle=0.45, ambient=25.0, seed=6)
    c = stripe_centres(img, full_mask(), min_snr=8.0)
    err = c[:, 1] - f(c[:, 0])
    assert len(c) > 0.8 * (W - 40)
    # speckle correlated over ~1.5 px with 45 % contrast moves each centre by ~0.3 px, unbiased
    assert abs(err.mean()) < 0.05 and err.std() < 0.4


def test_no_stripe_gives_nothing() -> None:
    rng = np.random.default_rng(0)
    img = np.clip(10 + rng.normal(0, 3, (H, W)), 0, 255).astype(np.uint8)
    assert len(stripe_centres(img, full_mask())) < 5
    assert stripe_centres(img, np.zeros((H, W), bool)).shape == (0, 2)
    with pytest.raises(ValueError, match="mask shape"):
        stripe_centres(img, np.ones((3, 3), bool))


def _edge_scene(offset_px, sigma, rho=0.32, seed=0):
    """Horizontal stripe running along a horizontal square edge ``offset_px`` below its centre.

    Columns of squares alternate every 40 px, so pure white and black stretches
    exist as well. Returns (stripe image, blackness as a bright image shows it, true y).
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(float)
    yc = 120.3
    cover = np.clip(yc + offset_px - (y - 0.5), 0, 1)  # part of the pixel above the edge
    blackfrac = np.where((x // 40) % 2 == 0, 1 - cover, cover)
    alb_stripe = 1 - (1 - rho) * blackfrac
    alb_bright = 1 - 0.82 * blackfrac
    sig = 230.0 * alb_stripe * np.exp(-0.5 * ((y - yc) / sigma) ** 2) + 3 * alb_bright
    img = cv2.GaussianBlur(sig, (0, 0), 0.7) + 2 + rng.normal(0, 0.5, sig.shape)
    bright = cv2.GaussianBlur(200 * alb_bright, (0, 0), 0.7) + rng.normal(0, 1.2, sig.shape)
    blk = np.clip((200 - bright) / (200 - 36), 0, 1)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), blk, yc


@pytest.mark.parametrize("offset", [-1.0, 0.0, 1.5])
def test_albedo_correction_removes_edge_bias(offset) -> None:
    """Along a black/white edge the plain centroid is pulled ~0.5-0.9 px; corrected < 0.1 px."""
    img, blk, yc = _edge_scene(offset, sigma=2.0)
    plain = stripe_centres(img, full_mask())
    corr = stripe_centres(img, full_mask(), blackness=blk, rho=0.32)
    assert np.abs(plain[:, 1] - yc).mean() > 0.4
    assert np.abs(corr[:, 1] - yc).mean() < 0.1


def test_reflectance_ratio_from_pure_squares() -> None:
    img, blk, _ = _edge_scene(10.0, sigma=1.6)
    _, info = stripe_centres(img, full_mask(), blackness=blk, return_info=True)
    assert abs(info["rho"] - 0.32) < 0.03
    assert abs(reflectance_ratio([info["samples"]]) - 0.32) < 0.03
    assert reflectance_ratio([]) is None


# --- the simulator: laser plane, E, alpha against truth -----------------------------------

def _truth_lines(truth, boards, index):
    from lidarcal.evaluate import truth_poses
    tplanes = [Plane(np.array(b["normal"]), b["d_mm"]) for b in truth["boards"]]
    tpl = []
    for b in boards:
        a = [min(angle_between_deg(b.plane.normal, p.normal),
                 180 - angle_between_deg(b.plane.normal, p.normal)) for p in tplanes]
        tpl.append(tplanes[int(np.argmin(a))])
    P = truth_poses(truth)[index]
    lp = Plane.from_normal_point(P.R[:, 2], P.T)
    E = intersect_planes(tpl[0], tpl[1], lp)
    return tpl, lp, E


BUNDLED = Path(__file__).resolve().parents[1] / "data" / "paper_rig"


@pytest.fixture(scope="module")
def paper_dataset(tmp_path_factory) -> tuple[Path, list[int]]:
    """The bundled paper-rig dataset (3 of its positions), else a fresh 3-position simulation."""
    if (BUNDLED / "truth.json").is_file() and (BUNDLED / "stripes").is_dir():
        return BUNDLED, [0, 43, 86]
    synthetic = pytest.importorskip("lidarcal.synthetic")
    out = tmp_path_factory.mktemp("paper") / "ds"
    path = synthetic.simulate(out, seed=3, rig="paper", n_positions=3, with_intrinsics=False,
                              with_sweeps=False)
    return path, [0, 1, 2]


def test_camera_lines_on_simulated_rig(paper_dataset) -> None:
    """Paper rig, truth camera: board planes < 0.02 deg, laser plane < 0.01 deg, E < 0.05 mm."""
    from lidarcal.board import find_v_boards
    from lidarcal.io.dataset import load_dataset, read_image
    from lidarcal.stripe import camera_lines, estimate_reflectance_ratio
    root, use = paper_dataset
    ds = load_dataset(root)
    truth = ds.truth()
    positions = [p for p in ds.positions if p.index in use]
    boards = find_v_boards(read_image(ds.board_image), ds.v_board, ds.camera)
    tplanes = [Plane(np.array(b["normal"]), b["d_mm"]) for b in truth["boards"]]
    for b in boards:
        errs = [min(angle_between_deg(b.plane.normal, p.normal),
                    180 - angle_between_deg(b.plane.normal, p.normal)) for p in tplanes]
        assert min(errs) < 0.02
        assert b.blackness is not None and 0.1 < b.bright_ratio < 0.3
    images = [read_image(p.stripe_image) for p in positions]
    rho = estimate_reflectance_ratio(ds.camera, images, boards)
    assert rho is not None and abs(rho - 0.32) < 0.05  # the simulator's stripe_albedo_black
    for pos, img in zip(positions, images):
        cl = camera_lines(ds.camera, img, boards, rho=rho)
        tpl, lp, E = _truth_lines(truth, boards, pos.index)
        a = angle_between_deg(cl.laser_plane.normal, lp.normal)
        assert min(a, 180 - a) < 0.01
        assert np.linalg.norm(cl.E - E) < 0.05
        lt = [unit(np.cross(tpl[k].normal, lp.normal)) for k in range(2)]
        lt = [lk if lk @ cl.l[k] > 0 else -lk for k, lk in enumerate(lt)]
        assert abs(cl.alpha_deg - np.degrees(np.arccos(lt[0] @ lt[1]))) < 0.01
        for k in range(2):  # each l[k] points from E towards its own stripe
            assert (cl.points_3d[k].mean(0) - cl.E) @ cl.l[k] > 0
            assert np.all(np.abs(tpl[k].distance(cl.points_3d[k])) < 0.2)
        assert cl.residual_rms_mm < 0.05
        assert len(cl.centres_px[0]) > 200 and len(cl.centres_px[1]) > 200


@pytest.mark.parametrize("channel", [2, 1])
def test_colour_laser_keeps_its_signal(tmp_path, channel) -> None:
    """A red (or green) laser in a BGR stripe image: read by its brightest channel, the
    stripe keeps its full peak (luminance would keep 30 % / 59 %) and its centres stay exact."""
    from lidarcal.io.dataset import read_stripe_image

    f = line(118.37, 0.17)
    gray = render_stripe(f, seed=4)
    rng = np.random.default_rng(5)
    bgr = np.clip(rng.normal(3.0, 1.0, (H, W, 3)), 0, 255).astype(np.uint8)
    bgr[:, :, channel] = gray
    path = tmp_path / "stripe.png"
    cv2.imwrite(str(path), bgr)
    img = read_stripe_image(path, (W, H))
    assert img.max() >= gray.max()
    c = stripe_centres(img, full_mask())
    err = (c[:, 1] - f(c[:, 0])) / np.sqrt(1 + 0.17**2)
    assert len(c) > 0.9 * (W - 40)
    assert abs(err.mean()) < 0.02 and err.std() < 0.06
