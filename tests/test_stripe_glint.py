"""A bright reflection (glint) beside the laser stripe: the coarse line must follow the stripe,
not the reflection (lidarcal.stripe_profile._bright_line)."""

from __future__ import annotations

import numpy as np
import pytest

from lidarcal.stripe import stripe_centres
from lidarcal.stripe_profile import _bright_line


def _frame(blob_amp: float, rng, shape=(400, 700), slope=0.05, y0=200.0):
    """A dark frame with a Gaussian stripe (peak 200 DN, sigma 1.5 px) on ``y = y0 + slope x``
    and a reflection (Gaussian, sigma 25 px, ``blob_amp`` DN) 30 px above it at x = 200."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(float)
    line = y0 + slope * x
    img = 3 + 200 * np.exp(-0.5 * ((y - line) / 1.5) ** 2)
    img += blob_amp * np.exp(-((x - 200) ** 2 + (y - (y0 + slope * 200 - 30)) ** 2) / (2 * 25 ** 2))
    img += rng.normal(0, 1.0, img.shape)
    mask = np.zeros(shape, bool)
    mask[40:h - 40, 40:w - 40] = True
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), mask, slope, y0


@pytest.mark.parametrize("seed", [0, 1])
def test_stripe_beside_a_saturated_reflection_is_found(seed):
    img, mask, slope, y0 = _frame(255.0, np.random.default_rng(seed))
    pts, info = stripe_centres(img, mask, return_info=True)
    assert len(pts) > 450 and info["problem"] is None, info.get("problem")
    err = pts[:, 1] - (y0 + slope * pts[:, 0])
    # 1 DN noise on a 200 DN stripe: rms 0.016 px, largest 0.048-0.056 px over seeds 0-5
    assert np.sqrt(np.mean(err ** 2)) < 0.025 and np.abs(err).max() < 0.08


def test_clean_stripe_line_unchanged_by_the_glint_path(monkeypatch):
    """Without a reflection the bright pixels spread ~2 px: the first line is kept, the same
    to the bit as with the glint path switched off."""
    import lidarcal.stripe_profile as sp

    img, mask, slope, y0 = _frame(0.0, np.random.default_rng(2))
    c, t = _bright_line(img, mask, 1.0)
    assert abs(t[1] / t[0] - slope) < 1e-3  # measured 1e-5
    assert abs(c[1] - (y0 + slope * c[0])) < 0.05  # measured 0.002 px
    monkeypatch.setattr(sp, "BLOB_SPREAD_PX", np.inf)
    c0, t0 = _bright_line(img, mask, 1.0)
    assert np.array_equal(c, c0) and np.array_equal(t, t0)
