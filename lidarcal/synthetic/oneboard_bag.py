"""``write_oneboard_bag``: a one-board recording (:mod:`lidarcal.synthetic.oneboard`) as a ROS bag.

The board is held still at each view for ``hold_s`` and carried by hand to the next
one in ``move_s`` (a cosine speed profile: slow at both ends, as a hand moves; with
``profile="linear"`` a constant speed that never stops, for a recording without a
still moment). The board also moves in before the first view and out after the last.
All streams run free at their own rates:

- ``/scan`` (``sensor_msgs/LaserScan``, metres): the scene traced at the board's pose of
  the scan's mid-time, fresh Gaussian range noise per scan (the rig's ``range_noise_mm``,
  rounded to integer mm), and about 2 % invalid returns (0, inf, NaN); the per-beam
  median of a hold's scans is the noise-free trace within noise;
- ``/camera/image_raw`` (``Image``, mono8) or ``.../compressed`` (png or jpeg
  ``CompressedImage``): the view's rendered photo plus fresh Gaussian pixel noise
  (``frame_noise``, gray levels) while still; while moving a cross-fade of the two
  views' photos shifted sideways, so every moving frame differs from the still ones;
- ``/camera/camera_info`` (``sensor_msgs/CameraInfo``, 1 Hz) with the rig's K and its
  distortion as ``distortion_model`` (``plumb_bob``, ``rational_polynomial`` or
  ``equidistant``), or none;
- optionally a second camera ``/camera2/image_raw`` (an ambiguous recording) or no scan
  topic at all (a broken one).

How a hand holds the board can be varied: ``order`` is the sequence of views held (a view
named again is a return to exactly its pose; named twice in a row, the board is taken
``excursion_mm`` sideways between the two holds and brought back: a pause twice at one
pose), and ``drift_mm`` lets the board drift while "held": during each hold of
``drift_holds`` (indices into the holds; default every hold) it slides at constant speed
by ``drift_mm`` in all along ``(n + e_u) / sqrt 2`` (its normal and its width), centred
on the view's pose (the pose of the hold's middle); the frames drift by the pixel shift
of the board's centre (a sub-pixel translation of the view's photo, the change of scale
neglected).

Returns the timeline: per view its hold window (s from the bag's first message).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bag import T0_NS, _header, _image_msg, _open_writer
from .oneboard import OneBoardRig, render_photo
from .scene import Cylinder, Rect, trace

_LOG_DELAY_S = 0.003  # a message is logged this long after its stamp


@dataclass(frozen=True)
class Hold:
    """The board of view ``index`` still from ``t_start_s`` to ``t_end_s`` (bag seconds);
    ``drift_mm``: how far it slid during the hold (0: still)."""

    index: int
    t_start_s: float
    t_end_s: float
    drift_mm: float = 0.0


def _rect_between(a: Rect, b: Rect, u: float) -> Rect:
    """The board at fraction ``u`` of the way from pose ``a`` to ``b`` (origin and axes
    interpolated linearly, the axes re-orthonormalised)."""
    o = (1 - u) * a.origin + u * b.origin
    e_u = (1 - u) * a.e_u + u * b.e_u
    e_u /= np.linalg.norm(e_u)
    e_v = (1 - u) * a.e_v + u * b.e_v
    e_v -= (e_v @ e_u) * e_u
    e_v /= np.linalg.norm(e_v)
    return Rect(o, e_u, e_v, a.width, a.height, pattern=a.pattern)


def _shifted(rect: Rect, d: np.ndarray) -> Rect:
    return Rect(rect.origin + d, rect.e_u, rect.e_v, rect.width, rect.height, pattern=rect.pattern)


def true_ranges_mm(rig: OneBoardRig, rect: Rect) -> np.ndarray:
    """The noise-free ranges (mm, NaN = no return) of the rig's LiDAR with the board at
    ``rect`` (the board, its stand and the static scene traced, as ``simulate_oneboard``)."""
    angles = rig.views[0].angle_deg
    u_l = np.column_stack([np.cos(np.radians(angles)), np.sin(np.radians(angles)),
                           np.zeros(len(angles))])
    stand = Cylinder(rect.point(rect.width / 2, rect.height), rect.e_v, 20.0, 0.0, 2000.0)
    t, _ = trace([rect, stand, *rig.surfaces], u_l @ rig.R.T, rig.T[None])
    return np.where(np.isfinite(t) & (t <= 30000), t, np.nan)


def write_oneboard_bag(rig: OneBoardRig, bag: str | Path, *, storage: str = "rosbag1",
                       images: str = "raw", seed: int = 0, hold_s: float = 1.0,
                       move_s: float = 0.6, scan_hz: float = 40.0, camera_hz: float = 15.0,
                       frame_noise: float = 1.5, profile: str = "cosine",
                       distortion_model: str | None = "plumb_bob",
                       second_camera: bool = False, with_scans: bool = True,
                       order: list[int] | None = None, excursion_mm: float = 150.0,
                       drift_mm: float = 0.0,
                       drift_holds: list[int] | None = None) -> list[Hold]:
    """Record the rig's views as a bag at ``bag`` (see the module docstring); returns the holds.

    ``storage``: ``"rosbag1"`` (a ``.bag`` file), ``"sqlite3"`` or ``"mcap"`` (ROS 2 folder).
    ``images``: ``"raw"`` (Image), ``"png"`` or ``"jpeg"`` (CompressedImage on
    ``/camera/image_raw/compressed``). Deterministic for a given ``seed``.
    """
    if storage not in ("rosbag1", "sqlite3", "mcap"):
        raise ValueError(f"storage must be rosbag1, sqlite3 or mcap, got {storage!r}")
    if profile not in ("cosine", "linear"):
        raise ValueError(f"profile must be cosine or linear, got {profile!r}")
    from rosbags.typesys import Stores, get_typestore

    ros1 = storage == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    rng = np.random.default_rng(seed)
    views = rig.views
    seq = list(range(len(views))) if order is None else [int(k) for k in order]
    if not seq or min(seq) < 0 or max(seq) >= len(views):
        raise ValueError(f"order must name views 0..{len(views) - 1}, got {order!r}")
    photos = [render_photo(rig, v, seed * 1000 + k) for k, v in enumerate(views)]
    # poses in time: away -> the held views (an excursion between two holds of one view) -> away
    away_in = _shifted(views[seq[0]].rect, np.array([600.0, 0, 0]))
    away_out = _shifted(views[seq[-1]].rect, np.array([-600.0, 0, 0]))
    rects, pics, held = [away_in], [np.roll(photos[seq[0]], 200, axis=1)], [None]
    for i, k in enumerate(seq):
        if i and k == seq[i - 1]:
            rects.append(_shifted(views[k].rect, excursion_mm * views[k].rect.e_u))
            pics.append(np.roll(photos[k], 60, axis=1))
            held.append(None)
        rects.append(views[k].rect)
        pics.append(photos[k])
        held.append(k)
    rects.append(away_out)
    pics.append(np.roll(photos[seq[-1]], -200, axis=1))
    held.append(None)
    drifting = set(range(len(seq)) if drift_holds is None else drift_holds) if drift_mm else set()
    segs: list[tuple[str, float, float, int, float]] = []  # kind, t0, t1, pose (move: from), drift
    holds: list[Hold] = []
    t = 0.0
    for k in range(len(rects) - 1):
        excursion = held[k] is None and held[k + 1] is not None and k > 0
        m = move_s / 2 if held[k + 1] is None and k + 1 < len(rects) - 1 or excursion else move_s
        segs.append(("move", t, t + m, k, 0.0))
        t += m
        if held[k + 1] is not None and hold_s > 0:
            d = drift_mm if len(holds) in drifting else 0.0
            segs.append(("hold", t, t + hold_s, k + 1, d))
            holds.append(Hold(held[k + 1], t, t + hold_s, d))
            t += hold_s
    t_end = t

    def drift_vec(k: int) -> np.ndarray:
        r = rects[k]
        d = np.cross(r.e_u, r.e_v) + r.e_u
        return d / np.linalg.norm(d)

    # a drifting hold starts at -drift/2 and ends at +drift/2: the moves join those ends
    off_start = {k: -0.5 * d * drift_vec(k) for kind, _, _, k, d in segs if kind == "hold" and d}
    off_end = {k: -v for k, v in off_start.items()}
    zero = np.zeros(3)

    def state(tm: float) -> tuple[int, int, float, np.ndarray]:
        """(pose a, pose b, u, offset): the board at fraction u from pose a to pose b, moved
        by ``offset`` (mm, camera frame; a drifting hold)."""
        for kind, a, b, k, d in segs:
            if tm <= b:
                if kind == "hold":
                    return k, k, 0.0, d * ((tm - a) / (b - a) - 0.5) * drift_vec(k)
                u = min(max((tm - a) / (b - a), 0.0), 1.0)
                return (k, k + 1, (0.5 * (1 - math.cos(math.pi * u)) if profile == "cosine" else u),
                        zero)
        return len(rects) - 1, len(rects) - 1, 0.0, zero

    def pixel_shift(k: int, off: np.ndarray) -> np.ndarray:
        """The image shift (px) of the board centre of pose ``k`` moved by ``off``."""
        r = rects[k]
        c = r.point(r.width / 2, r.height / 2)
        p0, p1 = rig.camera.K @ c, rig.camera.K @ (c + off)
        return p1[:2] / p1[2] - p0[:2] / p0[2]

    angles = views[0].angle_deg
    n_beams = angles.size
    span = 0.5 / scan_hz  # beam times cover half the scan period
    LaserScan = ts.types["sensor_msgs/msg/LaserScan"]
    cache: dict[int, np.ndarray] = {}

    def scan_msg(t0: float):
        a, b, u, off = state(t0 + span / 2)
        if a == b and off.any():
            r = true_ranges_mm(rig, _shifted(rects[a], off))
        elif a == b:
            if a not in cache:
                cache[a] = true_ranges_mm(rig, rects[a])
            r = cache[a]
        else:
            r = true_ranges_mm(rig, _rect_between(_shifted(rects[a], off_end.get(a, zero)),
                                                  _shifted(rects[b], off_start.get(b, zero)), u))
        r = np.rint(r + rng.normal(0, rig.range_noise_mm, n_beams))
        m = r / 1000.0
        bad = rng.random(n_beams) < 0.02
        m = np.where(bad, np.array([0.0, np.inf, np.nan])[rng.integers(0, 3, n_beams)], m)
        m = np.where(np.isfinite(r) | bad, m, np.inf).astype(np.float32)
        return LaserScan(header=_header(ts, t0, ros1, "laser"),
                         angle_min=math.radians(angles[0]), angle_max=math.radians(angles[-1]),
                         angle_increment=math.radians(angles[1] - angles[0]),
                         time_increment=span / max(n_beams - 1, 1), scan_time=1.0 / scan_hz,
                         range_min=0.05, range_max=30.0, ranges=m,
                         intensities=np.zeros(0, dtype=np.float32))

    def frame(tm: float) -> np.ndarray:
        a, b, u, off = state(tm)
        if a == b:
            base = pics[a].astype(np.float64)
            shift = pixel_shift(a, off)
        else:
            mix = (1 - u) * pics[a].astype(np.float64) + u * pics[b].astype(np.float64)
            base = np.roll(mix, round(40 * math.sin(math.pi * u)), axis=1)
            shift = ((1 - u) * pixel_shift(a, off_end.get(a, zero))
                     + u * pixel_shift(b, off_start.get(b, zero)))
        if shift.any():
            import cv2

            base = cv2.warpAffine(base, np.array([[1.0, 0, shift[0]], [0, 1.0, shift[1]]]),
                                  (base.shape[1], base.shape[0]), flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_REPLICATE)
        return np.clip(np.rint(base + rng.normal(0, frame_noise, base.shape)), 0, 255).astype(np.uint8)

    def info_msg(tm: float):
        cam = rig.camera
        d = {"plumb_bob": list(cam.dist[:5]), "rational_polynomial": [*cam.dist[:5], 0, 0, 0],
             "equidistant": [0.01, -0.002, 0.0, 0.0]}[distortion_model]
        P = np.hstack([cam.K, np.zeros((3, 1))])
        fields = {"header": _header(ts, tm, ros1, "camera"), "height": cam.image_size[1],
                  "width": cam.image_size[0], "distortion_model": distortion_model,
                  "binning_x": 0, "binning_y": 0,
                  "roi": ts.types["sensor_msgs/msg/RegionOfInterest"](
                      x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)}
        arrays = {"d": np.array(d, float), "k": cam.K.reshape(-1), "r": np.eye(3).reshape(-1),
                  "p": P.reshape(-1)}
        fields.update({(k.upper() if ros1 else k): v for k, v in arrays.items()})
        return ts.types["sensor_msgs/msg/CameraInfo"](**fields)

    events: list[tuple[float, int, str, float]] = []  # log time, order, kind, stamp
    k = 0

    def add(kind: str, start: float, rate: float, delay: float) -> None:
        nonlocal k
        tm = start
        while tm + delay <= t_end:
            events.append((tm + delay, k, kind, tm))
            k += 1
            tm += 1.0 / rate

    if with_scans:
        add("scan", 0.011, scan_hz, span + _LOG_DELAY_S)
    add("image", 0.023, camera_hz, _LOG_DELAY_S)
    if second_camera:
        add("image2", 0.041, camera_hz, _LOG_DELAY_S)
    if distortion_model is not None:
        add("info", 0.005, 1.0, _LOG_DELAY_S)
    events.sort()

    suffix = "" if images == "raw" else "/compressed"
    img_type = "sensor_msgs/msg/Image" if images == "raw" else "sensor_msgs/msg/CompressedImage"
    specs = {"image": ("/camera/image_raw" + suffix, img_type)}
    if with_scans:
        specs["scan"] = ("/scan", "sensor_msgs/msg/LaserScan")
    if second_camera:
        specs["image2"] = ("/camera2/image_raw" + suffix, img_type)
    if distortion_model is not None:
        specs["info"] = ("/camera/camera_info", "sensor_msgs/msg/CameraInfo")
    writer, conns = _open_writer(Path(bag), storage, ts, specs)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    try:
        for log_s, _, kind, tm in events:
            if kind == "scan":
                msg = scan_msg(tm)
            elif kind == "info":
                msg = info_msg(tm)
            else:
                msg = _image_msg(ts, _header(ts, tm, ros1, "camera"), frame(tm), images)
            writer.write(conns[kind], T0_NS + round(log_s * 1e9), serialize(msg, specs[kind][1]))
    finally:
        writer.close()
    return holds
