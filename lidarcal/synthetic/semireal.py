"""Semi-real laser photos: a red line laser rendered into real lights-on chessboard photos.

The test data of :mod:`lidarcal.laserplane` on real images: the real photos of a
chessboard (``data/real_tapas``: real lighting, lens, hands, red labels, floor)
with the stripe of a line laser drawn in on the board's true plane, then passed
through what a real camera does to a bright red line. The equations:

(S1) board pose ``X = R_b P + T_b`` by ``cv2.solvePnP`` of the real photo's corners,
     stray corners replaced (eq. 1); its plane ``n_b . X = d_b`` (eq. 3) is the truth the stripe lies on.
(S2) each pixel's ray ``X = t (x, y, 1)``, ``(x, y)`` the undistorted normalised
     pixel (eq. 5), meets the board (inside the board's physical outline: the pattern
     plus ``board_margin_mm``) or, beyond it, a wall ``Z = z_wall``:
     ``t = d_s / (n_s . (x, y, 1))``.
(S3) the laser sheet ``n_L . X = d_L`` has a Gaussian profile of 1-sigma ``s`` across
     it: irradiance ``E(X) = P exp(-(n_L . X - d_L)^2 / (2 s^2))``, averaged over
     ``ss x ss`` sub-pixels, times a speckle field (mean 1, contrast ``c``).
(S4) linear signal per channel ``c``: ``I_c = e rho_c + k_c rho E`` with ``rho_c``
     the photo's own pixel (sRGB decoded to linear), ``rho`` its luminance over the
     board's white (the surface's albedo), ``k_c`` the sensor's response to the
     laser's wavelength (red: R 1, G ~0.1, B ~0.05), then lens halo and PSF.
(S5) sensor and camera: clip at full well, blooming (the excess spills into the
     neighbours), Bayer RGGB mosaic and demosaicing (``cv2.cvtColor``; of the change the
     laser makes: the photo carries its own camera's demosaicing already; ``remosaic``: of
     the whole photo, its colour fringes doubled), auto white
     balance (gains >= 1: a clipped core stays white), sRGB encoding, 8 bits, JPEG
     with 4:2:0 chroma subsampling.

A laser core ``P`` tens of times the white paper's level clips every channel: a
white core in a red halo, as real photos show. ``upscale`` makes large photos
(the real photo resized, the camera's ``K`` scaled, the laser drawn at the full
resolution); ``pad_frac`` puts the photo in a larger frame (the board no longer
fills it); ``exif_orientation`` writes the JPEG with that EXIF tag over the
sensor's (landscape) pixels, as a phone held upright does.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np

from ..board import board_view
from ..camera import undistort_pixels
from ..corners import detect_chessboard
from ..geometry import Plane, unit
from ..io.dataset import BoardSpec, CameraModel, write_json_atomic

_CHANNEL = {"blue": 0, "green": 1, "red": 2}


@dataclass(frozen=True)
class StripeLook:
    """How the camera sees the laser (S3-S5); mm, px (of the written photo), linear units
    of the board's white."""

    sheet_sigma_mm: float = 1.0
    peak: float = 6.0                      # P: the sheet's peak on white paper, x white level
    response: tuple[float, float, float] = (0.05, 0.10, 1.0)  # k_c (B, G, R) for 650 nm
    halo: float = 0.1                      # share of the stripe's light in a wide halo
    halo_sigma_px: float = 3.0
    psf_sigma_px: float = 0.6
    bloom: float = 0.25                    # share of the clipped excess spilled around
    bloom_sigma_px: float = 1.5
    speckle: float = 0.3                   # speckle contrast (std / mean)
    speckle_grain_px: float = 1.0
    exposure: float = 1.0                  # e: the scene's exposure (> 1: white squares clip)
    awb: tuple[float, float, float] = (1.06, 1.0, 1.0)     # B, G, R gains after demosaicing
    bayer: bool = True
    remosaic: bool = False                 # the whole photo demosaiced again: its colour
                                           # fringes at the square edges doubled (a camera
                                           # with strong fringes or chromatic aberration)
    jpeg_quality: int | None = 90          # None: PNG
    read_noise: float = 0.002              # linear, x white
    board_margin_mm: float = 60.0          # physical board beyond the pattern's outer squares
    z_wall_mm: float = 2600.0              # the surface beyond the board
    upscale: float = 1.0
    pad_frac: float = 0.0                  # the frame grown by this share of each side
    exif_orientation: int = 1


@dataclass(frozen=True)
class RealView:
    """One real photo with its board pose (S1)."""

    name: str
    image: np.ndarray      # BGR uint8
    R: np.ndarray          # board -> camera
    T: np.ndarray          # (3,) mm
    rms_px: float


def read_real_views(folder: str | Path) -> tuple[CameraModel, BoardSpec, list[RealView]]:
    """The camera, board and photos of a real recording (``camera.json``, ``board.json``,
    ``NN.png``) with each photo's board pose by solvePnP of its corners (S1), a stray
    corner replaced (:func:`lidarcal.laserplane.board_view_robust`: the TAPAS views 02 and
    06 have outer corners 3-5 px off, dragged by the fiducial rings)."""
    from ..laserplane import board_view_robust, read_camera_json

    folder = Path(folder)
    camera = read_camera_json(folder / "camera.json")
    b = json.loads((folder / "board.json").read_text())
    board = BoardSpec(tuple(b["inner_corners"]), float(b["square_mm"]))
    views = []
    for p in sorted(folder.glob("*.png")):
        img = cv2.imread(str(p), cv2.IMREAD_COLOR)
        corners = detect_chessboard(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), board.pattern_size)
        if corners is None:
            continue
        v, _ = board_view_robust(camera, corners, board)
        views.append(RealView(p.name, img, v.R_pnp, np.ravel(v.T_pnp),
                              float(v.reprojection_rms_px[1])))
    return camera, board, views


def choose_laser_plane(views: list[RealView], board: BoardSpec,
                       emitter_mm: tuple[float, float, float] = (-250.0, 60.0, 0.0),
                       incline_deg: float = 25.0) -> Plane:
    """A laser sheet from an emitter beside the camera through the middle of the boards'
    patterns, its trace inclined ``incline_deg`` from the image's vertical."""
    cols, rows = board.inner_corners
    mid = np.array([(cols - 1) / 2, (rows - 1) / 2, 0.0]) * board.square_mm
    C = np.mean([v.R @ mid + v.T for v in views], axis=0)
    E = np.asarray(emitter_mm, float)
    a = np.radians(incline_deg)
    along = np.array([np.sin(a), np.cos(a), 0.0])  # a direction in the sheet
    n = unit(np.cross(C - E, along))
    pl = Plane.from_normal_point(n, E)
    return pl if pl.d >= 0 else Plane(-pl.normal, -pl.d)


def scaled_camera(camera: CameraModel, scale: float, pad: tuple[int, int] = (0, 0)
                  ) -> CameraModel:
    """The camera of the photo resized by ``scale`` (pixel centres: ``u' = s (u + 1/2) -
    1/2``) inside a frame grown by ``pad`` = (px left/right, px top/bottom) after it."""
    K = np.array(camera.K, float)
    S = np.array([[scale, 0, 0.5 * scale - 0.5 + pad[0]],
                  [0, scale, 0.5 * scale - 0.5 + pad[1]], [0, 0, 1.0]])
    w, h = camera.image_size
    size = (round(w * scale) + 2 * pad[0], round(h * scale) + 2 * pad[1])
    return CameraModel(S @ K, np.asarray(camera.dist, float), size, source=camera.source)


def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    v = v.astype(np.float32) / 255.0
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _linear_to_srgb8(v: np.ndarray) -> np.ndarray:
    v = np.clip(v, 0.0, 1.0)
    s = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
    return np.clip(np.rint(255.0 * s), 0, 255).astype(np.uint8)


def _sheet_distance(camera: CameraModel, px: np.ndarray, R: np.ndarray, T: np.ndarray,
                    board: BoardSpec, laser: Plane, look: StripeLook) -> np.ndarray:
    """(S2) distance (mm) to the laser sheet of the surface point each pixel (N, 2) sees."""
    xy = undistort_pixels(camera, px)
    rays = np.column_stack([xy, np.ones(len(xy))])
    nb = R[:, 2]
    t = (nb @ T) / (rays @ nb)
    X = t[:, None] * rays
    P = (X - T) @ R  # board coordinates
    cols, rows = board.inner_corners
    sq, m = board.square_mm, look.board_margin_mm
    on = ((P[:, 0] > -sq - m) & (P[:, 0] < cols * sq + m) & (P[:, 1] > -sq - m)
          & (P[:, 1] < rows * sq + m) & (t > 0))
    Xw = (look.z_wall_mm / rays[:, 2])[:, None] * rays
    X = np.where(on[:, None], X, Xw)
    return laser.distance(X)


def _sheet_image(camera: CameraModel, shape: tuple[int, int], R: np.ndarray, T: np.ndarray,
                 board: BoardSpec, laser: Plane, look: StripeLook) -> np.ndarray:
    """(S3) the sheet's profile ``exp(-delta^2 / 2 s^2)`` per pixel (H, W), averaged over
    sub-pixels; computed only in a band found on a coarse grid of pixels."""
    H, W = shape
    step = max(1, round(max(H, W) / 400))
    gy, gx = np.mgrid[0:H + step:step, 0:W + step:step]
    grid = np.column_stack([gx.ravel(), gy.ravel()]).astype(float)
    dg = np.abs(_sheet_distance(camera, grid, R, T, board, laser, look)).reshape(gx.shape)
    # mm per px at the grid (the band must cover one grid step of the slowest change)
    # mm per px of the surfaces (the board-wall jumps left out): the band holds every pixel
    # within 6 sigma of the sheet, on either side of a grid step
    px_mm = max(float(np.nanpercentile(np.abs(np.diff(dg, axis=1)), 75)) / step, 1e-3)
    band = 6 * look.sheet_sigma_mm + 3 * step * px_mm
    near = (dg < band).astype(np.uint8)
    near = cv2.dilate(near, np.ones((3, 3), np.uint8))
    full = cv2.resize(near, (gx.shape[1] * step, gx.shape[0] * step),
                      interpolation=cv2.INTER_NEAREST)[:H, :W]
    ys, xs = np.nonzero(full)
    out = np.zeros((H, W), np.float32)
    if xs.size == 0:
        return out
    ss = int(np.clip(np.ceil(3 * px_mm / look.sheet_sigma_mm), 1, 5))
    acc = np.zeros(xs.size)
    for i in range(ss):
        for j in range(ss):
            px = np.column_stack([xs + (j + 0.5) / ss - 0.5, ys + (i + 0.5) / ss - 0.5])
            d = _sheet_distance(camera, px, R, T, board, laser, look)
            acc += np.exp(-0.5 * (d / look.sheet_sigma_mm) ** 2)
    out[ys, xs] = acc / ss ** 2
    return out


def _speckle(shape: tuple[int, int], look: StripeLook, rng: np.random.Generator) -> np.ndarray:
    """Multiplicative speckle, mean 1, contrast ``look.speckle``, grain ``speckle_grain_px``."""
    if look.speckle <= 0:
        return np.ones(shape, np.float32)
    z = rng.standard_normal(shape, dtype=np.float32)
    z = cv2.GaussianBlur(z, (0, 0), look.speckle_grain_px)
    z /= max(float(z.std()), 1e-6)
    return np.maximum(1.0 + look.speckle * z, 0.0).astype(np.float32)


def _bayer(lin: np.ndarray) -> np.ndarray:
    """(S5) RGGB mosaic of a linear BGR image (clipped at 1) and OpenCV's edge-aware
    demosaicing."""
    q = np.clip(np.rint(lin * 65535.0), 0, 65535).astype(np.uint16)
    m = np.empty(q.shape[:2], np.uint16)
    m[0::2, 0::2] = q[0::2, 0::2, 2]
    m[0::2, 1::2] = q[0::2, 1::2, 1]
    m[1::2, 0::2] = q[1::2, 0::2, 1]
    m[1::2, 1::2] = q[1::2, 1::2, 0]
    return cv2.cvtColor(m, cv2.COLOR_BayerBG2BGR_EA).astype(np.float32) / 65535.0  # RGGB


def render_semireal(view: RealView, camera: CameraModel, board: BoardSpec, laser: Plane,
                    look: StripeLook, rng: np.random.Generator
                    ) -> tuple[np.ndarray, CameraModel]:
    """One semi-real photo (BGR uint8, before JPEG) and the camera it was taken with (S1-S5)."""
    img = view.image
    cam = camera
    if look.upscale != 1.0:
        w, h = camera.image_size
        img = cv2.resize(img, (round(w * look.upscale), round(h * look.upscale)),
                         interpolation=cv2.INTER_CUBIC)
    if look.pad_frac > 0:
        px, py = round(look.pad_frac * img.shape[1]), round(look.pad_frac * img.shape[0])
        big = cv2.copyMakeBorder(img, py, py, px, px, cv2.BORDER_REPLICATE)
        soft = cv2.GaussianBlur(big, (0, 0), 0.02 * big.shape[1])
        inside = np.zeros(big.shape[:2], bool)
        inside[py:py + img.shape[0], px:px + img.shape[1]] = True
        img = np.where(inside[..., None], big, soft)
        cam = scaled_camera(camera, look.upscale, (px, py))
    elif look.upscale != 1.0:
        cam = scaled_camera(camera, look.upscale)
    H, W = img.shape[:2]
    lin = _srgb_to_linear(img)
    lum = lin @ np.array([0.0722, 0.7152, 0.2126], np.float32)
    # the board's white: a high percentile of the luminance over the pattern
    outline = board_view(cam, _project_corners(cam, view, board), board).outline_px
    mask = np.zeros((H, W), np.uint8)
    cv2.fillPoly(mask, [np.round(outline).astype(np.int32)], 1)
    white = float(np.percentile(lum[mask.astype(bool)], 95))
    albedo = np.clip(lum / max(white, 1e-3), 0.0, 1.2)
    sheet = _sheet_image(cam, (H, W), view.R, view.T, board, laser, look)
    E = look.peak * albedo * sheet * _speckle((H, W), look, rng)
    E = cv2.GaussianBlur(E, (0, 0), look.psf_sigma_px)
    E = (1 - look.halo) * E + look.halo * cv2.GaussianBlur(E, (0, 0), look.halo_sigma_px)
    base = np.clip(look.exposure * lin, 0.0, 1.0)
    sig = look.exposure * lin + white * E[..., None] * np.array(look.response, np.float32)
    excess = np.maximum(sig - 1.0, 0.0)
    sig = sig + look.bloom * cv2.GaussianBlur(excess, (0, 0), look.bloom_sigma_px)
    sig = sig + look.read_noise * rng.standard_normal(sig.shape, dtype=np.float32)
    sig = np.clip(sig, 0.0, 1.0)
    if look.bayer and look.remosaic:
        sig = _bayer(sig)
    elif look.bayer:  # the photo carries its camera's demosaicing: only the change made anew
        sig = np.clip(base + _bayer(sig) - _bayer(base), 0.0, 1.0)
    gains = np.array(look.awb, np.float32)
    sig = sig * (gains / gains.min())
    return _linear_to_srgb8(sig), cam


def _project_corners(cam: CameraModel, view: RealView, board: BoardSpec) -> np.ndarray:
    from ..camera import project_points

    return project_points(cam, board.object_points() @ view.R.T + view.T)


def encode_photo(img: np.ndarray, look: StripeLook) -> tuple[bytes, str]:
    """(S5) the photo's file bytes and suffix: JPEG 4:2:0 at ``jpeg_quality`` (with an EXIF
    orientation tag when ``exif_orientation`` != 1), else PNG."""
    if look.jpeg_quality is None:
        ok, buf = cv2.imencode(".png", img)
        return buf.tobytes(), ".png"
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(look.jpeg_quality),
                                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
                                         cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420])
    if not ok:
        raise OSError("cannot encode a JPEG")
    data = buf.tobytes()
    if look.exif_orientation != 1:
        data = with_exif_orientation(data, look.exif_orientation)
    return data, ".jpg"


def with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an APP1 EXIF segment holding the orientation tag (0x0112) after SOI."""
    from PIL import Image

    exif = Image.Exif()
    exif[0x0112] = int(orientation)
    payload = exif.tobytes()  # b"Exif\0\0" + TIFF
    seg = b"\xff\xe1" + (len(payload) + 2).to_bytes(2, "big") + payload
    return jpeg[:2] + seg + jpeg[2:]


#: the kinds of semi-real photo sets of :func:`write_semireal_photos`
KINDS = {
    "jpeg": StripeLook(),
    "fringes": StripeLook(remosaic=True),
    "jpeg80": StripeLook(jpeg_quality=80, peak=15.0, sheet_sigma_mm=0.7),
    "bright": StripeLook(exposure=1.4, peak=15.0, jpeg_quality=85),
    "png": StripeLook(jpeg_quality=None, bayer=False, speckle=0.15),
    "portrait": StripeLook(exif_orientation=6),
    "big": StripeLook(upscale=6.25, speckle_grain_px=2.0, halo_sigma_px=18.0,
                      bloom_sigma_px=6.0, psf_sigma_px=2.0),
    "bigpad": StripeLook(upscale=3.125, pad_frac=0.5, speckle_grain_px=1.5,
                         halo_sigma_px=9.0, bloom_sigma_px=3.0, psf_sigma_px=1.0),
}


def write_semireal_photos(real: str | Path, out: str | Path, kind: str = "jpeg",
                          seed: int = 0, shots: int = 2, look: StripeLook | None = None,
                          laser: Plane | None = None, names: tuple[str, ...] | None = None
                          ) -> Path:
    """Write ``out/NN_k.jpg`` (``shots`` photos per real view: the stripe's speckle and
    noise drawn anew), ``out/camera.json`` and ``out/truth.json`` (as
    :func:`lidarcal.synthetic.laserphotos.write_laser_photos`: ``laser_plane``, ``pattern``,
    ``square_mm``, ``photos`` with each board pose).

    ``kind`` names a :data:`KINDS` look (``look`` overrides it); ``laser`` defaults to
    :func:`choose_laser_plane`; ``names`` picks real photos (default: all with a board).
    """
    look = look or KINDS[kind]
    camera, board, views = read_real_views(real)
    if names is not None:
        views = [v for v in views if v.name in names]
    laser = laser or choose_laser_plane(views, board)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    photos, cam = [], camera
    for j, v in enumerate(views):
        for k in range(shots):
            rng = np.random.default_rng([seed, 7101, j, k])
            lk = replace(look, exposure=look.exposure * (1.0 + 0.08 * k))
            img, cam = render_semireal(v, camera, board, laser, lk, rng)
            data, suffix = encode_photo(img, lk)
            name = f"{Path(v.name).stem}_{k}{suffix}"
            (out / name).write_bytes(data)
            photos.append({"name": name, "kind": kind, "R": v.R.tolist(),
                           "T_mm": v.T.tolist(), "real": v.name,
                           "real_rms_px": v.rms_px})
    write_json_atomic(out / "camera.json", {"K": np.asarray(cam.K).tolist(),
                                            "dist": list(np.asarray(cam.dist, float)),
                                            "image_size": list(cam.image_size),
                                            "source": "lidarcal.synthetic.semireal"})
    truth = {"laser_plane": {"normal": laser.normal.tolist(), "d_mm": float(laser.d)},
             "laser_colour": "red", "pattern": list(board.inner_corners),
             "square_mm": board.square_mm, "seed": seed, "kind": kind, "photos": photos}
    write_json_atomic(out / "truth.json", truth)
    return out
