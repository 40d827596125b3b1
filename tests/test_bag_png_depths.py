"""The synthetic bag writer records a folder whose PNGs are 16-bit or BGRA (raw Image
messages: mono16, bgra8) and ``lidarcal import`` gives the 8-bit frames back (combo_sweep:
a 16-bit folder recorded on one camera topic crashed rosbags' serializer)."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from lidarcal.io.bag import import_bag
from lidarcal.io.dataset import load_dataset
from lidarcal.synthetic.bag import write_bag


@pytest.mark.parametrize("kind", ["16bit", "bgra"])
def test_raw_frames_of_other_depths_round_trip(small_dataset, tmp_path, kind):
    ds = tmp_path / "ds"
    shutil.copytree(small_dataset, ds)
    pngs = [ds / "board.png", *sorted((ds / "stripes").glob("*.png"))]
    orig = {p.name: cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in pngs}
    for p in pngs:
        g = orig[p.name]
        cv2.imwrite(str(p), g.astype(np.uint16) * 257 if kind == "16bit"
                    else cv2.cvtColor(g, cv2.COLOR_GRAY2BGRA))
    bag = tmp_path / "rec.bag"
    write_bag(ds, bag, storage="rosbag1", images="raw", single_camera_topic=True, sweeps=False,
              rig_json=tmp_path / "rig.json", seed=1)
    import_bag(bag, tmp_path / "rig.json", tmp_path / "imp")
    got = load_dataset(tmp_path / "imp")
    assert len(got.positions) == 4
    for pos, src in zip(got.positions, sorted((ds / "stripes").glob("*.png"))):
        img = cv2.imread(str(pos.stripe_image), cv2.IMREAD_GRAYSCALE)
        want = orig[src.name]
        if kind == "16bit":  # mono16 -> 8 bits: / 256, rounded (lidarcal.io.bag)
            want = ((want.astype(np.uint32) * 257 + 128) >> 8).clip(0, 255).astype(np.uint8)
        assert np.array_equal(img, want), src.name
