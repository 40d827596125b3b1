"""``lidarcal planes`` on the real TAPAS views perturbed as other recordings differ.

Each perturbation writes a copy of the views folder (photos and/or scans changed), runs
:func:`lidarcal.planes.run_planes` on it and compares the pose with the unperturbed fit: the
difference in the unperturbed fit's sigmas (Mahalanobis over its 6x6 covariance, and per axis),
the views used, the RMS and the warnings; or the one-line error. A perturbed result is fine when
it is within ~3 sigma of the unperturbed one, or fails / warns honestly.

    .venv/bin/python scripts/real_robustness.py [--only NAME ...] [--wall-mm 40 80 150]
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidarcal.degeneracy import pose_difference
from lidarcal.io.dataset import BoardSpec, DatasetError
from lidarcal.planes import run_planes

SRC = REPO / "data" / "real_tapas"
NAMES = [f"{k:02d}" for k in range(7)]


def _scan(name: str) -> tuple[np.ndarray, np.ndarray]:
    a = np.loadtxt(SRC / f"{name}.csv", delimiter=",", skiprows=1)
    return a[:, 0], a[:, 1]


def _write_scan(path: Path, ang: np.ndarray, rng: list, extra: dict | None = None) -> None:
    cols = {"angle_deg": [f"{x:.2f}" for x in ang], "range_mm": [str(r) for r in rng]}
    cols.update(extra or {})
    keys = list(cols)
    lines = [",".join(keys)] + [",".join(cols[k][i] for k in keys) for i in range(len(ang))]
    path.write_text("\n".join(lines) + "\n")


def _copy(dst: Path) -> None:
    for p in SRC.iterdir():
        if p.suffix in (".png", ".csv", ".json"):
            shutil.copy(p, dst / p.name)


def _photos(dst: Path, fn, suffix: str = ".png", params=()) -> None:
    for n in NAMES:
        img = cv2.imread(str(SRC / f"{n}.png"), cv2.IMREAD_UNCHANGED)
        (dst / f"{n}.png").unlink()
        cv2.imwrite(str(dst / f"{n}{suffix}"), fn(img, n), list(params))


def _scans(dst: Path, fn) -> None:
    for n in NAMES:
        ang, rng = _scan(n)
        fn(dst / f"{n}.csv", ang, rng, n)


def _board_run(ang, rng, full, name):
    """Beams of the board in view ``name`` (the unperturbed fit's choice)."""
    v = next(v for v in full.views if v.name == name)
    return v.beams


def perturbations(full, walls_mm: tuple[float, ...] = (40.0,)) -> dict:
    """name -> function(dst folder) that perturbs the copied views there; one wall perturbation
    per distance (mm) behind the board in ``walls_mm``."""
    rs = np.random.default_rng(0)

    def jpeg(d):
        _photos(d, lambda im, n: im, ".jpg", (cv2.IMWRITE_JPEG_QUALITY, 70))

    def rot180(d):
        _photos(d, lambda im, n: cv2.rotate(im, cv2.ROTATE_180))

    def gamma(d):
        lut = np.clip(255 * (np.arange(256) / 255) ** 1.8 * 1.1 + 10, 0, 255).astype(np.uint8)
        _photos(d, lambda im, n: cv2.LUT(im, lut))

    def light(d):  # a bright blob (a lamp's reflection) on one side of each photo
        def f(im, n):
            h, w = im.shape[:2]
            yy, xx = np.mgrid[:h, :w]
            blob = 120 * np.exp(-((xx - 0.8 * w) ** 2 + (yy - 0.3 * h) ** 2) / (2 * 60.0 ** 2))
            out = im.astype(float) + (blob[..., None] if im.ndim == 3 else blob)
            return np.clip(out, 0, 255).astype(np.uint8)
        _photos(d, f)

    def marker(d):  # a small printed 3x3 checker pasted in a corner of every photo
        tile = np.kron(np.indices((4, 4)).sum(0) % 2, np.ones((12, 12))) * 255

        def f(im, n):
            im = im.copy()
            t = tile.astype(np.uint8)
            if im.ndim == 3:
                t = np.repeat(t[..., None], im.shape[2], axis=2)
            im[10:58, 10:58] = t
            return im
        _photos(d, f)

    def upscale(d):
        _photos(d, lambda im, n: cv2.resize(im, None, fx=2, fy=2, interpolation=cv2.INTER_CUBIC))
        cam = json.loads((SRC / "camera.json").read_text())
        K = np.array(cam["K"])
        K[:2, :] *= 2
        K[0, 2] += 0.5  # pixel centres: x2 = 2 x1 + 0.5
        K[1, 2] += 0.5
        cam["K"] = K.tolist()
        cam["image_size"] = [1280, 960]
        (d / "camera.json").write_text(json.dumps(cam))

    def decimate(d):
        _scans(d, lambda p, a, r, n: _write_scan(p, a[::2], [int(x) for x in r[::2]]))

    def quantise10(d):
        _scans(d, lambda p, a, r, n: _write_scan(p, a, [int(10 * np.rint(x / 10)) for x in r]))

    def nonfinite(d):
        def f(p, a, r, n):
            txt = [str(int(x)) for x in r]
            for i in rs.choice(len(r), 40, replace=False):
                txt[i] = rs.choice(["nan", "inf", "0"])
            _write_scan(p, a, txt)
        _scans(d, f)

    def intensity(d):
        _scans(d, lambda p, a, r, n: _write_scan(p, a, [int(x) for x in r], {
            "intensity": [str(int(v)) for v in rs.integers(500, 4000, len(r))]}))

    def wall_behind(d, dist_mm):  # a wall dist_mm behind the board, filling the scan beside it
        def f(p, a, r, n):
            b = _board_run(a, r, full, n)
            r = r.astype(float).copy()
            lo, hi = b.min(), b.max()
            sl = slice(max(lo - 120, 0), lo)
            sr = slice(hi + 1, min(hi + 121, len(r)))
            # the board's line extended, dist_mm farther
            th = np.radians(a)
            pts = np.column_stack([r[b] * np.cos(th[b]), r[b] * np.sin(th[b])])
            c = pts.mean(0)
            u = np.linalg.svd(pts - c)[2][0]
            nrm = np.array([-u[1], u[0]])
            off = nrm @ c + dist_mm * np.sign(nrm @ c)
            for s in (sl, sr):
                dirs = np.column_stack([np.cos(th[s]), np.sin(th[s])])
                r[s] = np.rint(off / (dirs @ nrm))
            _write_scan(p, a, [int(x) if np.isfinite(x) and x > 0 else 0 for x in r])
        _scans(d, f)

    def clutter(d):  # a flat thing of board-like length (0.7 m) at 1.4 m beside the board
        def f(p, a, r, n):
            b = _board_run(a, r, full, n)
            r = r.astype(float).copy()
            th = np.radians(a)
            side = np.arange(b.max() + 30, min(b.max() + 30 + 110, len(r)))
            if len(side) < 60:
                side = np.arange(max(b.min() - 140, 0), b.min() - 30)
            mid = th[side].mean()
            nrm = np.array([np.cos(mid + 0.3), np.sin(mid + 0.3)])
            dirs = np.column_stack([np.cos(th[side]), np.sin(th[side])])
            r[side] = np.rint(1400 * np.cos(0.3) / (dirs @ nrm) + rs.normal(0, 4, len(side)))
            _write_scan(p, a, [int(x) if np.isfinite(x) and x > 0 else 0 for x in r])
        _scans(d, f)

    walls = {f"wall_{w:g}mm_behind": (lambda d, w=w: wall_behind(d, w)) for w in walls_mm}
    return {"jpeg70": jpeg, "rotated180": rot180, "gamma": gamma, "light": light,
            "marker": marker, "upscaled2x": upscale, "decimated0.5deg": decimate,
            "quantised10mm": quantise10, "nan_inf_0": nonfinite, "intensity_column": intensity,
            **walls, "clutter_0.7m": clutter}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--wall-mm", nargs="*", type=float, default=[40.0],
                    help="distances (mm) of the wall behind the board, one perturbation each")
    a = ap.parse_args(argv)
    board = BoardSpec((8, 5), 100.0)
    t0 = time.process_time()
    full = run_planes(SRC, SRC / "camera.json", board)
    cov = full.uncertainty.covariance
    P = np.linalg.pinv(cov, rcond=1e-12, hermitian=True)
    sd = np.sqrt(np.diag(cov))
    print(f"unperturbed: RMS {full.total_rms_mm:.2f} mm, T {np.round(full.T, 1)}, "
          f"sigma T {np.round(sd[3:], 1)} mm, rot {np.round(np.degrees(sd[:3]), 2)} deg")
    print(f"{'perturbation':18s} {'used':>4s} {'RMS':>5s} {'|dT|':>6s} {'drot':>5s} "
          f"{'max|d|/sig':>10s} {'mahal':>6s}  warnings / error")
    for name, fn in perturbations(full, tuple(a.wall_mm)).items():
        if a.only and name not in a.only:
            continue
        with tempfile.TemporaryDirectory() as tmp:
            d = Path(tmp)
            _copy(d)
            fn(d)
            try:
                r = run_planes(d, d / "camera.json", board)
            except DatasetError as e:
                print(f"{name:18s} error: {e}")
                continue
        Rf, Tf = full.R, full.T
        if name == "rotated180":  # the photos of a camera turned 180 deg about its optical axis
            Rz = np.diag([-1.0, -1.0, 1.0])
            Rf, Tf = Rz @ Rf, Rz @ Tf
        d6 = pose_difference(r.R, r.T, Rf, Tf)
        extra = [w[:90] for w in r.warnings if "views disagree" not in w]
        print(f"{name:18s} {sum(r.used):4d} {r.total_rms_mm:5.2f} {np.linalg.norm(d6[3:]):6.1f} "
              f"{np.degrees(np.linalg.norm(d6[:3])):5.2f} {np.max(np.abs(d6) / sd):10.2f} "
              f"{np.sqrt(d6 @ P @ d6):6.2f}  {' | '.join(extra)}")
    print(f"CPU {time.process_time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
