"""A folder of views for the one-board calibration (``lidarcal planes``).

Contract: the folder holds pairs ``NAME.png`` (or ``.jpg``/``.jpeg``) + ``NAME.csv``
taken at the same moment. The CSV has a header and either the columns
``angle_deg,range_mm`` (one row per beam, ascending angles; 0 or empty = no
return) or ``x_mm,y_mm`` (points in the LiDAR's scan plane, x = range cos(angle),
y = range sin(angle); both 0 or empty = no return). Other columns are ignored.
An image without a scan (or the reverse) is an error naming the file.
``lidarcal import BAG --views`` writes such a folder from a ROS bag
(:mod:`lidarcal.io.bag_views`; its ``views.json``, ``camera.json`` and, with ``--pattern`` and
``--square-mm``, ``board.json`` are not pairs).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .dataset import DatasetError, _delimiter, _ranges, read_csv_columns, read_scan

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class ViewPair:
    """One view: the photo's path and the scan as beams (``range_mm`` NaN = no return)."""

    name: str
    image_path: Path
    scan_path: Path
    angle_deg: np.ndarray  # shape (N,)
    range_mm: np.ndarray  # shape (N,)


def read_scan_any(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A scan CSV as ``(angle_deg, range_mm)``: columns ``angle_deg,range_mm`` or ``x_mm,y_mm``.

    ``x_mm,y_mm`` rows become beams by ``angle = atan2(y, x)``, ``range = hypot(x, y)``
    (eq. 6 inverted), sorted by angle; a row with both 0 or empty is no return and
    is dropped.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "missing scan; every photo needs NAME.csv beside it")
    try:
        with open(path, encoding="utf-8-sig", errors="replace") as f:
            first = f.readline()
    except OSError as e:
        raise DatasetError(path, f"cannot be read ({e.strerror or e}); copy it again or re-export "
                                 "it") from None
    header = [h.strip() for h in first.split(_delimiter(first))]
    if "angle_deg" in header and "range_mm" in header:
        return read_scan(path)
    if not ("x_mm" in header and "y_mm" in header):
        raise DatasetError(path, f"header {','.join(header)!r}: expected columns angle_deg,range_mm "
                                 "or x_mm,y_mm; re-export the scan with one of these headers")
    cols = read_csv_columns(path, ("x_mm", "y_mm"), "expected header x_mm,y_mm")
    vals = []
    for name in ("x_mm", "y_mm"):
        text = [t if t.strip() else "0" for t in cols[name]]
        try:
            v = np.array(text, dtype=float)
        except ValueError:
            bad = next(k for k, t in enumerate(text) if not _is_float(t))
            raise DatasetError(path, f"row {bad + 2}: '{name}' is not a number ({text[bad]!r}); "
                                     "fix or re-export the file") from None
        if not np.all(np.isfinite(v)):
            bad = int(np.flatnonzero(~np.isfinite(v))[0])
            raise DatasetError(path, f"row {bad + 2}: '{name}' is not finite; fix or re-export "
                                     "the file")
        vals.append(v)
    x, y = vals
    keep = (x != 0) | (y != 0)
    if np.count_nonzero(keep) < 2:
        raise DatasetError(path, "scan has fewer than 2 returns; check the file")
    ang = np.degrees(np.arctan2(y[keep], x[keep]))
    rng = _ranges([], path, None, np.hypot(x[keep], y[keep]))  # the unit check
    order = np.argsort(ang, kind="stable")
    ang, rng = ang[order], rng[order]
    if np.any(np.diff(ang) <= 0):
        raise DatasetError(path, "two points share one beam angle; one point per beam expected")
    return ang, rng


def _is_float(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def read_view_pairs(folder: str | Path) -> list[ViewPair]:
    """Every ``NAME.png|jpg`` + ``NAME.csv`` pair of ``folder``, sorted by name.

    Raises :class:`DatasetError` when the folder is missing, holds no pairs, or a
    photo lacks its scan (or a scan its photo).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(folder, "not a folder; expected a folder of NAME.png + NAME.csv pairs")
    images = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_SUFFIXES}
    scans = {p.stem: p for p in sorted(folder.glob("*.csv"))}
    lonely_img = sorted(set(images) - set(scans))
    lonely_scan = sorted(set(scans) - set(images))
    if lonely_img:
        raise DatasetError(images[lonely_img[0]], f"photo without its scan {lonely_img[0]}.csv; "
                                                  "add the scan or remove the photo")
    if lonely_scan:
        raise DatasetError(scans[lonely_scan[0]], f"scan without its photo {lonely_scan[0]}.png; "
                                                  "add the photo or remove the scan")
    if not images:
        raise DatasetError(folder, "holds no NAME.png|jpg + NAME.csv pairs; put each photo beside "
                                   "its scan, under the same name")
    out = []
    for name in sorted(images):
        ang, rng = read_scan_any(scans[name])
        out.append(ViewPair(name, images[name], scans[name], ang, rng))
    return out


#: the optional file of a view-pairs folder that names its board (inner corners, square size)
BOARD_JSON = "board.json"


def board_spec(folder: str | Path, pattern: tuple[int, int] | None = None,
               square_mm: float | None = None):
    """The chessboard of a view-pairs folder: ``pattern`` and ``square_mm`` when both are given,
    else the folder's ``board.json`` ``{"inner_corners": [8, 5], "square_mm": 100}`` (the keys
    of dataset.json's boards); one of them given alone overrides that key of the file."""
    from .dataset import BoardSpec, _board, read_json_object

    if pattern is not None and square_mm is not None:
        if square_mm <= 0:
            raise DatasetError(Path(folder), f"square size must be positive, got {square_mm:g}")
        return BoardSpec(tuple(pattern), float(square_mm))
    if not Path(folder).is_dir():
        raise DatasetError(Path(folder), "not a folder; expected a folder of NAME.png + NAME.csv "
                                         "pairs")
    path = Path(folder) / BOARD_JSON
    fix = 'write {"inner_corners": [8, 5], "square_mm": 100} there (the board\'s inner corners ' \
          'and square side, mm) or give --pattern and --square-mm'
    raw = read_json_object(path, f"missing: no board given; {fix}", fix)
    board = _board(raw, path, "board")
    if pattern is not None:
        board = BoardSpec(tuple(pattern), board.square_mm)
    if square_mm is not None:
        board = BoardSpec(board.inner_corners, float(square_mm))
    return board
