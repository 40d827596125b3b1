"""Observations of the joint fit: :class:`JointData` and its builders."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..geometry import Pose
from ..io.dataset import BoardSpec, CameraModel
from ..scan_edges import EdgeZones, edge_zones, trim_edges


@dataclass(frozen=True, eq=False)
class JointData:
    """Every observation the joint fit uses, flattened over positions and boards.

    ``scan_xy`` (M, 2): kept board returns in the LiDAR plane (eq. 6) with their
    position ``scan_pos`` (M,) (index into ``psi_deg``) and board ``scan_board`` (M,).
    ``stripe_px`` (S, 2): stripe-centre pixels (distorted) with ``stripe_rays``
    (S, 3) = undistorted rays ``(x, y, 1)``, ``stripe_pos``, ``stripe_board``.
    ``board_R``, ``board_T`` (2, 3, 3), (2, 3): board poses (eq. 1) from the
    homography; ``corners_px`` the detected corners per board and
    ``object_points`` (C, 3) the board coordinates (None: no corner residuals).
    ``samples``: the single-shot poses (section 1), for the start and warnings.
    Ranging (:mod:`lidarcal.ranging`): ``board_spec`` and ``black_parity`` (per
    board, :func:`lidarcal.ranging.black_parity`) let the fit tell which returns
    hit a black square; ``scan_dark`` (M,) gives that directly instead (0..1, held).
    ``edge_zones``: the returns dropped at the ends of every scan segment before the fit
    (:func:`lidarcal.scan_edges.edge_zones`; None: not searched).
    """

    camera: CameraModel
    psi_deg: np.ndarray
    indices: np.ndarray
    scan_xy: np.ndarray
    scan_pos: np.ndarray
    scan_board: np.ndarray
    stripe_px: np.ndarray
    stripe_rays: np.ndarray
    stripe_pos: np.ndarray
    stripe_board: np.ndarray
    board_R: np.ndarray
    board_T: np.ndarray
    corners_px: tuple[np.ndarray, np.ndarray] | None
    object_points: np.ndarray | None
    samples: list[Pose] = field(default_factory=list)
    board_spec: BoardSpec | None = None
    black_parity: tuple[int | None, int | None] | None = None
    scan_dark: np.ndarray | None = None
    edge_zones: EdgeZones | None = None

    @property
    def n_positions(self) -> int:
        return len(self.psi_deg)

    def without_stripes(self) -> JointData:
        """The same data with no stripe observations (the scan-only fit)."""
        e = np.zeros(0, int)
        return replace(self, stripe_px=np.zeros((0, 2)), stripe_rays=np.zeros((0, 3)),
                       stripe_pos=e, stripe_board=e)

    @property
    def can_see_dark(self) -> bool:
        """Whether the returns from black squares can be told (given, or board + colours known)."""
        if self.scan_dark is not None:
            return bool(np.any(self.scan_dark > 0) and np.any(self.scan_dark < 1))
        return (self.board_spec is not None and self.black_parity is not None
                and all(p is not None for p in self.black_parity))


def _stripe_rays(camera: CameraModel, px: np.ndarray, points: np.ndarray | None = None
                 ) -> np.ndarray:
    """Undistorted rays ``(x, y, 1)`` (S, 3) through the stripe-centre pixels ``px``.

    ``points``: the same centres already back-projected (eq. 5, section 1,
    ``CameraLines.points_3d``): their rays are ``P / P_z``, used when a sample of them
    reprojects onto its pixels through ``camera`` (to 1e-6 px); otherwise, or without
    them, every pixel is undistorted (:func:`lidarcal.camera.pixel_rays`).
    """
    from ..camera import pixel_rays, project_points

    if len(px) == 0:
        return np.zeros((0, 3))
    if points is not None and points.shape == (len(px), 3):
        with np.errstate(invalid="ignore", divide="ignore"):
            rays = points / points[:, 2:3]
        pick = np.unique(np.linspace(0, len(px) - 1, min(len(px), 64)).astype(int))
        pick = pick[np.all(np.isfinite(rays[pick]), axis=1)]
        if len(pick) and np.max(np.abs(project_points(camera, rays[pick]) - px[pick])) < 1e-6:
            return rays
    return pixel_rays(camera, px)


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """Rows of ``a`` (N, k) with every entry finite: ``np.all(np.isfinite(a), axis=1)``, column
    by column (numpy's reduction over short rows is slow)."""
    ok = np.ones(len(a), bool)
    for j in range(a.shape[1]):
        ok &= np.isfinite(a[:, j])
    return ok


def build_joint_data(camera: CameraModel, psi_deg, scans: list[tuple[np.ndarray, np.ndarray]],
                     stripes: list[tuple[np.ndarray, np.ndarray]], board_R: np.ndarray,
                     board_T: np.ndarray, corners_px=None, object_points=None,
                     samples: list[Pose] | None = None, indices=None,
                     board_spec: BoardSpec | None = None,
                     black_parity: tuple[int | None, int | None] | None = None,
                     stripe_points: list[tuple[np.ndarray, np.ndarray]] | None = None
                     ) -> JointData:
    """:class:`JointData` from per-position observations, already assigned to boards.

    Parameters
    ----------
    scans : list of (points_board0 (M0, 2), points_board1 (M1, 2)), one per position
        LiDAR-plane points (eq. 6) on board 0 and board 1.
    stripes : list of (centres_board0 (S0, 2), centres_board1 (S1, 2)), one per position
        Stripe-centre pixels (distorted) on board 0 and board 1.
    board_R, board_T : arrays (2, 3, 3), (2, 3)
        Board poses (eq. 1); the planes are ``R[:, 2] . X = R[:, 2] . T``.
    board_spec, black_parity : optional
        The chessboard and which square parity is black on each board
        (:func:`lidarcal.ranging.black_parity`): the fit then knows the returns
        from black squares (ranging model).
    stripe_points : list of (points_board0 (S0, 3), points_board1 (S1, 3)), optional
        The stripe centres back-projected onto their boards (section 1): their rays
        save undistorting every pixel again (checked on a sample).
    """
    psi = np.asarray(psi_deg, dtype=float).ravel()
    if len(scans) != len(psi) or len(stripes) != len(psi):
        raise ValueError(f"Expected one scan and one stripe pair per position ({len(psi)}), got "
                         f"{len(scans)} and {len(stripes)}")
    n2 = 2 * len(psi)  # (position, board) groups, 2 i + b
    scan = [np.asarray(sc[b], dtype=float).reshape(-1, 2) for sc in scans for b in range(2)]
    cent = [np.asarray(st[b], dtype=float).reshape(-1, 2) for st in stripes for b in range(2)]
    g_scan = np.repeat(np.arange(n2), [len(a) for a in scan])
    g_cent = np.repeat(np.arange(n2), [len(a) for a in cent])
    xy = np.concatenate(scan) if scan else np.zeros((0, 2))
    keep = _finite_rows(xy)
    if not keep.all():
        xy, g_scan = xy[keep], g_scan[keep]
    stripe_px = np.concatenate(cent) if cent else np.zeros((0, 2))
    pts = None
    if stripe_points is not None and len(psi):
        pts = np.concatenate([np.asarray(sp[b], dtype=float).reshape(-1, 3)
                              for sp in stripe_points for b in range(2)])
    rays = _stripe_rays(camera, stripe_px, pts)
    ok = _finite_rows(rays)
    if not ok.all():
        stripe_px, rays, g_cent = stripe_px[ok], rays[ok], g_cent[ok]
    return JointData(camera, psi, np.arange(len(psi)) if indices is None else np.asarray(indices),
                     xy, g_scan // 2, g_scan % 2, stripe_px, rays, g_cent // 2, g_cent % 2,
                     np.asarray(board_R, float), np.asarray(board_T, float),
                     None if corners_px is None else tuple(np.asarray(c, float) for c in corners_px),
                     None if object_points is None else np.asarray(object_points, float),
                     list(samples or []), board_spec,
                     None if black_parity is None else tuple(black_parity))


def scan_edge_zones(positions) -> EdgeZones:
    """The edge zones of the positions' scan segments (:func:`lidarcal.scan_edges.edge_zones`:
    residuals to each position's own free V lines, pooled over the positions)."""
    segs = []
    for p in positions:
        free = p.lidar_lines.free or p.lidar_lines
        segs += [(p.segments.points1, free.line1, True), (p.segments.points2, free.line2, False)]
    return edge_zones(segs)


def joint_data(result, board_poses: str = "homography") -> JointData:
    """:class:`JointData` from a :class:`lidarcal.pipeline.CalibrationResult`.

    Board ``k`` gets scan segment ``pose.info["pairs"][k]`` (``points1`` for 0,
    ``points2`` for 1), less its edge zones (:func:`scan_edge_zones`: returns whose spot
    straddles the hinge or a board's edge), and the stripe centres ``camera_lines.centres_px[k]``.
    ``board_poses``: "homography" (eq. 2, ``BoardView.R, T``) or "pnp"
    (``cv2.solvePnP``, ``BoardView.R_pnp, T_pnp``).
    """
    if board_poses not in ("homography", "pnp"):
        raise ValueError(f"board_poses must be 'homography' or 'pnp', got {board_poses!r}")
    pnp = board_poses == "pnp"
    scans, stripes, points = [], [], []
    zones = scan_edge_zones(result.positions)
    for p in result.positions:
        pairs = p.pose.info.get("pairs", (0, 1))
        seg = (trim_edges(p.segments.points1, True, zones), trim_edges(p.segments.points2, False, zones))
        scans.append((seg[pairs[0]], seg[pairs[1]]))
        stripes.append(tuple(p.camera_lines.centres_px))
        points.append(tuple(getattr(p.camera_lines, "points_3d", None) or (None, None)))
    if any(q is None for pair in points for q in pair):
        points = None
    boards = result.boards
    spec: BoardSpec | None = getattr(getattr(result, "dataset", None), "v_board", None)
    obj = spec.object_points() if spec is not None else None
    parity = None
    if spec is not None:
        from ..ranging import black_parity

        parity = tuple(black_parity(b, result.camera, spec) for b in boards)
    data = build_joint_data(result.camera, [p.psi_deg for p in result.positions], scans, stripes,
                            np.array([b.R_pnp if pnp else b.R for b in boards]),
                            np.array([b.T_pnp if pnp else b.T for b in boards]),
                            [b.corners_px for b in boards] if obj is not None else None, obj,
                            [p.pose for p in result.positions], [p.index for p in result.positions],
                            spec, parity, points)
    return replace(data, edge_zones=zones)
