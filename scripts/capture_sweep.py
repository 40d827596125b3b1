"""Harsher captures: perturb a simulated dataset's images, calibrate, compare with the truth.

usage::

    python scripts/capture_sweep.py DATASET --work WORKDIR [--cases NAME ...] [--list]
                                    [--csv OUT.csv] [--keep] [--check]

``DATASET`` is a dataset with ``truth.json`` (``lidarcal simulate OUT --seed N --rig
paper|wide|harsh --positions 15 --no-sweeps``). For every case (all by default; ``--list``
prints them) the script writes a copy of the dataset under ``WORKDIR/CASE`` whose images are
perturbed as the case says (every other file is hard-linked; ``dataset.json`` is copied
when the case changes ``lidar.laser_colour``), runs ``lidarcal calibrate CASE --out
CASE/out`` in a subprocess (and ``lidarcal check`` with ``--check``) and prints one row per
case: the exit status, the positions used and skipped, how many warnings, the mean and
largest true centre error of ``poses`` (mm, :func:`lidarcal.evaluate.pose_errors`), the
mean z/x axis errors (deg), the share of positions whose centre, z and x errors all lie
within 2 sigma (``cov2s``) and the worst error/sigma ratio, and the first warning or the
error line. A case is marked ``BAD`` when calibrate exits 0 but a true error lies outside
2 sigma at some position (a confident wrong answer); ``--csv`` writes the rows.

The cases are the captures a real lab or an independent simulator may produce (each
alone at a few strengths, some combined):

- stripe frames: the room lights on (the boards visible at 30-120 DN on white squares;
  ``lit``) and the same with a lit frame without the laser subtracted (``litsub``);
  saturated and blooming stripe cores (``sat``); motion blur/defocus (``blur``);
  vignetting (``vig``); gamma and exposure changing from frame to frame (``gamma``); hot
  pixels and a bright reflection (``hot``, ``blob``); the stripe partly occluded on one
  board (``occl``); colour frames of a red or green laser on a board lit in white
  (``red``/``green``, with ``lidar.laser_colour`` auto or set);
- board.png: glare, uneven light, defocus, low contrast, noise, an occluder on one
  board, JPEG blocking (``board_*``);
- PNG variants: 16-bit (full range and 12-bit values), RGBA, palette, gray stored as
  three equal channels (``png_*``), applied to every image.

The perturbations are seeded (``--seed``), so a row is reproducible.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from lidarcal.evaluate import pose_errors, truth_poses


@dataclass
class Ctx:
    """What a perturbation may use: the clean board image, a seeded generator, the frame's
    number and the dataset's truth."""

    board: np.ndarray
    rng: np.random.Generator
    frame: int = 0
    truth: dict = field(default_factory=dict)


Perturb = Callable[[np.ndarray, Ctx], np.ndarray]


def _u8(a: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(a), 0, 255).astype(np.uint8)


def _white_level(board: np.ndarray) -> float:
    """The board's white squares in board.png (its 97th percentile, DN)."""
    return float(np.percentile(board, 97))


def lights_on(level: float, subtract: bool = False, noise: float = 2.0) -> Perturb:
    """The room lights on: the lit board scaled so white squares read ``level`` DN added to
    the stripe frame, with sensor noise; ``subtract``: minus a second lit frame without the
    laser (its own noise), clipped at 0, as a lab that subtracts a background frame does."""
    def f(img, c):
        amb = c.board.astype(np.float32) * (level / _white_level(c.board))
        out = img.astype(np.float32) + amb + c.rng.normal(0, noise, img.shape)
        if subtract:
            out -= _u8(amb + c.rng.normal(0, noise, img.shape)).astype(np.float32)
        return _u8(out)
    return f


def saturate(gain: float, bloom: float = 0.0) -> Perturb:
    """Exposure ``gain`` x, clipped at 255; ``bloom``: the light above 255 spills into a
    Gaussian halo (sigma 3 px) of that share."""
    def f(img, c):
        a = img.astype(np.float32) * gain
        if bloom > 0:
            over = np.maximum(a - 255.0, 0)
            a = a + bloom * cv2.GaussianBlur(over, (0, 0), 3.0)
        return _u8(a)
    return f


def blur(sigma: float) -> Perturb:
    """Defocus: a Gaussian blur of ``sigma`` px."""
    return lambda img, c: cv2.GaussianBlur(img, (0, 0), sigma)


def motion(length: int) -> Perturb:
    """Motion blur: a vertical box of ``length`` px (the stripe smeared across itself)."""
    k = np.ones((length, 1), np.float32) / length
    return lambda img, c: _u8(cv2.filter2D(img.astype(np.float32), -1, k))


def vignette(strength: float) -> Perturb:
    """Brightness falls to ``1 - strength`` at the image corners (quadratic in radius)."""
    def f(img, c):
        h, w = img.shape[:2]
        y, x = np.mgrid[0:h, 0:w]
        r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        g = 1 - strength * r2
        return _u8(img * (g if img.ndim == 2 else g[..., None]))
    return f


def gamma_exposure(spread: float) -> Perturb:
    """Auto exposure: each frame its own gain in ``[1 - spread, 1 + spread]`` and gamma in
    ``[1 - spread, 1 + spread]`` (``255 (gain x / 255) ** gamma``)."""
    def f(img, c):
        gain = c.rng.uniform(1 - spread, 1 + spread)
        gam = c.rng.uniform(1 - spread, 1 + spread)
        return _u8(255.0 * np.clip(gain * img.astype(np.float32) / 255.0, 0, 1) ** gam)
    return f


def hot_pixels(n: int) -> Perturb:
    """``n`` hot pixels at 255 (the same pixels in every frame, as a sensor's)."""
    def f(img, c):
        r = np.random.default_rng(12345)
        ys, xs = r.integers(0, img.shape[0], n), r.integers(0, img.shape[1], n)
        out = img.copy()
        out[ys, xs] = 255
        return out
    return f


def _stripe_extent(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    g = img if img.ndim == 2 else img.max(axis=2)
    ys, xs = np.nonzero(g > max(40, np.percentile(g, 99.5) * 0.5))
    return ys, xs


def reflection(amplitude: float, sigma: float = 15.0) -> Perturb:
    """A bright specular blob (Gaussian, ``amplitude`` DN) on the left board, near the
    stripe (30 px above it at a quarter of its length)."""
    def f(img, c):
        ys, xs = _stripe_extent(img)
        if xs.size == 0:
            return img
        x0 = int(np.percentile(xs, 25))
        y0 = int(np.median(ys[np.abs(xs - x0) < 5])) - 30 if np.any(np.abs(xs - x0) < 5) else int(np.median(ys))
        h, w = img.shape[:2]
        y, x = np.mgrid[0:h, 0:w]
        blob = amplitude * np.exp(-((x - x0) ** 2 + (y - y0) ** 2) / (2 * sigma ** 2))
        return _u8(img.astype(np.float32) + (blob if img.ndim == 2 else blob[..., None]))
    return f


def occlude_stripe(share: float) -> Perturb:
    """The stripe hidden (set to the frame's background) over ``share`` of the left board's
    columns, from 10 % of the stripe's length on."""
    def f(img, c):
        _ys, xs = _stripe_extent(img)
        if xs.size == 0:
            return img
        lo, hi = xs.min(), xs.max()
        a = int(lo + 0.1 * (hi - lo))
        b = int(a + share * 0.5 * (hi - lo))
        out = img.copy()
        out[:, a:b] = np.median(img)
        return out
    return f


def coloured(channel: int, level: float, leak: float = 0.15) -> Perturb:
    """A BGR frame: the board lit in white at ``level`` DN on white squares, the laser in
    channel ``channel`` (2 red, 1 green) with ``leak`` of it in the other two."""
    def f(img, c):
        amb = c.board.astype(np.float32) * (level / _white_level(c.board))
        las = img.astype(np.float32)
        out = np.repeat(amb[..., None], 3, axis=2) + c.rng.normal(0, 2.0, img.shape + (3,))
        for k in range(3):
            out[..., k] += las * (1.0 if k == channel else leak)
        return _u8(out)
    return f


def compose(*fs: Perturb) -> Perturb:
    """The perturbations one after the other."""
    def f(img, c):
        for g in fs:
            img = g(img, c)
        return img
    return f


# ---- board.png -------------------------------------------------------------------

def glare(amplitude: float, sigma: float = 80.0, where: tuple[float, float] = (0.3, 0.4)) -> Perturb:
    """A glare patch of ``amplitude`` DN (Gaussian, ``sigma`` px) at the image fraction ``where``."""
    def f(img, c):
        h, w = img.shape[:2]
        y, x = np.mgrid[0:h, 0:w]
        g = amplitude * np.exp(-((x - where[0] * w) ** 2 + (y - where[1] * h) ** 2) / (2 * sigma ** 2))
        return _u8(img.astype(np.float32) + g)
    return f


def uneven(low: float) -> Perturb:
    """Light falling linearly from 1 on the right to ``low`` on the left."""
    def f(img, c):
        w = img.shape[1]
        return _u8(img * np.linspace(low, 1.0, w)[None, :])
    return f


def contrast(k: float) -> Perturb:
    """Contrast scaled by ``k`` about the median."""
    def f(img, c):
        m = float(np.median(img))
        return _u8((img.astype(np.float32) - m) * k + m)
    return f


def noise(sigma: float) -> Perturb:
    """White Gaussian noise of ``sigma`` DN."""
    return lambda img, c: _u8(img + c.rng.normal(0, sigma, img.shape))


def occluder(frac: tuple[float, float, float, float]) -> Perturb:
    """A dark object (a person's arm) over the rectangle ``(x0, y0, x1, y1)`` in image fractions."""
    def f(img, c):
        h, w = img.shape[:2]
        out = img.copy()
        out[int(frac[1] * h):int(frac[3] * h), int(frac[0] * w):int(frac[2] * w)] = 25
        return out
    return f


def jpeg(quality: int) -> Perturb:
    """JPEG-compressed at ``quality`` and decoded (8 x 8 blocking)."""
    def f(img, c):
        _ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    return f


# ---- PNG variants (the writer, not the pixels) ----------------------------------------

def png_writer(kind: str) -> Callable[[Path, np.ndarray], None]:
    """A PNG writer of an 8-bit gray image: ``16bit`` (x 257, full range), ``12bit``
    (x 16, a 12-bit sensor's values in a 16-bit PNG), ``rgba`` (opaque alpha), ``gray3``
    (three equal channels), ``palette`` (Pillow's 'P' mode), ``gray_alpha`` (Pillow 'LA')."""
    def w(path: Path, img: np.ndarray) -> None:
        if kind == "16bit":
            cv2.imwrite(str(path), img.astype(np.uint16) * 257)
        elif kind == "12bit":
            cv2.imwrite(str(path), img.astype(np.uint16) * 16)
        elif kind == "rgba":
            cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGRA))
        elif kind == "gray3":
            cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
        elif kind in ("palette", "gray_alpha"):
            from PIL import Image
            im = Image.fromarray(img, "L")
            im = im.convert("P") if kind == "palette" else im.convert("LA")
            im.save(path)
        else:
            raise ValueError(kind)
    return w


@dataclass
class Case:
    """One perturbed copy: what is done to the stripe frames, to board.png, how every image
    is written, and dataset.json's ``lidar.laser_colour`` (None: as it is)."""

    name: str
    stripes: Perturb | None = None
    board: Perturb | None = None
    writer: str | None = None
    laser_colour: str | None = None


def cases() -> list[Case]:
    """Every case of the sweep (see the module docstring)."""
    C = Case
    out = [C("clean")]
    out += [C(f"lit{v}", lights_on(v)) for v in (30, 60, 120)]
    out += [C(f"litsub{v}", lights_on(v, subtract=True)) for v in (60, 120)]
    out += [C("sat2", saturate(2.0)), C("sat4", saturate(4.0)), C("sat4_bloom", saturate(4.0, 0.5))]
    out += [C(f"blur{s}", blur(s)) for s in (1, 2, 3)] + [C("motion5", motion(5))]
    out += [C(f"blur{s}_both", blur(s), board=blur(s)) for s in (2, 3)]
    out += [C("vig0.5", vignette(0.5))]
    out += [C("gamma0.3", gamma_exposure(0.3)), C("gamma0.5", gamma_exposure(0.5))]
    out += [C("hot500", hot_pixels(500)), C("blob150", reflection(150)), C("blob255", reflection(255, 25))]
    out += [C("occl0.3", occlude_stripe(0.3)), C("occl0.6", occlude_stripe(0.6))]
    out += [C("red60", coloured(2, 60)), C("red60_set", coloured(2, 60), laser_colour="red"),
            C("green120", coloured(1, 120)), C("red120_sat", compose(saturate(2.5), coloured(2, 120)))]
    out += [C("lit60_vig_blur2", compose(blur(2), lights_on(60), vignette(0.5))),
            C("lit120_sat_hot", compose(saturate(3.0, 0.3), lights_on(120), hot_pixels(300))),
            C("lit60_gamma", compose(lights_on(60), gamma_exposure(0.4)))]
    out += [C("board_glare", board=glare(150)), C("board_glare_sat", board=glare(255, 120)),
            C("board_uneven0.3", board=uneven(0.3)), C("board_blur2", board=blur(2)),
            C("board_blur3", board=blur(3)), C("board_contrast0.25", board=contrast(0.25)),
            C("board_noise10", board=noise(10)), C("board_noise20", board=noise(20)),
            C("board_occl", board=occluder((0.62, 0.55, 0.80, 0.95))),
            C("board_jpeg30", board=jpeg(30)), C("board_jpeg10", board=jpeg(10)),
            C("board_all", board=compose(uneven(0.5), blur(1.5), noise(6), jpeg(40)))]
    out += [C(f"png_{k}", writer=k) for k in ("16bit", "12bit", "rgba", "gray3", "palette", "gray_alpha")]
    return out


def write_case(src: Path, dst: Path, case: Case, seed: int) -> None:
    """``dst``: a copy of the dataset ``src`` with the case's images; the rest hard-linked."""
    if dst.exists():
        shutil.rmtree(dst)
    board = cv2.imread(str(src / "board.png"), cv2.IMREAD_GRAYSCALE)
    truth = json.loads((src / "truth.json").read_text())
    writer = png_writer(case.writer) if case.writer else (lambda p, im: cv2.imwrite(str(p), im))
    for root, _dirs, files in os.walk(src):
        rel = Path(root).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for name in sorted(files):
            s, d = Path(root) / name, dst / rel / name
            if name == "dataset.json" and case.laser_colour:
                j = json.loads(s.read_text())
                j["lidar"]["laser_colour"] = case.laser_colour
                d.write_text(json.dumps(j, indent=2))
                continue
            is_stripe = rel.parts[:1] == ("stripes",) and name.endswith(".png")
            is_board = rel == Path(".") and name == "board.png"
            is_photo = rel.parts[:1] == ("intrinsics",) and name.endswith(".png")
            todo = (case.stripes if is_stripe else case.board if is_board else None)
            if todo is None and not (case.writer and (is_stripe or is_board or is_photo)):
                os.link(s, d)
                continue
            img = cv2.imread(str(s), cv2.IMREAD_GRAYSCALE)
            if todo is not None:
                frame = int(Path(name).stem) if name[:-4].isdigit() else 0
                ctx = Ctx(board, np.random.default_rng([seed, frame, int(is_board)]), frame, truth)
                img = todo(img, ctx)
            if img.ndim == 3:
                cv2.imwrite(str(d), img)
            else:
                writer(d, img)


def evaluate_case(ds: Path, out: Path, proc: subprocess.CompletedProcess) -> dict:
    """The row of one case: exit status, positions, warnings, true errors and coverage."""
    row = {"exit": proc.returncode, "used": "", "skipped": "", "warnings": "",
           "centre_mm": "", "centre_max_mm": "", "z_deg": "", "x_deg": "", "cov2s": "",
           "worst_ratio": "", "note": ""}
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith(("warning:", "error:"))]
    if proc.returncode != 0 or not (out / "calibration.json").exists():
        row["note"] = lines[-1][:160] if lines else proc.stderr.strip()[-160:]
        return row
    cal = json.loads((out / "calibration.json").read_text())
    truth = json.loads((ds / "truth.json").read_text())
    P = type(next(iter(truth_poses(truth).values())))
    est = {int(p["index"]): P.from_dict(p) for p in cal["poses"]}
    e = pose_errors(est, truth)
    sig = {int(s["index"]): s for s in (cal.get("sigma") or {}).get("poses", [])}
    ratios = []
    for _, r in e.iterrows():
        s = sig.get(int(r["index"]), {})
        rr = [r[k] / s[k] for k in ("centre_mm", "z_axis_deg", "x_axis_deg") if s.get(k)]
        ratios.append(max(rr) if rr else np.inf)
    ratios = np.array(ratios)
    row.update(used=len(cal["poses"]), skipped=len(cal.get("skipped", [])),
               warnings=len(cal.get("warnings", [])),
               centre_mm=round(float(e.centre_mm.mean()), 4),
               centre_max_mm=round(float(e.centre_mm.max()), 4),
               z_deg=round(float(e.z_axis_deg.mean()), 5), x_deg=round(float(e.x_axis_deg.mean()), 5),
               cov2s=round(float(np.mean(ratios <= 2.0)), 3), worst_ratio=round(float(ratios.max()), 2))
    extra = [w for w in cal.get("warnings", []) if "span only" not in w]
    row["note"] = ("BAD: outside 2 sigma; " if row["cov2s"] < 1.0 else "") + (extra[0][:140] if extra else "")
    return row


def run(ds: Path, work: Path, names: list[str] | None, seed: int, check: bool,
        keep: bool) -> list[dict]:
    """Write, calibrate and evaluate every chosen case; one row each (printed as it comes)."""
    rows = []
    chosen = [c for c in cases() if not names or c.name in names]
    if names and len(chosen) != len(names):
        raise SystemExit(f"unknown case(s): {sorted(set(names) - {c.name for c in chosen})}")
    exe = [sys.executable, "-m", "lidarcal"]
    for case in chosen:
        d = work / case.name
        write_case(ds, d, case, seed)
        proc = subprocess.run(exe + ["calibrate", str(d), "--out", str(d / "out")],
                              capture_output=True, text=True, check=False)
        row = {"case": case.name, **evaluate_case(d, d / "out", proc)}
        if check:
            chk = subprocess.run(exe + ["check", str(d), "--sheet", str(d / "check.png")],
                                 capture_output=True, text=True, check=False)
            row["check_exit"] = chk.returncode
        print("  ".join(f"{k}={v}" for k, v in row.items() if v != ""), flush=True)
        rows.append(row)
        if not keep:
            shutil.rmtree(d)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("dataset", type=Path, nargs="?")
    ap.add_argument("--work", type=Path, help="where the perturbed copies go")
    ap.add_argument("--cases", nargs="*", help="case names (default: all; --list prints them)")
    ap.add_argument("--list", action="store_true")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--csv", type=Path)
    ap.add_argument("--check", action="store_true", help="also run lidarcal check")
    ap.add_argument("--keep", action="store_true", help="keep the perturbed copies")
    a = ap.parse_args(argv)
    if a.list:
        print("\n".join(c.name for c in cases()))
        return 0
    if a.dataset is None or a.work is None:
        ap.error("DATASET and --work are required")
    if not (a.dataset / "truth.json").exists():
        ap.error(f"{a.dataset}: no truth.json (a simulated dataset is needed)")
    a.work.mkdir(parents=True, exist_ok=True)
    rows = run(a.dataset, a.work, a.cases, a.seed, a.check, a.keep)
    if a.csv:
        keys = list(dict.fromkeys(k for r in rows for k in r))
        with open(a.csv, "w", newline="") as fh:
            w = csv.DictWriter(fh, keys)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
