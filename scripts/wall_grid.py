"""A board held in front of a wall: `calibrate_planes` over a grid of wall steps and range noise.

Simulated one-board views (:func:`lidarcal.synthetic.oneboard.simulate_oneboard` with
``wall_behind_mm``, corners from the true board pose with 0.2 px noise) are scored against the
truth; the real TAPAS views (data/real_tapas) with a wall inserted beside the board (the board's
line shifted back by the step, 120 beams each side, as scripts/real_robustness.py, with the view's
own noise about lines, 3.7-4.3 mm) and Gaussian range noise added to board and wall (integer mm)
are scored against the unperturbed fit of the same method. The board's margins are measured in
the photos (:mod:`lidarcal.board_margin`, as ``lidarcal planes`` does; the simulated photos
rendered) unless ``--assumed-margin`` (the margin assumed, half the pattern's shorter side, as
before the measurement). Prints,
per case: views used, the translation and rotation error, the largest error in units of the
reported (or unperturbed) 1-sigma, and whether the "cannot be told" warning was given.

    .venv/bin/python scripts/wall_grid.py [--seeds 0 1] [--walls 5 10 20 40] [--noise 1 3 5]
                                          [--no-real] [--no-sim] [--assumed-margin]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidarcal.degeneracy import pose_difference
from lidarcal.io.dataset import BoardSpec
from lidarcal.planes import apply_board_margins, calibrate_planes, run_planes
from lidarcal.synthetic.oneboard import (
    render_photo,
    simulate_oneboard,
    views_for_planes,
    wall_beside_board,
)

TOLD = "cannot be told from the surface behind it"


def _row(label: str, res, d6: np.ndarray, sd: np.ndarray, extra: str = "") -> None:
    told = sum(TOLD in w for w in res.warnings)
    ratio = np.abs(d6) / np.where(np.isfinite(sd) & (sd > 0), sd, np.nan)
    print(f"{label:28s} {sum(res.used):2d}/{len(res.used)} |dT| {np.linalg.norm(d6[3:]):7.2f} mm "
          f"drot {np.degrees(np.linalg.norm(d6[:3])):6.3f} deg  max|d|/sig {np.nanmax(ratio):5.2f}"
          f"  told-warnings {told}{extra}", flush=True)


def _sd(res) -> np.ndarray:
    return np.array([np.radians(x) if x is not None else np.nan
                     for x in res.uncertainty.rotation_deg]
                    + [x if x is not None else np.nan for x in res.uncertainty.translation_mm])


def simulated(seeds, walls, noises, assumed: bool) -> None:
    for noise in noises:
        for seed in seeds:
            for wall in [None, *walls]:
                rig = simulate_oneboard(seed, 8, wall_behind_mm=wall, range_noise_mm=noise)
                views = views_for_planes(rig)
                if not assumed:
                    m = apply_board_margins(views, [render_photo(rig, v, k) for k, v in
                                                    enumerate(rig.views)], rig.camera)
                    print(f"  margins measured {m.axis_margin_mm} +- {m.axis_sigma_mm} mm "
                          f"(truth {rig.views[0].rect.pattern[3]:g})")
                res = calibrate_planes(views)
                d6 = pose_difference(res.R, res.T, rig.R, rig.T)
                on = [np.mean(t.on_board[v.beams]) for v, t, u in zip(res.views, rig.views, res.used)
                      if u]
                _row(f"sim seed {seed} noise {noise:g} wall {wall}", res, d6, _sd(res),
                     f"  on-board share of the returns used >= {min(on):.3f}")


def real(walls, noises, assumed: bool) -> None:
    # the reference: the unperturbed fit of the same method (its margins carried by the views)
    full = run_planes(ROOT / "data/real_tapas", ROOT / "data/real_tapas/camera.json",
                      BoardSpec((8, 5), 100.0), assumed_margin=assumed)
    print(f"TAPAS grown extent per axis (u, v): {full.views[0].board.grow_mm} mm")
    sd = np.sqrt(np.diag(full.uncertainty.covariance))
    print(f"TAPAS unperturbed: {sum(full.used)} views, sigma T {np.round(sd[3:], 2)} mm")
    for noise in noises:
        for wall in walls:
            rng = np.random.default_rng(int(10 * wall + noise))
            views = [wall_beside_board(v, wall, noise, rng) for v in full.views]
            res = calibrate_planes(views)
            d6 = pose_difference(res.R, res.T, full.R, full.T)
            kept = [len(np.intersect1d(v.beams, w.beams)) / len(v.beams)
                    for v, w, u in zip(full.views, res.views, res.used) if u]
            _row(f"TAPAS +noise {noise:g} wall {wall:g}", res, d6, sd,
                 f"  share of the board's returns kept >= {min(kept):.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="*", type=int, default=[0, 1])
    ap.add_argument("--walls", nargs="*", type=float, default=[5.0, 10.0, 20.0, 40.0])
    ap.add_argument("--noise", nargs="*", type=float, default=[1.0, 3.0, 5.0])
    ap.add_argument("--no-real", action="store_true")
    ap.add_argument("--no-sim", action="store_true")
    ap.add_argument("--assumed-margin", action="store_true")
    a = ap.parse_args(argv)
    t0 = time.process_time()
    if not a.no_sim:
        simulated(a.seeds, a.walls, a.noise, a.assumed_margin)
    if not a.no_real:
        real(a.walls, a.noise, a.assumed_margin)
    print(f"CPU {time.process_time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
