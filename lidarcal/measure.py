"""Point clouds from a turntable sweep (eq. 28) and the diameter of a disc (section 3.2).

A sweep is many scans taken while the turntable steps through angles psi. With
a calibrated pose function ``model.pose(psi_deg) -> Pose`` every return becomes
a camera-frame point, eq. (28)::

    X_c = R(psi) [rho cos theta, rho sin theta, 0]^T + T(psi)

The beams of a sweep form a grid: one row per psi (a scan line), one column per
beam angle. :func:`measure_disc` finds the disc in that grid and measures it.

Algorithm
---------
1. **Disc.** Grid neighbours (along a scan line and across psi) are joined when
   their 3D points are closer than four beam spacings at that range (+ 6 noise
   sigmas, noise from the second differences of range). Of the connected
   pieces, the disc is the largest one lying *in front of* its surroundings
   (its valid neighbours are farther away: wall, mixed rim returns), so the
   wall and the post behind the disc are never picked. A RANSAC plane, refined
   by total least squares on the inliers, gives the disc plane; disc hits are
   the returns within ``k`` robust sigmas (MAD of the range residuals) of it,
   in one 4-connected piece.
2. **Rim / mixed returns** are the returns near the disc that are not hits:
   behind the disc plane by more than ``k`` sigmas (energy mixed between disc
   and wall) or in front of it. They never enter the plane or the circle as
   points. Each beam ray is intersected with the disc plane instead (the
   beam direction is exact, the range is not), and each beam gets a *disc
   fraction* ``g``: 1 for a disc hit, 0 for a clean background return or no
   return, ``(r_bg - r) / (r_bg - r_disc)`` for a mixed return between the
   disc (``r_disc``: the ray's range to the plane) and the local background
   (``r_bg``: a high percentile of the returns behind the disc nearby).
3. **Boundary, interval censored.** The energy share ``g`` becomes the
   spot's area fraction on the disc, ``f = g / (kappa (1 - g) + g)``, for a
   disc returning ``kappa`` times the background's energy per unit area
   (:class:`Footprint`, default 1; ``kappa`` cannot be read from ranges:
   another ratio looks exactly like another radius). The rim lies between
   every pair of grid neighbours with ``f >= 1/2`` on the disc side and ``f <
   1/2`` outside: along the scan lines (the chord ends) and across psi (the
   top and bottom of the disc are bounded by consecutive scan lines). The
   crossing is placed at ``f = 1/2`` by linear interpolation (a hit next to
   a miss: the midpoint). With a symmetric spot the true rim is where half
   of the spot is on the disc, so the estimate is unbiased for energy-mixed
   ranges and for first-echo scanners with a 50 % threshold.
   The circle through the outermost hits (the paper's contour,
   ``naive_diameter_mm``) is biased small by about half a beam step plus
   the spot radius; moving the edges half a step out over-corrects when the
   scanner reports a return with less than half its spot on the disc. A
   first-echo scanner with threshold ``t`` reports no mixed ranges, so its
   offset cannot be seen in ranges at all: give its :class:`Footprint` and
   the hit/miss crossings are moved in by the distance at which a round
   spot covers ``t``. A pair whose next beam outwards is inside again is
   not a rim (the disc is convex): dropouts and stray ranges are skipped.
   A wide spot (:mod:`lidarcal.spot`): the mixed band's width is measured against the
   background plane; where it exceeds :data:`NEAR_CELLS` cells, the rim is searched and the
   mixed returns read that far, each against its ray's range to the background plane.
4. **Circle.** Centre (in the disc plane) and radius by robust weighted least
   squares on the crossings; each weight is the inverse variance of a uniform
   position on its [hit, miss] interval projected on the radial direction,
   so crossings bounded tightly in radius count most. Outliers (post, stray
   returns) are dropped and the circle refitted. The spot's sigma is read from
   the mixed returns (probit regression) and the radius grows by the half-share
   contour's offset inside a convex rim, ``sigma_t^2 / (2 r)`` (:mod:`lidarcal.spot`;
   ~0.007 mm on the paper rig, 0.3 mm for a 6.5 mm spot sigma on a 140 mm disc).
   Diameter = 2 r; centre and normal are in the camera frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import pandas as pd
from scipy import ndimage, sparse
from scipy.optimize import brentq, least_squares
from scipy.sparse import csgraph

from . import spot
from .geometry import MAD_TO_SIGMA, Plane, Pose, fit_circle_2d, fit_plane, plane_basis
from .io.dataset import LidarSpec
from .ranging import ranging_of

#: inlier band of the disc plane, in robust range-noise sigmas
K_SIGMA = 4.0
#: rim search and background window around the disc hits (cells) for a spot about a beam wide;
#: a wider mixed band (lidarcal.spot.mixed_band_mm) widens both
NEAR_CELLS = 4


class PoseFunction(Protocol):
    """Anything with ``pose(psi_deg) -> Pose`` (a fitted turntable model, a truth rig)."""

    def pose(self, psi_deg: float) -> Pose: ...


@dataclass(frozen=True)
class Footprint:
    """What the scanner reports for a beam split between the disc and the background.

    The default (all fields at their defaults) is the symmetric case: the rim
    is where the disc and the background return equal energy (mixed ranges)
    or where a first-echo scanner switches at half its spot.

    ``reflectivity_ratio``: energy returned per unit spot area by the disc
    over that of the background (energy-weighted mixed ranges put the
    half-share point off the rim unless it is 1). With ``lambertian`` the
    ratio is also multiplied by ``cos(incidence)`` on the disc over that on
    the background (local background plane fitted from the returns).
    ``threshold`` and ``divergence_deg``: a first-echo scanner reports the
    nearest surface once ``threshold`` of its round uniform spot (full
    angular diameter ``divergence_deg``) is on it, and no mixed ranges.
    """

    divergence_deg: float = 0.0
    threshold: float = 0.5
    reflectivity_ratio: float = 1.0
    lambertian: bool = False

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise ValueError(f"Footprint threshold must be in (0, 1), got {self.threshold}")
        if self.threshold != 0.5 and not self.divergence_deg > 0:
            raise ValueError("Footprint with threshold != 0.5 needs the spot's divergence_deg > 0, "
                             f"got {self.divergence_deg}")
        if not self.reflectivity_ratio > 0:
            raise ValueError(f"Footprint reflectivity_ratio must be > 0, got {self.reflectivity_ratio}")

    def edge_offset(self) -> float:
        """Distance, in spot radii, outside an edge at which the spot covers ``threshold``.

        Fraction of a unit disc beyond a chord at distance x from its centre:
        ``(acos x - x sqrt(1 - x^2)) / pi``; solved for ``threshold``.
        """
        def frac(x: float) -> float:
            return (np.arccos(x) - x * np.sqrt(1.0 - x * x)) / np.pi - self.threshold

        return float(brentq(frac, -1.0, 1.0))


@dataclass(frozen=True)
class SweepGrid:
    """A sweep as a grid: rows = distinct psi (scan lines), columns = beam angles.

    ``range_mm`` is NaN for no return; ``row`` is the sweep row of each cell
    (-1: not in the sweep). Beam ``(i, j)`` is the ray
    ``origin[i] + s * direction[i, j]``, ``s >= 0``, in the camera frame.
    """

    psi_deg: np.ndarray  # (P,)
    angle_deg: np.ndarray  # (B,)
    range_mm: np.ndarray  # (P, B)
    row: np.ndarray  # (P, B) int
    origin: np.ndarray  # (P, 3)
    direction: np.ndarray  # (P, B, 3), unit

    @property
    def points(self) -> np.ndarray:
        """Camera-frame points (P, B, 3), eq. (28); NaN where there is no return."""
        return self.origin[:, None, :] + self.range_mm[..., None] * self.direction


@dataclass(frozen=True)
class DiscMeasurement:
    """A measured disc (camera frame, mm) and the arrays behind it (for figures).

    ``normal`` follows :class:`~lidarcal.geometry.Plane` (pointing away from
    the camera's optical centre). ``cloud`` holds every return of the sweep
    (eq. 28); ``disc_mask`` the disc hits used for the plane, ``rim_mask`` the
    rejected rim / mixed returns near the disc. ``boundary_inside`` /
    ``boundary_outside`` are the beams (ray meets disc plane) bounding the rim
    from inside (hit) and outside (miss or mixed), ``crossings`` the rim
    estimates between them, ``crossing_inlier`` the ones the circle kept;
    ``circle`` 180 points on the fitted circle.
    """

    diameter_mm: float
    center_mm: np.ndarray
    normal: np.ndarray
    points: int
    naive_diameter_mm: float
    diameter_std_mm: float
    noise_mm: float
    cloud: np.ndarray = field(repr=False)
    disc_mask: np.ndarray = field(repr=False)
    rim_mask: np.ndarray = field(repr=False)
    boundary_inside: np.ndarray = field(repr=False)
    boundary_outside: np.ndarray = field(repr=False)
    crossings: np.ndarray = field(repr=False)
    crossing_inlier: np.ndarray = field(repr=False)
    circle: np.ndarray = field(repr=False)
    info: dict = field(default_factory=dict, compare=False, repr=False)

    def to_dict(self) -> dict:
        """The summary (no arrays), as in ``measurements.json``."""
        return {"diameter_mm": self.diameter_mm, "center_mm": self.center_mm.tolist(),
                "normal": self.normal.tolist(), "points": self.points,
                "naive_diameter_mm": self.naive_diameter_mm,
                "diameter_std_mm": self.diameter_std_mm, "noise_mm": self.noise_mm}


# --------------------------------------------------------------------------- eq. (28)

def _poses(model: PoseFunction, psi_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """R (n, 3, 3) and T (n, 3) of ``model.pose`` at each psi (one call per psi)."""
    Rs, Ts = [], []
    for psi in psi_deg:
        p = model.pose(float(psi))
        Rs.append(np.asarray(p.R, dtype=float))
        Ts.append(np.asarray(p.T, dtype=float).reshape(3))
    return np.asarray(Rs).reshape(-1, 3, 3), np.asarray(Ts).reshape(-1, 3)


def _columns(sweep: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    missing = [c for c in ("psi_deg", "angle_deg", "range_mm") if c not in sweep.columns]
    if missing:
        raise ValueError(f"Expected a sweep with columns psi_deg, angle_deg, range_mm; "
                         f"missing {', '.join(missing)}")
    return (sweep["psi_deg"].to_numpy(float), sweep["angle_deg"].to_numpy(float),
            sweep["range_mm"].to_numpy(float))


def sweep_points(sweep: pd.DataFrame, model: PoseFunction) -> np.ndarray:
    """Camera-frame point of every sweep row, eq. (28); shape (N, 3), NaN rows = no return.

    Row ``k`` of the result belongs to row ``k`` of ``sweep`` (its psi, beam
    angle and range stay in the DataFrame). ``model.pose`` is called once per
    distinct psi; the rest is vectorised.
    """
    return returns_points(*_columns(sweep), model)


def returns_points(psi_deg: np.ndarray, angle_deg: np.ndarray, range_mm: np.ndarray,
                   model: PoseFunction) -> np.ndarray:
    """Camera-frame points (N, 3) of LiDAR returns, eq. (28):
    ``X_c = R(psi) [rho cos theta, rho sin theta, 0]^T + T(psi)``, with ``rho`` the range
    corrected by the model's ranging terms (:func:`lidarcal.ranging.ranging_of`) and
    ``model.pose`` called once per distinct ``psi``; NaN ranges give NaN rows."""
    rng = ranging_of(model).correct(np.asarray(range_mm, dtype=float))
    psi = np.broadcast_to(np.asarray(psi_deg, dtype=float), rng.shape)
    upsi, inv = np.unique(psi, return_inverse=True)
    R, T = _poses(model, upsi)
    th = np.radians(np.asarray(angle_deg, dtype=float))
    local = np.column_stack([rng * np.cos(th), rng * np.sin(th), np.zeros_like(rng)])  # eq. (6)
    return np.einsum("nij,nj->ni", R[inv], local) + T[inv]


def sweep_grid(sweep: pd.DataFrame, model: PoseFunction,
               lidar: LidarSpec | None = None) -> SweepGrid:
    """Arrange a sweep as a (psi, beam) grid with the camera-frame ray of every beam.

    Beam columns come from ``lidar`` (``angle_min_deg + k angle_step_deg``) when
    given, else from the distinct angles in the sweep. Ranges outside the
    LiDAR's ``[range_min_mm, range_max_mm]`` count as no return.
    """
    psi, ang, rng = _columns(sweep)
    rng = ranging_of(model).correct(rng)  # range offset (lidarcal.ranging) before eq. (28)
    if len(psi) == 0:
        raise ValueError("Empty sweep: no rows")
    rng = np.where(rng > 0, rng, np.nan)
    upsi, pi = np.unique(psi, return_inverse=True)
    if lidar is not None:
        beam = np.rint((ang - lidar.angle_min_deg) / lidar.angle_step_deg).astype(int)
        if beam.min() < 0 or beam.max() >= lidar.n_beams:
            raise ValueError(f"Sweep angles {ang.min():g}..{ang.max():g} deg fall outside the "
                             f"LiDAR's {lidar.angle_min_deg:g}..{lidar.angle_max_deg:g} deg")
        angles = lidar.angles_deg()
        rng = np.where((rng < lidar.range_min_mm) | (rng > lidar.range_max_mm), np.nan, rng)
    else:
        angles, beam = np.unique(np.round(ang, 6), return_inverse=True)
    R, T = _poses(model, upsi)
    th = np.radians(angles)
    u = np.column_stack([np.cos(th), np.sin(th), np.zeros_like(th)])
    direction = np.einsum("pij,bj->pbi", R, u)
    P, B = len(upsi), len(angles)
    rgrid = np.full((P, B), np.nan)
    row = np.full((P, B), -1, dtype=int)
    rgrid[pi, beam] = rng
    row[pi, beam] = np.arange(len(psi))
    return SweepGrid(upsi, np.asarray(angles, float), rgrid, row, T, direction)


# --------------------------------------------------------------------------- helpers

def _mad_sigma(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(x - np.median(x))))


def _range_noise(r: np.ndarray) -> float:
    """Range noise from second differences along scan lines (robust: MAD / sqrt(6))."""
    d2 = r[:, :-2] - 2 * r[:, 1:-1] + r[:, 2:]
    d2 = d2[np.isfinite(d2)]
    if len(d2) < 10:
        return float("nan")
    return float(MAD_TO_SIGMA * np.median(np.abs(d2)) / np.sqrt(6.0))


_DIRS = ((0, 1), (0, -1), (1, 0), (-1, 0))


def _shift(a: np.ndarray, di: int, dj: int, fill) -> np.ndarray:
    """``out[i, j] = a[i + di, j + dj]`` (``fill`` outside the grid)."""
    out = np.full_like(a, fill)
    P, B = a.shape[:2]
    si = slice(max(di, 0), P + min(di, 0))
    sj = slice(max(dj, 0), B + min(dj, 0))
    ti = slice(max(-di, 0), P + min(-di, 0))
    tj = slice(max(-dj, 0), B + min(-dj, 0))
    out[ti, tj] = a[si, sj]
    return out


def _components(grid: SweepGrid, sigma0: float) -> np.ndarray:
    """Label grid cells by surface (-1: no return): neighbours joined below a range-scaled gap."""
    X = grid.points
    r = grid.range_mm
    valid = np.isfinite(r)
    P, B = r.shape
    idx = np.arange(P * B).reshape(P, B)
    rows, cols = [], []
    for di, dj in ((0, 1), (1, 0)):
        a = (slice(0, P - di), slice(0, B - dj))
        b = (slice(di, P), slice(dj, B))
        step = np.linalg.norm(grid.direction[a] - grid.direction[b], axis=-1)  # angle, rad
        gap = np.linalg.norm(X[a] - X[b], axis=-1)
        limit = 4.0 * 0.5 * (r[a] + r[b]) * step + 6.0 * sigma0
        ok = valid[a] & valid[b] & (gap < limit)
        rows.append(idx[a][ok])
        cols.append(idx[b][ok])
    i = np.concatenate(rows)
    j = np.concatenate(cols)
    G = sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(P * B, P * B))
    _, lab = csgraph.connected_components(G, directed=False)
    lab = lab.reshape(P, B)
    return np.where(valid, lab, -1)


def _front_component(labels: np.ndarray, r: np.ndarray, min_size: int) -> list[int]:
    """Candidate disc components, best first: large, and nearer than their valid neighbours."""
    n = labels.max() + 1
    size = np.bincount(labels[labels >= 0], minlength=n)
    front = np.zeros(n)
    total = np.zeros(n)
    for di, dj in _DIRS:
        lb = _shift(labels, di, dj, -2)
        rb = _shift(r, di, dj, np.nan)
        edge = (labels >= 0) & (lb >= 0) & (lb != labels)
        la = labels[edge]
        total += np.bincount(la, minlength=n)
        front += np.bincount(la, weights=(rb[edge] > r[edge]).astype(float), minlength=n)
    frac = np.where(total > 0, front / np.maximum(total, 1), 1.0)
    # the background spans the sweep: it meets both first and last scan line or beam
    def touches(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (np.bincount(a[a >= 0], minlength=n) > 0) & (np.bincount(b[b >= 0], minlength=n) > 0)
    spans = touches(labels[0], labels[-1]) | touches(labels[:, 0], labels[:, -1])
    ok = np.flatnonzero((size >= min_size) & (frac >= 0.6) & ~spans)
    ok = ok[np.argsort(-size[ok])]
    return [int(k) for k in ok]


def _ransac_plane(pts: np.ndarray, tol: float, rng: np.random.Generator,
                  n_hyp: int = 300, n_score: int = 3000) -> Plane:
    """Plane with most points within ``tol`` (vectorised RANSAC), refined by TLS."""
    score_pts = pts if len(pts) <= n_score else pts[rng.choice(len(pts), n_score, replace=False)]
    tri = pts[rng.integers(0, len(pts), (n_hyp, 3))]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(nrm, axis=1)
    good = ln > 1e-9 * max(ln.max(), 1e-300)
    nrm = nrm[good] / ln[good, None]
    d = np.einsum("hi,hi->h", nrm, tri[good, 0])
    count = (np.abs(score_pts @ nrm.T - d) < tol).sum(0)
    k = int(np.argmax(count))
    inl = np.abs(pts @ nrm[k] - d[k]) < tol
    pl = fit_plane(pts[inl])
    return fit_plane(pts[np.abs(pl.distance(pts)) < tol])


def _walk_back(hit: np.ndarray, inside: np.ndarray, di: int, dj: int, depth: int) -> np.ndarray:
    """Cells from which, stepping ``-(di, dj)`` through ``inside`` cells, a hit is met within ``depth``."""
    ok = np.zeros_like(hit)
    chain = np.ones_like(hit)
    for s in range(1, depth + 1):
        ok |= chain & _shift(hit, -s * di, -s * dj, False)
        chain &= _shift(inside, -s * di, -s * dj, False)
    return ok


def _trimmed_circle(pts: np.ndarray, x0: np.ndarray) -> tuple[np.ndarray, float]:
    """Geometric circle fit, with points beyond 4 robust sigmas of the first fit dropped."""
    if len(pts) < 3:
        return x0[:2].copy(), float(x0[2])
    c, r = fit_circle_2d(pts)
    res = np.hypot(*(pts - c).T) - r
    ok = np.abs(res - np.median(res)) <= 4.0 * max(_mad_sigma(res), 1e-9)
    return fit_circle_2d(pts[ok]) if ok.sum() >= 3 else (c, r)


def _background_cos(grid: SweepGrid, clean: np.ndarray, hits: np.ndarray, sigma: float,
                    rng: np.random.Generator) -> np.ndarray:
    """|cos(incidence)| of every beam on the background plane fitted near the disc (1 if none)."""
    ring = ndimage.binary_dilation(hits, structure=np.ones((3, 3), bool), iterations=10)
    pts = grid.points[clean & ring]
    if len(pts) < 10:
        return np.ones(hits.shape)
    try:
        pl = _ransac_plane(pts, K_SIGMA * sigma, rng)
    except ValueError:
        return np.ones(hits.shape)
    return np.maximum(np.abs(np.einsum("pbi,i->pb", grid.direction, pl.normal)), 0.05)


def _rim_foreshortening(er: np.ndarray, basis: np.ndarray, beam: np.ndarray) -> np.ndarray:
    """How much shorter a radial step at the rim looks across the beam, per crossing (0.05..1).

    ``er`` (n, 2): the rim's radial direction in the disc plane (``basis`` (2, 3) its axes);
    ``beam`` (n, 3): unit beam directions. A step ``x`` along ``er`` moves the rim's tangent
    line, seen in the plane perpendicular to the beam, by ``s x``: ``s`` is the part of the
    projected radial direction perpendicular to the projected tangent (1 for a disc facing
    the beam; ``cos(incidence)`` where the rim runs across the tilt). An offset of the spot's
    edge response, a distance across the beam, is ``1 / s`` times longer on the disc.
    """
    e3 = er @ basis
    t3 = np.column_stack([-er[:, 1], er[:, 0]]) @ basis
    pr = e3 - np.einsum("ki,ki->k", e3, beam)[:, None] * beam
    pt = t3 - np.einsum("ki,ki->k", t3, beam)[:, None] * beam
    pt /= np.maximum(np.linalg.norm(pt, axis=1, keepdims=True), 1e-12)
    s = np.linalg.norm(pr - np.einsum("ki,ki->k", pr, pt)[:, None] * pt, axis=1)
    return np.clip(s, 0.05, 1.0)


# --------------------------------------------------------------------------- section 3.2

def measure_disc(sweep: pd.DataFrame, model: PoseFunction, lidar: LidarSpec | None = None,
                 footprint: Footprint | None = None, seed: int = 0) -> DiscMeasurement:
    """Measure a disc in a sweep (section 3.2): diameter, centre and normal, camera frame.

    Parameters
    ----------
    sweep : DataFrame with psi_deg, angle_deg, range_mm (NaN or 0 = no return),
        as :func:`lidarcal.io.dataset.read_sweep` returns it.
    model : pose function, ``model.pose(psi_deg) -> Pose`` (eqs. 26-27).
    lidar : the LiDAR's beam angles and range limits (optional; else the
        sweep's distinct angles are the beams).
    footprint : how the scanner reports a beam split between disc and
        background (:class:`Footprint`); the default is the symmetric case.
        Needed for unequal disc / background reflectivity (mixed ranges) or
        a first-echo threshold other than 1/2 (module docstring, step 3).
    seed : RANSAC seed (results are deterministic).

    Raises ``ValueError`` when no disc or too little rim is found.
    """
    grid = sweep_grid(sweep, model, lidar)
    rng = np.random.default_rng(seed)
    r = grid.range_mm
    P, B = r.shape
    valid = np.isfinite(r)
    if valid.sum() < 30:
        raise ValueError(f"Sweep has {int(valid.sum())} returns; too few to find a disc")
    sigma0 = _range_noise(r)
    if not np.isfinite(sigma0) or sigma0 <= 0:
        sigma0 = 1e-3 * float(np.nanmedian(r))
    X = grid.points

    # 1. the disc: a large surface in front of its surroundings, then its plane
    labels = _components(grid, sigma0)
    cands = _front_component(labels, r, min_size=30)
    if not cands:
        raise ValueError("No surface in front of the background found: is the disc in the sweep?")
    plane = None
    for lab in cands[:5]:
        comp = labels == lab
        try:
            pl = _ransac_plane(X[comp], 3.0 * sigma0 + 1e-6, rng)
        except ValueError:
            continue
        res = np.abs(pl.distance(X[comp]))
        if np.mean(res < 4.0 * sigma0 + 1e-6) >= 0.5:
            plane = pl
            break
    if plane is None:
        raise ValueError("No planar surface in front of the background found (no disc?)")

    denom = np.einsum("pbi,i->pb", grid.direction, plane.normal)
    hits = comp
    for _ in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            r_disc = (plane.d - grid.origin @ plane.normal)[:, None] / denom
        r_disc = np.where(np.abs(denom) > 1e-9, r_disc, np.nan)
        dr = r - r_disc
        sigma = _mad_sigma(dr[hits & (np.abs(dr) < 6.0 * sigma0 + 1e-6)])
        if not np.isfinite(sigma) or sigma <= 0:
            sigma = sigma0
        on = comp & (np.abs(dr) <= K_SIGMA * sigma)
        lab_on, n_on = ndimage.label(on)
        if n_on == 0:
            raise ValueError("No disc returns on the fitted plane")
        hits = lab_on == (1 + int(np.argmax(np.bincount(lab_on[on])[1:])))
        if hits.sum() < 30:
            raise ValueError(f"Only {int(hits.sum())} disc returns found; too few")
        plane = fit_plane(X[hits])
        denom = np.einsum("pbi,i->pb", grid.direction, plane.normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        r_disc = (plane.d - grid.origin @ plane.normal)[:, None] / denom
    r_disc = np.where((np.abs(denom) > 1e-9) & (r_disc > 0), r_disc, np.nan)
    dr = r - r_disc
    sigma = _mad_sigma(dr[hits])

    # 2. rim / mixed returns and the disc fraction g of every beam near the disc
    band = K_SIGMA * sigma
    behind = valid & (dr > band)
    front = valid & (dr < -band)
    # the beam spot's mixed band around the disc (lidarcal.spot): a spot several beams wide
    # needs the rim searched, and the background read, beyond the 4 cells a narrow one needs
    Pd = grid.origin[:, None, :] + r_disc[..., None] * grid.direction
    spacing = spot.grid_spacing_mm(Pd, hits)
    bg_plane = spot.background_plane(X, behind, hits, spacing, K_SIGMA * sigma,
                                     lambda p, tol: _ransac_plane(p, tol, np.random.default_rng(seed + 1)),
                                     grid.origin.mean(0))
    band_mm = 0.0
    if bg_plane is not None:
        r_bg_plane = spot.ray_range_to_plane(grid.origin, grid.direction, bg_plane)
        band_mm = spot.mixed_band_mm(behind & (r < r_bg_plane - band), grid.row >= 0, hits, spacing)
    reach = tuple(max(NEAR_CELLS, int(np.ceil(band_mm / s)) + 1) if np.isfinite(s) and s > 0
                  else NEAR_CELLS for s in spacing)
    wide = reach != (NEAR_CELLS, NEAR_CELLS)
    near = hits | spot.ring(hits, reach)
    cand = behind & near
    r_bg = np.full((P, B), np.nan)
    ci, cj = np.nonzero(cand)
    if wide and len(ci):  # the band is wider than the local window: the background plane's range
        r_bg[ci, cj] = r_bg_plane[ci, cj]
    elif len(ci):
        w = NEAR_CELLS
        oi, oj = np.meshgrid(np.arange(-w, w + 1), np.arange(-w, w + 1), indexing="ij")
        ii = np.clip(ci[:, None] + oi.ravel(), 0, P - 1)
        jj = np.clip(cj[:, None] + oj.ravel(), 0, B - 1)
        vals = np.where(behind[ii, jj], r[ii, jj], np.nan)
        enough = np.isfinite(vals).sum(1) >= 3
        with np.errstate(all="ignore"):
            q = np.nanpercentile(np.where(enough[:, None], vals, 0.0), 90, axis=1)
        r_bg[ci, cj] = np.where(enough, q, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        g_mixed = (r_bg - r) / (r_bg - r_disc)
        g_min = band / (r_bg - r_disc)
    g_mixed = np.where(np.isfinite(g_mixed) & (g_mixed > g_min), np.clip(g_mixed, 0, 1), 0.0)
    in_sweep = grid.row >= 0
    g = np.full((P, B), np.nan)
    g[in_sweep & ~valid] = 0.0  # no return
    g[behind] = 0.0
    g[cand] = g_mixed[cand]
    g[hits] = 1.0
    g[~np.isfinite(r_disc)] = np.nan
    mixed = cand & (g > 0)
    rim = near & valid & ~hits & (mixed | front | (np.abs(dr) <= band))

    # 3. rim crossings between neighbours: inside f >= 1/2, outside f < 1/2, where f is the
    # spot's area fraction on the disc (the energy share g corrected for the reflectivities)
    fp = footprint if footprint is not None else Footprint()
    kappa = np.full((P, B), fp.reflectivity_ratio)
    if fp.lambertian:
        kappa *= np.abs(denom) / _background_cos(grid, behind & (g == 0), hits, sigma, rng)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.where((g > 0) & (g < 1), g / (kappa * (1.0 - g) + g), g)
    inside = np.isfinite(g) & (g >= 0.5)
    ins, outs, qs, hard, rd = [], [], [], [], []
    dirs_mid = []
    for di, dj in _DIRS:
        depth = reach[0] - 1 if di else reach[1] - 1  # 3 for a narrow spot
        eligible = hits | (mixed & inside & _walk_back(hits, inside & ~hits, di, dj, depth))
        gb = _shift(g, di, dj, np.nan)
        # the disc is convex: beyond the rim the next beam is outside too (this
        # drops dropouts and stray ranges inside the disc or notching its rim)
        beyond_in = _shift(inside, 2 * di, 2 * dj, False)
        pair = eligible & np.isfinite(gb) & (gb < 0.5) & ~beyond_in
        a = np.nonzero(pair)
        b = (a[0] + di, a[1] + dj)
        ga, gbv = g[a], g[b]
        u = (ga - 0.5) / (ga - gbv)
        Pa, Pb = Pd[a], Pd[b]
        ins.append(Pa)
        outs.append(Pb)
        qs.append(Pa + u[:, None] * (Pb - Pa))
        hard.append(hits[a] & (gbv == 0.0))
        rd.append(0.5 * (r_disc[a] + r_disc[b]))
        dirs_mid.append(grid.direction[a] + grid.direction[b])
    Pin, Pout, Q = np.vstack(ins), np.vstack(outs), np.vstack(qs)
    hard = np.concatenate(hard)
    rd = np.concatenate(rd)
    dmid = np.vstack(dirs_mid)
    dmid /= np.linalg.norm(dmid, axis=1, keepdims=True)
    if len(Q) < 10:
        raise ValueError(f"Only {len(Q)} rim crossings found; the sweep does not cover the disc")

    # 4. circle in the disc plane
    Bs = plane_basis(plane.normal)
    origin = plane.project(X[hits].mean(0)[None])[0]

    def to2(p: np.ndarray) -> np.ndarray:
        return (p - origin) @ Bs.T

    q2, a2, b2 = to2(Q), to2(Pin), to2(Pout)
    seg = b2 - a2
    L = np.linalg.norm(seg, axis=1)
    offset = 0.0
    if fp.threshold != 0.5:
        offset = fp.edge_offset() * np.tan(np.radians(fp.divergence_deg) / 2)

    def prepare(c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        er = q2 - c
        er /= np.maximum(np.linalg.norm(er, axis=1, keepdims=True), 1e-12)
        cosphi = np.abs(np.einsum("ki,ki->k", seg, er)) / np.maximum(L, 1e-12)
        sig = np.sqrt((L * cosphi) ** 2 / 12.0 + (0.1 * L) ** 2)
        pts = q2
        if offset != 0.0:
            # move hit/miss crossings in by the spot's edge offset, measured in
            # the plane perpendicular to the beam, mapped back onto the disc plane
            delta = np.where(hard, offset * rd / _rim_foreshortening(er, Bs, dmid), 0.0)
            pts = q2 - delta[:, None] * er
        return pts, sig

    def solve(x0: np.ndarray, keep: np.ndarray, loss: str):
        pts, sig = prepare(x0[:2])
        pts, sig = pts[keep], sig[keep]

        def res(x: np.ndarray) -> np.ndarray:
            return (np.hypot(pts[:, 0] - x[0], pts[:, 1] - x[1]) - x[2]) / sig

        return least_squares(res, x0, loss=loss, f_scale=2.0, x_scale="jac")

    # start: centre and size of the hit region (uniform disc: E|p - c|^2 = r^2 / 2)
    h2 = to2(Pd[hits])
    c0 = h2.mean(0)
    x = np.array([*c0, np.sqrt(2.0 * np.mean(np.sum((h2 - c0) ** 2, 1)))])
    keep = np.ones(len(q2), bool)
    sol = solve(x, keep, "soft_l1")
    x = sol.x
    for _ in range(2):
        pts, sig = prepare(x[:2])
        resid = (np.hypot(pts[:, 0] - x[0], pts[:, 1] - x[1]) - x[2]) / sig
        keep = np.abs(resid) < 5.0
        sol = solve(x, keep, "linear")
        x = sol.x
    # the paper's contour: circle through the outermost disc hits (biased small)
    filled = ndimage.binary_fill_holes(hits)
    outer = hits & ~ndimage.binary_erosion(filled, border_value=1)
    c_naive, r_naive = _trimmed_circle(to2(Pd[outer]), x)
    J = sol.jac
    dof = max(int(keep.sum()) - 3, 1)
    s2 = float(2 * sol.cost / dof)
    try:
        cov = np.linalg.inv(J.T @ J) * s2
        r_std = float(np.sqrt(max(cov[2, 2], 0.0)))
    except np.linalg.LinAlgError:
        r_std = float("nan")
    # the edge response's foreshortening on the disc plane, averaged as the fit weighs the
    # crossings (a radial shift x_i of crossing i moves the radius by sum w_i x_i / sum w_i)
    pts, sig = prepare(x[:2])
    er = pts[keep] - x[:2]
    er /= np.maximum(np.linalg.norm(er, axis=1, keepdims=True), 1e-12)
    w = 1.0 / sig[keep] ** 2
    stretch = float(np.sum(w / _rim_foreshortening(er, Bs, dmid[keep])) / np.sum(w))
    # the spot from the mixed returns' disc fractions (lidarcal.spot): its sigma across the
    # beam, and the half-share contour's offset inside the convex rim, sigma_t^2 / (2 R)
    mix = mixed & np.isfinite(g) & (g < 1)
    spot_sigma, spot_n = spot.spot_sigma_mm(g[mix], to2(Pd[mix]), grid.direction[mix], Bs, x[:2], abs(x[2]),
                                            min_returns=len(Q) // 2)  # mixed returns at most crossings
    curvature = spot.curvature_offset_mm(spot_sigma, er, dmid[keep], Bs, abs(x[2]), w)
    radius = abs(x[2]) + curvature
    centre = origin + x[:2] @ Bs
    t = np.linspace(0, 2 * np.pi, 180, endpoint=False)
    circle = centre + radius * (np.outer(np.cos(t), Bs[0]) + np.outer(np.sin(t), Bs[1]))

    cells = grid.row >= 0
    order = np.argsort(grid.row[cells])
    flat_valid = valid[cells][order]
    cloud = X[cells][order][flat_valid]
    disc_mask = hits[cells][order][flat_valid]
    rim_mask = rim[cells][order][flat_valid]
    info = {"crossings": len(Q), "crossings_used": int(keep.sum()),
            "hard_crossings": int(hard.sum()), "mixed_returns": int(mixed.sum()),
            "naive_center_mm": (origin + c_naive @ Bs).tolist(),
            "edge_offset_mm": float(offset * np.nanmedian(rd)) if offset else 0.0,
            "scan_lines": int(P), "beams": int(B), "rim_stretch": stretch,
            "spot_sigma_mm": spot_sigma, "spot_returns": spot_n, "rim_curvature_mm": curvature,
            "mixed_band_mm": band_mm, "grid_spacing_mm": list(spacing)}
    return DiscMeasurement(
        diameter_mm=float(2 * radius), center_mm=centre, normal=plane.normal.copy(),
        points=int(hits.sum()), naive_diameter_mm=float(2 * r_naive),
        diameter_std_mm=2 * r_std, noise_mm=float(sigma),
        cloud=cloud, disc_mask=disc_mask, rim_mask=rim_mask,
        boundary_inside=Pin, boundary_outside=Pout, crossings=Q, crossing_inlier=keep,
        circle=circle, info=info)
