"""``simulate``: write a complete dataset folder in the contract (``docs/dataset-format.md``)."""

from __future__ import annotations

import gzip
import io
import shutil
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..io.dataset import DATASET_FORMAT, write_json_atomic
from .config import RigConfig, get_rig
from .lidar import beam_angles_deg, simulate_scans
from .render import (
    RayMap,
    albedo_table,
    expose_bright,
    expose_dark,
    render_view,
    smooth_field,
    stripe_signal,
)
from .scene import InfinitePlane
from .truth import (
    STREAM_BOARD_IMAGE,
    STREAM_FIELD,
    STREAM_SCAN,
    STREAM_STRIPE,
    STREAM_SWEEP,
    RigTruth,
    _rng,
    make_truth,
)

STREAM_INTRINSICS_IMAGE = 9
# zlib level 9; noisy bright images compress best with Huffman-only coding, sparse dark frames
# with run-length matches on unfiltered rows (both also fast)
_PNG_BRIGHT = [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
_PNG_DARK = [cv2.IMWRITE_PNG_COMPRESSION, 9, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_RLE,
             cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
_OWNED = ("dataset.json", "positions.csv", "truth.json", "board.png", "stripes", "scans", "measure",
          "intrinsics")


def fmt_psi(x: float) -> str:
    """Turntable angle as written: 2 decimals when exact, else 4."""
    s = f"{x:.2f}"
    return s if abs(float(s) - x) < 1e-9 else f"{x:.4f}"


def _fmt_ranges(r: np.ndarray) -> list[str]:
    return ["0" if v == 0 else f"{v:.1f}" for v in r.tolist()]


def _write_png(path: Path, img: np.ndarray, dark: bool = False) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), img, _PNG_DARK if dark else _PNG_BRIGHT):
        raise OSError(f"{path}: cannot write image")


def scan_csv(angles_deg: np.ndarray, ranges_mm: np.ndarray) -> str:
    """``scans/NNNN.csv`` text: ``angle_deg,range_mm``, angles with 6 decimals, ranges with 1 (0 = none)."""
    ang = [f"{a:.6f}" for a in angles_deg.tolist()]
    return "angle_deg,range_mm\n" + "".join(f"{a},{r}\n" for a, r in zip(ang, _fmt_ranges(ranges_mm)))


def sweep_csv_gz(psi_deg: np.ndarray, angles_deg: np.ndarray, ranges_mm: np.ndarray) -> bytes:
    """``measure/*.csv.gz`` bytes: long form ``psi_deg,angle_deg,range_mm``; gzip with mtime 0 (reproducible)."""
    ang = [f"{a:.6f}" for a in angles_deg.tolist()]
    parts = ["psi_deg,angle_deg,range_mm\n"]
    for psi, row in zip(psi_deg.tolist(), ranges_mm):
        p = fmt_psi(psi)
        parts.append("".join(f"{p},{a},{r}\n" for a, r in zip(ang, _fmt_ranges(row))))
    buf = io.BytesIO()
    with gzip.GzipFile(filename="", mode="wb", fileobj=buf, mtime=0, compresslevel=9) as f:
        f.write("".join(parts).encode())
    return buf.getvalue()


def z_axis_hint(truth: RigTruth) -> list[int]:
    """``lidar.z_axis_hint`` as a user would write it: the camera axis (``[0, -1, 0]`` = up)
    nearest to the LiDAR's true z axis at the middle position (``[0, 1, 0]`` upside down)."""
    z = truth.pose_ref.z_axis
    i = int(np.argmax(np.abs(z)))
    return [int(np.sign(z[i])) if j == i else 0 for j in range(3)]


def dataset_json(truth: RigTruth, with_intrinsics: bool, with_sweeps: bool) -> dict:
    """The ``dataset.json`` of a simulated dataset (rig description, no truth)."""
    rig = truth.rig
    out: dict = {"format": DATASET_FORMAT}
    if rig.camera_in_dataset or not with_intrinsics:
        out["camera"] = {"image_size": list(rig.image_size), "K": truth.K.tolist(), "dist": truth.dist.tolist()}
    if with_intrinsics:
        out["intrinsics_board"] = {"inner_corners": list(rig.intrinsics_inner_corners),
                                   "square_mm": rig.intrinsics_square_mm}
    out["v_board"] = {"inner_corners": list(rig.v_inner_corners), "square_mm": rig.v_square_mm}
    out["lidar"] = {"angle_min_deg": rig.lidar_angle_min_deg, "angle_max_deg": rig.lidar_angle_max_deg,
                    "angle_step_deg": rig.lidar_angle_step_deg, "range_min_mm": rig.lidar_range_min_mm,
                    "range_max_mm": rig.lidar_range_max_mm, "z_axis_hint": z_axis_hint(truth)}
    out["measurements"] = [{"name": d.name, "sweep": f"measure/{d.name}.csv.gz", "object": "disc",
                            "reference_diameter_mm": float(2 * d.disc.radius)}
                           for d in (truth.discs if with_sweeps else [])]
    out["synthetic"] = {"generator": "lidarcal.synthetic", "rig": rig.name, "seed": truth.seed}
    return out


def _prepare(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out}: folder is not empty; pass overwrite=True (--overwrite) "
                                  "to replace the dataset in it")
        for name in _OWNED:  # only what simulate writes; other files are left alone
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def simulate(out: str | Path, seed: int = 0, rig: str | RigConfig = "paper", *,
             n_positions: int | None = None, with_intrinsics: bool | None = None,
             with_sweeps: bool = True, overwrite: bool = False,
             positions: Sequence[int] | None = None) -> Path:
    """Simulate a rig and write a complete dataset folder (with ``truth.json``); returns its path.

    Deterministic: the same ``seed``, rig and options give the same bytes.
    Every image, scan and sweep has its own random stream, so ``positions``
    (a subset of position indices) renders exactly the same files as the
    full run for those positions (positions.csv and truth.json then list only
    them). Refuses to write into a non-empty folder unless ``overwrite``.
    """
    rig = get_rig(rig)
    if n_positions is not None:
        rig = rig.with_(n_positions=int(n_positions))
    if with_intrinsics is None:
        with_intrinsics = rig.n_intrinsics_views > 0
    out = Path(out)
    truth = make_truth(seed, rig, with_discs=with_sweeps, with_intrinsics=with_intrinsics)
    n = len(truth.psi_deg)
    idx = list(range(n)) if positions is None else sorted({int(i) for i in positions})
    if any(i < 0 or i >= n for i in idx):
        raise ValueError(f"positions must be in 0..{n - 1}, got {positions}")
    _prepare(out, overwrite)

    rays = RayMap.build(truth.K, truth.dist, rig.image_size)
    view = render_view(rays, truth.surfaces, albedo_table(rig, "bright"), rig.supersample,
                       rig.antialias)
    _write_png(out / "board.png", expose_bright(view.albedo, rig, _rng(seed, STREAM_BOARD_IMAGE)))

    # stripes and scans
    ambient = view.albedo * np.float32(rig.ambient_dn)
    modulation = None
    if rig.albedo_modulation > 0:
        f = smooth_field(view.albedo.shape, 40.0, _rng(seed, STREAM_FIELD))
        modulation = np.exp(rig.albedo_modulation * f).astype(np.float32)
    # stripe brightness falls off as (r_ref / r)^2; r_ref = the nearest board corner
    r_ref = float(min(np.linalg.norm(b.rect.corners() - truth.pose_ref.T, axis=1).min() for b in truth.boards))
    angles = beam_angles_deg(rig)
    rows = ["index,psi_deg,stripe_image,scan\n"]
    for i in idx:
        pose = truth.pose_at(truth.psi_true_deg[i])
        rng = _rng(seed, STREAM_STRIPE, i)
        sig = stripe_signal(rays, view, truth.surfaces, pose, rig, truth.sheet_sigma_mm, r_ref, rng,
                            modulation)
        _write_png(out / "stripes" / f"{i:04d}.png", expose_dark(ambient + sig, rig, rng), dark=True)
        ranges = simulate_scans(truth.surfaces, pose.R, pose.T, rig, _rng(seed, STREAM_SCAN, i))[0]
        (out / "scans").mkdir(exist_ok=True)
        (out / "scans" / f"{i:04d}.csv").write_text(scan_csv(angles, ranges))
        rows.append(f"{i},{fmt_psi(truth.psi_deg[i])},stripes/{i:04d}.png,scans/{i:04d}.csv\n")
    (out / "positions.csv").write_text("".join(rows))

    if with_intrinsics:
        table = albedo_table(rig, "bright")
        for j, v in enumerate(truth.intrinsics_views):
            z_back = float(v.board.origin[2]) + 600.0
            wall = InfinitePlane(np.array([0.0, 0.0, 1.0]), z_back)
            iv = render_view(rays, [v.board, wall], table, rig.supersample, rig.antialias)
            img = expose_bright(iv.albedo, rig, _rng(seed, STREAM_INTRINSICS_IMAGE, j))
            _write_png(out / "intrinsics" / f"view_{j + 1:02d}.png", img)

    if with_sweeps:
        (out / "measure").mkdir(exist_ok=True)
        for j, d in enumerate(truth.discs):
            R, T = truth.poses_at(d.psi_true_deg)
            ranges = simulate_scans(d.surfaces, R, T, rig, _rng(seed, STREAM_SWEEP, j))
            (out / "measure" / f"{d.name}.csv.gz").write_bytes(sweep_csv_gz(d.psi_deg, angles, ranges))

    write_json_atomic(out / "dataset.json", dataset_json(truth, with_intrinsics, with_sweeps))
    write_json_atomic(out / "truth.json", truth.to_dict(idx))
    return out
