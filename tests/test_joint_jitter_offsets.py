"""The joint fit warns when the encoder jitter it found is not told apart from the stripes'
offsets (combo_sweep: wide rig + 0.02 deg jitter + a 270-deg LiDAR yawed 90 deg gave a pose
z axis 5 sigma off with no warning). The noise dicts are the joint fits' own, measured on
the simulated rigs named."""

from __future__ import annotations

import pytest

from lidarcal.joint.fit import jitter_offset_warnings
from lidarcal.joint.params import JITTER_OFFSET_RATIO

# calibration.json sigma.noise (stripe parts) and sigma.angle_jitter_deg, measured
WIDE_JITTER = ({"stripe0_px": 0.0239, "stripe0_offset_px": 0.435,
                "stripe1_px": 0.0256, "stripe1_offset_px": 0.4382}, 0.0288)  # z axis 5 sigma off
HARSH = ({"stripe0_px": 0.2294, "stripe0_offset_px": 0.0,
          "stripe1_px": 0.2302, "stripe1_offset_px": 0.0258}, 0.0024)        # within 2 sigma
NO_JITTER = ({"stripe0_px": 0.0209, "stripe0_offset_px": 0.0023,
              "stripe1_px": 0.0197, "stripe1_offset_px": 0.0}, 0.0)


def test_jitter_mixed_with_stripe_offsets_is_warned():
    w = jitter_offset_warnings(*WIDE_JITTER)
    assert len(w) == 1 and "0.0288 deg" in w[0] and "18x" in w[0] and "several sigma" in w[0]


@pytest.mark.parametrize("case", [HARSH, NO_JITTER])
def test_separated_jitter_or_none_is_not_warned(case):
    assert jitter_offset_warnings(*case) == []


def test_offsets_without_a_jitter_are_the_noise_models_business():
    """Large stripe offsets alone (no jitter found) are modelled, not a jitter problem."""
    assert jitter_offset_warnings(WIDE_JITTER[0], 0.0) == []


def test_the_ratio_is_of_the_worse_board():
    noise = {"stripe0_px": 0.1, "stripe0_offset_px": 0.0,
             "stripe1_px": 0.1, "stripe1_offset_px": 0.1 * JITTER_OFFSET_RATIO * 1.01}
    assert len(jitter_offset_warnings(noise, 0.01)) == 1
    noise["stripe1_offset_px"] = 0.1 * JITTER_OFFSET_RATIO * 0.99
    assert jitter_offset_warnings(noise, 0.01) == []
