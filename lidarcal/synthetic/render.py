"""Image formation through the real lens model: bright chessboard images and dark stripe images.

Every pixel is mapped once through the inverse of OpenCV's distortion model to a
ray ``(x, y, 1)`` in the camera frame (:class:`RayMap`). Sub-pixel samples use
the local Jacobian of that map (exact to second order over a pixel). Pixels
are shaded at their centre; pixels where the material or surface changes
(square edges, board outlines) are re-rendered with ``n x n`` samples and
averaged (area anti-aliasing). Then: Gaussian optical PSF, sensor noise,
rounding and clipping to 8 bits.

Stripe images (section 1.3): the laser sheet is the LiDAR scan plane at that
position. A surface point at distance ``dist`` from the plane receives
``peak * albedo * exp(-dist^2 / (2 sigma^2)) * cos(incidence) * (r_ref / r)^2``
when it lies inside the LiDAR's aperture (in front of it when that is within +-90 deg), and is not shadowed
(a ray from the LiDAR centre reaches it first). Only pixels whose centre point
lies within a few sigma of the plane (plus the pixel's footprint on the
surface) are evaluated.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

from ..geometry import Pose
from .config import RigConfig
from .scene import (
    BLACK,
    DISC,
    NOTHING,
    POST,
    WALL,
    WHITE,
    InfinitePlane,
    Rect,
    materials,
    surface_normals,
    trace,
)


def _front(ql: np.ndarray, rig) -> np.ndarray:
    """LiDAR-frame points the scanner can see by their side: in front (x > 0) for an aperture
    within +-90 deg (then the angle test alone would also pass points behind), any side for a
    wider one (270 or 360 deg scanners)."""
    if max(abs(rig.lidar_angle_min_deg), abs(rig.lidar_angle_max_deg)) > 90.0:
        return np.ones(len(ql), bool)
    return ql[:, 0] > 0

def distort_normalized(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """OpenCV's distortion (k1, k2, p1, p2, k3) of normalised coordinates (..., 2)."""
    k1, k2, p1, p2, k3 = (list(dist) + [0.0] * 5)[:5]
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort_pixels(px: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of distorted pixels (N, 2).

    ``cv2.undistortPoints`` (with iteration criteria) gives the start; three Newton steps on OpenCV's
    forward model make the round trip exact to ~1e-9 px even with strong
    distortion.
    """
    px = np.asarray(px, dtype=float).reshape(-1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 5, 1e-12)
    xy = cv2.undistortPoints(px.reshape(-1, 1, 2), K, dist, None, None, criteria=crit).reshape(-1, 2)
    target = (np.column_stack([px, np.ones(len(px))]) @ np.linalg.inv(K).T)[:, :2]
    k1, k2, p1, p2, k3 = (list(np.ravel(dist)) + [0.0] * 5)[:5]
    x, y = xy[:, 0].copy(), xy[:, 1].copy()
    for _ in range(3):  # Newton on the forward model with its analytic Jacobian
        r2 = x * x + y * y
        rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)
        xy2 = x * y
        fx = x * rad + 2 * p1 * xy2 + p2 * (r2 + 2 * x * x) - target[:, 0]
        fy = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * xy2 - target[:, 1]
        cross = 2 * xy2 * drad + 2 * p1 * x + 2 * p2 * y
        a = rad + 2 * x * x * drad + 2 * p1 * y + 6 * p2 * x
        d = rad + 2 * y * y * drad + 6 * p1 * y + 2 * p2 * x
        det = a * d - cross * cross
        x -= (d * fx - cross * fy) / det
        y -= (a * fy - cross * fx) / det
    xy = np.column_stack([x, y])
    return xy


#: sub-pixel sample patterns of the area anti-aliasing (:func:`subpixel_offsets`)
ANTIALIAS_PATTERNS = ("grid", "multi-jittered")


def subpixel_offsets(n: int, pattern: str = "grid") -> np.ndarray:
    """Offsets (S = n*n, 2) from the pixel centre, in px, of the area anti-aliasing samples.

    ``"grid"``: a regular n x n grid. ``"multi-jittered"``: the canonical multi-jittered
    pattern (Chiu, Shirley, Wang, "Multi-jittered sampling", Graphics Gems IV, 1994), sample (i, j) at ``x = (i + (j + 1/2)/n)/n - 1/2``,
    ``y = (j + (i + 1/2)/n)/n - 1/2``: one sample in each cell of the n x n grid AND in each of
    the n^2 columns and rows of width 1/n^2. A regular n x n grid projects onto only n
    distinct x (and y) values, so the pixel area an edge parallel to the pixel rows or columns
    covers was rounded to steps of 1/n: the edge rendered up to 1/(2n) px from where it is
    (0.125 px at n = 4), the same along its whole length. Measured on the wide rig (seed 37):
    board.png's corner rows nearest the horizon (whose square edges run along the pixel rows)
    were 0.08-0.10 px off, the V corners 0.030/0.016 px rms from truth against 0.008 px at
    n = 16; with this pattern the steps are 1/n^2 and the V corners 0.008 px rms (n = 4).
    "grid" stays the default: every stored simulated dataset (``data/paper_rig``) was rendered
    with it and regenerates byte for byte."""
    if pattern == "grid":
        off = (np.arange(n) + 0.5) / n - 0.5
        du, dv = np.meshgrid(off, off)
        return np.column_stack([du.ravel(), dv.ravel()])
    if pattern != "multi-jittered":
        raise ValueError(f"unknown anti-aliasing pattern {pattern!r}; expected one of "
                         f"{ANTIALIAS_PATTERNS}")
    i, j = (a.ravel().astype(float) for a in np.meshgrid(np.arange(n), np.arange(n)))
    return np.column_stack([(i + (j + 0.5) / n) / n - 0.5, (j + (i + 0.5) / n) / n - 0.5])


_RAYMAP_CACHE: dict = {}


@dataclass
class RayMap:
    """Undistorted ray ``(x, y, 1)`` of every pixel centre, and its Jacobian per pixel."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    xy: np.ndarray   # (H, W, 2)
    J: np.ndarray    # (H, W, 2, 2): d(x, y) / d(u, v)

    @staticmethod
    def build(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> RayMap:
        """The ray map of a camera (cached: the last few cameras are kept)."""
        key = (tuple(np.asarray(K, float).ravel()), tuple(np.asarray(dist, float).ravel()), tuple(size))
        if key not in _RAYMAP_CACHE:
            if len(_RAYMAP_CACHE) >= 2:
                _RAYMAP_CACHE.pop(next(iter(_RAYMAP_CACHE)))
            _RAYMAP_CACHE[key] = RayMap._build(K, dist, size)
        return _RAYMAP_CACHE[key]

    @staticmethod
    def _build(K: np.ndarray, dist: np.ndarray, size: tuple[int, int]) -> RayMap:
        w, h = size
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        xy = undistort_pixels(np.column_stack([u.ravel(), v.ravel()]), K, dist).reshape(h, w, 2)
        J = np.stack([np.gradient(xy, axis=1), np.gradient(xy, axis=0)], axis=-1)
        return RayMap(np.asarray(K, float), np.asarray(dist, float), size, xy, J)

    def centre_dirs(self) -> np.ndarray:
        h, w = self.xy.shape[:2]
        return np.concatenate([self.xy.reshape(-1, 2), np.ones((h * w, 1))], axis=1)

    def sub_dirs(self, flat_idx: np.ndarray, n: int, pattern: str = "grid") -> np.ndarray:
        """Rays of ``n x n`` sub-samples of the given pixels (:func:`subpixel_offsets`):
        (len(flat_idx), n*n, 3)."""
        offs = subpixel_offsets(n, pattern)                                # (S, 2)
        xy = self.xy.reshape(-1, 2)[flat_idx]                       # (M, 2)
        J = self.J.reshape(-1, 2, 2)[flat_idx]                      # (M, 2, 2)
        sub = xy[:, None, :] + np.einsum("mij,sj->msi", J, offs)    # (M, S, 2)
        return np.concatenate([sub, np.ones(sub.shape[:2] + (1,))], axis=2)


def albedo_table(rig: RigConfig, kind: str) -> np.ndarray:
    """Relative reflectance per material code for the bright image or the laser stripe."""
    t = np.zeros(6)
    if kind == "bright":
        t[WHITE], t[BLACK], t[WALL], t[POST], t[DISC] = 1.0, rig.black_albedo, rig.wall_albedo, \
            rig.post_albedo, 0.6
    elif kind == "stripe":
        t[WHITE], t[BLACK], t[WALL], t[POST], t[DISC] = 1.0, rig.stripe_albedo_black, \
            rig.stripe_albedo_wall, rig.stripe_albedo_wall, 0.8
    else:
        raise ValueError(f"unknown albedo kind {kind!r}")
    t[NOTHING] = 0.0
    return t


@dataclass
class SceneView:
    """What the camera sees of a static scene: hit points, surfaces and the anti-aliased albedo."""

    points: np.ndarray      # (H, W, 3) float32, NaN where nothing is hit
    surface: np.ndarray     # (H, W) int16, -1 = nothing
    footprint: np.ndarray   # (H, W) float32: size of the pixel on the surface, mm (inf at depth edges)
    albedo: np.ndarray      # (H, W) float32, bright-image albedo, anti-aliased
    interior: np.ndarray    # (H, W) bool: same surface as all 4 neighbours


def render_view(rays: RayMap, surfaces: list, table: np.ndarray, n_sub: int,
                pattern: str = "grid") -> SceneView:
    """Ray-cast the scene at every pixel, anti-alias edge pixels with ``n_sub x n_sub`` samples
    (placed by ``pattern``, :func:`subpixel_offsets`)."""
    w, h = rays.size
    dirs = rays.centre_dirs()
    t, idx = trace(surfaces, dirs)
    pts = dirs * t[:, None]
    pts[idx < 0] = np.nan
    mat = materials(surfaces, pts, idx)
    alb = table[mat].astype(np.float32)
    key = (idx.astype(np.int32) * 8 + mat).reshape(h, w)
    edge = np.zeros((h, w), bool)
    dh = key[:, 1:] != key[:, :-1]
    dv = key[1:, :] != key[:-1, :]
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    # any straight edge cutting a pixel separates its centre from a 4-neighbour's: no dilation needed
    flat = np.flatnonzero(edge)
    S = n_sub * n_sub
    for start in range(0, len(flat), 100_000):
        f = flat[start:start + 100_000]
        sd = rays.sub_dirs(f, n_sub, pattern).reshape(-1, 3)
        ts, ids = trace(surfaces, sd)
        p = sd * ts[:, None]
        m = materials(surfaces, p, ids)
        alb[f] = table[m].reshape(-1, S).mean(axis=1)
    sid = idx.reshape(h, w)
    interior = np.zeros((h, w), bool)
    interior[1:-1, 1:-1] = ((sid[1:-1, 1:-1] == sid[:-2, 1:-1]) & (sid[1:-1, 1:-1] == sid[2:, 1:-1])
                            & (sid[1:-1, 1:-1] == sid[1:-1, :-2]) & (sid[1:-1, 1:-1] == sid[1:-1, 2:]))
    P = pts.reshape(h, w, 3)
    fp = np.full((h, w), 0.0)
    with np.errstate(invalid="ignore"):
        gx = np.linalg.norm(P[:, 1:] - P[:, :-1], axis=2)
        gy = np.linalg.norm(P[1:] - P[:-1], axis=2)
    gx = np.where(np.isfinite(gx), gx, np.inf)
    gy = np.where(np.isfinite(gy), gy, np.inf)
    fp[:, 1:] = np.maximum(fp[:, 1:], gx)
    fp[:, :-1] = np.maximum(fp[:, :-1], gx)
    fp[1:] = np.maximum(fp[1:], gy)
    fp[:-1] = np.maximum(fp[:-1], gy)
    return SceneView(P.astype(np.float32), sid, fp.astype(np.float32), alb.reshape(h, w), interior)


def expose_bright(albedo: np.ndarray, rig: RigConfig, rng: np.random.Generator) -> np.ndarray:
    """A bright image: ``white_dn * albedo``, optical blur, Gaussian sensor noise, 8 bits."""
    img = cv2.GaussianBlur(albedo * np.float32(rig.white_dn), (0, 0), rig.psf_sigma_px)
    img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(rig.bright_noise_dn)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def expose_dark(signal: np.ndarray, rig: RigConfig, rng: np.random.Generator) -> np.ndarray:
    """A dark frame: optical blur, black level, read + shot noise, rounding, clipping at 0 and 255."""
    img = cv2.GaussianBlur(signal.astype(np.float32), (0, 0), rig.psf_sigma_px)
    sigma = np.sqrt(np.float32(rig.read_noise_dn) ** 2 + np.float32(rig.shot_noise_gain) * np.maximum(img, 0))
    img = img + np.float32(rig.dark_level_dn) + rng.standard_normal(img.shape, dtype=np.float32) * sigma
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def smooth_field(shape: tuple[int, int], corr_px: float, rng: np.random.Generator) -> np.ndarray:
    """Zero-mean, unit-std Gaussian random field with correlation length ``corr_px``."""
    f = gaussian_filter(rng.standard_normal(shape).astype(np.float32), corr_px)
    s = f.std()
    return f / s if s > 0 else f


def stripe_signal(rays: RayMap, view: SceneView, surfaces: list, pose: Pose, rig: RigConfig,
                  sheet_sigma_mm: float, r_ref_mm: float, rng: np.random.Generator,
                  modulation: np.ndarray | None = None, n_sub: int = 3) -> np.ndarray:
    """Laser-stripe irradiance (DN, before blur and noise) of one position; see module docstring.
    The ``n_sub x n_sub`` samples per pixel sit as ``rig.antialias`` places them
    (:func:`subpixel_offsets`)."""
    h, w = view.surface.shape
    n = pose.z_axis.astype(np.float32)
    d = np.float32(n @ pose.T)
    with np.errstate(invalid="ignore"):
        dist_c = np.abs(view.points @ n - d)
    # pixels whose centre is within the Gaussian's reach (peak * g > ~0.3 DN) plus the pixel's
    # footprint, and whose centre is not far outside the LiDAR's aperture
    reach = sheet_sigma_mm * np.sqrt(2 * np.log(max(rig.stripe_peak_dn, 1.0) / 0.3)) + view.footprint
    cand = np.flatnonzero((dist_c <= reach).ravel())
    if len(cand):
        ql = pose.inverse_apply(view.points.reshape(-1, 3)[cand].astype(float))
        ang = np.degrees(np.arctan2(ql[:, 1], ql[:, 0]))
        margin = 2.0
        keep = _front(ql, rig) & (ang >= rig.lidar_angle_min_deg - margin) & (ang <= rig.lidar_angle_max_deg + margin)
        cand = cand[keep | ~np.isfinite(view.footprint.ravel()[cand])]
    out = np.zeros(h * w, np.float32)
    if len(cand) == 0:
        return out.reshape(h, w)
    S = n_sub * n_sub
    sd = rays.sub_dirs(cand, n_sub, rig.antialias)                   # (C, S, 3)
    sc = view.surface.ravel()[cand]
    t = np.empty(sd.shape[:2])
    idx = np.repeat(sc[:, None], S, axis=1).astype(np.int16)
    # interior pixels (same surface as all 4 neighbours) of planar surfaces: intersect that plane only
    todo = ~view.interior.ravel()[cand]
    for k, surf in enumerate(surfaces):
        m = (sc == k) & ~todo
        if not np.any(m):
            continue
        if isinstance(surf, (Rect, InfinitePlane)):
            nk = surf.normal
            dk = float(nk @ surf.origin) if isinstance(surf, Rect) else surf.d
            t[m] = dk / (sd[m] @ nk)
        else:
            todo |= sc == k
    if np.any(todo):
        tt, ii = trace(surfaces, sd[todo].reshape(-1, 3))
        t[todo] = tt.reshape(-1, S)
        idx[todo] = ii.reshape(-1, S)
    sd, t, idx = sd.reshape(-1, 3), t.ravel(), idx.ravel()
    p = sd * t[:, None]
    dist = p @ pose.z_axis - pose.z_axis @ pose.T
    g = np.where(idx >= 0, np.exp(-0.5 * (dist / sheet_sigma_mm) ** 2), 0.0)
    on = np.flatnonzero(g > 1e-4)
    val = np.zeros(len(g))
    if len(on):
        q = p[on]
        ql = pose.inverse_apply(q)
        ang = np.degrees(np.arctan2(ql[:, 1], ql[:, 0]))
        inside = _front(ql, rig) & (ang >= rig.lidar_angle_min_deg) & (ang <= rig.lidar_angle_max_deg)
        # shadows: the first surface along the ray from the LiDAR centre must be this point
        ray = q - pose.T
        t2, _ = trace(surfaces, ray, origins=pose.T)
        lit = inside & (t2 >= 1 - 1e-6)
        table = albedo_table(rig, "stripe")
        mats = materials(surfaces, q, idx[on])
        nrm = surface_normals(surfaces, q, idx[on])
        rlen = np.linalg.norm(ray, axis=1)
        cos_inc = np.abs(np.einsum("ij,ij->i", nrm, ray)) / rlen
        val[on] = (lit * table[mats] * cos_inc * (r_ref_mm / rlen) ** 2 * g[on])
    pix = val.reshape(-1, S).mean(axis=1) * rig.stripe_peak_dn
    if modulation is not None:
        pix *= modulation.ravel()[cand]
    if rig.speckle_contrast > 0:
        rows, cols = np.divmod(cand, w)
        r0, r1, c0, c1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
        f = smooth_field((r1 - r0, c1 - c0), rig.speckle_corr_px, rng)
        c = rig.speckle_contrast
        pix *= np.exp(c * f[rows - r0, cols - c0] - 0.5 * c * c)
    out[cand] = pix
    return out.reshape(h, w)
