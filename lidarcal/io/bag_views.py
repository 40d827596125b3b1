"""``lidarcal import BAG --views --out DIR``: a one-board recording -> a folder of view pairs.

The common rig (one flat chessboard moved by hand in front of a camera and a 2D LiDAR,
as CamLaserCalibraTool and RADLOCC users record it) gives a bag with a
``sensor_msgs/LaserScan`` topic, an ``Image`` or ``CompressedImage`` topic and maybe a
``CameraInfo``. The board is held still for a moment, moved, held still again; each
still moment is one view of ``lidarcal planes`` (contract: :mod:`lidarcal.io.pairs`).

Still intervals are found from the data, with thresholds from the data's own noise:

- **scans**: the range noise of each beam is measured from the differences of
  consecutive scans, ``d ~ N(0, 2 sigma_b^2)`` while still: ``sigma_b`` from the 25th
  percentile of ``|d|`` (:func:`beam_noise_mm`, with the continuity correction of
  integer-mm readings); a beam that sees the moving board a share ``c`` of the time
  reads too noisy by ``Phi^-1((1 + 0.25 / (1 - c)) / 2) / Phi^-1(0.625)`` (10 %: 1.11,
  30 %: 1.46), which makes its motion test more lenient, never stricter. Two scans
  differ when a run of at least ``MIN_RUN`` = 3 adjacent beams differ by more than ``K_SIGMA sqrt(2) sigma_b`` (4 sigma, and at least 1.5 range
  quanta): a mixed return flickering at an edge changes one beam, a moving board a run of
  them. Still runs (:func:`still_runs`): a run grows while each scan agrees with the one
  before it and with the per-beam median of the run's first scans (``K_SIGMA sqrt(1 +
  pi / (2 n)) sigma_b``), so a slow drift adds up and ends it; then each run is trimmed
  to where its scans agree with its own median.
- **frames**: each frame becomes block means (``cv2.resize`` with ``INTER_AREA`` to
  about 80 blocks across), which averages the pixel noise; two frames differ when at
  least ``MIN_RUN`` connected blocks change by more than ``K_SIGMA sqrt(2) sigma_f``
  after removing the median change (a global brightness flicker), with ``sigma_f`` the
  blocks' noise measured as ``1.4826 MAD / sqrt(2)`` of consecutive frames' differences
  (median over the frame pairs; at least half a gray level). Still runs as for scans,
  of at least two frames (one frame cannot show that the image holds still).
- a **still interval** is where a still run of scans and a still run of frames overlap
  and holds at least ``min_scans`` whole scans (beams ``stamp .. stamp + (n - 1)
  time_increment``) and a frame.
- **holds** (:func:`sort_holds`, tests of :class:`AgreeTest`): two sets of still readings
  show one pose when the per-beam medians of their scans and the per-block medians of
  their frames agree within ``K_SIGMA`` times the noise of a difference of two medians.
  An interval whose halves do not agree, and consecutive intervals with no move between
  them (no two consecutive readings differ) that do not all agree, are a board that slid
  while held: not used (a warning names the hold). The remaining intervals that agree
  are one pose held twice (a pause, a return): one view, so that ``lidarcal planes`` does
  not count one pose twice and report falsely small sigmas.
- per view: the frame nearest the middle of its interval (of the merged intervals, the
  one with the most frames) and the per-beam clipped mean of all its scans
  (:func:`lidarcal.io.bag_combine.combine_scans`, at most the noise of their median,
  ``sqrt(pi / (2 n))`` of one scan's; mixed returns and dropouts left out).

Views are named ``view_NNN_tSS.SS`` (index, the frame's time in seconds from the bag's
first message). Topics, clocks and invalid returns follow :mod:`lidarcal.io.bag`.
"""

from __future__ import annotations

import itertools
import math
import os
import shutil
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from .bag_combine import combine_scans
from .bag_frames import image_from_msg
from .bag_read import (
    IMAGE_TYPES,
    LASERSCAN,
    Clock,
    connections,
    open_bag,
    pick_topic,
    reader_errors,
    scan_from_msg,
    unreadable_bag,
)
from .bag_write import finish_out, prepare_out, scan_csv_text, write_png
from .camera_files import pinhole_from_ros
from .dataset import DatasetError, write_json_atomic

CAMERAINFO = "sensor_msgs/msg/CameraInfo"
K_SIGMA = 4.0  # a beam or block changed: beyond 4 sigma of a difference of two readings
MIN_RUN = 3  # ... in a run of >= 3 adjacent beams, a connected group of >= 3 blocks
BLOCKS_ACROSS = 80
MIN_FRAME_THRESHOLD = 0.5  # gray levels: noise-free frames still need a real change
FEW_VIEWS = 5


# ----------------------------------------------------------------------------- scans


def beam_noise_mm(ranges_mm: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-beam range noise ``sigma_b`` (mm) of a scan sequence (m, n) and the range quantum.

    From the differences ``d`` of consecutive scans valid in both (``d ~ N(0, 2 sigma^2)``
    while still): with ``k_b`` the 25th percentile of ``|d|`` and ``p_b`` the share of
    ``|d| <= k_b``, ``sigma_b = (k_b + q / 2) / (sqrt(2) Phi^-1((1 + p_b) / 2))``, where
    ``q`` is the range quantum (the smallest non-zero ``|d|``, 1 mm for integer-mm
    scanners; ``q / 2`` is the continuity correction of integer readings, ~0 for float
    ones). A beam that sees the moving board a share ``c`` of the time reads too noisy by
    ``Phi^-1((1 + 0.25 / (1 - c)) / 2) / Phi^-1(0.625)`` (10 %: x1.11). A beam without such pairs gets the median of the others; a
    beam whose readings never change gets 0.
    """
    from scipy.special import ndtri

    d = np.abs(np.diff(ranges_mm, axis=0))
    valid = np.isfinite(d)
    nz = d[valid & (d > 0)]
    quantum = float(nz.min()) if nz.size else 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # beams that never return
        k = np.nanpercentile(d, 25, axis=0, method="lower") if d.shape[0] else np.full(ranges_mm.shape[1], np.nan)
        p = np.sum(valid & (d <= k + 1e-6 * max(quantum, 1e-3)), axis=0) / np.sum(valid, axis=0)
        sigma = (k + quantum / 2) / (math.sqrt(2.0) * ndtri((1 + p) / 2))
    ok = np.isfinite(sigma)
    sigma = np.where(ok, sigma, np.median(sigma[ok]) if ok.any() else 0.0)
    return sigma, quantum


def longest_run(mask: np.ndarray) -> int:
    """The length of the longest run of True in a 1-D boolean array."""
    a, b = _longest_run_bounds(mask)
    return b - a


def scans_differ(a: np.ndarray, b: np.ndarray, threshold_mm: np.ndarray) -> bool:
    """Whether two scans differ: ``MIN_RUN`` adjacent beams, valid in both, further apart
    than their threshold."""
    with np.errstate(invalid="ignore"):
        return longest_run(np.abs(a - b) > threshold_mm) >= MIN_RUN


def _longest_run_bounds(mask: np.ndarray) -> tuple[int, int]:
    """``[a, b)`` of the first longest run of True (``(0, 0)`` when there is none)."""
    if not mask.any():
        return 0, 0
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k])


def _median_noise_factor(n: int) -> float:
    """``f``: one reading against the median of ``n`` readings differs with ``sqrt(1 + c)``
    times the noise of one reading (``c`` = 1 for one reading, 1/2 for the mean of two,
    ``pi / (2 n)`` for a median of more)."""
    return math.sqrt(1.0 + (1.0 if n == 1 else 0.5 if n == 2 else math.pi / (2.0 * n)))


def _nanmedian(x: np.ndarray) -> np.ndarray:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN beams stay NaN
        return np.nanmedian(x, axis=0)


def still_runs(stack: np.ndarray, differ, min_len: int) -> list[tuple[int, int]]:
    """Runs ``(first, last)`` of a sequence of readings ``stack`` (scans or frames' block
    means, in time order) during which nothing moved, of at least ``min_len`` readings.

    ``differ(x, ref, f)`` tells whether reading ``x`` differs from ``ref`` beyond ``f``
    times the noise of one reading. Two steps:

    1. growing: a run starts at a reading; its reference is the median of its first
       readings (recomputed whenever the run's length doubles); the run ends at a reading
       that differs from the one before it (``f = sqrt(2)``) or from the reference (``f``
       of :func:`_median_noise_factor`), so a slow drift that no consecutive pair shows
       adds up and ends it, and a run started in the slow end of a move ends where the
       hold begins;
    2. trimming: a run of ``min_len`` or more is kept where its readings agree with the
       run's own median: the longest agreeing stretch is a still run and the parts before
       and after it are examined the same way.
    """
    n = len(stack)
    grown: list[tuple[int, int]] = []
    start, ref, n_ref = 0, stack[0] if n else None, 1
    for j in range(1, n):
        if differ(stack[j], stack[j - 1], math.sqrt(2.0)) or differ(
                stack[j], ref, _median_noise_factor(n_ref)):
            grown.append((start, j))
            start, ref, n_ref = j, stack[j], 1
        elif (j - start + 1) >= 2 * n_ref:
            n_ref = j - start + 1
            ref = _nanmedian(stack[start:j + 1])
    if n:
        grown.append((start, n))
    out: list[tuple[int, int]] = []

    def trim(i: int, j: int) -> None:  # the readings [i, j)
        if j - i < min_len:
            return
        ref = _nanmedian(stack[i:j])
        f = _median_noise_factor(j - i)
        agree = np.array([not differ(stack[q], ref, f) for q in range(i, j)])
        a, b = _longest_run_bounds(agree)
        if b - a == j - i:
            out.append((i, j - 1))
        elif b > a:
            trim(i, i + a)
            trim(i + a, i + b)
            trim(i + b, j)

    for i, j in grown:
        trim(i, j)
    return sorted(out)


# ----------------------------------------------------------------------------- frames


def frame_blocks(img: np.ndarray) -> np.ndarray:
    """Block means of a frame's gray levels, about ``BLOCKS_ACROSS`` blocks across (float32)."""
    g = img if img.ndim == 2 else cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    h, w = g.shape
    side = max(1, round(max(w, h) / BLOCKS_ACROSS))
    return cv2.resize(g.astype(np.float32), (max(1, w // side), max(1, h // side)),
                      interpolation=cv2.INTER_AREA)


def _block_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = a - b
    return d - np.median(d)


def frame_noise(blocks: list[np.ndarray]) -> float:
    """The block means' noise ``sigma_f``: ``1.4826 MAD / sqrt(2)`` of consecutive frames'
    block differences (the median change removed), the median over the frame pairs."""
    if len(blocks) < 2:
        return 0.0
    mads = [float(np.median(np.abs(_block_change(a, b)))) for a, b in itertools.pairwise(blocks)]
    return 1.4826 * float(np.median(mads)) / math.sqrt(2.0)


def frames_differ(a: np.ndarray, b: np.ndarray, threshold: float) -> bool:
    """Whether two frames' block means differ: a connected group of ``MIN_RUN`` blocks that
    changed by more than ``threshold`` (the median change removed)."""
    mask = (np.abs(_block_change(a, b)) > threshold).astype(np.uint8)
    if int(mask.sum()) < MIN_RUN:
        return False
    _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    return int(stats[1:, cv2.CC_STAT_AREA].max()) >= MIN_RUN


# ----------------------------------------------------------------------------- intervals


@dataclass(frozen=True)
class StillInterval:
    """Where a still run of scans and one of frames overlap (bag clock, s)."""

    t_start: float
    t_end: float
    scans: list[int]  # whole scans inside
    frames: list[int]  # frames inside
    middle_frame: int  # the frame nearest the middle of the interval


def still_intervals(scan_runs, scan_t0, scan_t1, frame_runs, frame_t,
                    min_scans: int) -> list[StillInterval]:
    """The overlaps of still scan runs and still frame runs (two or more frames) holding at
    least ``min_scans`` whole scans and a frame, in time order."""
    out = []
    fr = [(frame_t[a], frame_t[b], a, b) for a, b in frame_runs if b > a]
    sr = [(scan_t0[i], scan_t1[j], i, j) for i, j in scan_runs if j - i + 1 >= min_scans]
    k = 0
    for s0, s1, i, j in sr:
        while k < len(fr) and fr[k][1] < s0:
            k += 1
        m = k
        while m < len(fr) and fr[m][0] <= s1:
            f0, f1, a, b = fr[m]
            lo, hi = max(s0, f0), min(s1, f1)
            scans = [q for q in range(i, j + 1) if scan_t0[q] >= lo and scan_t1[q] <= hi]
            frames = [q for q in range(a, b + 1) if lo <= frame_t[q] <= hi]
            if len(scans) >= min_scans and frames:
                mid = 0.5 * (lo + hi)
                out.append(StillInterval(lo, hi, scans, frames,
                                         min(frames, key=lambda q: (abs(frame_t[q] - mid), q))))
            m += 1
    return sorted(out, key=lambda s: s.t_start)


# ----------------------------------------------------------------------------- holds


@dataclass(frozen=True)
class AgreeTest:
    """Whether two sets of still readings (two still intervals, or the halves of one) show
    the same pose within the measured noise: the per-beam medians of their scans do not
    differ (:func:`scans_differ`) beyond ``K_SIGMA sqrt(c_a + c_b) sigma_b`` and the
    per-block medians of their frames do not differ (:func:`frames_differ`) beyond
    ``K_SIGMA sqrt(c_a + c_b) sigma_f``, with ``c`` the variance of a median of ``n``
    readings in units of one reading's (1, 1/2, ``pi / (2 n)``: :func:`_median_noise_factor`);
    the floors of the still runs (1.5 range quanta, ``MIN_FRAME_THRESHOLD``) apply."""

    scans: np.ndarray  # (m, n) ranges, mm, time order
    blocks: np.ndarray  # (k, h, w) frames' block means, time order
    sigma_s: np.ndarray  # K_SIGMA sigma_b per beam, mm
    floor_s: float
    sigma_f: float  # frames' block noise, gray levels
    _medians: dict = field(default_factory=dict, repr=False)  # (kind, indices) -> median

    def _median(self, kind: str, idx) -> np.ndarray:
        key = (kind, tuple(idx))
        if key not in self._medians:
            self._medians[key] = (_nanmedian(self.scans[list(idx)]) if kind == "scans"
                                  else np.median(self.blocks[list(idx)], axis=0))
        return self._medians[key]

    def agree(self, scans_a, frames_a, scans_b, frames_b) -> bool:
        def c(n: int) -> float:
            return _median_noise_factor(n) ** 2 - 1.0

        f = math.sqrt(c(len(scans_a)) + c(len(scans_b)))
        if scans_differ(self._median("scans", scans_a), self._median("scans", scans_b),
                        np.maximum(f * self.sigma_s, self.floor_s)):
            return False
        if not len(frames_a) or not len(frames_b):
            return True
        f = math.sqrt(c(len(frames_a)) + c(len(frames_b)))
        return not frames_differ(self._median("frames", frames_a),
                                 self._median("frames", frames_b),
                                 max(f * K_SIGMA * self.sigma_f, MIN_FRAME_THRESHOLD))

    def same_pose(self, a: StillInterval, b: StillInterval) -> bool:
        return self.agree(a.scans, a.frames, b.scans, b.frames)

    def drifts(self, iv: StillInterval) -> bool:
        """Whether the first and second halves of an interval's scans (and of its frames)
        differ: a board that slid during the hold, slower than the still runs notice."""
        h, g = len(iv.scans) // 2, len(iv.frames) // 2
        return not self.agree(iv.scans[:h], iv.frames[:g], iv.scans[h:], iv.frames[g:])

    def moved_between(self, a: StillInterval, b: StillInterval) -> bool:
        """Whether two consecutive scans, or two consecutive frames, between the end of
        ``a`` and the start of ``b`` differ (the still runs' test of a reading against the
        one before it): the board was carried, not only drifting, between the two."""
        thr = np.maximum(math.sqrt(2.0) * self.sigma_s, self.floor_s)
        if any(scans_differ(self.scans[q + 1], self.scans[q], thr)
               for q in range(a.scans[-1], b.scans[0])):
            return True
        thr_f = max(math.sqrt(2.0) * K_SIGMA * self.sigma_f, MIN_FRAME_THRESHOLD)
        return any(frames_differ(self.blocks[q + 1], self.blocks[q], thr_f)
                   for q in range(a.frames[-1], b.frames[0]))


@dataclass(frozen=True)
class Holds:
    """The still intervals sorted into views: ``groups`` (indices of the intervals of one
    view, first interval first, in time order) and ``drifting`` (intervals not used, by the
    hold they belong to: its intervals and why)."""

    groups: list[list[int]]
    drifting: list[tuple[list[int], str]]

    def why(self, i: int) -> str | None:
        """Why interval ``i`` was dropped (None: it is in a view)."""
        return next((w for ch, w in self.drifting if i in ch), None)


def sort_holds(intervals: list[StillInterval], test: AgreeTest) -> Holds:
    """Still intervals -> views: a drifting hold is dropped, one pose held twice is one view.

    1. *drift*: an interval whose halves differ (:meth:`AgreeTest.drifts`), or consecutive
       intervals with no move between them (:meth:`AgreeTest.moved_between`) that do not
       all show one pose: the board slid during one hold and the still runs cut it into
       pieces. Every interval of such a hold is dropped (its pieces are near-copies of one
       pose that would count as independent views in ``lidarcal planes``).
    2. *merge*: the remaining intervals that show the same pose within the noise
       (:meth:`AgreeTest.same_pose`; the board paused twice, or was brought back exactly)
       form one view; an interval joins the first view whose every interval it agrees with.
    """
    drifting: list[tuple[list[int], str]] = []
    chain = [0] if intervals else []
    chains = []
    for i in range(1, len(intervals)):
        if test.moved_between(intervals[i - 1], intervals[i]):
            chains.append(chain)
            chain = [i]
        else:
            chain.append(i)
    if chain:
        chains.append(chain)
    for ch in chains:
        inside = [i for i in ch if test.drifts(intervals[i])]
        pieces = len(ch) > 1 and not all(test.same_pose(intervals[i], intervals[j])
                                         for i, j in itertools.combinations(ch, 2))
        if inside or pieces:
            drifting.append((ch, f"{len(ch)} still piece(s) with no move between them that "
                                 "differ beyond the noise" if pieces else
                                 "its first and second halves differ beyond the noise"))
    dropped = {i for ch, _ in drifting for i in ch}
    groups: list[list[int]] = []
    for i in (i for i in range(len(intervals)) if i not in dropped):
        for g in groups:
            if all(test.same_pose(intervals[i], intervals[j]) for j in g):
                g.append(i)
                break
        else:
            groups.append([i])
    return Holds(groups, drifting)


# ----------------------------------------------------------------------------- camera info


def camera_from_info(msg, topic: str) -> tuple[dict | None, str | None]:
    """``camera.json`` (K, dist, image_size) from a CameraInfo, or a warning why not.

    ROS's ``plumb_bob`` D = (k1, k2, t1, t2, k3) and ``rational_polynomial`` (k1, k2, t1,
    t2, k3, k4, k5, k6) are OpenCV's order; lidarcal's camera model holds k1, k2, p1, p2,
    k3, so the rational terms must be 0. ``equidistant`` (fisheye) and other models are not
    a pinhole model with OpenCV's distortion: no camera.json, a warning saying what to do.
    """
    K = np.asarray(getattr(msg, "k", None) if hasattr(msg, "k") else msg.K, float).reshape(3, 3)
    D = np.asarray(getattr(msg, "d", None) if hasattr(msg, "d") else msg.D, float).reshape(-1)
    model = str(msg.distortion_model).strip()
    size = [int(msg.width), int(msg.height)]
    fix = ("calibrate the camera from chessboard photos with `lidarcal intrinsics` (it writes "
           "camera.json) and give that to planes with --camera")
    if not (K[0, 0] > 0 and K[1, 1] > 0) or min(size) <= 0:
        return None, (f"{topic}: CameraInfo has no calibration (K {K.tolist()}, size {size}); "
                      f"camera.json not written; {fix}")
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1 or int(msg.roi.width) or int(msg.roi.height):
        return None, (f"{topic}: CameraInfo uses binning or a region of interest (K is for the "
                      f"full sensor); camera.json not written; {fix}")
    block, why = pinhole_from_ros(K, D, model, size)
    if block is None:
        tail = ("(5 coefficients)" if "k4..k6" in why else
                "(or record rectified images with their CameraInfo)")
        return None, f"{topic}: CameraInfo {why}; camera.json not written; {fix} {tail}"
    return {**block, "source": f"CameraInfo {topic} ({model or 'no distortion'})"}, None


# ----------------------------------------------------------------------------- import


@dataclass
class ImportedView:
    name: str
    t_s: float  # the frame's time, s from the bag's first message
    t_start_s: float
    t_end_s: float
    n_scans: int
    n_frames: int
    intervals: list[int] = field(default_factory=list)  # still intervals merged into it


@dataclass
class ViewsResult:
    out: Path
    views: list[ImportedView]
    scan_runs: int  # still runs of scans with >= min_scans scans
    frame_runs: int  # still runs of frames with >= 2 frames
    scan_noise_mm: float  # median over beams of sigma_b
    frame_noise: float  # sigma_f, gray levels
    topics: dict[str, str | None]
    camera_written: bool
    warnings: list[str] = field(default_factory=list)
    n_intervals: int = 0  # still intervals found (views + merged + drifting)
    n_drifting: int = 0  # still intervals dropped: the board slid during the hold


def import_views(bag: str | os.PathLike, out: str | os.PathLike, *,
                 scan_topic: str | None = None, image_topic: str | None = None,
                 camera_info_topic: str | None = None, min_scans: int = 5,
                 pattern: tuple[int, int] | None = None, square_mm: float | None = None,
                 overwrite: bool = False, progress: bool = False) -> ViewsResult:
    """A one-board bag -> a folder of ``NAME.png`` + ``NAME.csv`` views (and ``camera.json``
    from a CameraInfo, ``views.json`` with what was found), written atomically.

    ``pattern`` (inner corners, columns x rows) and ``square_mm`` (both or neither): the
    board, written as ``board.json`` (:func:`lidarcal.io.pairs.board_spec` reads it, so
    ``lidarcal planes DIR`` needs no ``--pattern``/``--square-mm``).

    See the module docstring for how the still intervals are found.
    """
    bag, out = Path(bag), Path(out)
    board = board_json(bag, pattern, square_mm)
    if min_scans < 3:
        raise DatasetError(bag, f"--min-scans must be >= 3 (a per-beam median needs 3 scans), "
                                f"got {min_scans}")
    reader = open_bag(bag)
    try:
        topics = {"scan": pick_topic(reader, scan_topic, (LASERSCAN,), "LaserScan",
                                     "--scan-topic", bag),
                  "image": pick_topic(reader, image_topic, IMAGE_TYPES, "camera image",
                                      "--image-topic", bag)}
        ns = topics["image"].removesuffix("/compressed").rsplit("/", 1)[0] + "/"
        topics["camera_info"] = pick_topic(reader, camera_info_topic, (CAMERAINFO,),
                                           "CameraInfo", "--camera-info-topic", bag,
                                           prefer=ns.lower(), required=False)
        return _import_views(reader, bag, out, topics, min_scans, overwrite, progress, board)
    except reader_errors() as e:
        raise unreadable_bag(bag, e) from None
    finally:
        reader.close()


def board_json(bag: Path, pattern: tuple[int, int] | None,
               square_mm: float | None) -> dict | None:
    """``board.json`` of a views folder (the keys of dataset.json's boards), or None."""
    if pattern is None and square_mm is None:
        return None
    if pattern is None or square_mm is None:
        raise DatasetError(bag, "--pattern and --square-mm go together (board.json needs the "
                                "inner corners and the square side); give both or neither")
    if (len(pattern) != 2 or not all(isinstance(v, int) and v >= 2 for v in pattern)):
        raise DatasetError(bag, f"--pattern must be COLSxROWS inner corners, each >= 2 (like "
                                f"8x5), got {'x'.join(map(str, pattern))}")
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise DatasetError(bag, f"--square-mm must be a number > 0 (the square side, mm), got "
                                f"{square_mm:g}")
    return {"inner_corners": [int(pattern[0]), int(pattern[1])], "square_mm": float(square_mm)}


def _import_views(reader, bag: Path, out: Path, topics: dict, min_scans: int, overwrite: bool,
                  progress: bool, board: dict | None = None) -> ViewsResult:
    from tqdm import tqdm

    clock = Clock()
    warn = clock.notes
    clock0 = reader.start_time * 1e-9
    scans, t0s, t1s = [], [], []
    blocks, ft = [], []
    frame_shape = None
    layout = None
    info = None
    conns = [c for role in ("scan", "image", "camera_info") for c in connections(reader, topics[role])]
    with tqdm(total=sum(c.msgcount for c in conns), unit="msg", disable=not progress,
              desc=f"import {bag.name}") as bar:
        for conn, log_ns, raw in reader.messages(connections=conns):
            bar.update(1)
            if conn.topic == topics["camera_info"]:
                if info is None:
                    info = reader.deserialize(raw, conn.msgtype)
                continue
            msg = reader.deserialize(raw, conn.msgtype)
            t = clock.time(conn.topic, msg, log_ns)
            if conn.topic == topics["scan"]:
                s = scan_from_msg(msg, t)
                if clock.mode[conn.topic] == "log":  # received after its last beam
                    s = replace(s, t0=2 * s.t0 - s.t1, t1=s.t0)
                if layout is None:
                    layout = s
                elif (s.range_mm.size != layout.range_mm.size
                      or abs(s.angle_min_deg - layout.angle_min_deg) > 1e-6
                      or abs(s.angle_step_deg - layout.angle_step_deg) > 1e-9):
                    raise DatasetError(bag, f"{conn.topic}: the beam layout changes within the "
                                            f"bag ({layout.range_mm.size} beams from "
                                            f"{layout.angle_min_deg:g} deg, then {s.range_mm.size} "
                                            f"from {s.angle_min_deg:g} deg); record one LiDAR "
                                            "configuration per bag")
                scans.append(s.range_mm.astype(np.float32))
                t0s.append(s.t0)
                t1s.append(s.t1)
            else:
                img = image_from_msg(msg, conn.msgtype, f"{bag}: {conn.topic}")
                if frame_shape is None:
                    frame_shape = img.shape
                elif img.shape != frame_shape:
                    raise DatasetError(bag, f"{conn.topic}: frames change size ({frame_shape} "
                                            f"then {img.shape}); record one camera mode per bag")
                blocks.append(frame_blocks(img))
                ft.append(t)
    if len(scans) < min_scans:
        raise DatasetError(bag, f"{topics['scan']}: {len(scans)} LaserScan message(s); a view "
                                f"needs {min_scans} scans while the board is still")
    if len(ft) < 2:
        raise DatasetError(bag, f"{topics['image']}: {len(ft)} frame(s); a view needs two "
                                "frames while the board is still")
    # time order (messages arrive in log order; stamps may interleave)
    so = np.argsort(t0s, kind="stable")
    R = np.vstack(scans)[so]
    t0 = np.asarray(t0s)[so]
    t1 = np.asarray(t1s)[so]
    fo = np.argsort(ft, kind="stable")
    fts = np.asarray(ft)[fo]
    blocks = [blocks[i] for i in fo]

    sigma_b, quantum = beam_noise_mm(R)
    sigma_s = (K_SIGMA * sigma_b).astype(np.float32)  # K sigma of one reading
    floor_s = np.float32(1.5 * quantum)
    sigma_f = frame_noise(blocks)
    s_runs = still_runs(R, lambda x, ref, f: scans_differ(x, ref, np.maximum(f * sigma_s, floor_s)),
                        min_scans)
    f_runs = still_runs(np.stack(blocks), lambda x, ref, f: frames_differ(
        x, ref, max(f * K_SIGMA * sigma_f, MIN_FRAME_THRESHOLD)), 2)
    thr_scan = np.maximum(math.sqrt(2.0) * sigma_s, floor_s)
    thr_frame = max(math.sqrt(2.0) * K_SIGMA * sigma_f, MIN_FRAME_THRESHOLD)
    n_srun = sum(j - i + 1 >= min_scans for i, j in s_runs)
    n_frun = sum(b > a for a, b in f_runs)
    intervals = still_intervals(s_runs, t0, t1, f_runs, fts, min_scans)
    noise_text = (f"scan noise {np.median(sigma_b):.3g} mm (median over beams), frame noise "
                  f"{sigma_f:.3g} gray levels")
    if not intervals:
        raise DatasetError(bag, f"no still interval: {n_srun} still run(s) of >= {min_scans} "
                                f"scans, {n_frun} still run(s) of >= 2 frames, none overlapping "
                                f"with {min_scans} whole scans and a frame ({noise_text}); hold "
                                "the board still at each view for about a second (at least "
                                f"{min_scans} scans and two frames)")
    holds = sort_holds(intervals, AgreeTest(R, np.stack(blocks), sigma_s, float(floor_s), sigma_f))
    for ch, why in holds.drifting:
        warn.append(f"the board moved slowly during the hold at "
                    f"{intervals[ch[0]].t_start - clock0:.2f}..{intervals[ch[-1]].t_end - clock0:.2f}"
                    f" s ({why}): not used as a view; hold the board still at each view")
    if not holds.groups:
        raise DatasetError(bag, f"no still view: all {len(intervals)} still interval(s) drifted "
                                f"(the board moved slowly while held; {noise_text}); hold the "
                                "board still at each view for about a second")
    if len(holds.groups) < FEW_VIEWS:
        warn.append(f"only {len(holds.groups)} view(s): lidarcal planes needs at least 3 "
                    f"views with differently tilted boards and fixes the pose better with "
                    f"{FEW_VIEWS} or more; record more holds")
    # a merged view's frame: the middle frame of its interval with the most frames
    main = [max(g, key=lambda i: (len(intervals[i].frames), -i)) for g in holds.groups]

    camera = None
    if topics["camera_info"] is not None and info is None:
        warn.append(f"{topics['camera_info']}: no CameraInfo message; camera.json not written")
    elif info is not None:
        camera, why = camera_from_info(info, topics["camera_info"])
        if why:
            warn.append(why)
        elif tuple(camera["image_size"]) != (frame_shape[1], frame_shape[0]):
            warn.append(f"{topics['camera_info']}: CameraInfo is {camera['image_size'][0]}x"
                        f"{camera['image_size'][1]} but the frames on {topics['image']} are "
                        f"{frame_shape[1]}x{frame_shape[0]}; camera.json not written")
            camera = None

    # the chosen frames: a second pass over the camera topic
    wanted = {int(fo[intervals[m].middle_frame]): k for k, m in enumerate(main)}
    names = [f"view_{k:03d}_t{fts[intervals[m].middle_frame] - clock0:.2f}"
             for k, m in enumerate(main)]
    tmp = prepare_out(out, overwrite)
    try:
        i = -1
        for conn, _, raw in reader.messages(connections=connections(reader, topics["image"])):
            i += 1
            if i in wanted:
                img = image_from_msg(reader.deserialize(raw, conn.msgtype), conn.msgtype,
                                     f"{bag}: {conn.topic}")
                write_png(tmp / f"{names[wanted[i]]}.png", img)
        angles = layout.angle_min_deg + np.arange(layout.range_mm.size) * layout.angle_step_deg
        views = []
        for k, (g, m) in enumerate(zip(holds.groups, main)):
            iv = intervals[m]
            scans_k = sorted(q for i in g for q in intervals[i].scans)
            r = combine_scans([R[q].astype(np.float64) for q in scans_k])
            (tmp / f"{names[k]}.csv").write_text(scan_csv_text(angles, r))
            views.append(ImportedView(names[k], float(fts[iv.middle_frame] - clock0),
                                      float(iv.t_start - clock0), float(iv.t_end - clock0),
                                      len(scans_k), sum(len(intervals[i].frames) for i in g),
                                      list(g)))
        view_of = {i: v.name for v in views for i in v.intervals}
        if camera is not None:
            write_json_atomic(tmp / "camera.json", camera)
        if board is not None:
            write_json_atomic(tmp / "board.json", board)
        write_json_atomic(tmp / "views.json", {
            "bag": str(bag), "topics": topics, "clock": dict(clock.mode),
            "scan_noise_mm": {"median": float(np.median(sigma_b)),
                              "p90": float(np.percentile(sigma_b, 90))},
            "range_quantum_mm": quantum, "frame_noise_gray": sigma_f,
            "scan_threshold_mm_median": float(np.median(thr_scan)),
            "frame_threshold_gray": thr_frame, "min_scans": min_scans,
            "still_scan_runs": n_srun, "still_frame_runs": n_frun,
            "still_intervals": [{"index": i, "t_start_s": round(iv.t_start - clock0, 6),
                                 "t_end_s": round(iv.t_end - clock0, 6), "scans": len(iv.scans),
                                 "frames": len(iv.frames), "view": view_of.get(i),
                                 **({"drifting": holds.why(i)} if holds.why(i) else {})}
                                for i, iv in enumerate(intervals)],
            "views": [{"name": v.name, "t_s": round(v.t_s, 6),
                       "t_start_s": round(v.t_start_s, 6), "t_end_s": round(v.t_end_s, 6),
                       "scans": v.n_scans, "frames": v.n_frames, "intervals": v.intervals}
                      for v in views]})
        finish_out(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return ViewsResult(out, views, n_srun, n_frun, float(np.median(sigma_b)), sigma_f, topics,
                       camera is not None, warn, len(intervals),
                       sum(len(ch) for ch, _ in holds.drifting))
