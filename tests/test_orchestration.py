"""How ``lidarcal calibrate`` spreads its work (issue 15) never changes its results.

The stripe images are decoded by a background thread that is stopped, not waited for,
before the positions are solved in forked worker processes (which read the images not
decoded by then); the command line imports with the garbage collector paused and frozen,
and its process reuses freed memory; ``LIDARCAL_TRACE`` marks the phases.
"""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys

import numpy as np
from conftest import bundled_dataset

from lidarcal.cli import main
from lidarcal.io.dataset import ImagePrefetch, load_dataset, read_stripe_image, spread_indices
from lidarcal.pipeline import calibrate, dataset_hash


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


def test_prefetch_decodes_the_images_asked_for_first(tmp_path):
    """``first`` images are decoded before the others: with room for only two images, those
    two (and no other) are held, as their own decoding reads them."""
    ds = load_dataset(bundled_dataset(tmp_path / "ds", n=8))
    w, h = ds.image_size
    with ImagePrefetch(ds.positions, ds.image_size, max_bytes=2 * w * h,
                       laser_colour=ds.lidar.laser_colour, first=[5, 2, 5, 99]) as pre:
        pre.join()
        held = [p.index for p in ds.positions if pre.get(p) is not None]
        assert held == [ds.positions[2].index, ds.positions[5].index]
        ref = read_stripe_image(ds.positions[5].stripe_image, ds.image_size,
                                ds.lidar.laser_colour)
        assert np.array_equal(pre.get(ds.positions[5]), ref)


def test_calibrate_prefetch_decodes_the_reflectance_images_first(tmp_path):
    """The prefetch calibrate (and the CLI) starts queues the positions the reflectance ratio
    reads before the workers fork (pipeline._rho_picks) ahead of the others."""
    from lidarcal.io.dataset import prefetch_stripe_images
    from lidarcal.pipeline import _rho_picks

    ds = load_dataset(bundled_dataset(tmp_path / "ds", n=12))
    picks = _rho_picks(ds.positions)
    with prefetch_stripe_images(ds, ds.positions) as pre:
        order = [p.index for p in pre._todo]
    assert order[:len(picks)] == [ds.positions[k].index for k in picks]
    assert sorted(order) == sorted(p.index for p in ds.positions)


def test_spread_indices():
    """Both ends, evenly spaced, distinct, at most k (all of a short list)."""
    assert spread_indices(87, 5) == [0, 22, 43, 64, 86]
    assert spread_indices(3, 5) == [0, 1, 2]
    assert spread_indices(1, 5) == [0]
    assert spread_indices(0, 5) == []
    got = spread_indices(40, 7)
    assert got[0] == 0 and got[-1] == 39 and len(set(got)) == 7
    assert max(np.diff(got)) - min(np.diff(got)) <= 1


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


def _without_command(path) -> dict:
    cal = json.loads(path.read_text())
    cal["provenance"].pop("command")
    return cal


def test_the_command_process_writes_what_main_writes_in_process_and_traces_it(tmp_path):
    """``python -m lidarcal calibrate`` as its own process (glibc's allocator set to reuse
    freed memory, :func:`lidarcal.cli._reuse_freed_memory`, and ``LIDARCAL_TRACE=1``) writes
    the calibration.json that ``main()`` called in-process (neither) writes, and its stderr
    carries the phase marks of :mod:`lidarcal.trace`: in order, one per position from two
    forked workers, every image decoded by the background thread."""
    ds = bundled_dataset(tmp_path / "ds", n=8)
    assert main(["calibrate", str(ds), "--out", str(tmp_path / "a"), "--no-progress"]) == 0
    p = subprocess.run([sys.executable, "-m", "lidarcal", "calibrate", str(ds), "--out",
                        str(tmp_path / "b"), "--no-progress"], capture_output=True, text=True,
                       env={**os.environ, "LIDARCAL_TRACE": "1"}, check=False)
    assert p.returncode == 0, p.stderr
    assert _without_command(tmp_path / "b" / "calibration.json") == \
        _without_command(tmp_path / "a" / "calibration.json")
    # the hash computed in a thread while the pose functions are fitted is the dataset's
    cal = json.loads((tmp_path / "b" / "calibration.json").read_text())
    assert cal["provenance"]["dataset_sha256"] == dataset_hash(load_dataset(ds))
    marks = [line.split() for line in p.stderr.splitlines() if line.startswith("lidarcal-trace ")]
    assert all(line.startswith(("lidarcal-trace ", "warning: ")) for line in p.stderr.splitlines())
    pids = {m[2] for m in marks}
    parent = marks[0][2]
    main_phases = [m[1] for m in marks if m[2] == parent and m[3] == "thread=MainThread"]
    order = ["start", "numpy", "cli", "args", "dataset", "imports", "camera", "boards", "rho",
             "decode-stopped", "positions", "fits", "joint", "written", "main-end", "atexit"]
    assert [ph for ph in main_phases if ph in order] == order
    tasks = [m for m in marks if m[1] == "task"]
    assert sorted(int(m[-1].split("=")[1]) for m in tasks) == list(range(8))
    assert {m[2] for m in tasks} <= pids - {parent} and len(pids - {parent}) == 2
    decoded = [m for m in marks if m[1] == "decode-end"]
    assert len(decoded) == 1 and "decoded=8" in decoded[0] and "of=8" in decoded[0]
    walls = [float(m[4].split("=")[1]) for m in marks if m[2] == parent and m[3] == "thread=MainThread"]
    assert walls == sorted(walls)
