"""``lidarcal import``: a ROS 1 ``.bag`` or ROS 2 bag (sqlite3, mcap) -> a dataset folder.

Read through the pure-Python ``rosbags`` library (no ROS install), streamed: the angle
topic is read first (one small pass), then the scans and frames, one message at a time;
only the frames of the position being combined are held in memory.

- ``sensor_msgs/LaserScan``: ranges in metres; a return is invalid when it is 0, inf,
  NaN or outside ``range_min..range_max`` of its message. ``header.stamp`` is the time
  of the first beam, beam ``k`` is at ``stamp + k * time_increment`` (ROS convention).
- ``sensor_msgs/Image`` (mono8, mono16, bgr8, rgb8, bgra8, rgba8) and
  ``sensor_msgs/CompressedImage`` (png, jpeg; image_transport's ``<topic>/compressed``).
  mono16 becomes 8 bits by dividing by 256 (cv_bridge's scaling).
- turntable angle: ``sensor_msgs/JointState`` (radians; ``joint`` picks the name) or
  ``std_msgs/Float64`` (radians, or degrees with ``angle_unit="deg"``).

Clock: a message's time is its ``header.stamp``; a message without a header (Float64),
or a topic whose stamps are more than 1 s from the bag's receive (log) times (another
clock), uses its log time instead (a scan then ends at its log time). Positions are the stationary periods of the angle
(:mod:`lidarcal.stationary`); a scan is used when all its beams fall inside a period,
a frame when its stamp does. Per position: the per-beam clipped mean of the valid returns
(:func:`combine_scans`) and the per-pixel median of the stripe frames; ``psi_deg`` is the median angle of
the period. Sweeps (RIG.json ``measurements`` with ``start_s``/``end_s``, seconds
from the bag's first message): every scan in the window, with psi interpolated
linearly in the angle readings at the scan's mid-time ``stamp + (n - 1) / 2 *
time_increment``. See ``docs/ros-bags.md``.
"""

from __future__ import annotations

import gzip
import io
import math
import os
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from ..geometry import MAD_TO_SIGMA
from ..stationary import (
    default_min_duration_s,
    default_tolerance_deg,
    encoder_resolution_deg,
    find_stationary,
    median_period_s,
)
from .bag_frames import COMPRESSED, LitSplit, frame_brightness, image_from_msg, split_lit_dark
from .dataset import (
    DATASET_FORMAT,
    DatasetError,
    current_umask,
    decode_image,
    write_json_atomic,
)
from .rig import RigFile, read_rig

LASERSCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
JOINTSTATE = "sensor_msgs/msg/JointState"
FLOAT64 = "std_msgs/msg/Float64"
IMAGE_TYPES = (IMAGE, COMPRESSED)
ANGLE_TYPES = (JOINTSTATE, FLOAT64)
_SLACK_S = 5.0  # a position is combined once the bag's log time is this far past its end


# ----------------------------------------------------------------------------- messages


@dataclass(frozen=True)
class Scan:
    """One LaserScan: ascending beam angles, ranges in mm (NaN = invalid), beam times (s)."""

    t0: float  # first beam
    t1: float  # last beam
    angle_min_deg: float
    angle_step_deg: float
    angle_max_msg_deg: float
    range_min_mm: float
    range_max_mm: float
    range_mm: np.ndarray  # (n,), ascending angle

    @property
    def t_mid(self) -> float:
        return 0.5 * (self.t0 + self.t1)


_FOREIGN_CLOCK_S = 1.0  # stamps further than this from the log times are on another clock


def _header_s(msg) -> float:
    hdr = getattr(msg, "header", None)
    return 0.0 if hdr is None else int(hdr.stamp.sec) + int(hdr.stamp.nanosec) * 1e-9


class Clock:
    """Message times: ``header.stamp`` per topic while it is on the bag's clock, else log time.

    Decided on a topic's first message: no header or a zero stamp -> ``"log"``; a stamp
    more than 1 s from the message's log time (a sensor clock, not the recorder's) ->
    ``"log"`` with a note; otherwise ``"header"``.
    """

    def __init__(self) -> None:
        self.mode: dict[str, str] = {}
        self.notes: list[str] = []

    def time(self, topic: str, msg, log_ns: int) -> float:
        log = log_ns * 1e-9
        st = _header_s(msg)
        mode = self.mode.get(topic)
        if mode is None:
            mode = "header" if st > 0 and abs(st - log) <= _FOREIGN_CLOCK_S else "log"
            if st > 0 and mode == "log":
                self.notes.append(f"{topic}: header stamps are {st - log:+.3g} s from the bag's "
                                  "receive times (another clock); its receive times are used")
            self.mode[topic] = mode
        return st if mode == "header" and st > 0 else log


def scan_from_msg(msg, t0: float) -> Scan:
    """A LaserScan in the contract's units: ascending angles (deg), ranges in mm, invalid = NaN."""
    r = np.asarray(msg.ranges, dtype=np.float64)
    n = r.size
    rmin, rmax = float(msg.range_min), float(msg.range_max)
    bad = ~np.isfinite(r) | (r <= 0) | (r < rmin) | (r > rmax)
    r = np.where(bad, np.nan, r * 1000.0)
    amin, inc = math.degrees(msg.angle_min), math.degrees(msg.angle_increment)
    if inc < 0:  # clockwise scanner: reverse to ascending angles
        r = r[::-1]
        amin, inc = amin + (n - 1) * inc, -inc
    span = abs(float(msg.time_increment)) * max(n - 1, 0)
    return Scan(t0, t0 + span, amin, inc, math.degrees(msg.angle_max), rmin * 1000.0,
                rmax * 1000.0, r)


# ----------------------------------------------------------------------------- topics


def _topics_text(reader) -> str:
    return ", ".join(f"{t} ({i.msgtype.replace('/msg/', '/')})" for t, i in sorted(reader.topics.items()))


def pick_topic(reader, given: str | None, types: tuple[str, ...], role: str, option: str,
               bag: Path, prefer: str | None = None, required: bool = True) -> str | None:
    """The topic for ``role``: ``given`` (or ``given/compressed``) or the only topic of ``types``
    (among several, the one whose name contains ``prefer``)."""
    topics = reader.topics
    if given is not None:
        for name in (given, given.rstrip("/") + "/compressed"):
            if name in topics:
                if topics[name].msgtype not in types:
                    raise DatasetError(bag, f"{option} {name} is {topics[name].msgtype}, expected "
                                            f"{' or '.join(types)}; the bag has: {_topics_text(reader)}")
                return name
        raise DatasetError(bag, f"no topic {given} ({option}); the bag has: {_topics_text(reader)}")
    cands = sorted(t for t, i in topics.items() if i.msgtype in types)
    # a raw and a compressed copy of one stream (image_transport): one stream, the raw one
    cands = [t for t in cands if not (t.endswith("/compressed") and t[:-11] in cands)]
    if prefer is not None and len(cands) > 1:
        named = [t for t in cands if prefer in t.lower()]
        cands = named if named else cands
    if len(cands) == 1:
        return cands[0]
    if not required and not cands:
        return None
    what = "no" if not cands else f"{len(cands)}"
    raise DatasetError(bag, f"{what} {role} topics ({' or '.join(types)}); name it with {option}; "
                            f"the bag has: {_topics_text(reader)}")


def _connections(reader, topic: str | None) -> list:
    return [c for c in reader.connections if c.topic == topic] if topic else []


@dataclass
class AngleStream:
    t_s: np.ndarray  # sorted
    psi_deg: np.ndarray


def read_angles(reader, topic: str, joint: str | None, unit: str, bag: Path,
                clock: Clock) -> AngleStream:
    """All turntable readings of ``topic`` (one pass over that topic only), in degrees."""
    conns = _connections(reader, topic)
    msgtype = conns[0].msgtype
    ts, ps = [], []
    idx: int | None = None
    several: dict[str, tuple[list[float], list[float]]] = {}  # joint -> (t, psi) to choose from
    seen: set[str] = set()
    for conn, log_ns, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        if msgtype == FLOAT64:
            val = float(msg.data)
        else:
            names, pos = list(msg.name), np.asarray(msg.position, dtype=float)
            if joint is None:  # every joint by name (publishers may send different subsets)
                t = clock.time(topic, msg, log_ns)
                for nm, v in zip(names or [str(i) for i in range(len(pos))], pos.tolist()):
                    if math.isfinite(v):
                        several.setdefault(nm, ([], []))[0].append(t)
                        several[nm][1].append(math.degrees(v))
                continue
            if idx is None or idx >= len(names) or names[idx] != joint:
                seen.update(names)
                if joint not in names:  # another publisher's joints
                    continue
                idx = names.index(joint)
            if idx >= len(pos):
                continue
            val = float(pos[idx])
        if not math.isfinite(val):
            continue
        ts.append(clock.time(topic, msg, log_ns))
        ps.append(val if unit == "deg" and msgtype == FLOAT64 else math.degrees(val))
    if several and not ts:
        name = next(iter(several)) if len(several) == 1 else _turntable_joint(several, topic, bag)
        if len(several) > 1:
            clock.notes.append(f"{topic}: joint {name!r} is the turntable (the only joint of "
                               f"{', '.join(several)} that holds and steps); --joint names another")
        ts, ps = several[name]
    if joint is not None and msgtype == JOINTSTATE and not ts:
        raise DatasetError(bag, f"{topic}: no joint {joint!r} (--joint); its joints: "
                                f"{', '.join(sorted(seen)) or '(unnamed)'}")
    if len(ts) < 3:
        raise DatasetError(bag, f"{topic}: {len(ts)} usable angle reading(s); need a turntable "
                                "angle stream (--angle-topic, --joint)")
    t, p = np.asarray(ts), np.asarray(ps)
    order = np.argsort(t, kind="stable")
    return AngleStream(t[order], p[order])


def _turntable_joint(joints: dict[str, tuple[list[float], list[float]]], topic: str,
                     bag: Path) -> str:
    """The joint that moves like a turntable: its readings hold still at three or more
    distinct angles (:func:`lidarcal.stationary.find_stationary` with the default tolerance
    and three reading periods). Exactly one such joint, or an error listing them all."""
    steps = {}
    for name, (t, p) in joints.items():
        t_a, p_a = np.asarray(t), np.asarray(p)
        order = np.argsort(t_a, kind="stable")
        t_a, p_a = t_a[order], p_a[order]
        if t_a.size < 3:
            steps[name] = 0
            continue
        tol = default_tolerance_deg(p_a)
        periods = find_stationary(t_a, p_a, tol, 3.0 * median_period_s(t_a))
        steps[name] = len({round(q.psi_deg / (2.0 * tol)) for q in periods})
    stepping = [n for n, k in steps.items() if k >= 3]
    if len(stepping) == 1:
        return stepping[0]
    seen = ", ".join(f"{n} ({k} still angle{'s' if k != 1 else ''})" for n, k in steps.items())
    raise DatasetError(bag, f"{topic} has {len(joints)} joints ({seen}) and "
                            f"{'none' if not stepping else len(stepping)} of them steps like a "
                            "turntable; name the turntable with --joint")


# ----------------------------------------------------------------------------- import


@dataclass
class ImportedPosition:
    index: int
    psi_deg: float
    t_start_s: float
    t_end_s: float
    n_scans: int
    n_frames: int


@dataclass
class ImportResult:
    out: Path
    positions: list[ImportedPosition]
    tolerance_deg: float
    min_duration_s: float
    topics: dict[str, str | None]
    sweeps: dict[str, int] = field(default_factory=dict)  # name -> scans
    warnings: list[str] = field(default_factory=list)


@dataclass
class _Acc:
    """What one stationary period collected so far."""

    scans: list[np.ndarray] = field(default_factory=list)
    frames: list[np.ndarray] = field(default_factory=list)
    board: list[np.ndarray] = field(default_factory=list)


def _fmt_range(v: float) -> str:
    return f"{v:.1f}" if math.isfinite(v) else "0"


def scan_csv_text(angles_deg: np.ndarray, range_mm: np.ndarray) -> str:
    """``scans/NNNN.csv``: angle_deg (6 decimals), range_mm (0.1 mm; 0 = no return)."""
    return "angle_deg,range_mm\n" + "".join(
        f"{a:.6f},{_fmt_range(r)}\n" for a, r in zip(angles_deg.tolist(), range_mm.tolist()))


#: a still scan's return farther than this many robust sigmas from its beam's median is left
#: out of the beam's mean (:func:`combine_scans`): false rejection ~1e-4 for Gaussian noise
CLIP_SIGMAS = 4.0


def combine_scans(ranges: list[np.ndarray]) -> np.ndarray:
    """Per-beam clipped mean of the valid returns of a position's still scans (NaN where no scan
    has one).

    The mean of the returns within ``CLIP_SIGMAS`` robust sigmas of the beam's median: a
    median-anchored trimmed mean (Huber, *Robust Statistics*, 1981, ch. 3). The median alone
    wastes information: for Gaussian range noise its variance is ``pi / 2`` of the mean's for
    many scans (1.35x for 3 scans, 1.43x for 5, 1.5x for 20), so every line fitted to the
    combined scan (eqs. 7-12) is that much noisier. The clip keeps the median's robustness:
    a spurious return, or a beam flickering between the board and the wall behind it, lies
    far from its beam's median and is left out, so one bad scan of three is rejected as the
    median rejects it. The noise sigma is pooled over the whole stack, from the differences
    of consecutive valid returns of each beam (``1.4826 median |d| / sqrt 2``: unbiased for
    any number of scans, two returns per outlier); ranges quantised much coarser than their
    noise give sigma 0 and the mean of the returns equal to the median, i.e. the median.
    """
    stack = np.vstack(ranges).astype(float)
    stack[~np.isfinite(stack)] = np.nan
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN beams stay NaN
        med = np.nanmedian(stack, axis=0)
        valid = np.isfinite(stack)
        d = np.concatenate([np.diff(stack[valid[:, j], j]) for j in range(stack.shape[1])]
                           ) if len(stack) > 1 else np.zeros(0)
        sigma = MAD_TO_SIGMA * float(np.median(np.abs(d))) / math.sqrt(2.0) if len(d) else 0.0
        keep = valid & (np.abs(stack - med) <= CLIP_SIGMAS * sigma)
        n = keep.sum(axis=0)
        mean = np.where(keep, stack, 0.0).sum(axis=0) / np.maximum(n, 1)
    return np.where(n > 0, mean, med)


def combine_frames(frames: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median of 8-bit frames (an even count: the two middle values' mean, half up).

    Up to 25 frames are sorted per pixel by an odd-even transposition network of
    ``np.minimum``/``np.maximum`` on whole frames (contiguous, ~10x faster than
    ``np.median`` along a stacked axis); more fall back to ``np.median``.
    """
    k = len(frames)
    if k == 1:
        return frames[0]
    if k > 25:
        stack = np.stack(frames).astype(np.float32)
        return np.floor(np.median(stack, axis=0) + 0.5).astype(np.uint8)
    s = list(frames)
    for i in range(k):
        for j in range(i % 2, k - 1, 2):
            s[j], s[j + 1] = np.minimum(s[j], s[j + 1]), np.maximum(s[j], s[j + 1])
    if k % 2:
        return s[k // 2]
    a, b = s[k // 2 - 1].astype(np.uint16), s[k // 2]
    return ((a + b + 1) // 2).astype(np.uint8)


def _write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write image")


class _ScanGeometry:
    """The beam layout of the first scan; every later scan must match it."""

    def __init__(self, s: Scan, topic: str, rig: RigFile):
        self.s, self.topic, self.n = s, topic, s.range_mm.size
        self.angles = s.angle_min_deg + np.arange(self.n) * s.angle_step_deg
        got = {"angle_min_deg": s.angle_min_deg, "angle_max_deg": float(self.angles[-1]),
               "angle_step_deg": s.angle_step_deg, "range_min_mm": s.range_min_mm,
               "range_max_mm": s.range_max_mm}
        tol = {"angle_min_deg": 1e-3, "angle_max_deg": 1e-3, "angle_step_deg": 1e-5,
               "range_min_mm": 1.0, "range_max_mm": 1.0}
        for k, v in rig.lidar_limits.items():
            if abs(v - got[k]) > tol[k]:
                raise DatasetError(rig.path, f"lidar.{k} is {v:g} but the LaserScan messages on "
                                             f"{topic} give {got[k]:.6g}; fix RIG.json or remove "
                                             "the key (the messages' values are used)")
        self.lidar = got

    def check(self, s: Scan, bag: Path) -> None:
        if (s.range_mm.size != self.n or abs(s.angle_min_deg - self.s.angle_min_deg) > 1e-6
                or abs(s.angle_step_deg - self.s.angle_step_deg) > 1e-9):
            raise DatasetError(bag, f"{self.topic}: the beam layout changes within the bag "
                                    f"({self.n} beams from {self.s.angle_min_deg:g} deg, then "
                                    f"{s.range_mm.size} from {s.angle_min_deg:g} deg); record one "
                                    "LiDAR configuration per bag")


def open_bag(path: Path):
    """An open ``rosbags`` AnyReader on a ROS 1 .bag (file) or a ROS 2 bag (folder)."""
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    if not path.exists():
        raise DatasetError(path, "no such bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    try:
        reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as e:
        msg = " ".join(str(e).split()) or type(e).__name__
        raise DatasetError(path, f"cannot be read as a ROS 1 or ROS 2 bag ({msg}); if the "
                                 "recording was cut short, reindex it (rosbag reindex, "
                                 "ros2 bag reindex)") from None
    return reader


def unreadable_bag(bag: Path, e: Exception) -> DatasetError:
    """The one-line error for a bag the reader gave up on (one of :func:`_reader_errors`)."""
    msg = " ".join(str(e).split()) or type(e).__name__
    return DatasetError(bag, f"cannot be read to the end ({msg}); the bag may be truncated "
                             "or corrupt: reindex it (rosbag reindex / ros2 bag reindex)")


def _reader_errors() -> tuple[type[Exception], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError, EOFError)


def _prepare_out(out: Path, overwrite: bool) -> Path:
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise DatasetError(out, "exists and is not empty; choose another --out or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.import-", dir=out.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp's 0700 would survive the rename
    return tmp


def _finish_out(tmp: Path, out: Path) -> None:
    old = None
    if out.exists():
        if out.is_dir() and not any(out.iterdir()):
            out.rmdir()
        else:
            old = out.parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old) if old.is_dir() else old.unlink()


def import_bag(bag: str | os.PathLike, rig: str | os.PathLike, out: str | os.PathLike, *,
               scan_topic: str | None = None, stripe_topic: str | None = None,
               board_topic: str | None = None, angle_topic: str | None = None,
               joint: str | None = None, angle_unit: str = "rad",
               board_image: str | os.PathLike | None = None,
               tolerance_deg: float | None = None, min_duration_s: float | None = None,
               frame_guard_s: float = 0.0, overwrite: bool = False, progress: bool = False) -> ImportResult:
    """Turn a bag into a dataset folder (``lidarcal-dataset/1``), written atomically.

    Positions are the angle stream's stationary periods (:func:`lidarcal.stationary.
    find_stationary`) that hold at least one whole scan and one stripe frame, numbered in
    time order; periods inside a sweep window are not positions. A stripe or board frame
    is used when ``[stamp - frame_guard_s, stamp + frame_guard_s]`` lies inside a period
    (set the guard to the exposure time when the stamp is not its middle).
    """
    bag, out = Path(bag), Path(out)
    rigf = read_rig(rig)
    if angle_unit not in ("rad", "deg"):
        raise ValueError(f"angle_unit must be 'rad' or 'deg', got {angle_unit!r}")
    if board_image is not None and not Path(board_image).is_file():
        raise DatasetError(board_image, "no such board image (--board-image)")
    reader = open_bag(bag)
    try:
        topics = {
            "scan": pick_topic(reader, scan_topic, (LASERSCAN,), "LaserScan", "--scan-topic", bag),
            "angle": pick_topic(reader, angle_topic, ANGLE_TYPES, "turntable angle", "--angle-topic",
                                bag, prefer="turntable"),
            "stripe": pick_topic(reader, stripe_topic, IMAGE_TYPES, "stripe image", "--stripe-topic",
                                 bag, prefer="stripe"),
        }
        if board_image is None:
            topics["board"] = pick_topic(reader, board_topic, IMAGE_TYPES, "board image",
                                         "--board-topic (or give --board-image FILE)", bag,
                                         prefer="board")
        else:
            topics["board"] = None
        return _import(reader, bag, rigf, out, topics, joint, angle_unit, board_image,
                       tolerance_deg, min_duration_s, frame_guard_s, overwrite, progress)
    except _reader_errors() as e:
        raise unreadable_bag(bag, e) from None
    finally:
        reader.close()


def _import(reader, bag, rigf, out, topics, joint, angle_unit, board_image, tolerance_deg,
            min_duration_s, frame_guard_s, overwrite, progress) -> ImportResult:
    from tqdm import tqdm

    clock = Clock()
    angles = read_angles(reader, topics["angle"], joint, angle_unit, bag, clock)
    if np.abs(angles.psi_deg).max() > 360.0:
        clock.notes.append(f"{topics['angle']}: angles reach {np.abs(angles.psi_deg).max():.0f} deg, "
                           "beyond a turn; if a Float64 angle is in degrees, pass --angle-unit deg")
    scan_conns = _connections(reader, topics["scan"])
    scan_count = sum(c.msgcount for c in scan_conns)
    span = max(reader.duration * 1e-9, 1e-9)
    scan_period = span / max(scan_count - 1, 1)  # refined below from the stamps
    tol = default_tolerance_deg(angles.psi_deg) if tolerance_deg is None else float(tolerance_deg)
    min_dur = (default_min_duration_s(median_period_s(angles.t_s), scan_period)
               if min_duration_s is None else float(min_duration_s))
    if not tol > 0 or not min_dur >= 0:
        raise DatasetError(bag, f"--tolerance-deg must be > 0 and --min-duration-s >= 0, "
                                f"got {tol}, {min_dur}")
    periods = find_stationary(angles.t_s, angles.psi_deg, tol, min_dur)
    t_bag0 = reader.start_time * 1e-9
    clock0 = t_bag0  # windows are seconds from the bag's first message
    windows = [(w, clock0 + w.start_s, clock0 + w.end_s) for w in rigf.sweeps]
    periods = [p for p in periods if not any(a <= p.t_end and p.t_start <= b for _, a, b in windows)]
    if not periods:
        raise DatasetError(bag, f"no stationary period on {topics['angle']}: the angle spans "
                                f"{angles.psi_deg.min():.4f}..{angles.psi_deg.max():.4f} deg over "
                                f"{angles.t_s[-1] - angles.t_s[0]:.1f} s ({angles.psi_deg.size} "
                                f"readings); positions must hold within {tol:.3g} deg for "
                                f">= {min_dur:.3g} s (--tolerance-deg, --min-duration-s)")

    lit = None
    if topics["board"] is not None and topics["board"] == topics["stripe"]:
        lit = _classify_frames(reader, bag, topics["stripe"], periods, frame_guard_s, clock, clock0)
    tmp = _prepare_out(out, overwrite)
    try:
        result = _stream(reader, bag, rigf, tmp, topics, angles, periods, windows, tol, min_dur,
                         board_image, progress, tqdm, clock0, frame_guard_s, clock, lit)
        _finish_out(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    result.out = out
    return result


@dataclass
class _LitFrames:
    """One camera topic for board and stripes: the lit/dark split and the board's period."""

    split: LitSplit
    board_period: int  # the stationary period with the most lit frames
    lit_per_period: dict[int, int]
    dark_per_period: dict[int, int]

    def meta(self, periods, clock0: float) -> dict:
        p = periods[self.board_period]
        return {"single_camera_topic": True, "lit_threshold": self.split.threshold,
                "lit_separability": round(self.split.separability, 4),
                "brightness_range": [self.split.lo, self.split.hi],
                "board_period": {"t_start_s": round(p.t_start - clock0, 6),
                                 "t_end_s": round(p.t_end - clock0, 6), "psi_deg": p.psi_deg,
                                 "lit_frames": self.lit_per_period[self.board_period]}}


def _classify_frames(reader, bag: Path, topic: str, periods, guard: float, clock: Clock,
                     clock0: float) -> _LitFrames:
    """One pass over the camera topic: each still frame's median brightness, split into lit
    and dark by Otsu's threshold (:func:`lidarcal.io.bag_frames.split_lit_dark`)."""
    starts = np.array([p.t_start for p in periods])
    meds, ks = [], []
    for conn, log_ns, raw in reader.messages(connections=_connections(reader, topic)):
        msg = reader.deserialize(raw, conn.msgtype)
        t = clock.time(topic, msg, log_ns)
        k = int(np.searchsorted(starts, t - guard, side="right")) - 1
        if k >= 0 and periods[k].contains(t - guard, t + guard):
            meds.append(frame_brightness(image_from_msg(msg, conn.msgtype, f"{bag}: {topic}")))
            ks.append(k)
    split = split_lit_dark(np.asarray(meds))
    if not split.has_lit:
        rng = f"{split.lo:.0f}..{split.hi:.0f}" if meds else "none"
        raise DatasetError(bag, f"{topic} is the board and the stripe topic but no lit frame was "
                                f"found among its {len(meds)} still frames (frame medians {rng} "
                                "of 255, one cluster); give the board as --board-image FILE "
                                "or its own --board-topic")
    lit, dark = {}, {}
    for m, k in zip(meds, ks):
        d = lit if m > split.threshold else dark
        d[k] = d.get(k, 0) + 1
    best = max(lit, key=lambda k: (lit[k], -k))
    return _LitFrames(split, best, lit, dark)


def _stream(reader, bag, rigf, tmp, topics, angles, periods, windows, tol, min_dur, board_image,
            progress, tqdm, clock0, frame_guard_s, clock: Clock,
            lit: _LitFrames | None = None) -> ImportResult:
    starts = np.array([p.t_start for p in periods])

    def period_of(t0: float, t1: float) -> int:
        k = int(np.searchsorted(starts, t0, side="right")) - 1
        return k if k >= 0 and periods[k].contains(t0, t1) else -1

    (tmp / "stripes").mkdir()
    (tmp / "scans").mkdir()
    conns = {role: _connections(reader, t) for role, t in topics.items()
             if t and not (role == "board" and t == topics["stripe"])}  # one camera: once
    role_of = {c.id: (role, c) for role, cs in conns.items() if role != "angle" for c in cs}
    wanted = [c for role, cs in conns.items() if role != "angle" for c in cs]
    acc: dict[int, _Acc] = {}
    done: dict[int, tuple[int, int]] = {}  # period -> (scans, frames) written
    geom: _ScanGeometry | None = None
    board: np.ndarray | None = None
    frame_shape: tuple | None = None
    sweep_rows: dict[str, list[tuple[float, np.ndarray]]] = {w.name: [] for w, _, _ in windows}
    warn: list[str] = clock.notes  # notes about clocks come first
    n_moving = {"scan": 0, "stripe": 0}
    scan_t: list[float] = []

    def flush(k: int) -> None:
        nonlocal board
        a = acc.pop(k)
        if a.board and board is None:
            board = combine_frames(a.board)
        if a.scans and a.frames:
            r = combine_scans(a.scans)
            (tmp / "scans" / f"p{k:06d}.csv").write_text(scan_csv_text(geom.angles, r))
            _write_png(tmp / "stripes" / f"p{k:06d}.png", combine_frames(a.frames))
        done[k] = (len(a.scans), len(a.frames))

    total = sum(c.msgcount for c in wanted)
    with tqdm(total=total, unit="msg", disable=not progress, desc=f"import {bag.name}") as bar:
        for conn, log_ns, raw in reader.messages(connections=wanted):
            bar.update(1)
            role, c = role_of[conn.id]
            msg = reader.deserialize(raw, c.msgtype)
            t = clock.time(c.topic, msg, log_ns)
            log_t = log_ns * 1e-9
            for k in [k for k in acc if periods[k].t_end + _SLACK_S < log_t]:
                flush(k)
            if role == "scan":
                s = scan_from_msg(msg, t)
                if clock.mode[c.topic] == "log":  # received after its last beam
                    s = replace(s, t0=2 * s.t0 - s.t1, t1=s.t0)
                if geom is None:
                    geom = _ScanGeometry(s, c.topic, rigf)
                geom.check(s, bag)
                scan_t.append(t)
                for w, a0, a1 in windows:
                    if a0 <= s.t_mid <= a1:
                        sweep_rows[w.name].append((s.t_mid, s.range_mm))
                k = period_of(s.t0, s.t1)
                if k < 0:
                    n_moving["scan"] += 1
                elif k not in done:
                    acc.setdefault(k, _Acc()).scans.append(s.range_mm)
                continue
            img = image_from_msg(msg, c.msgtype, f"{bag}: {c.topic}")
            k = period_of(t - frame_guard_s, t + frame_guard_s)
            if lit is not None and k >= 0 and frame_brightness(img) > lit.split.threshold:
                role = "board"  # a lit frame of the one camera topic: the board, never a stripe
                if k != lit.board_period:
                    continue
            if role == "board":
                if k >= 0 and board is None:
                    if k in done:
                        board = img
                    else:
                        acc.setdefault(k, _Acc()).board.append(img)
                continue
            if frame_shape is None:
                frame_shape = img.shape
            elif img.shape != frame_shape:
                raise DatasetError(bag, f"{c.topic}: frames change size ({frame_shape} then "
                                        f"{img.shape}); record one camera mode per bag")
            if k < 0:
                n_moving["stripe"] += 1
            elif k not in done:
                acc.setdefault(k, _Acc()).frames.append(img)
        for k in sorted(acc):
            flush(k)

    if geom is None:
        raise DatasetError(bag, f"{topics['scan']}: no LaserScan messages")
    if frame_shape is None:
        raise DatasetError(bag, f"{topics['stripe']}: no stripe frames")
    if lit is not None:
        for k in sorted(k for k in lit.lit_per_period if not lit.dark_per_period.get(k)):
            p = periods[k]
            warn.append(f"{topics['stripe']}: the still period at {p.t_start - clock0:.2f}.."
                        f"{p.t_end - clock0:.2f} s (psi {p.psi_deg:.4f} deg) has lit frames only "
                        "(the board): not a stripe position")
    # positions: periods with at least one whole scan and one stripe frame, in time order
    used, skipped = [], []
    for k, p in enumerate(periods):
        ns, nf = done.get(k, (0, 0))
        (used if ns and nf else skipped).append((k, p, ns, nf))
    if skipped:
        warn.append(f"{len(skipped)} stationary period(s) without a whole scan or a stripe frame "
                    "were not used (at psi " + ", ".join(f"{p.psi_deg:.4f}" for _, p, _, _ in
                                                         skipped[:8])
                    + (", ..." if len(skipped) > 8 else "") + " deg)")
    if len(used) < 3:
        raise DatasetError(bag, f"{len(used)} usable position(s) (stationary periods with a whole "
                                f"scan and a stripe frame) of {len(periods)} stationary periods; "
                                "the method needs 3; check the topics, --tolerance-deg and "
                                "--min-duration-s")
    psis = [p.psi_deg for _, p, _, _ in used]
    order = np.argsort(psis)
    gaps = np.diff(np.asarray(psis)[order])
    if np.any(gaps <= tol):
        i = int(np.argmin(gaps))
        raise DatasetError(bag, f"two positions at the same angle ({psis[order[i]]:.4f} and "
                                f"{psis[order[i + 1]]:.4f} deg); every position needs its own angle "
                                "(drop the repeat from the recording or lower --tolerance-deg)")
    spacing = float(np.median(np.abs(np.diff(psis))))
    if tol > 0.1 * spacing:
        warn.append(f"the stationarity tolerance {tol:.3g} deg is more than 10 % of the position "
                    f"spacing {spacing:.3g} deg; check --tolerance-deg")
    positions: list[ImportedPosition] = []
    rows = ["index,psi_deg,stripe_image,scan\n"]
    for i, (k, p, ns, nf) in enumerate(used):
        os.replace(tmp / "scans" / f"p{k:06d}.csv", tmp / "scans" / f"{i:04d}.csv")
        os.replace(tmp / "stripes" / f"p{k:06d}.png", tmp / "stripes" / f"{i:04d}.png")
        rows.append(f"{i},{p.psi_deg:.6f},stripes/{i:04d}.png,scans/{i:04d}.csv\n")
        positions.append(ImportedPosition(i, p.psi_deg, p.t_start, p.t_end, ns, nf))
    (tmp / "positions.csv").write_text("".join(rows))

    # board image
    if board_image is not None:
        board = decode_image(board_image, fix="give the lit board image as a PNG (--board-image)")
    if board is None:
        raise DatasetError(bag, f"{topics['board']}: no board frame while the turntable is still; "
                                "record a lit frame at a stop or give --board-image FILE")
    if board.dtype == np.uint16:
        board = np.clip((board.astype(np.uint32) + 128) >> 8, 0, 255).astype(np.uint8)
    if board.shape[:2] != frame_shape[:2]:
        raise DatasetError(bag, f"board image is {board.shape[1]}x{board.shape[0]}, stripe frames "
                                f"are {frame_shape[1]}x{frame_shape[0]}; both come from one camera")
    _write_png(tmp / "board.png", board)

    # sweeps
    sweeps: dict[str, int] = {}
    for w, _, _ in windows:
        rows_w = sweep_rows[w.name]
        psi_rows = _sweep_psi(rows_w, angles, tol)
        if len(psi_rows) < 2:
            raise DatasetError(rigf.path, f"measurement {w.name!r}: {len(psi_rows)} scan(s) in "
                                          f"{w.start_s:g}..{w.end_s:g} s while the turntable turns; "
                                          "check start_s/end_s (seconds from the bag's first message)")
        (tmp / "measure").mkdir(exist_ok=True)
        (tmp / "measure" / f"{w.name}.csv.gz").write_bytes(sweep_csv_gz(psi_rows, geom.angles))
        sweeps[w.name] = len(psi_rows)

    # camera frame size against RIG.json
    cam = rigf.base.get("camera")
    if cam is not None and tuple(cam["image_size"]) != (frame_shape[1], frame_shape[0]):
        raise DatasetError(rigf.path, f"camera.image_size is {cam['image_size']} but the frames on "
                                      f"{topics['stripe']} are {frame_shape[1]}x{frame_shape[0]}; "
                                      "give the camera block of the camera that recorded the bag")
    if rigf.intrinsics_dir is not None:
        _copy_intrinsics(rigf.intrinsics_dir, tmp / "intrinsics")

    scan_period = median_period_s(np.asarray(scan_t))
    ds = {"format": DATASET_FORMAT, **rigf.base,
          "lidar": {**{k: round(v, 6 if k.endswith("_deg") else 3) for k, v in geom.lidar.items()},
                    "z_axis_hint": rigf.z_axis_hint},
          "measurements": [{"name": w.name, "sweep": f"measure/{w.name}.csv.gz", "object": w.object,
                            **({"reference_diameter_mm": w.reference_diameter_mm}
                               if w.reference_diameter_mm is not None else {})}
                           for w, _, _ in windows],
          "import": {"bag": str(bag), "topics": topics, "clock": dict(clock.mode),
                     **({"camera": lit.meta(periods, clock0)} if lit is not None else {}),
                     "tolerance_deg": tol, "min_duration_s": min_dur,
                     "encoder_resolution_deg": encoder_resolution_deg(angles.psi_deg),
                     "angle_rate_hz": 1.0 / median_period_s(angles.t_s),
                     "scan_rate_hz": 1.0 / scan_period if scan_period > 0 else None,
                     "scans_while_moving": n_moving["scan"],
                     "stripe_frames_while_moving": n_moving["stripe"],
                     "positions": [{"index": q.index, "t_start_s": round(q.t_start_s - clock0, 6),
                                    "t_end_s": round(q.t_end_s - clock0, 6),
                                    "scans": q.n_scans, "stripe_frames": q.n_frames}
                                   for q in positions]}}
    write_json_atomic(tmp / "dataset.json", ds)
    return ImportResult(tmp, positions, tol, min_dur, topics, sweeps, warn)


def _sweep_psi(rows: list[tuple[float, np.ndarray]], angles: AngleStream,
               tol: float) -> list[tuple[float, np.ndarray]]:
    """psi at each scan's mid-time (linear interpolation in the angle readings); scans outside
    the readings' time span are dropped, and so is a scan within ``tol`` of the one kept before
    it (the turntable still)."""
    out: list[tuple[float, np.ndarray]] = []
    t0, t1 = angles.t_s[0], angles.t_s[-1]
    for t, r in sorted(rows, key=lambda x: x[0]):
        if not t0 <= t <= t1:
            continue
        psi = float(np.interp(t, angles.t_s, angles.psi_deg))
        if out and abs(psi - out[-1][0]) <= tol:
            continue
        out.append((psi, r))
    return out


def sweep_csv_gz(rows: list[tuple[float, np.ndarray]], angles_deg: np.ndarray) -> bytes:
    """``measure/NAME.csv.gz``: long form psi_deg, angle_deg, range_mm (0 = no return)."""
    ang = [f"{a:.6f}" for a in angles_deg.tolist()]
    parts = ["psi_deg,angle_deg,range_mm\n"]
    for psi, r in rows:
        p = f"{psi:.6f}"
        parts.append("".join(f"{p},{a},{_fmt_range(v)}\n" for a, v in zip(ang, r.tolist())))
    buf = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=6) as f:
        f.write("".join(parts).encode())
    return buf.getvalue()


def _copy_intrinsics(src: Path, dst: Path) -> None:
    """The intrinsics photos as ``intrinsics/*.png`` (other image formats converted)."""
    dst.mkdir()
    n = 0
    for p in sorted(src.iterdir()):
        ext = p.suffix.lower()
        if ext == ".png":
            shutil.copyfile(p, dst / p.name)
        elif ext in (".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
            img = decode_image(p, fix="copy the intrinsics photo again or remove it")
            _write_png(dst / f"{p.stem}.png", img)
        else:
            continue
        n += 1
    if n == 0:
        raise DatasetError(src, "holds no .png/.jpg/.bmp/.tif chessboard photos (RIG.json "
                                "intrinsics); put the photos there or remove 'intrinsics'")
