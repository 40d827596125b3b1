"""Camera and board variants other than the presets (``scripts/rig_sweep.py`` measures more):
small simulated rigs, calibrated, checked against their truth.json."""

from __future__ import annotations

import numpy as np

from lidarcal.evaluate import pose_errors
from lidarcal.geometry import Pose
from lidarcal.pipeline import calibrate, calibration_dict
from lidarcal.synthetic import simulate
from lidarcal.synthetic.config import PAPER


def _errors_and_sigmas(ds, cal: dict):
    import json

    truth = json.loads((ds / "truth.json").read_text())
    e = pose_errors({int(p["index"]): Pose.from_dict(p) for p in cal["poses"]}, truth)
    sig = {int(s["index"]): s for s in cal["sigma"]["poses"]}
    s = {q: np.array([sig[int(i)][q] for i in e["index"]], float)
         for q in ("centre_mm", "z_axis_deg", "x_axis_deg")}
    return e, s


def test_camera_from_photos_sigmas_carry_the_intrinsics_error(tmp_path):
    """The paper's long-focal camera calibrated from its photos (not given in dataset.json):
    the intrinsics' error turns the whole reconstructed scene (both board planes, so the rig)
    by a few thousandths of a degree, beyond the scans' and stripes' own sigma. Before the
    intrinsics' covariance entered the held planes' consider term, the z axis's true error
    lay outside its 2-sigma at every position (0.0034 deg against sigma 0.0014, 14 positions,
    seed 1); with a camera from dataset.json (exact) the sigmas are the corners' alone."""
    rig = PAPER.with_(camera_in_dataset=False, n_positions=14, psi_step_deg=1.6538)
    ds = simulate(tmp_path / "ds", seed=1, rig=rig, with_sweeps=False, positions=range(0, 14, 2))
    res = calibrate(ds)
    assert res.intrinsics is not None  # the camera came from the photos
    e, s = _errors_and_sigmas(ds, calibration_dict(res))
    for q in ("centre_mm", "z_axis_deg", "x_axis_deg"):
        assert np.all(e[q].to_numpy() <= 2 * s[q]), (q, e[q].to_numpy(), s[q])
