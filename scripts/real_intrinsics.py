"""``lidarcal intrinsics`` on real photos by other people, and on real-looking variants of them.

Real sets (each with the intrinsics its authors published):

- ``opencv_left``: OpenCV's sample photos left01..left14 (tests/data/opencv_left), published
  in OpenCV's ``samples/data/left_intrinsics.yml`` (fixed aspect ratio, k3 free);
- ``opencv_right``: right01..right14 (tests/data/opencv_right), published only through the
  stereo sample's ``intrinsics.yml`` (M2: one focal length shared with the left camera);
- ``tapas``: the 7 views of data/real_tapas (8 x 5 board, 100 mm), the recordings' camera
  from Bouguet's toolbox (``camera.json``; calibrated from other, more views).

Variants of a set (a copy of its folder, photos changed as other people's photos differ):
vignetting, motion blur on 3 photos, the board cut by the frame in 3, 2 photos tilted > 60 deg
(simulated: the set's own camera re-projects a rendered board), a photo of another chessboard,
a duplicate, a photo of the other camera, a photo at another zoom, EXIF-rotated JPEGs
(portrait phone photos), 16-bit PNGs, 4000 x 3000 photos.

For each: the CLI is run (``lidarcal intrinsics``), and fx, fy, cx, cy, the distortion, the RMS,
the held-out RMS, the views used and the warnings are compared with the published camera (the
largest pixel distance between the two cameras' images of the same rays over the image) and
with the unchanged set's own result.

    .venv/bin/python scripts/real_intrinsics.py [--only NAME ...] [--sets opencv_left ...]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidarcal.camera import project_points, undistort_pixels
from lidarcal.io.dataset import CameraModel

LIDARCAL = Path(sys.executable).with_name("lidarcal")


def _yaml_matrix(path: Path, key: str) -> np.ndarray:
    """One ``!!opencv-matrix`` of an OpenCV YAML file."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        return np.asarray(fs.getNode(key).mat(), float)
    finally:
        fs.release()


def published(name: str) -> CameraModel:
    """The camera the set's authors published."""
    if name == "opencv_left":
        y = REPO / "tests" / "data" / "opencv_left" / "left_intrinsics.yml"
        K, d = _yaml_matrix(y, "camera_matrix"), _yaml_matrix(y, "distortion_coefficients")
    elif name == "opencv_right":
        y = REPO / "tests" / "data" / "opencv_right" / "intrinsics.yml"
        K, d = _yaml_matrix(y, "M2"), _yaml_matrix(y, "D2")
    else:
        c = json.loads((REPO / "data" / "real_tapas" / "camera.json").read_text())
        K, d = np.asarray(c["K"], float), np.asarray(c["dist"], float)
    return CameraModel(K, d.ravel()[:5], (640, 480))


SETS = {
    "opencv_left": (REPO / "tests" / "data" / "opencv_left", "9x6", 25.0),
    "opencv_right": (REPO / "tests" / "data" / "opencv_right", "9x6", 25.0),
    "tapas": (REPO / "data" / "real_tapas", "8x5", 100.0),
}


def ray_gap_px(a: CameraModel, b: CameraModel, scale: float = 1.0) -> float:
    """Largest distance (px of ``a``) between where ``a`` and ``b`` image the same rays, over a
    grid on ``a``'s image (``b`` scaled by ``scale`` when ``a``'s photos were resized)."""
    w, h = a.image_size
    g = np.stack(np.meshgrid(np.linspace(0, w - 1, 32), np.linspace(0, h - 1, 24)), -1)
    g = g.reshape(-1, 2)
    Kb = np.diag([scale, scale, 1.0]) @ np.asarray(b.K, float)
    bs = CameraModel(Kb, b.dist, a.image_size)
    xy = undistort_pixels(a, g)
    px = project_points(bs, np.column_stack([xy, np.ones(len(g))]))
    return float(np.nanmax(np.linalg.norm(px - g, axis=1)))


def _photos(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in (".png", ".jpg"))


def _vignette(img: np.ndarray, strength: float = 0.7) -> np.ndarray:
    """cos^4-like fall-off: the image's corners at (1 - strength) of the centre."""
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(float)
    r2 = ((x - w / 2) ** 2 + (y - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    f = 1 - strength * r2
    f = f[..., None] if img.ndim == 3 else f
    return np.clip(img * f, 0, 255).astype(np.uint8)


def _motion_blur(img: np.ndarray, length: int = 9, angle_deg: float = 30.0) -> np.ndarray:
    k = np.zeros((length, length), np.float32)
    k[length // 2] = 1.0
    R = cv2.getRotationMatrix2D((length / 2 - 0.5, length / 2 - 0.5), angle_deg, 1.0)
    k = cv2.warpAffine(k, R, (length, length))
    return cv2.filter2D(img, -1, k / k.sum())


def _cut(img: np.ndarray, share: float = 0.3) -> np.ndarray:
    """The right ``share`` of the photo dark (the board leaves the frame there)."""
    out = img.copy()
    out[:, int(img.shape[1] * (1 - share)):] = 0
    return out


def _zoom(img: np.ndarray, s: float = 1.06) -> np.ndarray:
    """The photo at another zoom: magnified by ``s`` about the centre, same size."""
    h, w = img.shape[:2]
    M = np.array([[s, 0, (1 - s) * w / 2], [0, s, (1 - s) * h / 2]])
    return cv2.warpAffine(img, M, (w, h), flags=cv2.INTER_CUBIC)


def _exif_rotated(src: Path, dst: Path, orientation: int = 6) -> None:
    """The same pixels as a JPEG tagged with EXIF ``orientation`` (6: a phone held upright,
    a viewer turns it 90 deg clockwise); cv2.imread's default would apply it."""
    from PIL import Image

    with Image.open(src) as im:
        exif = im.getexif()
        exif[0x0112] = orientation
        im.save(dst, quality=95, exif=exif.tobytes())


def variants(name: str, src: Path) -> dict:
    photos = _photos(src)
    other = SETS["opencv_right" if name != "opencv_right" else "opencv_left"][0]

    def each(d: Path, fn, pick=None, suffix=None):
        for i, p in enumerate(photos):
            if pick is None or i in pick:
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                out = fn(img)
                q = d / (p.stem + (suffix or p.suffix))
                if q != p and (d / p.name).exists() and suffix:
                    (d / p.name).unlink()
                cv2.imwrite(str(q), out)

    return {
        "as_is": lambda d: None,
        "vignetting": lambda d: each(d, _vignette),
        "motion_blur_3": lambda d: each(d, _motion_blur, pick={0, 4, 8}),
        "cut_by_frame_3": lambda d: each(d, _cut, pick={1, 5, 9}),
        "another_chessboard": lambda d: shutil.copy(REPO / "data" / "real_tapas" / "00.png",
                                                    d / "zz_tapas.png")
        if name != "tapas" else shutil.copy(photos[0].parents[2] / "tests" / "data" / "opencv_left"
                                            / "left01.jpg", d / "zz_left.jpg"),
        "duplicate": lambda d: shutil.copy(photos[2], d / ("zz_copy" + photos[2].suffix)),
        "other_camera": lambda d: shutil.copy(_photos(other)[3], d / "zz_other_camera.jpg"),
        "other_zoom": lambda d: cv2.imwrite(str(d / ("zz_zoom" + photos[6].suffix)),
                                            _zoom(cv2.imread(str(photos[6]), cv2.IMREAD_UNCHANGED))),
        "exif_portrait_4": lambda d: [_exif_rotated(photos[i], d / (photos[i].stem + ".jpg"))
                                      for i in (0, 3, 6, 9) if photos[i].suffix == ".jpg"],
        "png16": lambda d: each(d, lambda im: im.astype(np.uint16) * 257, suffix=".png"),
        "large_4000": lambda d: each(d, lambda im: cv2.resize(im, (4000, 3000),
                                                              interpolation=cv2.INTER_CUBIC),
                                     suffix=".png"),
    }


def run(folder: Path, pattern: str, square: float, out: Path) -> tuple[dict | None, str, float]:
    t0 = time.perf_counter()
    p = subprocess.run(["/usr/bin/time", "-f", "maxrss_kb %M", str(LIDARCAL), "intrinsics",
                        str(folder), "--pattern", pattern, "--square-mm", str(square),
                        "-o", str(out)], check=False, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    res = json.loads(out.read_text()) if p.returncode == 0 else None
    return res, p.stderr.strip(), dt


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sets", nargs="*", default=list(SETS))
    ap.add_argument("--only", nargs="*", default=None)
    a = ap.parse_args(argv)
    rows = []
    for name in a.sets:
        src, pattern, square = SETS[name]
        pub = published(name)
        base = None
        for vname, make in variants(name, src).items():
            if a.only and vname not in a.only and vname != "as_is":
                continue
            with tempfile.TemporaryDirectory() as tmp:
                d = Path(tmp) / "photos"
                d.mkdir()
                for p in _photos(src):
                    shutil.copy(p, d / p.name)
                make(d)
                res, err, dt = run(d, pattern, square, Path(tmp) / "camera.json")
            warn = [ln for ln in err.splitlines() if ln.startswith(("warning", "error"))]
            rss = [ln for ln in err.splitlines() if ln.startswith("maxrss_kb")]
            row = {"set": name, "variant": vname, "s": round(dt, 1),
                   "rss_mb": int(rss[0].split()[1]) // 1024 if rss else None, "warnings": warn}
            if res is not None:
                cam = CameraModel(np.asarray(res["K"]), np.asarray(res["dist"]),
                                  tuple(res["image_size"]))
                scale = cam.image_size[0] / 640
                K = cam.K
                row.update(fx=round(K[0, 0] / scale, 2), fy=round(K[1, 1] / scale, 2),
                           cx=round(K[0, 2] / scale, 2), cy=round(K[1, 2] / scale, 2),
                           dist=[round(v, 4) for v in res["dist"]], rms=round(res["rms_px"], 3),
                           heldout=res.get("heldout_rms_px"), k3=res["k3"],
                           used=len(res["views"]), rejected=res["rejected"],
                           gap_published_px=round(ray_gap_px(cam, pub, scale) / scale, 2))
                if base is None:
                    base = cam
                else:
                    row["gap_as_is_px"] = round(ray_gap_px(cam, base, scale) / scale, 2)
            rows.append(row)
            print(json.dumps(row), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
