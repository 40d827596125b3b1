"""``write_bag``: record a dataset folder as a ROS bag, the way a lab would record its rig.

The turntable stops at each position of ``positions.csv`` (``dwell_s``), then turns to
the next one (``move_s``, a cosine speed profile); after the calibration it sweeps every
``measure/*.csv.gz`` at constant speed. All streams run free at their own rates over the
whole recording, so scans and stripe frames are also taken DURING the moves:

- ``/turntable/joint_states`` (``sensor_msgs/JointState``, radians; optionally a second
  joint and an encoder quantum) or ``/turntable/angle`` (``std_msgs/Float64``);
- ``/scan`` (``sensor_msgs/LaserScan``, metres; ``header.stamp`` = first beam). While the
  turntable holds a position (within ``hold_band_deg``) a scan is the position's scan with
  a few returns invalidated per scan (0, inf, NaN, beyond ``range_max``, below
  ``range_min``; the per-beam clipped mean of the valid returns is the original scan); while it
  moves, a wrong scan (ranges 3 % long and shifted by 7 beams) that must never be used;
- ``/camera/stripes/image_raw`` (mono8 or bgr8 ``Image``) or ``.../compressed`` (png or
  jpeg ``CompressedImage``), running during the calibration only: the position's stripe
  image while still, a shifted and blurred frame while moving;
- ``/camera/board/image_raw`` (or compressed): the lit board image, at the first stop.
- or, with ``single_camera_topic=True``, one ``/camera/image_raw`` (or compressed) for
  both: the lights are on for the first ``dwell_s`` of the first stop (lit board frames),
  then off (stripe frames), as a lab with one camera records.

``write_bag`` also writes the RIG.json that ``lidarcal import`` needs and returns it.
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..io.dataset import load_dataset, read_scan, read_sweep

T0_NS = 1_700_000_000 * 1_000_000_000  # the recording's wall-clock start


def bag_start_s(bag: Path) -> float:
    """A simulated bag's first message, s after the recording's zero (``T0_NS``): the offset
    between the bag's clock and the simulator's truth times."""
    from ..io.bag_read import open_bag

    r = open_bag(bag)
    try:
        return (r.start_time - T0_NS) * 1e-9
    finally:
        r.close()


@dataclass(frozen=True)
class _Stop:
    psi: float
    t_a: float  # arrival
    t_d: float  # departure
    index: int  # position index, or -1 for a stop that is not a calibration position


def _cosine(a: float, b: float, t0: float, t1: float, t: float) -> float:
    u = min(max((t - t0) / (t1 - t0), 0.0), 1.0)
    return a + (b - a) * 0.5 * (1.0 - math.cos(math.pi * u))


class _Motion:
    """The true turntable angle psi(t) (deg): stops, cosine moves and linear sweeps."""

    def __init__(self):
        self.segs: list[tuple[str, float, float, float, float]] = []  # kind, t0, t1, a, b
        self._cache: list[float] = []

    def add(self, kind: str, t0: float, t1: float, a: float, b: float) -> None:
        self.segs.append((kind, t0, t1, a, b))

    def __call__(self, t: float) -> float:
        j = bisect.bisect_left(self._ends, t)  # segment ends are increasing
        if j >= len(self.segs):
            return self.segs[-1][4]
        kind, t0, t1, a, b = self.segs[j]
        if t < t0:
            return a
        if kind == "move":
            return _cosine(a, b, t0, t1, t)
        if kind == "sweep":
            return a + (b - a) * (t - t0) / (t1 - t0)
        return a

    @property
    def _ends(self) -> list[float]:
        if len(self._cache) != len(self.segs):
            self._cache = [s[2] for s in self.segs]
        return self._cache

    @property
    def end(self) -> float:
        return self.segs[-1][2]


def _header(ts, t: float, ros1: bool, frame: str):
    Time = ts.types["builtin_interfaces/msg/Time"]
    Header = ts.types["std_msgs/msg/Header"]
    ns = T0_NS + round(t * 1e9)
    stamp = Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return Header(seq=0, stamp=stamp, frame_id=frame) if ros1 else Header(stamp=stamp, frame_id=frame)


def _image_msg(ts, hdr, img: np.ndarray, images: str):
    if images == "raw":
        # the folder's PNG as it is: 16-bit gray as mono16 (little-endian bytes), 16-bit colour
        # as its top 8 bits, BGRA as bgra8 (a 16-bit or 4-channel PNG crashed the serializer)
        ch = 1 if img.ndim == 2 else img.shape[2]
        if img.dtype == np.uint16 and ch > 1:
            img = (img >> 8).astype(np.uint8)
        wide = img.dtype == np.uint16
        enc = {1: "mono16" if wide else "mono8", 3: "bgr8", 4: "bgra8"}[ch]
        h, w = img.shape[:2]
        data = np.ascontiguousarray(img.astype("<u2") if wide else img).view(np.uint8).reshape(-1)
        return ts.types["sensor_msgs/msg/Image"](
            header=hdr, height=h, width=w, encoding=enc, is_bigendian=0,
            step=w * ch * (2 if wide else 1), data=data)
    ext = ".png" if images == "png" else ".jpg"
    ok, buf = cv2.imencode(ext, img, [cv2.IMWRITE_PNG_COMPRESSION, 1] if images == "png"
                           else [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise OSError(f"cannot encode a frame as {images}")
    fmt = ("mono8" if img.ndim == 2 else "bgr8") + ("; png compressed " if images == "png"
                                                   else "; jpeg compressed ") + "bgr8"
    return ts.types["sensor_msgs/msg/CompressedImage"](header=hdr, format=fmt,
                                                       data=buf.reshape(-1).astype(np.uint8))


def write_bag(dataset: str | Path, bag: str | Path, *, storage: str = "rosbag1",
              images: str = "raw", seed: int = 0, dwell_s: float = 1.0, move_s: float = 0.4,
              angle_hz: float = 50.0, scan_hz: float = 40.0, camera_hz: float = 2.0,
              angle_msg: str = "joint", extra_joint: bool = False,
              encoder_step_deg: float | None = None, hold_band_deg: float = 0.005,
              sweeps: bool = True, scan_clock_offset_s: float = 0.0,
              single_camera_topic: bool = False, lit_s: float | None = None,
              stepping_joint: bool = False,
              rig_json: str | Path | None = None) -> dict:
    """Record the dataset folder ``dataset`` as a bag at ``bag``; returns the RIG.json dict.

    ``storage``: ``"rosbag1"`` (a ``.bag`` file), ``"sqlite3"`` or ``"mcap"`` (a ROS 2 bag
    folder). ``images``: ``"raw"`` (Image), ``"png"`` or ``"jpeg"`` (CompressedImage on
    ``<topic>/compressed``). RIG.json (camera, boards, z-axis hint, LiDAR limits and the
    sweep windows in seconds from the bag's first message) is written to ``rig_json``
    when given. ``angle_msg``: ``"joint"`` (JointState, radians), ``"float64"`` (radians)
    or ``"float64_deg"`` (degrees). ``scan_clock_offset_s`` stamps the scans on another clock (a LiDAR's own
    time). ``single_camera_topic``: board and stripe frames on one ``/camera/image_raw``
    (lights on for the first ``lit_s`` of the first stop, default ``dwell_s``; the first
    stop lasts ``2 dwell_s``, so ``lit_s = 2 dwell_s`` leaves it without a dark frame).
    ``stepping_joint`` (with
    ``extra_joint``): the second joint steps too (half the turntable's angle) instead of
    holding still. Deterministic for a given ``seed``.
    """
    if storage not in ("rosbag1", "sqlite3", "mcap"):
        raise ValueError(f"storage must be rosbag1, sqlite3 or mcap, got {storage!r}")
    if angle_msg not in ("joint", "float64", "float64_deg"):
        raise ValueError(f"angle_msg must be joint, float64 or float64_deg, got {angle_msg!r}")
    if images not in ("raw", "png", "jpeg"):
        raise ValueError(f"images must be raw, png or jpeg, got {images!r}")
    from rosbags.typesys import Stores, get_typestore

    ds = load_dataset(dataset)
    rng = np.random.default_rng(seed)
    ros1 = storage == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.LATEST)
    lid = ds.lidar
    angles_deg = lid.angles_deg()
    n_beams = angles_deg.size

    # --- the motion: calibration stops, then one sweep per measurement
    motion, stops = _Motion(), []
    t = 0.0
    psi_prev = ds.positions[0].psi_deg
    for p in ds.positions:
        if p.psi_deg != psi_prev:
            motion.add("move", t, t + move_s, psi_prev, p.psi_deg)
            t += move_s
        dwell = dwell_s * (2.0 if not stops else 1.0)  # the first stop also shows the lit board
        motion.add("stop", t, t + dwell, p.psi_deg, p.psi_deg)
        stops.append(_Stop(p.psi_deg, t, t + dwell, p.index))
        t += dwell
        psi_prev = p.psi_deg
    t_cal_end = t
    windows, sweep_data = [], []
    for m in (ds.measurements if sweeps else []):
        df = read_sweep(m.sweep, None)
        upsi = np.unique(df["psi_deg"].to_numpy())
        steps = np.diff(upsi)
        if upsi.size < 2 or np.ptp(steps) > 1e-6:
            raise ValueError(f"{m.sweep}: write_bag needs evenly spaced sweep angles")
        v = float(steps[0]) * scan_hz  # one scan per sweep angle
        lead = 0.25  # s of ramp before the first and after the last scan
        a0, a1 = upsi[0] - v * lead, upsi[-1] + v * lead
        move = max(0.5, abs(a0 - psi_prev) / 20.0)
        motion.add("move", t, t + move, psi_prev, a0)
        t += move
        motion.add("stop", t, t + 0.5, a0, a0)
        stops.append(_Stop(a0, t, t + 0.5, -1))
        t += 0.5
        t_first = t + lead
        dur = (upsi.size - 1) / scan_hz + 2 * lead
        motion.add("sweep", t, t + dur, a0, a1)
        grid = {round(float(x), 6): df[df["psi_deg"] == x]["range_mm"].to_numpy() for x in upsi}
        sweep_data.append((t_first, upsi, grid))
        windows.append({"name": m.name, "start_s": round(t_first - 0.5 / scan_hz, 6),
                        "end_s": round(t_first + (upsi.size - 0.5) / scan_hz, 6),
                        "object": m.object, "reference_diameter_mm": m.reference_diameter_mm})
        t += dur
        psi_prev = a1
    motion.add("stop", t, t + 0.5, psi_prev, psi_prev)

    cal_stops = [s for s in stops if s.index >= 0]
    arrivals = [s.t_a for s in cal_stops]

    def held(t0: float, t1: float) -> _Stop | None:
        """The calibration stop whose angle is held (within the band) over [t0, t1]."""
        j = bisect.bisect_right(arrivals, t0 + 0.2)
        for s in cal_stops[max(j - 2, 0): j + 1]:
            if (s.t_a - 0.2 <= t0 and t1 <= s.t_d + 0.2
                    and max(abs(motion(x) - s.psi) for x in np.linspace(t0, t1, 5)) <= hold_band_deg):
                return s
        return None

    # --- the events, in log-time order: (log_s, order, kind, stamp_s, payload)
    events: list[tuple[float, int, str, float, object]] = []
    k = 0
    tt = 0.0
    while tt <= motion.end:
        events.append((tt + 0.001, k, "angle", tt, None))
        k += 1
        tt += 1.0 / angle_hz
    span = 0.6 / scan_hz  # beam times cover 60 % of the scan period (a 216 deg window of 360)
    tt = 0.013
    sweep_times = {}
    for t_first, upsi, grid in sweep_data:
        for i, x in enumerate(upsi):
            sweep_times[round(t_first + i / scan_hz - span / 2, 9)] = grid[round(float(x), 6)]
    while tt + span <= motion.end:
        events.append((tt + span + 0.003, k, "scan", tt, None))
        k += 1
        tt += 1.0 / scan_hz
    for t_start, ranges in sweep_times.items():  # sweep scans: stamped so their mid-time is exact
        events.append((t_start + span + 0.003, k, "sweep_scan", t_start, ranges))
        k += 1
    # free-running scans that overlap a sweep scan are dropped (one LiDAR, one scan at a time)
    sweep_starts = np.array(sorted(sweep_times))
    if sweep_starts.size:
        def clash(ts_: float) -> bool:
            j = np.searchsorted(sweep_starts, ts_)
            near = sweep_starts[max(j - 1, 0): j + 1]
            return bool(np.any(np.abs(near - ts_) < 1.0 / scan_hz))
        events = [e for e in events if e[2] != "scan" or not clash(e[3])]
    tt = 0.031
    while tt < t_cal_end:
        events.append((tt + 0.030, k, "stripe", tt, None))
        k += 1
        tt += 1.0 / camera_hz
    s0 = stops[0]
    for tb in (() if single_camera_topic else (s0.t_a + 0.25, s0.t_a + 0.75)):
        events.append((tb + 0.030, k, "board", tb, None))
        k += 1
    events.sort()

    # --- write
    scans = {p.index: read_scan(p.scan, None)[1] for p in ds.positions}  # NaN = no return
    stripe_cache: dict[int, np.ndarray] = {}
    pos_by_index = {p.index: p for p in ds.positions}

    def stripe(idx: int) -> np.ndarray:
        if idx not in stripe_cache:
            stripe_cache.clear()
            stripe_cache[idx] = cv2.imread(str(pos_by_index[idx].stripe_image), cv2.IMREAD_UNCHANGED)
        return stripe_cache[idx]

    board = cv2.imread(str(ds.board_image), cv2.IMREAD_UNCHANGED)
    rmin, rmax = lid.range_min_mm / 1000.0, lid.range_max_mm / 1000.0
    LaserScan = ts.types["sensor_msgs/msg/LaserScan"]

    def scan_msg(t0: float, ranges_mm: np.ndarray, corrupt: bool):
        r = np.where(np.isfinite(ranges_mm), ranges_mm / 1000.0, np.inf).astype(np.float32)
        if corrupt:  # invalid returns the combination of the valid ones must skip
            bad = rng.random(n_beams) < 0.05
            kind = rng.integers(0, 5, n_beams)
            vals = np.array([0.0, np.inf, np.nan, rmax * 1.5, rmin * 0.5], dtype=np.float32)
            r = np.where(bad, vals[kind], r).astype(np.float32)
        return LaserScan(header=_header(ts, t0 + scan_clock_offset_s, ros1, "laser"),
                         angle_min=math.radians(lid.angle_min_deg),
                         angle_max=math.radians(lid.angle_max_deg),
                         angle_increment=math.radians(lid.angle_step_deg),
                         time_increment=span / max(n_beams - 1, 1), scan_time=1.0 / scan_hz,
                         range_min=rmin, range_max=rmax, ranges=r,
                         intensities=np.zeros(0, dtype=np.float32))

    def last_stop_before(t0: float) -> _Stop:
        j = bisect.bisect_right(arrivals, t0)
        return cal_stops[max(j - 1, 0)]

    cams = ("/camera/image_raw",) * 2 if single_camera_topic else (
        "/camera/stripes/image_raw", "/camera/board/image_raw")
    topic_img, topic_board = (c + ("" if images == "raw" else "/compressed") for c in cams)
    img_type = "sensor_msgs/msg/Image" if images == "raw" else "sensor_msgs/msg/CompressedImage"
    angle_topic = "/turntable/joint_states" if angle_msg == "joint" else "/turntable/angle"
    angle_type = "sensor_msgs/msg/JointState" if angle_msg == "joint" else "std_msgs/msg/Float64"
    specs = {"angle": (angle_topic, angle_type), "scan": ("/scan", "sensor_msgs/msg/LaserScan"),
             "stripe": (topic_img, img_type), "board": (topic_board, img_type)}
    if single_camera_topic:
        del specs["board"]
    writer, conns = _open_writer(Path(bag), storage, ts, specs)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    try:
        for log_s, _, kind, t_msg, payload in events:
            if kind == "angle":
                psi = motion(t_msg)
                if encoder_step_deg:
                    psi = round(psi / encoder_step_deg) * encoder_step_deg
                rad = math.radians(psi)
                if angle_msg == "joint":
                    names = ["pan_dummy", "turntable"] if extra_joint else ["turntable"]
                    pos = ([0.5 * rad if stepping_joint else 0.1, rad] if extra_joint
                           else [rad])
                    msg = ts.types["sensor_msgs/msg/JointState"](
                        header=_header(ts, t_msg, ros1, "base"), name=names,
                        position=np.array(pos), velocity=np.zeros(0), effort=np.zeros(0))
                else:
                    msg = ts.types["std_msgs/msg/Float64"](
                        data=psi if angle_msg == "float64_deg" else rad)
                role = "angle"
            elif kind in ("scan", "sweep_scan"):
                if kind == "sweep_scan":
                    msg = scan_msg(t_msg, payload, corrupt=False)
                else:
                    s = held(t_msg, t_msg + span)
                    if s is not None:
                        msg = scan_msg(t_msg, scans[s.index], corrupt=True)
                    else:  # moving: a wrong scan
                        ref = scans[last_stop_before(t_msg).index]
                        msg = scan_msg(t_msg, np.roll(ref * 1.03, 7), corrupt=False)
                role = "scan"
            else:
                if kind == "board":
                    img = board
                else:
                    s = held(t_msg, t_msg)
                    if (single_camera_topic and s is s0
                            and t_msg < s0.t_a + (dwell_s if lit_s is None else lit_s)):
                        img = board  # the lights are on for the first dwell of the first stop
                    elif s is not None:
                        img = stripe(s.index)
                    else:  # moving: shifted, blurred, brighter
                        base = stripe(last_stop_before(t_msg).index)
                        shifted = np.roll(base, 15, axis=1)
                        img = cv2.add(cv2.GaussianBlur(shifted, (0, 0), 3.0), shifted // 2)
                msg = _image_msg(ts, _header(ts, t_msg, ros1, "camera"), img, images)
                role = kind
            writer.write(conns[role], T0_NS + round(log_s * 1e9), serialize(msg, specs[role][1]))
    except BaseException:
        writer.close()
        raise
    writer.close()

    rig = {"v_board": ds.raw["v_board"],
           "lidar": {**{k: ds.raw["lidar"][k] for k in ("angle_min_deg", "angle_max_deg",
                                                          "angle_step_deg", "range_min_mm",
                                                          "range_max_mm") if k in ds.raw["lidar"]},
                     "z_axis_hint": ds.raw["lidar"].get("z_axis_hint", [0, -1, 0])},
           "measurements": windows}
    if ds.raw.get("camera") is not None:
        rig["camera"] = ds.raw["camera"]
    if ds.raw.get("intrinsics_board") is not None:
        rig["intrinsics_board"] = ds.raw["intrinsics_board"]
        if ds.raw.get("camera") is None:
            rig["intrinsics"] = str((ds.root / "intrinsics").resolve())
    if rig_json is not None:
        Path(rig_json).write_text(json.dumps(rig, indent=2) + "\n")
    return rig


def _open_writer(path: Path, storage: str, ts, specs: dict):
    """An open rosbags writer with one connection per role."""
    if storage == "rosbag1":
        from rosbags.rosbag1 import Writer

        w = Writer(path)
        w.open()
        conns = {r: w.add_connection(t, m, typestore=ts) for r, (t, m) in specs.items()}
        return w, conns
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    w = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
    w.open()
    conns = {r: w.add_connection(t, m, typestore=ts) for r, (t, m) in specs.items()}
    return w, conns


