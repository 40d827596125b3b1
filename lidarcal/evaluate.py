"""Compare estimates with a simulator's ``truth.json`` (evaluation only, never calibration)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

from . import paper
from .geometry import Plane, Pose, angle_between_deg, intersect_planes


def pose_error(est: Pose, truth: Pose) -> dict[str, float]:
    """True error of one pose: LiDAR centre (mm), z axis and x axis (deg)."""
    return {
        "centre_mm": float(np.linalg.norm(np.asarray(est.T) - np.asarray(truth.T))),
        "z_axis_deg": angle_between_deg(est.z_axis, truth.z_axis),
        "x_axis_deg": angle_between_deg(est.x_axis, truth.x_axis),
    }


def truth_poses(truth: dict) -> dict[int, Pose]:
    """``truth.json`` poses by position index."""
    return {int(p["index"]): Pose.from_dict(p) for p in truth["poses"]}


def pose_errors(estimates: dict[int, Pose], truth: dict) -> pd.DataFrame:
    """One row per position present in both: index, centre_mm, z_axis_deg, x_axis_deg."""
    import pandas as pd

    tp = truth_poses(truth)
    rows = [{"index": i, **pose_error(p, tp[i])} for i, p in sorted(estimates.items()) if i in tp]
    return pd.DataFrame(rows, columns=["index", "centre_mm", "z_axis_deg", "x_axis_deg"])


def axis_direction_error_deg(direction: np.ndarray, truth_direction: np.ndarray) -> float:
    """Angle between two axis directions, as lines (sign ignored), deg."""
    a = angle_between_deg(direction, truth_direction)
    return min(a, 180.0 - a)


def truth_board_planes(truth: dict) -> list[Plane]:
    """The V-board planes of ``truth.json`` (``normal . X = d_mm``)."""
    return [Plane.from_normal_point(np.asarray(b["normal"], float),
                                    np.asarray(b["normal"], float) * float(b["d_mm"]))
            for b in truth["boards"]]


def plane_error(est: Plane, truth: Plane) -> dict[str, float]:
    """Normal angle (deg, sign ignored) and distance error (mm) along the truth normal at the
    point of the truth plane nearest the camera."""
    ang = angle_between_deg(est.normal, truth.normal)
    ang = min(ang, 180.0 - ang)
    foot = truth.normal * truth.d
    return {"normal_deg": ang, "offset_mm": float(abs(est.distance(foot)[0]))}


def match_planes(est: list[Plane], truth: list[Plane]) -> list[int]:
    """For each estimated plane, the index of the truth plane with the nearest normal."""
    return [int(np.argmin([plane_error(e, t)["normal_deg"] for t in truth])) for e in est]


def truth_laser_plane(pose: Pose) -> Plane:
    """The LiDAR scan plane (its z = 0 plane) of a truth pose, in the camera frame."""
    return Plane.from_normal_point(pose.z_axis, pose.T)


def truth_E(truth: dict, index: int) -> np.ndarray:
    """E of section 1.3 from the truth: both board planes and the truth laser plane."""
    b1, b2 = truth_board_planes(truth)[:2]
    return intersect_planes(b1, b2, truth_laser_plane(truth_poses(truth)[index]))


def truth_lines(truth: dict, index: int, order: list[int] | None = None
                ) -> tuple[np.ndarray, np.ndarray, float]:
    """Section 1.3 from the truth at one position: E (3,), the stripe rays l (2, 3) and alpha
    (rad). ``l_k = n_k x n_L`` (board ``k``'s plane with the truth laser plane) is oriented
    from E towards board ``k``'s outline centre, as the stripe runs; ``alpha = arccos(l_0 .
    l_1)``. ``order``: truth.json's board indices in the estimate's order
    (:func:`match_planes`); default truth.json's order."""
    order = [0, 1] if order is None else list(order)
    planes = truth_board_planes(truth)
    laser = truth_laser_plane(truth_poses(truth)[index])
    E = intersect_planes(planes[order[0]], planes[order[1]], laser)
    l = []
    for k in order:
        v = np.cross(planes[k].normal, laser.normal)
        v /= np.linalg.norm(v)
        centre = np.mean(np.asarray(truth["boards"][k]["outline_mm"], float), axis=0)
        l.append(v if (centre - E) @ v >= 0 else -v)
    l = np.vstack(l)
    return E, l, float(np.arccos(np.clip(l[0] @ l[1], -1.0, 1.0)))


def stripe_errors_px(centres_px: np.ndarray, truth: dict, index: int, board: int,
                     image_size: tuple[int, int]) -> np.ndarray:
    """Signed distances (px, (N,)) of stripe centres ``centres_px`` (N, 2) on board ``board``
    (truth.json's index) at position ``index`` from the true stripe: the line where the truth
    laser plane (the LiDAR's z = 0 plane) cuts that board's plane (eq. 5 read backwards),
    projected through the true camera with its distortion (``cv2.projectPoints``) and
    sampled every ~0.05 px; each centre's distance along the curve's normal to its nearest
    sample."""
    import cv2
    from scipy.spatial import cKDTree

    B = truth_board_planes(truth)[board]
    laser = truth_laser_plane(truth_poses(truth)[index])
    d = np.cross(B.normal, laser.normal)
    d /= np.linalg.norm(d)
    p0 = np.linalg.solve(np.vstack([B.normal, laser.normal, d]), np.array([B.d, laser.d, 0.0]))
    t = (np.asarray(truth["boards"][board]["outline_mm"], float) - p0) @ d
    cam = truth_camera(truth, image_size)
    ends, _ = cv2.projectPoints(p0 + np.array([t.min(), t.max()])[:, None] * d, np.zeros(3),
                                np.zeros(3), cam.K, cam.dist)
    n = int(np.ceil(20 * np.linalg.norm(np.ptp(ends.reshape(-1, 2), axis=0)))) + 2
    X = p0 + np.linspace(t.min(), t.max(), n)[:, None] * d
    curve = cv2.projectPoints(X, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    pts = np.asarray(centres_px, float).reshape(-1, 2)
    i = np.clip(cKDTree(curve).query(pts)[1], 1, len(curve) - 2)
    tan = curve[i + 1] - curve[i - 1]
    tan /= np.linalg.norm(tan, axis=1)[:, None]
    return np.sum((pts - curve[i]) * np.column_stack([-tan[:, 1], tan[:, 0]]), axis=1)


def truth_scan_line(truth: dict, index: int, board: int):
    """Board ``board`` (truth.json's index) seen in the LiDAR plane at position ``index``: the
    board plane ``n . X = d`` with ``X = R x + T`` (``X_cam = R @ X_lidar + T``) cut by the
    LiDAR's z = 0 plane, a :class:`~lidarcal.scan.Line2D` ``n' . p = c`` oriented so that
    ``c >= 0`` (a positive distance is beyond the board, away from the LiDAR)."""
    from .scan import Line2D

    P = truth_poses(truth)[index]
    B = truth_board_planes(truth)[board]
    n = np.asarray(P.R).T @ B.normal
    c = float(B.d - B.normal @ np.asarray(P.T))
    s = float(np.hypot(n[0], n[1])) * (1.0 if c >= 0 else -1.0)
    return Line2D(n[:2] / s, c / s)


def scan_range_errors(line, angle_deg: np.ndarray, range_mm: np.ndarray) -> dict[str, np.ndarray]:
    """Range errors of returns on a known line (eq. 6 read backwards): the measured range minus
    the true range ``c / (n . b)`` along each beam ``b = (cos theta, sin theta)``, mm, and the
    incidence angle of each beam on the line (deg). ``line`` from :func:`truth_scan_line`."""
    th = np.radians(np.asarray(angle_deg, float))
    nb = np.cos(th) * line.normal[0] + np.sin(th) * line.normal[1]
    return {"error_mm": np.asarray(range_mm, float) - line.offset / nb,
            "incidence_deg": np.degrees(np.arccos(np.clip(np.abs(nb), 0.0, 1.0)))}


def segment_boards(truth: dict, position) -> tuple[int, int]:
    """truth.json's board index of scan segment 1 and 2 of a pipeline position (its camera
    boards matched by normal, :func:`match_planes`, and the pose's pairing
    ``info["pairs"]``: camera board k <-> segment ``pairs[k]``)."""
    order = match_planes(list(position.camera_lines.board_planes), truth_board_planes(truth))
    pairs = list(position.pose.info["pairs"])
    return order[pairs.index(0)], order[pairs.index(1)]


def v_fit_crlb(points1: np.ndarray, points2: np.ndarray, normal1: np.ndarray, offsets: tuple[
        float, float], alpha: float, sign: int, range_noise_mm: float) -> dict[str, object]:
    """Cramer-Rao bound of the constrained V fit of eqs. (7)-(12) for range noise along the
    beams (the LiDAR's noise model: ``r_i = c_k / (n_k . b_i) + e_i``, ``e_i ~ N(0, s^2)``,
    ``b_i`` the unit beam direction of point ``i``).

    The V has three parameters: the normal angle ``phi`` of line 1 (``n1 = (cos phi, sin phi)``,
    ``n2 = Rot(sign alpha) n1``) and the offsets ``c1``, ``c2`` (``n_k . p = c_k``). Their
    Fisher information is ``J^T J / s^2`` with ``dr/dc_k = 1 / (n_k . b)`` and
    ``dr/dphi = -c_k (n_k^perp . b) / (n_k . b)^2``. The LiDAR centre seen from the V
    (``o = Rot(-phi) (-E)``, E the vertex) carries the bound that limits a single-shot pose's
    centre (eq. 14): ``cov_o = G cov G^T`` with G its Jacobian (central differences).

    Returns ``cov`` (3 x 3, of phi [rad], c1, c2 [mm]), ``phi_std_deg`` and ``centre_rms_mm``
    (``sqrt(trace(cov_o))``, the in-plane rms of the centre's error at the bound).
    """
    from .scan import Line2D, intersect_lines_2d

    p = [np.asarray(points1, float), np.asarray(points2, float)]
    b = [q / np.linalg.norm(q, axis=1)[:, None] for q in p]
    ca, sa = np.cos(sign * alpha), np.sin(sign * alpha)
    Q = np.array([[ca, -sa], [sa, ca]])
    phi0 = float(np.arctan2(normal1[1], normal1[0]))

    def normals(phi: float) -> tuple[np.ndarray, np.ndarray]:
        n1 = np.array([np.cos(phi), np.sin(phi)])
        return n1, Q @ n1

    n = normals(phi0)
    rows = []
    for k in range(2):
        nb = b[k] @ n[k]
        perp = b[k] @ np.array([-n[k][1], n[k][0]])
        J = np.zeros((len(b[k]), 3))
        J[:, 0] = -offsets[k] * perp / nb ** 2
        J[:, 1 + k] = 1.0 / nb
        rows.append(J)
    J = np.vstack(rows)
    cov = range_noise_mm ** 2 * np.linalg.inv(J.T @ J)

    def origin(x: np.ndarray) -> np.ndarray:
        n1, n2 = normals(x[0])
        E = intersect_lines_2d(Line2D(n1, x[1]), Line2D(n2, x[2]))
        c, s = np.cos(x[0]), np.sin(x[0])
        return np.array([[c, s], [-s, c]]) @ (-E)

    x0 = np.array([phi0, offsets[0], offsets[1]])
    h = np.array([1e-7, 1e-4, 1e-4])
    G = np.column_stack([(origin(x0 + h[i] * np.eye(3)[i]) - origin(x0 - h[i] * np.eye(3)[i]))
                         / (2 * h[i]) for i in range(3)])
    cov_o = G @ cov @ G.T
    return {"cov": cov, "phi_std_deg": float(np.degrees(np.sqrt(cov[0, 0]))),
            "centre_cov": cov_o, "centre_rms_mm": float(np.sqrt(np.trace(cov_o)))}


# ------------------------------------------------------------------ the notebooks' truth tables


def truth_camera(truth: dict, image_size: tuple[int, int]):
    """The true camera of ``truth.json`` (K, dist padded to OpenCV's five terms)."""
    from .io.dataset import CameraModel

    dist = np.asarray(truth["camera"]["dist"], float)
    return CameraModel(np.asarray(truth["camera"]["K"], float), np.r_[dist, np.zeros(5 - len(dist))],
                       tuple(image_size))


def intrinsics_error(camera, true_camera) -> pd.DataFrame:
    """fx, fy, cx, cy (px), k1, k2 of an estimated camera against the truth: truth, estimate,
    error."""
    import pandas as pd

    def params(c):
        return [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], *np.asarray(c.dist, float)[:2]]

    err = pd.DataFrame({"truth": params(true_camera), "estimate": params(camera)},
                       index=["fx", "fy", "cx", "cy", "k1", "k2"])
    err["error"] = err.estimate - err.truth
    return err


def ray_direction_error_deg(camera, true_camera, grid: tuple[int, int] = (25, 20)) -> np.ndarray:
    """Angle (deg) between the rays of two cameras (Zhang's model with distortion) through a
    ``grid`` (columns, rows) of pixels spanning the image: what an intrinsics error does to a
    back-projected point."""
    from .camera import pixel_rays
    from .geometry import unit

    w, h = camera.image_size
    px = np.stack(np.meshgrid(np.linspace(0, w - 1, grid[0]), np.linspace(0, h - 1, grid[1])),
                  -1).reshape(-1, 2)
    cos = (unit(pixel_rays(camera, px)) * unit(pixel_rays(true_camera, px))).sum(1)
    return np.degrees(np.arccos(np.clip(cos, -1, 1)))


def board_plane_table(views, true_planes: list[Plane] | None = None) -> tuple[pd.DataFrame, list]:
    """The two V-board planes (section 1.2) by both methods, homography + SVD (eqs. 2-3) and
    ``cv2.solvePnP``: normal, d_mm, reprojection RMS and, with ``true_planes``, the plane
    errors (:func:`plane_error`). Returns the table and the truth plane matched to each board
    (``None`` without truth)."""
    import pandas as pd

    match = match_planes([v.plane for v in views], true_planes) if true_planes is not None \
        else [None] * len(views)
    rows = []
    for k, (v, j) in enumerate(zip(views, match)):
        for method, plane, rms in (("homography + SVD, eqs. (2)-(3)", v.plane, v.reprojection_rms_px[0]),
                                   ("solvePnP", v.plane_pnp, v.reprojection_rms_px[1])):
            err = plane_error(plane, true_planes[j]) if j is not None else {}
            rows.append({"board": k, "method": method, "normal": plane.normal.round(5),
                         "d_mm": plane.d, **err, "reproj_rms_px": rms})
    return pd.DataFrame(rows), match


def v_angle_deg(board_planes: list[Plane], laser_plane: Plane) -> float:
    """The angle alpha (deg) between the two lines the boards cut from the laser plane (section
    1.3): the angle of the V in the scan, from the planes' normals."""
    n1, n2 = (np.asarray(p.normal, float) for p in board_planes[:2])
    d1, d2 = np.cross(n1, laser_plane.normal), np.cross(n2, laser_plane.normal)
    return float(np.degrees(np.arccos(abs(np.dot(d1, d2)) / np.linalg.norm(d1) / np.linalg.norm(d2))))


def model_errors(res, truth: dict, models: dict | None = None) -> pd.DataFrame:
    """Mean true error of each pose function of a calibration (``res.fitted(model)`` against
    ``truth.json``: centre_mm, z_axis_deg, x_axis_deg, axis_direction_deg) and of the single-shot
    samples; ``models`` name -> function, by default the paper chain, rigid and joint fits."""
    import pandas as pd

    cols = ["centre_mm", "z_axis_deg", "x_axis_deg"]
    if models is None:
        models = {"paper chain": res.paper_model, "rigid": res.rigid_model, "joint": res.joint_model}
    rows = {}
    for name, fn in models.items():
        if fn is None:
            continue
        e = pose_errors(res.fitted(fn), truth)[cols].mean()
        e["axis_direction_deg"] = axis_direction_error_deg(fn.axis.direction,
                                                           np.array(truth["axis"]["direction"]))
        rows[name] = e
    rows["samples"] = pose_errors(res.samples, truth)[cols].mean()
    return pd.DataFrame(rows).T


#: the paper's Table 1 (section 2, its rig): mean distance of the fitted poses to the samples


def table1_comparison(models: dict, res, truth: dict | None = None) -> pd.DataFrame:
    """Table 1 of the paper for each pose function: (a) its mean distance to the samples it was
    fitted to (:func:`lidarcal.turntable.table1`), with truth (b) its mean true error, and the
    samples' own true error; the paper's row last. Index (model, comparison)."""
    import pandas as pd

    from .turntable import table1

    cols = ["centre_mm", "z_axis_deg", "x_axis_deg"]
    psi, samples = res.psi_deg, [p.pose for p in res.positions]
    rows = {}
    for name, m in models.items():
        rows[(name, "(a) vs samples")] = table1(m, psi, samples)[cols].mean()
        if truth is not None:
            rows[(name, "(b) vs truth")] = pose_errors({p.index: m.pose(p.psi_deg) for p in res.positions},
                                                       truth)[cols].mean()
    if truth is not None:
        rows[("single-shot samples", "(b) vs truth")] = pose_errors(res.samples, truth)[cols].mean()
    rows[("paper, Table 1", "(a) vs samples")] = pd.Series({k: mean for k, (mean, _) in paper.TABLE1.items()})
    return pd.DataFrame(rows).T


def fits_pose_error(fits: dict, positions, true_poses: dict[int, Pose]) -> pd.DataFrame:
    """Mean true pose error (:func:`pose_error`) of each fitted pose function (name -> function
    with ``position_psi``, e.g. joint fits with and without the jitter model) over ``positions``,
    each at its own corrected angle; plus the fitted ``jitter_deg``."""
    import pandas as pd

    table = pd.DataFrame({name: pd.DataFrame([pose_error(m.pose(m.position_psi(p.index, p.psi_deg)),
                                                         true_poses[p.index]) for p in positions]).mean()
                          for name, m in fits.items()}).T
    table["jitter_deg"] = [m.jitter_deg for m in fits.values()]
    return table


def v_fit_table(fits: dict, E_true_mm: np.ndarray | None = None) -> pd.DataFrame:
    """The V fits of one scan (section 1.4) side by side: E (mm, scan plane), the V's angle
    (deg), residual RMS (mm) and, with the true E in the LiDAR frame, its error (mm)."""
    import pandas as pd

    return pd.DataFrame([{"fit": name, "E_mm": f.E.round(2), "angle_deg": np.degrees(f.alpha),
                          "rms_mm": f.residual_rms_mm,
                          **({"E_error_mm": float(np.linalg.norm(f.E - np.asarray(E_true_mm)[:2]))}
                             if E_true_mm is not None else {})} for name, f in fits.items()])


def candidate_table(candidates: dict, z_axis_hint: np.ndarray, pose_true: Pose | None = None) -> pd.DataFrame:
    """The two segment-to-board assignments of a pose (section 1.5): ``z . hint`` (the
    z_axis_hint picks the positive one) and, with truth, each one's :func:`pose_error`."""
    import pandas as pd

    return pd.DataFrame([{"assignment": name, "z . hint": float(np.dot(c.z_axis, z_axis_hint)),
                          **(pose_error(c, pose_true) if pose_true is not None else {})}
                         for name, c in candidates.items()])


def axis_table(models: dict, axis_true=None, near_mm: np.ndarray | None = None) -> pd.DataFrame:
    """The turntable axis of each pose function (section 2): direction and point and, with the
    true axis, the direction error (deg) and the distance between the axes near ``near_mm``."""
    import pandas as pd

    from .turntable import axis_distance_mm

    return pd.DataFrame([{"model": k, "axis_direction": m.axis.direction.round(6),
                          "axis_point_mm": m.axis.point.round(2),
                          **({"axis_direction_error_deg": axis_direction_error_deg(m.axis.direction, axis_true.direction),
                              "axis_offset_mm": axis_distance_mm(m.axis, axis_true, near_mm)}
                             if axis_true is not None else {})} for k, m in models.items()])
