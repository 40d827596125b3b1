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

import os
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..stationary import (
    default_min_duration_s,
    default_tolerance_deg,
    encoder_resolution_deg,
    find_stationary,
    median_period_s,
)
from .bag_angles import AngleStream, read_angles
from .bag_combine import CLIP_SIGMAS, combine_frames, combine_scans
from .bag_frames import COMPRESSED, LitSplit, frame_brightness, image_from_msg, split_lit_dark
from .bag_read import (
    ANGLE_TYPES,
    FLOAT64,
    IMAGE,
    IMAGE_TYPES,
    JOINTSTATE,
    LASERSCAN,
    Clock,
    Scan,
    connections,
    open_bag,
    pick_topic,
    reader_errors,
    scan_from_msg,
    unreadable_bag,
)
from .bag_write import (
    copy_intrinsics,
    finish_out,
    prepare_out,
    scan_csv_text,
    sweep_csv_gz,
    write_png,
)
from .dataset import DATASET_FORMAT, DatasetError, decode_image, write_json_atomic
from .rig import RigFile, read_rig

# the names the bag readers used to hold, still importable from here
__all__ = [
    "ANGLE_TYPES", "CLIP_SIGMAS", "COMPRESSED", "FLOAT64", "IMAGE", "IMAGE_TYPES", "JOINTSTATE",
    "LASERSCAN", "AngleStream", "Clock", "ImportResult", "ImportedPosition", "Scan",
    "combine_frames", "combine_scans", "image_from_msg", "import_bag", "open_bag", "pick_topic",
    "read_angles", "scan_csv_text", "scan_from_msg", "sweep_csv_gz", "unreadable_bag",
]

_SLACK_S = 5.0  # a position is combined once the bag's log time is this far past its end


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
    except reader_errors() as e:
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
    scan_conns = connections(reader, topics["scan"])
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
    tmp = prepare_out(out, overwrite)
    try:
        result = _stream(reader, bag, rigf, tmp, topics, angles, periods, windows, tol, min_dur,
                         board_image, progress, tqdm, clock0, frame_guard_s, clock, lit)
        finish_out(tmp, out)
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
    for conn, log_ns, raw in reader.messages(connections=connections(reader, topic)):
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
    conns = {role: connections(reader, t) for role, t in topics.items()
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
            write_png(tmp / "stripes" / f"p{k:06d}.png", combine_frames(a.frames))
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
    write_png(tmp / "board.png", board)

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
        copy_intrinsics(rigf.intrinsics_dir, tmp / "intrinsics")

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
