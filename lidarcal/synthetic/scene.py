"""Surfaces of a simulated scene and a vectorised ray caster (camera frame, mm).

Every surface answers ``intersect(origins, dirs) -> t`` (NaN for a miss; the
hit is ``origin + t * dir``) and ``material(points) -> int`` codes of
:data:`MATERIALS`. Rays are not normalised: camera rays are ``(x, y, 1)``, so
``t`` is the depth; LiDAR rays are unit vectors, so ``t`` is the range.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# material codes: 0 = nothing hit
NOTHING, WHITE, BLACK, WALL, POST, DISC = 0, 1, 2, 3, 4, 5
MATERIALS = {NOTHING: "nothing", WHITE: "white", BLACK: "black", WALL: "wall", POST: "post",
             DISC: "disc"}
_EPS = 1e-9


def _plane_t(origins: np.ndarray, dirs: np.ndarray, normal: np.ndarray, d: float) -> np.ndarray:
    denom = dirs @ normal
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (d - origins @ normal) / denom
    t[~(t > _EPS)] = np.nan
    return t


@dataclass(frozen=True)
class Rect:
    """Rectangle ``origin + u e_u + v e_v``, ``0 <= u <= width``, ``0 <= v <= height``.

    ``pattern`` = ``(cols, rows, square_mm, margin_mm)``: a chessboard of
    ``cols x rows`` squares starting ``margin_mm`` from the origin corner (first
    square black), white around it; ``None`` for a plain surface of ``plain``.
    """

    origin: np.ndarray
    e_u: np.ndarray
    e_v: np.ndarray
    width: float
    height: float
    pattern: tuple[int, int, float, float] | None = None
    plain: int = WHITE

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.e_u, self.e_v)
        return n / np.linalg.norm(n)

    def uv(self, points: np.ndarray) -> np.ndarray:
        return np.stack([points @ self.e_u - self.origin @ self.e_u,
                         points @ self.e_v - self.origin @ self.e_v], axis=-1)

    def point(self, u: float | np.ndarray, v: float | np.ndarray) -> np.ndarray:
        u, v = np.asarray(u, dtype=float), np.asarray(v, dtype=float)
        return self.origin + u[..., None] * self.e_u + v[..., None] * self.e_v

    def corners(self) -> np.ndarray:
        return self.point(np.array([0, self.width, self.width, 0.0]),
                          np.array([0, 0, self.height, self.height]))

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        n = self.normal
        t = _plane_t(origins, dirs, n, float(n @ self.origin))
        # u, v of the hit without forming the points: (o + t d - origin) . e
        u = (origins @ self.e_u - self.origin @ self.e_u) + t * (dirs @ self.e_u)
        v = (origins @ self.e_v - self.origin @ self.e_v) + t * (dirs @ self.e_v)
        t[~((u >= 0) & (u <= self.width) & (v >= 0) & (v <= self.height))] = np.nan
        return t

    def material(self, points: np.ndarray) -> np.ndarray:
        if self.pattern is None:
            return np.full(len(points), self.plain, dtype=np.int8)
        cols, rows, sq, margin = self.pattern
        uv = (self.uv(points) - margin) / sq
        i, j = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        inside = (i >= 0) & (i < cols) & (j >= 0) & (j < rows)
        black = inside & ((i + j) % 2 == 0)
        return np.where(black, BLACK, WHITE).astype(np.int8)


@dataclass(frozen=True)
class InfinitePlane:
    """Plane ``normal . X = d`` (a background wall)."""

    normal: np.ndarray
    d: float
    plain: int = WALL

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        return _plane_t(origins, dirs, self.normal, self.d)

    def material(self, points: np.ndarray) -> np.ndarray:
        return np.full(len(points), self.plain, dtype=np.int8)


@dataclass(frozen=True)
class Disc:
    """Flat disc: centre, unit normal, radius."""

    centre: np.ndarray
    normal: np.ndarray
    radius: float
    plain: int = DISC

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        t = _plane_t(origins, dirs, self.normal, float(self.normal @ self.centre))
        r = np.linalg.norm(origins - self.centre + t[:, None] * dirs, axis=1)
        t[~(r <= self.radius)] = np.nan
        return t

    def material(self, points: np.ndarray) -> np.ndarray:
        return np.full(len(points), self.plain, dtype=np.int8)


@dataclass(frozen=True)
class Cylinder:
    """Cylinder of ``radius`` around ``point + s * direction``, ``s_min <= s <= s_max``."""

    point: np.ndarray
    direction: np.ndarray
    radius: float
    s_min: float
    s_max: float
    plain: int = POST

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        k = self.direction
        o = origins - self.point                       # (1, 3) or (N, 3)
        ok = o @ k
        dk = dirs @ k
        op = o - ok[:, None] * k
        dp = dirs - dk[:, None] * k
        a = np.einsum("ij,ij->i", dp, dp)
        b = 2 * (dp @ op[0] if len(op) == 1 else np.einsum("ij,ij->i", op, dp))
        c = np.einsum("ij,ij->i", op, op) - self.radius**2
        disc = b * b - 4 * a * c
        t = np.full(len(dirs), np.nan)
        m = np.flatnonzero(disc >= 0)
        if len(m) == 0:
            return t
        am, bm, _cm = a[m], b[m], (c if len(c) == 1 else c[m])
        sq = np.sqrt(disc[m])
        with np.errstate(invalid="ignore", divide="ignore"):
            t1 = (-bm - sq) / (2 * am)
            t2 = (-bm + sq) / (2 * am)
        tm = np.where(t1 > _EPS, t1, np.where(t2 > _EPS, t2, np.nan))
        s = (ok if len(ok) == 1 else ok[m]) + tm * dk[m]
        tm[~((s >= self.s_min) & (s <= self.s_max))] = np.nan
        t[m] = tm
        return t

    def material(self, points: np.ndarray) -> np.ndarray:
        return np.full(len(points), self.plain, dtype=np.int8)


Surface = Rect | InfinitePlane | Disc | Cylinder


def trace(surfaces: list, dirs: np.ndarray, origins: np.ndarray | None = None,
          chunk: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray: ``(t, surface index)``; misses get ``t = inf``, index -1."""
    dirs = np.asarray(dirs, dtype=float).reshape(-1, 3)
    n = len(dirs)
    origins = np.zeros((1, 3)) if origins is None else np.asarray(origins, dtype=float).reshape(-1, 3)
    single = len(origins) == 1
    t_best = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int16)
    for start in range(0, n, chunk):
        sl = slice(start, min(n, start + chunk))
        o, d = (origins if single else origins[sl]), dirs[sl]
        tb, ib = t_best[sl], idx[sl]
        for k, s in enumerate(surfaces):
            t = s.intersect(o, d)
            better = t < tb  # NaN compares False
            tb[better] = t[better]
            ib[better] = k
    return t_best, idx


def materials(surfaces: list, points: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Material code of each hit point (``NOTHING`` where ``idx == -1``)."""
    out = np.zeros(len(idx), dtype=np.int8)
    for k, s in enumerate(surfaces):
        m = idx == k
        if np.any(m):
            out[m] = s.material(points[m])
    return out


def surface_normals(surfaces: list, points: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Unit surface normal at each hit point (zeros where nothing was hit)."""
    out = np.zeros((len(idx), 3))
    for k, s in enumerate(surfaces):
        m = idx == k
        if not np.any(m):
            continue
        if isinstance(s, Cylinder):
            q = points[m] - s.point
            q = q - np.outer(q @ s.direction, s.direction)
            out[m] = q / np.linalg.norm(q, axis=1, keepdims=True)
        else:
            out[m] = s.normal
    return out
