"""Reading ROS 1 / ROS 2 bags through ``rosbags`` (no ROS install): opening a bag, picking a
topic, message times and ``sensor_msgs/LaserScan`` in the contract's units.

Shared by the turntable import (:mod:`lidarcal.io.bag`) and the one-board import
(:mod:`lidarcal.io.bag_views`); images are decoded by :mod:`lidarcal.io.bag_frames`.

- ``sensor_msgs/LaserScan``: ranges in metres; a return is invalid when it is 0, inf,
  NaN or outside ``range_min..range_max`` of its message. ``header.stamp`` is the time
  of the first beam, beam ``k`` is at ``stamp + k * time_increment`` (ROS convention).
- Clock (:class:`Clock`): a message's time is its ``header.stamp``; a message without a
  header (Float64), or a topic whose stamps are more than 1 s from the bag's receive (log)
  times (another clock), uses its log time instead. See ``docs/ros-bags.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bag_frames import COMPRESSED
from .dataset import DatasetError

LASERSCAN = "sensor_msgs/msg/LaserScan"
IMAGE = "sensor_msgs/msg/Image"
JOINTSTATE = "sensor_msgs/msg/JointState"
FLOAT64 = "std_msgs/msg/Float64"
IMAGE_TYPES = (IMAGE, COMPRESSED)
ANGLE_TYPES = (JOINTSTATE, FLOAT64)


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


def connections(reader, topic: str | None) -> list:
    return [c for c in reader.connections if c.topic == topic] if topic else []


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
    """The one-line error for a bag the reader gave up on (one of :func:`reader_errors`)."""
    msg = " ".join(str(e).split()) or type(e).__name__
    return DatasetError(bag, f"cannot be read to the end ({msg}); the bag may be truncated "
                             "or corrupt: reindex it (rosbag reindex / ros2 bag reindex)")


def reader_errors() -> tuple[type[Exception], ...]:
    from rosbags.highlevel import AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.serde import SerdeError

    return (AnyReaderError, ReaderError1, ReaderError2, SerdeError, EOFError)
