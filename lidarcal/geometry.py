"""Shared geometry: planes, lines, poses and the small fits every step uses.

Convention: camera frame is OpenCV's (x right, y down, z forward), lengths in
mm, angles in radians inside the package (degrees only at the edges, in names
ending ``_deg``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: Median absolute deviation -> standard deviation for Gaussian noise (1 / Phi^-1(3/4)).
MAD_TO_SIGMA = 1.4826


def median(v: np.ndarray, *, overwrite: bool = False) -> float:
    """``np.median(v)`` of a finite, non-empty 1-D array, the same value, by one partition
    about the upper middle (the lower middle of an even count is the largest entry below
    it), without ``np.median``'s dispatch and checks: the per-position steps and the joint
    fit's noise model take thousands of medians. ``overwrite``: ``v`` is a temporary and may
    be reordered, else it is copied."""
    w = v if overwrite else v.copy()
    k = len(w) // 2
    w.partition(k)
    if len(w) % 2:
        return float(w[k])
    return (float(w[:k].max()) + float(w[k])) / 2


def as_points(points: np.ndarray, dim: int = 3) -> np.ndarray:
    """Return ``points`` as a float array of shape (N, dim); a single point becomes (1, dim)."""
    arr = np.asarray(points, dtype=float)
    if arr.ndim == 1:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"Expected points with shape (N, {dim}), got {arr.shape}")
    return arr


def unit(v: np.ndarray) -> np.ndarray:
    """Normalise vector(s) along the last axis."""
    v = np.asarray(v, dtype=float)
    n = np.sqrt(np.add.reduce(v * v, axis=-1, keepdims=True))  # np.linalg.norm's, unwrapped
    if (n == 0).any():
        raise ValueError("Cannot normalise a zero vector")
    return v / n


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The cross product of two single 3-vectors, ``np.cross(a, b)`` to the last bit, without
    its broadcasting machinery (which costs ten times the product on one pair)."""
    a0, a1, a2 = np.asarray(a, dtype=float).tolist()
    b0, b1, b2 = np.asarray(b, dtype=float).tolist()
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def angle_between(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors in radians (numerically safe near 0 and pi)."""
    a, b = unit(a), unit(b)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b) if a.ndim > 1 or b.ndim > 1
                                           else cross3(a, b)), np.dot(a, b)))


def angle_between_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two vectors in degrees."""
    return float(np.degrees(angle_between(a, b)))


@dataclass(frozen=True)
class Plane:
    """Plane ``normal . X = d`` in the camera frame, ``|normal| = 1``, mm (eq. 3).

    Convention: the sign is chosen so that ``d >= 0`` (the normal points away
    from the camera's optical centre) unless the plane passes through it.
    """

    normal: np.ndarray  # shape (3,)
    d: float

    @staticmethod
    def from_normal_point(normal: np.ndarray, point: np.ndarray) -> Plane:
        n = unit(normal)
        d = float(n @ np.asarray(point, dtype=float))
        if d < 0:
            n, d = -n, -d
        return Plane(n, d)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of points (N, 3) to the plane, mm."""
        return as_points(points) @ self.normal - self.d

    def intersect_rays(self, directions: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
        """Points where rays ``origin + t * directions`` meet the plane (N, 3).

        Rays parallel to the plane give NaN.
        """
        dirs = as_points(directions)
        o = np.zeros(3) if origin is None else np.asarray(origin, dtype=float)
        denom = dirs @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.d - o @ self.normal) / denom
        t = np.where(np.abs(denom) < 1e-12, np.nan, t)
        return o + t[:, None] * dirs

    def project(self, points: np.ndarray) -> np.ndarray:
        """Orthogonal projection of points onto the plane."""
        p = as_points(points)
        return p - self.distance(p)[:, None] * self.normal

    def to_algebraic(self) -> np.ndarray:
        """Coefficients (a, b, c) of eq. (4), ``a x + b y + c z = 1`` (requires d != 0)."""
        return self.normal / self.d

    def to_dict(self) -> dict:
        return {"normal": self.normal.tolist(), "d_mm": float(self.d)}


def fit_plane(points: np.ndarray, weights: np.ndarray | None = None) -> Plane:
    """Total-least-squares plane through points (the geometric fit of eq. 4).

    The normal is the right singular vector of the centred points with the
    smallest singular value; this minimises the sum of squared orthogonal
    distances. Needs at least 3 non-collinear points.
    """
    p = as_points(points)
    if len(p) < 3:
        raise ValueError(f"A plane needs at least 3 points, got {len(p)}")
    w = np.ones(len(p)) if weights is None else np.asarray(weights, dtype=float)
    c = (w[:, None] * p).sum(0) / w.sum()
    _, s, vt = np.linalg.svd(np.sqrt(w)[:, None] * (p - c), full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-300):
        raise ValueError("Points are collinear: the plane is undetermined")
    return Plane.from_normal_point(vt[-1], c)


def fit_plane_algebraic(points: np.ndarray) -> Plane:
    """Algebraic least squares of eq. (4): ``a x + b y + c z = 1`` (the paper's form).

    Minimises the algebraic residual, not the orthogonal distance; kept to show
    the difference with :func:`fit_plane`.
    """
    p = as_points(points)
    abc, *_ = np.linalg.lstsq(p, np.ones(len(p)), rcond=None)
    n = np.linalg.norm(abc)
    return Plane.from_normal_point(abc / n, abc / n**2)


def intersect_planes(p1: Plane, p2: Plane, p3: Plane) -> np.ndarray:
    """The point common to three planes (3 x 3 linear system); E in section 1.3."""
    A = np.vstack([p1.normal, p2.normal, p3.normal])
    b = np.array([p1.d, p2.d, p3.d])
    if abs(np.linalg.det(A)) < 1e-9:
        raise ValueError("Planes do not meet in a single point")
    return np.linalg.solve(A, b)


@dataclass(frozen=True)
class Line3D:
    """Line ``X = point + t * direction`` (|direction| = 1), mm."""

    point: np.ndarray
    direction: np.ndarray

    def distance(self, points: np.ndarray) -> np.ndarray:
        p = as_points(points) - self.point
        return np.linalg.norm(p - np.outer(p @ self.direction, self.direction), axis=1)

    def foot(self, points: np.ndarray) -> np.ndarray:
        """Orthogonal projection of points onto the line."""
        p = as_points(points) - self.point
        return self.point + np.outer(p @ self.direction, self.direction)


def line_difference(a: Line3D, b: Line3D, near: np.ndarray) -> tuple[float, float]:
    """Two estimates of one line (e.g. two fits of the turntable axis, eq. 18): the angle
    between their directions (deg, sign-free) and the distance (mm) of ``b``'s point nearest
    ``near`` (e.g. the LiDAR centre) from ``a``."""
    ka, kb = unit(a.direction), unit(b.direction)
    angle = float(np.degrees(np.arccos(min(abs(float(ka @ kb)), 1.0))))
    return angle, float(a.distance(b.foot(near))[0])


def nearest_rotation(M: np.ndarray) -> tuple[np.ndarray, float]:
    """Nearest proper rotation to ``M`` in the Frobenius norm (SVD), and that distance.

    Returns ``(R, ||M - R||_F)``. A determinant of -1 in ``U V^T`` is fixed by
    flipping the last singular vector, so ``R`` is always in SO(3).
    """
    M = np.asarray(M, dtype=float)
    if M.shape != (3, 3):
        raise ValueError(f"Expected a matrix with shape (3, 3), got {M.shape}")
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    return R, float(np.linalg.norm(M - R))


def check_rotation(R: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Validate a rotation matrix; raise ``ValueError`` saying what is wrong."""
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise ValueError(f"Expected rotation matrix with shape (3, 3), got {R.shape}")
    if np.linalg.norm(R.T @ R - np.eye(3)) > tol:
        raise ValueError("Expected an orthonormal matrix, R^T R differs from I")
    if np.linalg.det(R) < 0:
        raise ValueError("Matrix has determinant -1: it probably represents a rotoreflection")
    return R


@dataclass(frozen=True)
class Pose:
    """LiDAR pose in the camera frame: ``X_camera = R @ X_lidar + T`` (eqs. 13-14).

    The columns of ``R`` are the LiDAR's x, y and z axes in the camera frame;
    ``T`` is its optical centre, mm. ``residual`` is how far the raw estimate was
    from a rotation before projection onto SO(3) (Frobenius norm), 0 if exact.
    """

    R: np.ndarray
    T: np.ndarray
    residual: float = 0.0
    info: dict = field(default_factory=dict, compare=False, repr=False)

    @property
    def x_axis(self) -> np.ndarray:
        return self.R[:, 0]

    @property
    def y_axis(self) -> np.ndarray:
        return self.R[:, 1]

    @property
    def z_axis(self) -> np.ndarray:
        return self.R[:, 2]

    def apply(self, points_lidar: np.ndarray) -> np.ndarray:
        """Map LiDAR-frame points (N, 3) into the camera frame."""
        return as_points(points_lidar) @ self.R.T + self.T

    def inverse_apply(self, points_cam: np.ndarray) -> np.ndarray:
        """Map camera-frame points (N, 3) into the LiDAR frame."""
        return (as_points(points_cam) - self.T) @ self.R

    def to_dict(self) -> dict:
        return {"R": np.asarray(self.R).tolist(), "T_mm": np.asarray(self.T).tolist()}

    @staticmethod
    def from_dict(d: dict) -> Pose:
        return Pose(np.asarray(d["R"], dtype=float), np.asarray(d["T_mm"], dtype=float))


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` of vectors ``v`` (..., 3): (..., 3, 3), with ``[v]x u = v x u`` (the six
    off-diagonal entries placed in a zero array)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotation_about_axis(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix by ``angle`` (rad) about unit ``axis``, right-handed (Rodrigues)."""
    K = skew(unit(axis))
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


def rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """``Exp(w)``: the rotation matrix of the rotation vector ``w`` (3,), rad (Rodrigues;
    the identity at 0)."""
    angle = float(np.linalg.norm(w))
    return np.eye(3) if angle == 0.0 else rotation_about_axis(w, angle)


def so3_left_jacobian(w: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian ``J_l(w) = I + (1 - cos th)/th^2 [w]x + (th - sin th)/th^3
    [w]x^2`` (``th = |w|``; its series to second order below 1e-6 rad): with ``R = Exp(w) R0``,
    ``d(R v)/dw = -[R v]x J_l(w)``."""
    W = skew(w)
    th = float(np.linalg.norm(w))
    if th < 1e-6:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    return np.eye(3) + (1 - np.cos(th)) / th**2 * W + (th - np.sin(th)) / th**3 * (W @ W)


def rotate_perpendicular(v: np.ndarray, axis: np.ndarray, angle: float | np.ndarray) -> np.ndarray:
    """Rodrigues' formula for vectors perpendicular to ``axis`` (eqs. 20, 23).

    ``v cos(t) + (k x v) sin(t)``: the ``k (k . v)(1 - cos t)`` term of the
    general formula vanishes because ``k . v = 0``. ``angle`` may be an array;
    the result then has shape (len(angle), 3).
    """
    k = unit(axis)
    t = np.asarray(angle, dtype=float)
    v = np.asarray(v, dtype=float)
    out = np.multiply.outer(np.cos(t), v) + np.multiply.outer(np.sin(t), np.cross(k, v))
    return out


def plane_basis(normal: np.ndarray) -> np.ndarray:
    """Two orthonormal vectors (2, 3) spanning the plane perpendicular to ``normal``."""
    n = unit(normal)
    a = np.array([1.0, 0, 0]) if abs(n[0]) < 0.9 else np.array([0, 1.0, 0])
    u = unit(np.cross(n, a))
    return np.vstack([u, np.cross(n, u)])


def fit_circle_2d_algebraic(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Kasa's algebraic circle fit: ``x^2 + y^2 + D x + E y + F = 0`` by linear least squares.

    Biased towards small radii on short arcs; kept for comparison with
    :func:`fit_circle_2d`. Needs at least 3 non-collinear points.
    """
    p = as_points(points, 2)
    if len(p) < 3:
        raise ValueError(f"A circle needs at least 3 points, got {len(p)}")
    m = p.mean(0)
    s = max(np.abs(p - m).max(), 1e-12)
    q = (p - m) / s
    A = np.column_stack([q, np.ones(len(q))])
    b = -(q**2).sum(1)
    (D, E, F), *_ = np.linalg.lstsq(A, b, rcond=None)
    c = np.array([-D / 2, -E / 2])
    r = np.sqrt(max(c @ c - F, 0.0))
    return c * s + m, float(r * s)


def fit_circle_2d(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Geometric circle fit: minimise ``sum w (|p - c| - r)^2`` (Levenberg-Marquardt).

    Started from :func:`fit_circle_2d_algebraic`; data are centred and scaled
    first. Needs at least 3 non-collinear points.
    """
    p = as_points(points, 2)
    c0, r0 = fit_circle_2d_algebraic(p)
    w = np.ones(len(p)) if weights is None else np.sqrt(np.asarray(weights, dtype=float))
    m = p.mean(0)
    s = max(np.abs(p - m).max(), 1e-12)
    q = (p - m) / s

    def res(x: np.ndarray) -> np.ndarray:
        return w * (np.hypot(q[:, 0] - x[0], q[:, 1] - x[1]) - x[2])

    x0 = np.array([*(c0 - m) / s, r0 / s])
    from scipy.optimize import least_squares  # here: finding the V's boards needs no scipy

    sol = least_squares(res, x0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.x[:2] * s + m, float(abs(sol.x[2]) * s)


@dataclass(frozen=True)
class Circle3D:
    """Circle in space: centre, unit normal of its plane, radius (mm)."""

    centre: np.ndarray
    normal: np.ndarray
    radius: float


def fit_circle_3d(points: np.ndarray, normal: np.ndarray | None = None,
                  algebraic: bool = False) -> Circle3D:
    """Circle through 3D points: plane by TLS (or the given normal), then a 2D circle fit.

    With ``normal`` given, the points are projected on the plane through their
    centroid perpendicular to it (as the paper does with Pi_O, eq. 18).
    """
    p = as_points(points)
    if normal is None:
        plane = fit_plane(p)
    else:
        plane = Plane.from_normal_point(normal, p.mean(0))
    B = plane_basis(plane.normal)
    origin = plane.normal * plane.d
    uv = (p - origin) @ B.T
    c2, r = (fit_circle_2d_algebraic if algebraic else fit_circle_2d)(uv)
    return Circle3D(origin + c2 @ B, plane.normal, r)
