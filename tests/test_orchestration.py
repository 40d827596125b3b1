"""How ``lidarcal calibrate`` spreads its work (issue 15) never changes its results.

The stripe images are decoded by a background thread that is stopped, not waited for,
before the positions are solved in forked worker processes (which read the images not
decoded by then); the command line imports with the garbage collector paused and frozen.
"""

from __future__ import annotations

import gc

from conftest import bundled_dataset

from lidarcal.cli import main
from lidarcal.io.dataset import ImagePrefetch, load_dataset
from lidarcal.pipeline import calibrate


def _samples(res) -> list[tuple]:
    return [(p.index, p.pose.R.tobytes(), p.pose.T.tobytes()) for p in res.positions]


def test_positions_are_solved_alike_however_their_images_arrive(tmp_path):
    """8 bundled positions (the worker pool runs for more than 4): prefetched by the default
    thread, decoded by the workers (a prefetch stopped before it started) and solved in this
    process one after the other give bit-identical single-shot poses."""
    ds = load_dataset(bundled_dataset(tmp_path / "ds", n=8))
    default = calibrate(ds, method="rigid", workers=2)
    stopped = ImagePrefetch(ds.positions, ds.image_size, laser_colour=ds.lidar.laser_colour)
    stopped.close()
    by_workers = calibrate(ds, method="rigid", workers=2, images=stopped)
    serial = calibrate(ds, method="rigid", workers=1)
    assert len(default.positions) == 8 and not default.skipped
    assert _samples(by_workers) == _samples(default)
    assert _samples(serial) == _samples(default)
    assert default.model.axis.direction.tobytes() == serial.model.axis.direction.tobytes()


def test_main_in_process_leaves_the_garbage_collector_as_found(small_dataset, tmp_path):
    """``main(argv)`` called in-process (tests, notebooks) unfreezes what it froze and leaves
    the collector enabled or disabled as it was."""
    assert gc.get_freeze_count() == 0
    assert main(["calibrate", str(small_dataset), "--out", str(tmp_path / "a"),
                 "--method", "rigid", "--no-progress"]) == 0
    assert gc.isenabled() and gc.get_freeze_count() == 0
    gc.disable()
    try:
        assert main(["calibrate", str(small_dataset), "--out", str(tmp_path / "b"),
                     "--method", "rigid", "--no-progress"]) == 0
        assert not gc.isenabled() and gc.get_freeze_count() == 0
    finally:
        gc.enable()
