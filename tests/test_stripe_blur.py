"""Stripe frames blurrier than board.png (lidarcal.stripe_albedo): the extra blur is found from
the stripe's brightness along itself and the albedo map is blurred to match."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import cv2
import numpy as np
import pytest

from lidarcal.io.dataset import load_dataset
from lidarcal.pipeline import _stripe_image, dataset_albedo, dataset_reflectance_ratio, find_boards
from lidarcal.stripe_albedo import albedo_blur, blur_blackness, smooth_along


def _stripe_samples(rng, blur: float, rho: float, n: int = 4, noise: float = 0.03):
    """``n`` stripes across squares of 37 px: mass = smooth trend x albedo of the blackness
    blurred by ``blur`` px, with multiplicative noise; blackness as the sharp map gives it."""
    out = []
    for k in range(n):
        x = np.arange(600.0)
        x = x[rng.random(600) > 0.1]  # some columns missing
        b = ((x + 11 * k) // 37 % 2).astype(float)
        trend = np.exp(3.0 + 0.3 * (x / 600) - 0.2 * (x / 600) ** 2)
        m = trend * (1 - (1 - rho) * smooth_along(x, b, blur)) * np.exp(rng.normal(0, noise, x.size))
        out.append((x, m, b))
    return out


@pytest.mark.parametrize("blur", [0.0, 1.5, 2.0, 3.0])
def test_albedo_blur_finds_the_injected_blur_and_ratio(blur):
    rng = np.random.default_rng(int(10 * blur))
    rho, found = albedo_blur(_stripe_samples(rng, blur, 0.3))
    assert abs(found - blur) <= 0.25, found
    assert abs(rho - 0.3) <= 0.02


def test_smooth_along_ignores_gaps():
    x = np.array([0.0, 1, 2, 10, 11, 12])
    b = np.array([1.0, 1, 1, 0, 0, 0])
    s = smooth_along(x, b, 1.0)
    assert np.allclose(s[:2], 1.0, atol=1e-6) and np.allclose(s[-2:], 0.0, atol=1e-6)
    assert smooth_along(x, b, 0.0) is b


def test_blurred_stripe_frames_found_and_matched_on_a_rig(small_dataset, tmp_path):
    """A rendered rig whose stripe frames (not board.png) are blurred by 2 px: the blur is found
    (within 0.5 px), the boards' maps are blurred, calibrate warns naming stripes/; the sharp rig
    finds none and keeps its reflectance ratio to the bit."""
    ds = load_dataset(small_dataset)
    boards = find_boards(ds, ds.camera)
    rho0, blur0 = dataset_albedo(ds.camera, boards, ds.positions)
    assert blur0 == 0.0 and rho0 == dataset_reflectance_ratio(ds.camera, boards, ds.positions)
    assert blur_blackness(boards, 0.0) is boards
    dst = tmp_path / "blurred"
    shutil.copytree(small_dataset, dst)
    for p in sorted((dst / "stripes").glob("*.png")):
        cv2.imwrite(str(p), cv2.GaussianBlur(cv2.imread(str(p), cv2.IMREAD_GRAYSCALE), (0, 0), 2.0))
    ds2 = load_dataset(dst)
    rho, blur = dataset_albedo(ds2.camera, boards, ds2.positions)
    assert 1.5 <= blur <= 2.5 and abs(rho - rho0) < 0.03
    matched = blur_blackness(boards, blur)
    assert matched[0].blackness.shape == boards[0].blackness.shape
    assert np.abs(matched[0].blackness - boards[0].blackness).max() > 0.3  # the edges softened
    img = _stripe_image(ds2.positions[0], ds2.camera)
    assert img.shape == (ds2.image_size[1], ds2.image_size[0])
    r = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(dst), "--out",
                        str(tmp_path / "out"), "--method", "rigid"], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    assert f"warning: {dst / 'stripes'}: the stripe images are blurrier than board.png" in r.stderr
    cal = json.loads((tmp_path / "out" / "calibration.json").read_text())
    assert any("blurrier than board.png" in w for w in cal["warnings"])
