"""PNG variants an independent simulator or camera may write (16-bit, RGBA, palette, gray as
three channels, gray + alpha): each read as the 8-bit image it holds, or refused naming the
file (never a silent mis-read)."""

from __future__ import annotations

import subprocess
import sys

import cv2
import numpy as np
import pytest
from PIL import Image

from lidarcal.io.dataset import DatasetError, read_image, read_stripe_image


@pytest.fixture
def gray() -> np.ndarray:
    """A dark frame with a bright stripe and every gray level present (uint8)."""
    rng = np.random.default_rng(3)
    img = rng.integers(0, 12, (48, 64)).astype(np.uint8)
    img[20:24] = 200
    img[0, :] = np.arange(64) * 4  # 0..252
    img[1, :] = 255
    return img


def _write(path, kind: str, img: np.ndarray) -> None:
    if kind == "16bit":
        cv2.imwrite(str(path), img.astype(np.uint16) * 257)
    elif kind == "16bit_bgr":
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR).astype(np.uint16) * 257)
    elif kind == "rgba":
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGRA))
    elif kind == "gray3":
        cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    elif kind == "palette":
        Image.fromarray(img, "L").convert("P").save(path)
    elif kind == "gray_alpha":
        Image.fromarray(img, "L").convert("LA").save(path)


@pytest.mark.parametrize("kind", ["16bit", "16bit_bgr", "rgba", "gray3", "palette", "gray_alpha"])
def test_png_variants_read_as_the_8bit_image(tmp_path, gray, kind):
    p = tmp_path / f"{kind}.png"
    _write(p, kind, gray)
    assert np.array_equal(read_image(p), gray)
    assert np.array_equal(read_stripe_image(p, (64, 48)), gray)
    assert np.array_equal(read_image(p, colour="max"), gray)


def test_16bit_full_range_rounds_to_nearest(tmp_path):
    v = np.array([[0, 128, 129, 257, 385, 386, 65406, 65535]], np.uint16)
    p = tmp_path / "r.png"
    cv2.imwrite(str(p), np.repeat(v, 2, axis=0))
    assert read_image(p)[0].tolist() == [0, 0, 1, 1, 1, 2, 254, 255]


def test_unscaled_12bit_values_are_refused_naming_the_file(tmp_path, gray):
    p = tmp_path / "raw12.png"
    cv2.imwrite(str(p), gray.astype(np.uint16) * 16)  # 0..4080: a 12-bit sensor, unscaled
    with pytest.raises(DatasetError, match=r"raw12\.png.*largest value is 4080.*x 16 for 12 bits"):
        read_image(p)
    f = tmp_path / "float.tiff"
    cv2.imwrite(str(f), gray.astype(np.float32))
    with pytest.raises(DatasetError, match="expected an 8- or 16-bit image, got float32"):
        read_image(f)


def test_calibrate_reads_a_16bit_dataset_as_the_8bit_one(dataset_copy, tmp_path):
    """Every image of a small rig rewritten as 16-bit PNGs: calibrate gives the same poses as
    on the 8-bit images (the 16-bit values are the 8-bit ones x 257)."""
    ref = tmp_path / "ref"
    run = [sys.executable, "-m", "lidarcal", "calibrate"]
    r0 = subprocess.run(run + [str(dataset_copy), "--out", str(ref), "--method", "rigid"],
                        capture_output=True, text=True, check=False)
    assert r0.returncode == 0, r0.stderr
    for p in [dataset_copy / "board.png", *sorted((dataset_copy / "stripes").glob("*.png"))]:
        cv2.imwrite(str(p), cv2.imread(str(p), cv2.IMREAD_GRAYSCALE).astype(np.uint16) * 257)
    out = tmp_path / "out16"
    r1 = subprocess.run(run + [str(dataset_copy), "--out", str(out), "--method", "rigid"],
                        capture_output=True, text=True, check=False)
    assert r1.returncode == 0, r1.stderr
    import json
    a = json.loads((ref / "calibration.json").read_text())["poses"]
    b = json.loads((out / "calibration.json").read_text())["poses"]
    assert [p["T_mm"] for p in a] == [p["T_mm"] for p in b]
    # 12-bit values left unscaled in board.png: exit 2, one line naming it
    board = dataset_copy / "board.png"
    cv2.imwrite(str(board), (cv2.imread(str(board), cv2.IMREAD_UNCHANGED) // 257 * 16).astype(np.uint16))
    r2 = subprocess.run(run + [str(dataset_copy), "--out", str(tmp_path / "o12")],
                        capture_output=True, text=True, check=False)
    assert r2.returncode == 2
    lines = r2.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {board}: 16-bit image"), r2.stderr
