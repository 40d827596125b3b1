"""What the bag imports write: scans as CSV text, sweeps as gzipped CSV, PNGs, the
intrinsics photos, and the output folder written atomically (a temporary folder beside it,
renamed at the end: :func:`prepare_out`, :func:`finish_out`).
"""

from __future__ import annotations

import gzip
import io
import math
import os
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from .dataset import DatasetError, current_umask, decode_image


def fmt_range(v: float) -> str:
    return f"{v:.1f}" if math.isfinite(v) else "0"


def scan_csv_text(angles_deg: np.ndarray, range_mm: np.ndarray) -> str:
    """``scans/NNNN.csv``: angle_deg (6 decimals), range_mm (0.1 mm; 0 = no return)."""
    return "angle_deg,range_mm\n" + "".join(
        f"{a:.6f},{fmt_range(r)}\n" for a, r in zip(angles_deg.tolist(), range_mm.tolist()))


def write_png(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise OSError(f"{path}: cannot write image")


def prepare_out(out: Path, overwrite: bool) -> Path:
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise DatasetError(out, "exists and is not empty; choose another --out or pass --overwrite")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.import-", dir=out.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp's 0700 would survive the rename
    return tmp


def finish_out(tmp: Path, out: Path) -> None:
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


def sweep_csv_gz(rows: list[tuple[float, np.ndarray]], angles_deg: np.ndarray) -> bytes:
    """``measure/NAME.csv.gz``: long form psi_deg, angle_deg, range_mm (0 = no return)."""
    ang = [f"{a:.6f}" for a in angles_deg.tolist()]
    parts = ["psi_deg,angle_deg,range_mm\n"]
    for psi, r in rows:
        p = f"{psi:.6f}"
        parts.append("".join(f"{p},{a},{fmt_range(v)}\n" for a, v in zip(ang, r.tolist())))
    buf = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=6) as f:
        f.write("".join(parts).encode())
    return buf.getvalue()


def copy_intrinsics(src: Path, dst: Path) -> None:
    """The intrinsics photos as ``intrinsics/*.png`` (other image formats converted)."""
    dst.mkdir()
    n = 0
    for p in sorted(src.iterdir()):
        ext = p.suffix.lower()
        if ext == ".png":
            shutil.copyfile(p, dst / p.name)
        elif ext in (".jpg", ".jpeg", ".bmp", ".tif", ".tiff"):
            img = decode_image(p, fix="copy the intrinsics photo again or remove it")
            write_png(dst / f"{p.stem}.png", img)
        else:
            continue
        n += 1
    if n == 0:
        raise DatasetError(src, "holds no .png/.jpg/.bmp/.tif chessboard photos (RIG.json "
                                "intrinsics); put the photos there or remove 'intrinsics'")
