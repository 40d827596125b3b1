"""``lidarcal planes`` with the board's margins measured (the default) or assumed, against the truth.

Rendered one-board folders (:func:`lidarcal.synthetic.oneboard.write_oneboard`: photos through
the lens, scans with integer-mm ranges) for each seed, board margin and wall (none, or a wall
parallel to every board this far behind it) are calibrated by :func:`lidarcal.planes.run_planes`
both ways. Prints per case the margins measured (truth: the simulated margin), views used, the
largest error in units of the reported 1-sigma, the share of wall returns among those used, and
how many views were named ("cannot be told from the surface behind it").

    .venv/bin/python scripts/margin_truth.py [--seeds 2 3 4] [--margins 60 30] [--walls 0 10]
                                             [--noise 3]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidarcal.degeneracy import pose_difference
from lidarcal.planes import run_planes
from lidarcal.synthetic.oneboard import simulate_oneboard, write_oneboard

TOLD = "cannot be told from the surface behind it"


def case(seed: int, margin: float, wall: float | None, noise: float, tmp: Path) -> list[str]:
    rig = simulate_oneboard(seed, 8, margin_mm=margin, wall_behind_mm=wall, range_noise_mm=noise)
    folder = write_oneboard(rig, tmp / f"s{seed}m{margin:g}w{wall}", seed=seed)
    rows = []
    for assumed in (True, False):
        res = run_planes(folder, folder / "camera.json", rig.board, assumed_margin=assumed)
        d6 = pose_difference(res.R, res.T, rig.R, rig.T)
        sd = np.array([np.radians(x) if x is not None else np.nan
                       for x in res.uncertainty.rotation_deg]
                      + [x if x is not None else np.nan for x in res.uncertainty.translation_mm])
        off = [1.0 - np.mean(t.on_board[v.beams]) for v, t, u in zip(res.views, rig.views, res.used)
               if u]
        bm = res.board_margins
        got = "assumed" if bm is None else f"u {bm['u_mm']} v {bm['v_mm']}"
        rows.append(f"seed {seed} margin {margin:g} wall {wall} {'assumed ' if assumed else 'measured'}"
                    f" ({got}): {sum(res.used)}/{len(res.used)} views, |dT| "
                    f"{np.linalg.norm(d6[3:]):.2f} mm, max|d|/sig {np.nanmax(np.abs(d6) / sd):.2f},"
                    f" wall returns <= {100 * max(off):.1f} %, named {sum(TOLD in w for w in res.warnings)}")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="*", type=int, default=[2, 3, 4])
    ap.add_argument("--margins", nargs="*", type=float, default=[60.0, 30.0])
    ap.add_argument("--walls", nargs="*", type=float, default=[0.0, 10.0])
    ap.add_argument("--noise", type=float, default=3.0)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        for seed in a.seeds:
            for margin in a.margins:
                for wall in a.walls:
                    for row in case(seed, margin, wall or None, a.noise, Path(tmp)):
                        print(row, flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
