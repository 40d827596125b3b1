"""The dataset contract (``docs/dataset-format.md``): read, validate, write.

Every problem with the input is raised as :class:`DatasetError`, whose text is
one line naming the file, what is wrong and what to do. The CLI prints it as
``error: FILE: ...`` and exits with status 2.
"""

from __future__ import annotations

import csv
import gzip
import io
import json
import math
import os
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Self

import cv2
import numpy as np

from ..laser_colour import LASER_COLOURS, laser_response
from ..trace import mark

DATASET_FORMAT = "lidarcal-dataset/1"
CALIBRATION_FORMAT = "lidarcal-calibration/1"
MEASUREMENTS_FORMAT = "lidarcal-measurements/1"
DEFAULT_Z_AXIS_HINT = (0.0, -1.0, 0.0)
#: stripe images, spread over the sweep (:func:`spread_indices`), that ``calibrate`` pools the
#: stripe's reflectance ratio from before its workers fork
#: (:func:`lidarcal.pipeline.dataset_reflectance_ratio`); its prefetch decodes them first
REFLECTANCE_IMAGES = 5


class DatasetError(Exception):
    """Bad input: ``str(err)`` is ``"FILE: what is wrong; what to do"``."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # picklable (worker processes return it), with both fields
        return (type(self), (self.path, self.problem))


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with OpenCV distortion ``(k1, k2, p1, p2, k3)``; pixels, mm-free."""

    K: np.ndarray  # shape (3, 3)
    dist: np.ndarray  # shape (5,)
    image_size: tuple[int, int]  # (width, height)
    source: str = "dataset.json"
    rms_px: float | None = None

    def to_dict(self) -> dict:
        out = {"K": self.K.tolist(), "dist": self.dist.tolist(), "source": self.source,
               "image_size": list(self.image_size)}
        if self.rms_px is not None:
            out["rms_px"] = float(self.rms_px)
        return out


@dataclass(frozen=True)
class BoardSpec:
    """A chessboard: ``inner_corners`` = (per_row, per_column), OpenCV's patternSize."""

    inner_corners: tuple[int, int]
    square_mm: float

    @property
    def pattern_size(self) -> tuple[int, int]:
        return self.inner_corners

    def object_points(self) -> np.ndarray:
        """Inner-corner coordinates on the board plane (z = 0), OpenCV's order, mm (N, 3)."""
        cols, rows = self.inner_corners
        xs, ys = np.meshgrid(np.arange(cols), np.arange(rows))
        return np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)]) * self.square_mm


@dataclass(frozen=True)
class LidarSpec:
    """Beam ``k`` has angle ``angle_min_deg + k * angle_step_deg``; angle 0 = LiDAR x axis."""

    angle_min_deg: float
    angle_max_deg: float
    angle_step_deg: float
    range_min_mm: float
    range_max_mm: float
    z_axis_hint: tuple[float, float, float] = DEFAULT_Z_AXIS_HINT
    #: the laser's colour in the stripe images (``lidar.laser_colour``): red, green, blue,
    #: gray (a NIR laser) or auto; see :func:`lidarcal.laser_colour.laser_response`
    laser_colour: str = "auto"

    @property
    def n_beams(self) -> int:
        return round((self.angle_max_deg - self.angle_min_deg) / self.angle_step_deg) + 1

    def angles_deg(self) -> np.ndarray:
        return self.angle_min_deg + np.arange(self.n_beams) * self.angle_step_deg


@dataclass(frozen=True)
class Position:
    """One turntable position: its angle and the files captured there."""

    index: int
    psi_deg: float
    stripe_image: Path
    scan: Path


@dataclass(frozen=True)
class MeasurementSpec:
    name: str
    sweep: Path
    object: str
    reference_diameter_mm: float | None


@dataclass
class Dataset:
    """A dataset folder, validated. Paths are absolute."""

    root: Path
    camera: CameraModel | None
    intrinsics_board: BoardSpec | None
    v_board: BoardSpec
    lidar: LidarSpec
    positions: list[Position]
    measurements: list[MeasurementSpec]
    image_size: tuple[int, int]
    raw: dict = field(repr=False, default_factory=dict)

    @property
    def board_image(self) -> Path:
        return self.root / "board.png"

    @property
    def dataset_json(self) -> Path:
        return self.root / "dataset.json"

    def intrinsics_images(self) -> list[Path]:
        d = self.root / "intrinsics"
        return sorted(d.glob("*.png")) if d.is_dir() else []

    def truth(self) -> dict | None:
        """``truth.json`` when present (synthetic datasets; evaluation only)."""
        p = self.root / "truth.json"
        return json.loads(p.read_text(encoding="utf-8-sig")) if p.is_file() else None


def read_json_object(path: Path, missing: str, fix: str, hint: str = "") -> dict:
    """The JSON object in ``path``, or :class:`DatasetError`: ``missing`` when there is no such
    file, ``not valid JSON (...); {fix}``, ``must hold a JSON object{hint}``."""
    if not path.is_file():
        raise DatasetError(path, missing)
    try:
        raw = json.loads(path.read_text(encoding="utf-8-sig"))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DatasetError(path, f"not valid JSON ({e}); {fix}") from None
    if not isinstance(raw, dict):
        raise DatasetError(path, f"must hold a JSON object{hint}")
    return raw


def _num(value: Any, path: Path, key: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise DatasetError(path, f"'{key}' must be a finite number, got {value!r}; fix dataset.json")
    if positive and value <= 0:
        raise DatasetError(path, f"'{key}' must be positive, got {value!r}; fix dataset.json")
    return float(value)


def _get(d: dict, key: str, path: Path, where: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise DatasetError(path, f"missing key '{where}{key}'; see dataset-format.md")
    return d[key]


def _board(d: Any, path: Path, key: str) -> BoardSpec:
    if not isinstance(d, dict):
        raise DatasetError(path, f"'{key}' must be an object with inner_corners and square_mm")
    ic = _get(d, "inner_corners", path, f"{key}.")
    if (not isinstance(ic, list) or len(ic) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 2 for v in ic)):
        raise DatasetError(path, f"'{key}.inner_corners' must be two integers >= 2, got {ic!r}")
    sq = _num(_get(d, "square_mm", path, f"{key}."), path, f"{key}.square_mm", positive=True)
    return BoardSpec((int(ic[0]), int(ic[1])), sq)


def _matrix(value: Any, shape: tuple[int, ...], path: Path, key: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise DatasetError(path, f"'{key}' must be numeric, got {value!r}") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise DatasetError(path, f"'{key}' must be a finite {shape} array, got {value!r}")
    return arr


def parse_camera(d: Any, path: Path) -> CameraModel:
    """The ``camera`` block of dataset.json."""
    if not isinstance(d, dict):
        raise DatasetError(path, "'camera' must be an object with image_size, K and dist")
    size = _get(d, "image_size", path, "camera.")
    if (not isinstance(size, list) or len(size) != 2
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)):
        raise DatasetError(path, f"'camera.image_size' must be [width, height], got {size!r}")
    K = _matrix(_get(d, "K", path, "camera."), (3, 3), path, "camera.K")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1) > 1e-9:
        raise DatasetError(path, "'camera.K' must have positive fx, fy and K[2][2] = 1")
    dist_raw = d.get("dist", [])
    if not isinstance(dist_raw, list) or len(dist_raw) > 8:
        raise DatasetError(path, f"'camera.dist' must be a list of up to 5 numbers, got {dist_raw!r}")
    dvals = _matrix(dist_raw, (len(dist_raw),), path, "camera.dist")
    if len(dvals) > 5 and np.any(dvals[5:] != 0):
        raise DatasetError(path, "'camera.dist' supports k1, k2, p1, p2, k3 only")
    dist = np.zeros(5)
    dist[: min(len(dvals), 5)] = dvals[:5]
    return CameraModel(K, dist, (int(size[0]), int(size[1])), source="dataset.json")


def load_dataset(root: str | os.PathLike) -> Dataset:
    """Read and validate a dataset folder (format ``lidarcal-dataset/1``).

    Checks dataset.json, positions.csv and that every referenced file exists;
    images and scans are read later, one position at a time.
    """
    root = Path(root).resolve()
    if not root.is_dir():
        raise DatasetError(root, "not a dataset folder (does not exist or is not a directory)")
    jpath = root / "dataset.json"
    raw = read_json_object(jpath, "missing; every dataset needs dataset.json (see "
                                  "dataset-format.md)", "fix or re-export it")
    fmt = raw.get("format")
    if fmt != DATASET_FORMAT:
        raise DatasetError(jpath, f"unknown format {fmt!r}, expected '{DATASET_FORMAT}'; "
                                  "convert the dataset or upgrade lidarcal")

    camera = parse_camera(raw["camera"], jpath) if raw.get("camera") is not None else None
    intr = _board(raw["intrinsics_board"], jpath, "intrinsics_board") \
        if raw.get("intrinsics_board") is not None else None
    v_board = _board(_get(raw, "v_board", jpath, ""), jpath, "v_board")

    ld = _get(raw, "lidar", jpath, "")
    if not isinstance(ld, dict):
        raise DatasetError(jpath, "'lidar' must be an object")
    vals = {k: _num(_get(ld, k, jpath, "lidar."), jpath, f"lidar.{k}")
            for k in ("angle_min_deg", "angle_max_deg", "angle_step_deg")}
    if vals["angle_step_deg"] <= 0 or vals["angle_max_deg"] <= vals["angle_min_deg"]:
        raise DatasetError(jpath, "'lidar' angles must satisfy angle_min < angle_max, step > 0")
    rmin = _num(ld.get("range_min_mm", 0.0), jpath, "lidar.range_min_mm")
    rmax = _num(ld.get("range_max_mm", 1e9), jpath, "lidar.range_max_mm", positive=True)
    if not 0 <= rmin < rmax:
        raise DatasetError(jpath, f"'lidar' needs 0 <= range_min_mm < range_max_mm, got {rmin:g} and "
                                  f"{rmax:g}; fix dataset.json")
    hint = ld.get("z_axis_hint", list(DEFAULT_Z_AXIS_HINT))
    hint_arr = _matrix(hint, (3,), jpath, "lidar.z_axis_hint")
    if np.linalg.norm(hint_arr) == 0:
        raise DatasetError(jpath, "'lidar.z_axis_hint' must not be the zero vector")
    colour = ld.get("laser_colour", "auto")
    if colour not in LASER_COLOURS:
        raise DatasetError(jpath, f"'lidar.laser_colour' must be one of {', '.join(LASER_COLOURS)}, "
                                  f"got {colour!r}")
    lidar = LidarSpec(vals["angle_min_deg"], vals["angle_max_deg"], vals["angle_step_deg"],
                      rmin, rmax, tuple(float(v) for v in hint_arr), colour)

    if camera is None and intr is None:
        raise DatasetError(jpath, "needs 'camera' (K, dist) or 'intrinsics_board' with "
                                  "intrinsics/*.png to calibrate the camera from")
    if camera is None and not sorted((root / "intrinsics").glob("*.png")):
        raise DatasetError(root / "intrinsics", "no 'camera' in dataset.json and no "
                                                "intrinsics/*.png views to calibrate from")

    image_size = camera.image_size if camera is not None else _image_size_from(root / "board.png")
    if not (root / "board.png").is_file():
        raise DatasetError(root / "board.png", "missing; the bright image of the V-board is required")

    positions = read_positions(root)
    measurements = _measurements(raw.get("measurements", []), root, jpath)
    return Dataset(root, camera, intr, v_board, lidar, positions, measurements, image_size, raw)


def _image_size_from(path: Path) -> tuple[int, int]:
    if not path.is_file():
        raise DatasetError(path, "missing; the bright image of the V-board is required")
    img = read_image(path)
    return (img.shape[1], img.shape[0])


def read_positions(root: Path) -> list[Position]:
    """``positions.csv``: index, psi_deg, stripe_image, scan; >= 3 rows, distinct angles."""
    ppath = root / "positions.csv"
    if not ppath.is_file():
        raise DatasetError(ppath, "missing; one row per turntable position is required")
    cols = read_csv_columns(ppath, ("index", "psi_deg", "stripe_image", "scan"),
                            "expected header index,psi_deg,stripe_image,scan")
    index = _numeric_column(cols["index"], ppath, "index", allow_empty=False, what="a number")
    psi = _numeric_column(cols["psi_deg"], ppath, "psi_deg", allow_empty=False, what="a number")
    for row, (img, scan) in enumerate(zip(cols["stripe_image"], cols["scan"])):
        if not img.strip() or not scan.strip():
            raise DatasetError(ppath, f"row {row + 2}: empty stripe_image or scan path")
    if len(psi) < 3:
        raise DatasetError(ppath, f"has {len(psi)} position(s); the method needs at least 3")
    for name, vals, what in (("psi_deg", psi, "turntable angles"), ("index", index, "indices")):
        seen: set[float] = set()
        for v in vals:
            if v in seen:
                shown = f"{v:g}" if name == "psi_deg" else f"{int(v)}"
                raise DatasetError(ppath, f"duplicate {name} {shown}; {what} must be distinct")
            seen.add(v)
    return [Position(int(i), float(a), (root / img.strip()).resolve(), (root / sc.strip()).resolve())
            for i, a, img, sc in zip(index, psi, cols["stripe_image"], cols["scan"])]


def read_csv_columns(path: Path, required: tuple[str, ...], expected: str,
                     gzipped: bool = False) -> dict[str, list[str]]:
    """The text of the ``required`` columns of a CSV file with a header row (other columns
    are ignored; blank lines are skipped; a missing trailing field reads as empty).

    Raises :class:`DatasetError` for an unreadable file, a missing column or a row with
    more fields than the header.
    """
    text = _read_text(path, gzipped)
    try:
        rows = [r for r in csv.reader(io.StringIO(text)) if r and any(c.strip() for c in r)]
    except csv.Error as e:
        raise _unreadable(path, gzipped, e) from None
    if not rows:
        raise DatasetError(path, f"not a readable CSV (the file is empty); {expected}")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in required if c not in header]
    if missing:
        raise DatasetError(path, f"missing column(s) {', '.join(missing)}; {expected}")
    n = len(header)
    for k, r in enumerate(rows[1:]):
        if len(r) > n:
            raise DatasetError(path, f"row {k + 2}: {len(r)} fields, the header has {n}; "
                                     "fix or re-export the file")
    where = [header.index(c) for c in required]
    body = rows[1:]
    return {c: [r[j] if j < len(r) else "" for r in body] for c, j in zip(required, where)}


def _read_text(path: Path, gzipped: bool = False) -> str:
    """The text of a (gzipped) CSV file, UTF-8 with or without a byte-order mark, line endings
    kept (the csv module reads them); :class:`DatasetError` when it cannot be read."""
    try:
        if gzipped:
            with gzip.open(path, "rt", newline="", encoding="utf-8-sig") as f:
                return f.read()
        with open(path, newline="", encoding="utf-8-sig") as f:
            return f.read()
    except (UnicodeDecodeError, OSError, EOFError) as e:
        raise _unreadable(path, gzipped, e) from None


def _unreadable(path: Path, gzipped: bool, e: Exception) -> DatasetError:
    return DatasetError(path, f"not a readable {'(gzip) ' if gzipped else ''}CSV "
                              f"({str(e).splitlines()[0] if str(e) else type(e).__name__})")


def _measurements(items: Any, root: Path, jpath: Path) -> list[MeasurementSpec]:
    if not isinstance(items, list):
        raise DatasetError(jpath, "'measurements' must be a list")
    out = []
    for i, m in enumerate(items):
        if not isinstance(m, dict) or "sweep" not in m:
            raise DatasetError(jpath, f"measurements[{i}] needs at least 'sweep'")
        ref = m.get("reference_diameter_mm")
        ref = None if ref is None else _num(ref, jpath, f"measurements[{i}].reference_diameter_mm")
        out.append(MeasurementSpec(str(m.get("name", Path(m["sweep"]).name.split(".")[0])),
                                   (root / m["sweep"]).resolve(), str(m.get("object", "disc")), ref))
    return out


def read_image(path: Path, image_size: tuple[int, int] | None = None, *,
               colour: str = "gray") -> np.ndarray:
    """An 8-bit PNG (16-bit: scaled by :func:`eight_bit_from_16`) as a grayscale uint8
    array; size checked if given.

    A BGR(A) image becomes gray by OpenCV's luminance weights (``colour="gray"``,
    for the bright board views) or by the brightest channel at each pixel
    (``colour="max"``, for the dark stripe images: a red or green laser keeps its
    full signal instead of 30 % or 59 % of it).
    """
    if colour not in ("gray", "max"):
        raise ValueError(f"colour must be 'gray' or 'max', got {colour!r}")
    img = _decode_8bit(path)
    if img.ndim == 3:
        if colour == "max":
            img = np.ascontiguousarray(img[:, :, :3].max(axis=2))
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return _checked_size(img, path, image_size)


def _decode_8bit(path: Path) -> np.ndarray:
    """``cv2.imread`` of an image as 8 bits per channel (gray or BGR(A)): 8-bit as stored,
    16-bit by :func:`eight_bit_from_16`; DatasetError otherwise."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing image; copy it again or drop this position")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(path, "cannot be decoded as an image (corrupt or not a PNG)")
    if img.dtype == np.uint16:
        return eight_bit_from_16(img, path)
    if img.dtype != np.uint8:
        raise DatasetError(path, f"expected an 8- or 16-bit image, got {img.dtype}; write "
                                 "8-bit gray or BGR PNGs")
    return img


#: A 16-bit image whose values all stay below this holds a 10- or 12-bit sensor's raw values
#: (PNG requires samples scaled to the full 16-bit range): refused, never read near black
MIN_16BIT_TOP = 4096


def eight_bit_from_16(img: np.ndarray, path: Path) -> np.ndarray:
    """A 16-bit image (PNG's full 0-65535 range) as uint8: ``round(v / 257)``, so that
    65535 -> 255 and an 8-bit image stored as 16 bits (``v * 257``) comes back exactly.

    Values that all stay below ``MIN_16BIT_TOP`` (a 10- or 12-bit camera's raw counts
    written unscaled, against the PNG specification) would read as an almost black image
    (at most 16 of 255): DatasetError naming the file instead of a guess of the bit depth.
    """
    top = int(img[..., :3].max()) if img.ndim == 3 else int(img.max())
    if top < MIN_16BIT_TOP:
        raise DatasetError(path, f"16-bit image whose largest value is {top} (below "
                                 f"{MIN_16BIT_TOP}): a 10- or 12-bit camera's raw values not "
                                 "scaled to 16 bits? Scale them to 0-65535 (x 16 for 12 bits) "
                                 "or write an 8-bit PNG")
    return ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)


def _checked_size(img: np.ndarray, path: Path, image_size: tuple[int, int] | None) -> np.ndarray:
    if image_size is not None and (img.shape[1], img.shape[0]) != tuple(image_size):
        raise DatasetError(Path(path), f"image is {img.shape[1]}x{img.shape[0]}, expected "
                                 f"{image_size[0]}x{image_size[1]} (camera.image_size)")
    return img


def read_stripe_image(path: Path, image_size: tuple[int, int] | None = None,
                      laser_colour: str = "auto") -> np.ndarray:
    """A stripe image as uint8: gray images as they are; colour images by
    :func:`lidarcal.laser_colour.laser_response` (a dark frame by its brightest channel, a
    lights-on photo by the laser colour's excess over the other channels)."""
    if laser_colour == "gray":
        return read_image(path, image_size, colour="max")
    img = _decode_8bit(path)  # decoded once: a gray image is used as it is
    if img.ndim == 2:
        return _checked_size(img, path, image_size)
    return _checked_size(laser_response(img[:, :, :3], laser_colour), path, image_size)


def spread_indices(n: int, k: int) -> list[int]:
    """At most ``k`` distinct indices of ``range(n)`` spread evenly over it, both ends
    included (``np.linspace`` rounded), ascending."""
    if n <= 0 or k <= 0:
        return []
    return sorted({round(v) for v in np.linspace(0, n - 1, min(k, n))})


class ImagePrefetch:
    """Stripe images decoded by a background thread while the caller does other work.

    ``cv2.imread`` releases the GIL, so decoding overlaps with imports and board
    detection in the main thread. Images beyond ``max_bytes`` are left to be read
    on demand; an unreadable image is kept as its :class:`DatasetError`, raised by
    :meth:`get` (so the caller's per-position error policy applies unchanged).
    Call :meth:`join` before forking worker processes (they then share the images).

    ``first``: indices into ``positions`` decoded before the others (e.g. the few images the
    caller reads before it forks, :func:`spread_indices`), so it need not decode them itself.

    Use it as a context manager (or call :meth:`close`): on leaving, decoding stops
    after the image in hand and the thread is joined, so no thread is left inside
    OpenCV when the interpreter exits (which aborts the process, status 134).

    With ``image_size`` known, the images are kept in one block (``(n, height, width)``
    uint8, one slice each) rather than one allocation each: numpy asks the kernel for
    huge pages for a block this large, so keeping 87 images of 2 MB costs ~90 page
    faults instead of ~43,000 (0.05-0.07 s of CPU), and forked workers inherit a
    fraction of the page tables (fork and exit of a child measured 8-13 ms instead of
    25-31 ms). An image of another shape or type is kept as decoded.
    """

    def __init__(self, positions: list[Position], image_size: tuple[int, int] | None,
                 max_bytes: float = 1 << 30, laser_colour: str = "auto",
                 first: Sequence[int] = ()):
        import threading

        self._images: dict[int, np.ndarray | DatasetError] = {}
        self._size = image_size
        self._colour = laser_colour
        n_max = len(positions)
        if image_size is not None:
            n_max = int(max_bytes // max(image_size[0] * image_size[1], 1))
        # ``first`` (indices into ``positions``) are decoded before the others, in that order
        head = list(dict.fromkeys(k for k in first if 0 <= k < len(positions)))
        order = head + sorted(set(range(len(positions))) - set(head))
        self._todo = [positions[k] for k in order[:n_max]]
        self._block = None if image_size is None or not self._todo else \
            np.empty((len(self._todo), image_size[1], image_size[0]), np.uint8)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lidarcal-prefetch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        mark("decode-start")
        for k, p in enumerate(self._todo):
            if self._stop.is_set():
                break
            try:
                self._images[p.index] = self._keep(k, read_stripe_image(
                    p.stripe_image, self._size, self._colour))
            except DatasetError as e:
                self._images[p.index] = e
        mark("decode-end", decoded=len(self._images), of=len(self._todo))

    def _keep(self, k: int, img: np.ndarray) -> np.ndarray:
        """Image ``k`` copied into its slice of the block (when it fits there)."""
        if self._block is None or img.shape != self._block.shape[1:] or img.dtype != np.uint8:
            return img
        self._block[k] = img
        return self._block[k]

    def join(self) -> ImagePrefetch:
        """Wait until every image is decoded."""
        self._thread.join()
        return self

    def close(self) -> None:
        """Stop decoding (after the image in hand) and join the thread; idempotent.
        Images not decoded by then are read on demand by :meth:`get`'s caller."""
        self._stop.set()
        self._thread.join()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def get(self, pos: Position) -> np.ndarray | None:
        """The decoded image of ``pos`` (None: not prefetched, read it yourself)."""
        img = self._images.get(pos.index)
        if isinstance(img, DatasetError):
            raise img
        return img


def prefetch_stripe_images(ds: Dataset, positions: list[Position]) -> ImagePrefetch:
    """The stripe images of ``positions`` decoding in a background thread, as ``calibrate``
    reads them: the :data:`REFLECTANCE_IMAGES` the reflectance ratio is pooled from
    (:func:`spread_indices`, before the workers fork) first, then the others."""
    return ImagePrefetch(positions, ds.image_size, laser_colour=ds.lidar.laser_colour,
                         first=spread_indices(len(positions), REFLECTANCE_IMAGES))


def read_scan(path: Path, lidar: LidarSpec | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``scans/NNNN.csv`` as ``(angle_deg, range_mm)``; no-return beams get range NaN.

    ``range_mm`` 0 or empty means no return. Ranges outside
    ``[range_min_mm, range_max_mm]`` are also marked as no return.
    Non-numeric, NaN or negative ranges are errors.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing scan; copy it again or drop this position")
    plain = _plain_scan_columns(_read_text(path))
    if plain is not None:  # every field a finite number: the checks below see the same values
        ang, rng = plain[0], _ranges([], path, lidar, plain[1])
    else:  # the careful reader, which names the offending row
        cols = read_csv_columns(path, ("angle_deg", "range_mm"),
                                "expected header angle_deg,range_mm")
        if not cols["angle_deg"]:
            raise DatasetError(path, "scan has no rows")
        ang = _numeric_column(cols["angle_deg"], path, "angle_deg", allow_empty=False)
        rng = _ranges(cols["range_mm"], path, lidar)
    if np.any(np.diff(ang) <= 0):
        raise DatasetError(path, "angles are not strictly ascending; one row per beam expected")
    if lidar is not None:
        _check_beam_angles(path, ang, lidar)
    return ang, rng


def _plain_scan_columns(text: str) -> tuple[np.ndarray, np.ndarray] | None:
    """``(angle_deg, range_mm)`` of a plain scan CSV by numpy's C reader (``np.loadtxt``), or
    None when the file needs :func:`read_csv_columns`'s careful reading.

    Plain: a header naming both columns, then rows of as many fields as the header, each a
    finite number (blank lines allowed). Anything else (quotes, empty fields, short or long
    rows, text, ``inf``/``nan``, no rows) gives None, and the careful reader then reads the
    same values or names the offending row, as it always did. ``np.loadtxt`` accepts no
    number that ``float`` rejects and rounds as ``float`` does (both correctly rounded).
    """
    if '"' in text:
        return None
    head, _, body = text.lstrip("\r\n").partition("\n")
    header = [h.strip() for h in head.split(",")]
    if "angle_deg" not in header or "range_mm" not in header or not body.strip():
        return None
    try:
        data = np.loadtxt(io.StringIO(body), delimiter=",", comments=None, ndmin=2)
    except ValueError:
        return None
    if data.shape[0] == 0 or data.shape[1] != len(header) or not np.isfinite(data).all():
        return None
    return data[:, header.index("angle_deg")], data[:, header.index("range_mm")]


def _check_beam_angles(path: Path, ang: np.ndarray, lidar: LidarSpec) -> None:
    """The scan's beams lie on dataset.json's layout (beam ``k`` at ``angle_min_deg + k *
    angle_step_deg``): not closer than half a step on average (angles in radians) and inside
    ``angle_min_deg..angle_max_deg`` (two steps of slack). Rows may be omitted or rounded."""
    step = lidar.angle_step_deg
    if len(ang) >= 2 and (ang[-1] - ang[0]) / (len(ang) - 1) < 0.5 * step:
        raise DatasetError(path, f"beam angles {ang[0]:g}..{ang[-1]:g} are "
                                 f"{(ang[-1] - ang[0]) / (len(ang) - 1):.3g} apart on average, less "
                                 f"than lidar.angle_step_deg {step:g} of dataset.json; are they in "
                                 "radians? angle_deg must be degrees")
    tol = 2 * step + 0.01
    if ang[0] < lidar.angle_min_deg - tol or ang[-1] > lidar.angle_max_deg + tol:
        raise DatasetError(path, f"beam angles {ang[0]:g}..{ang[-1]:g} deg lie outside dataset.json's "
                                 f"lidar.angle_min_deg..angle_max_deg ({lidar.angle_min_deg:g}.."
                                 f"{lidar.angle_max_deg:g}); fix dataset.json's lidar block or the scan")


_NON_FINITE = {"inf", "infinity", "nan"}  # range_mm spellings of "no return" (_ranges)


def _ranges(text: list[str], path: Path, lidar: LidarSpec | None,
            values: np.ndarray | None = None) -> np.ndarray:
    """Range column (its text, or its finite ``values``): empty or 0 = no return, NaN (as are
    ranges outside the LiDAR's limits). ``inf``, ``-inf`` and ``nan`` are no return too: ROS
    exports a LaserScan's beams that way (REP 117: +inf nothing within range_max, -inf too
    close, NaN an invalid measurement)."""
    if values is None:
        text = ["0" if t.strip().lower().lstrip("+-") in _NON_FINITE else t for t in text]
    rng = _numeric_column(text, path, "range_mm", allow_empty=True) if values is None \
        else values.copy()
    if np.any(rng < 0):
        row = int(np.flatnonzero(rng < 0)[0])
        raise DatasetError(path, f"row {row + 2}: negative range {rng[row]:g}; ranges must be >= 0")
    no_return = rng == 0
    if lidar is not None:
        outside = (rng < lidar.range_min_mm) | (rng > lidar.range_max_mm)
        # a whole scan outside the limits is a unit problem, not a scene (10: not a stray beam)
        if np.all(outside | no_return) and np.count_nonzero(~no_return) >= 10:
            raise DatasetError(path, f"every return is outside range_min_mm..range_max_mm "
                                     f"({lidar.range_min_mm:g}..{lidar.range_max_mm:g}; median range "
                                     f"{np.median(rng[~no_return]):g}); ranges must be in mm")
        no_return |= outside
    rng[no_return] = np.nan
    return rng


def _numeric_column(text: list[str], path: Path, name: str, allow_empty: bool,
                    what: str = "a finite number") -> np.ndarray:
    """Floats from CSV fields; an empty field is 0 when ``allow_empty``; anything that is not
    a finite number raises :class:`DatasetError` naming the row."""
    if allow_empty:
        text = [t if t.strip() else "0" for t in text]
    try:
        vals = np.array(text, dtype=float)
    except ValueError:
        vals = np.array([_to_float(t) for t in text], dtype=float)
    bad = ~np.isfinite(vals)
    if np.any(bad):
        row = int(np.flatnonzero(bad)[0])
        raise DatasetError(path, f"row {row + 2}: '{name}' is not {what} "
                                 f"({text[row]!r}); fix or re-export the file")
    return vals


def _to_float(t: str) -> float:
    try:
        return float(t)
    except ValueError:
        return math.nan


def read_sweep(path: Path, lidar: LidarSpec | None = None):
    """``measure/*.csv.gz``: long form psi_deg, angle_deg, range_mm (NaN = no return), as a
    :class:`pandas.DataFrame`."""
    import pandas as pd

    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing sweep file listed in dataset.json 'measurements'")
    need = ("psi_deg", "angle_deg", "range_mm")
    try:  # fast path: pandas' C parser; only an empty field reads as NaN (= no return)
        df = pd.read_csv(path, usecols=list(need), keep_default_na=False, na_values=[""])
        fast = all(df[c].dtype.kind in "if" for c in need) and not df.empty
    except (ValueError, UnicodeDecodeError, OSError, EOFError, pd.errors.ParserError):
        fast = False
    if fast and np.isfinite(df[list(need)].fillna(0.0).to_numpy(float)).all():
        psi, ang = df["psi_deg"].to_numpy(float), df["angle_deg"].to_numpy(float)
        rng = _ranges([], path, lidar, df["range_mm"].fillna(0.0).to_numpy(float))
    else:  # the careful path, which names the offending row
        cols = read_csv_columns(path, need, "expected header psi_deg,angle_deg,range_mm",
                                gzipped=path.suffix == ".gz")
        psi = _numeric_column(cols["psi_deg"], path, "psi_deg", allow_empty=False)
        ang = _numeric_column(cols["angle_deg"], path, "angle_deg", allow_empty=False)
        rng = _ranges(cols["range_mm"], path, lidar)
    return pd.DataFrame({"psi_deg": psi, "angle_deg": ang, "range_mm": rng})


def write_atomic(path: str | os.PathLike, write: Callable[[Path], object],
                 suffix: str | None = None) -> Path:
    """Call ``write(tmp)`` on a temporary file beside ``path``, then rename it to ``path``
    (never half-written; the temporary file is removed on any error). ``suffix``: the
    temporary file's (default ``path``'s own, for writers that infer the format from it)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix if suffix is None
                               else suffix, dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        os.chmod(tmp, 0o666 & ~current_umask())  # mkstemp's 0600 would survive the rename
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def current_umask() -> int:
    """The process's umask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write JSON to a temporary file in the same folder, then rename (never half-written)."""
    text = json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n"
    write_atomic(path, lambda tmp: tmp.write_text(text), ".tmp")


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")
