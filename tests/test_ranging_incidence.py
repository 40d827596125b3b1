"""A LiDAR whose ranges grow with the incidence angle (``k (1/cos - 1)``) against the joint
fit's range offset (combo3 round, ``scripts/combo_sweep.py`` ``paper_incidence10``: the joint
fit read a 10 mm incidence bias as a -9.2 mm zero offset and sat 10.3 mm from the truth at
12.7 of its sigmas, 'poses_rigid' 0.66 mm, with no doubting warning).

On a plane at distance ``d`` a range error ``f(theta)`` moves the point off the plane by
``f cos(theta)``: an offset ``c`` by ``c cos(theta)``, an incidence bias by ``k - k cos(theta)``,
i.e. an offset ``-k`` plus the constant ``k`` along both board normals, which is a shift of
the LiDAR. Plane scans cannot tell the two apart, so without dataset.json's own prior on
the offset the sigmas cover both the joint fit (offset) and the rigid fit (raw ranges)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lidarcal.evaluate import pose_errors
from lidarcal.pipeline import calibrate, calibration_dict
from lidarcal.synthetic import simulate
from lidarcal.synthetic.config import PAPER


def _rig(name: str, **changes):
    """The paper preset's 21.5 deg span over 5 positions (the combo's span, fewer stops)."""
    return PAPER.with_(name=name, n_positions=5, psi_step_deg=round(21.5 / 4, 4), **changes)


def _errors(ds, res) -> tuple[dict, dict, dict]:
    """Centre errors (mm) of the joint fit and the rigid fit per position, and 'sigma'."""
    truth = json.loads((ds / "truth.json").read_text())
    cal = calibration_dict(res)
    out = []
    for m in (res.joint_model, res.rigid_model):
        psi = getattr(m, "position_psi", lambda i, a: a)  # the joint fit's jitter-corrected angle
        est = {r.index: m.pose(psi(r.index, r.psi_deg)) for r in res.positions}
        out.append(pose_errors(est, truth).set_index("index")["centre_mm"].to_dict())
    return out[0], out[1], cal


@pytest.mark.parametrize("seed", [3, 8])
def test_an_incidence_bias_read_as_an_offset_widens_the_sigmas(tmp_path, seed):
    ds = simulate(tmp_path / "inc", seed=seed, rig=_rig("paper-incidence", incidence_extra_mm=10.0),
                  with_intrinsics=False, with_sweeps=False)
    res = calibrate(ds, progress=False)
    joint, rigid, cal = _errors(ds, res)
    assert cal["ranging"]["offset_mm"] < -5.0          # the bias is taken for an offset ...
    assert min(joint.values()) > 5.0                   # ... and the joint fit moves with it
    assert max(rigid.values()) < 2.0                   # the raw ranges' fit stays near the truth
    (w,) = [w for w in cal["warnings"] if "from the rigid fit's" in w]
    assert "incidence angle" in w and "'sigma' is widened" in w and "range_offset_mm" in w, w
    assert cal["sigma"]["widened_to_rigid"] is True
    sig = {s["index"]: s["centre_mm"] for s in cal["sigma"]["poses"]}
    for i, e in joint.items():
        assert e < 2.0 * sig[i], (i, e, sig[i])


def test_an_offset_the_datasets_prior_confirms_keeps_its_sigmas(tmp_path):
    """A true -10 mm zero offset: the joint fit finds it; without a prior the sigmas cover the
    rigid fit as well (the incidence reading), with dataset.json's ``lidar.range_offset_mm``
    prior (-10 +- 1 mm) they stay the joint fit's own and hold the truth."""
    ds = simulate(tmp_path / "off", seed=3, rig=_rig("paper-offset", range_offset_mm=-10.0),
                  with_intrinsics=False, with_sweeps=False)
    res = calibrate(ds, progress=False)
    joint, rigid, cal = _errors(ds, res)
    assert max(joint.values()) < 1.0 and min(rigid.values()) > 5.0
    assert cal["sigma"]["widened_to_rigid"] is True
    meta = json.loads((ds / "dataset.json").read_text())
    meta.setdefault("lidar", {}).update(range_offset_mm=-10.0, range_offset_sigma_mm=1.0)
    (ds / "dataset.json").write_text(json.dumps(meta))
    res = calibrate(ds, progress=False)
    joint, _, cal = _errors(ds, res)
    (w,) = [w for w in cal["warnings"] if "from the rigid fit's" in w]
    assert "agrees with dataset.json's prior -10 +- 1 mm" in w, w
    assert "widened_to_rigid" not in cal["sigma"]
    sig = {s["index"]: s["centre_mm"] for s in cal["sigma"]["poses"]}
    assert all(joint[i] < 2.0 * sig[i] for i in joint), (joint, sig)
    assert np.isclose(cal["ranging"]["offset_mm"], -10.0, atol=3 * cal["ranging"]["offset_sigma_mm"])


def test_a_doubted_offset_widens_the_diameters_offset_term():
    """combo3 ``disc_incidence10``: the sweeps were corrected by the -9.2 mm offset the joint
    fit took from an incidence bias; 300 mm discs 0.9-1.1 mm off at 1.7-2.1 sigma. Where the
    calibration widened its sigmas to the rigid fit the offset term of a diameter's sigma
    carries the offset itself; elsewhere its own sigma."""
    from types import SimpleNamespace

    from lidarcal.disc import doubted_offset_sigma
    from lidarcal.ranging import RangingModel

    rng = RangingModel(offset_mm=-9.23, offset_sigma_mm=0.76)
    plain = SimpleNamespace(ranging=rng, data={"sigma": {"method": "joint"}})
    assert doubted_offset_sigma(plain) == pytest.approx(0.76)
    doubted = SimpleNamespace(ranging=rng, data={"sigma": {"widened_to_rigid": True}})
    assert doubted_offset_sigma(doubted) == pytest.approx(np.hypot(9.23, 0.76))
    assert doubted_offset_sigma(SimpleNamespace(ranging=RangingModel(), data={})) == 0.0
