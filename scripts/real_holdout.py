"""Held-out performance of ``lidarcal planes`` on the real TAPAS views (cross-validation).

Every split of the views into a training set (fitted by :func:`lidarcal.planes.calibrate_planes`)
and held-out views (leave-1-out, leave-2-out, leave-3-out by default): the held-out views' board
returns (the beams the all-views fit chose) mapped by the training pose, their point-to-plane RMS
against the held-out views' own board planes (from their photos), and its ratio to the in-sample
RMS of the all-views fit (issue 13's acceptance: held-out <= 6 mm and <= 1.25x in-sample). Also:
the training pose's distance from the all-views pose in the training fit's own sigmas (does the
sigma cover the leave-out error?) and whether the training fit named an undetermined direction.

    .venv/bin/python scripts/real_holdout.py [DIR] [--min-out 1] [--max-out 3] [--csv FILE]
                                             [--assumed-margin]

The board's margins are measured in the photos, as ``lidarcal planes`` does (``--assumed-margin``:
the margin assumed, half the pattern's shorter side; the numbers below are with it, measured
before the margins; with them: in-sample 4.21 mm, leave-1-out 3.96-5.82 mm, ratio 0.94-1.38).

Measured on data/real_tapas (in-sample RMS of the 7-view fit 4.25 mm): leave-1-out held-out RMS
3.85-5.74 mm (ratio 0.90-1.35; 00 and 01 above 1.25: their own in-sample RMS is 4.75 and 4.50
mm, a sag of ~6 mm along board 00; trimming edge returns, a range offset or a dark-square bias
do not explain it). Before the restarts and the profile check, 5 splits were 110-230 mm off,
2 of them silently (held out 00 05 06 and 01 05 06: 4 views with boards within 7-18 deg of
perpendicular to the scan plane); after, every split more than 30 mm off names an undetermined
direction (sigma null), 5 of those now land within 10 mm, and 4 four-view splits adopt a far
valley that fits as well (named, sigma null).
"""

from __future__ import annotations

import argparse
import copy
import itertools
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from lidarcal.io.dataset import DatasetError
from lidarcal.io.pairs import board_spec
from lidarcal.planes import calibrate_planes, plane_residuals_mm, run_planes


def holdout_table(views, full, max_out: int = 3, min_out: int = 1, seed: int = 0) -> list[dict]:
    """One row per split: training views fitted, held-out views scored (see the module doc)."""
    names = [v.name for v in views]
    rows = []
    for k in range(min_out, max_out + 1):
        for out in itertools.combinations(range(len(views)), k):
            train = [copy.copy(views[j]) for j in range(len(views)) if j not in out]
            for t in train:
                t.beams = np.zeros(0, int)
            row = {"held_out": " ".join(names[j] for j in out), "k": k}
            try:
                r = calibrate_planes(train, seed=seed)
            except DatasetError as e:
                row.update(error=e.problem.split(";")[0])
                rows.append(row)
                continue
            res = np.concatenate([plane_residuals_mm(views[j], r.R, r.T) for j in out])
            ins = np.concatenate([plane_residuals_mm(views[j], full.R, full.T) for j in out])
            drot = Rotation.from_matrix(r.R @ full.R.T).as_rotvec()
            dT = r.T - full.T
            cov = r.uncertainty.covariance
            d6 = np.concatenate([drot, dT])
            und = bool(r.uncertainty.undetermined)
            # Mahalanobis distance of the all-views pose in the training fit's covariance (over
            # its determined directions)
            mah = float(np.sqrt(d6 @ np.linalg.pinv(cov, rcond=1e-12, hermitian=True) @ d6))
            row.update(rms=float(np.sqrt(np.mean(res ** 2))),
                       in_sample_same=float(np.sqrt(np.mean(ins ** 2))),
                       ratio=float(np.sqrt(np.mean(res ** 2))) / full.total_rms_mm,
                       dT=float(np.linalg.norm(dT)), drot_deg=float(np.degrees(np.linalg.norm(drot))),
                       mahal=mah, undetermined=und,
                       warned=any("undetermined" in w or "too few" in w for w in r.warnings),
                       scale=r.refined.noise_scale)
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default=str(REPO / "data" / "real_tapas"))
    ap.add_argument("--camera", default=None, help="camera.json (default: FOLDER/camera.json)")
    ap.add_argument("--max-out", type=int, default=3)
    ap.add_argument("--min-out", type=int, default=1)
    ap.add_argument("--csv", default=None)
    ap.add_argument("--assumed-margin", action="store_true")
    a = ap.parse_args(argv)
    folder = Path(a.folder)
    cpath = Path(a.camera) if a.camera else folder / "camera.json"
    t0 = time.process_time()
    full = run_planes(folder, cpath, board_spec(folder), assumed_margin=a.assumed_margin)
    views = full.views
    print(f"board margins: {full.board_margins}")
    print(f"all {len(views)} views: in-sample point-to-plane RMS {full.total_rms_mm:.2f} mm "
          f"(per view {', '.join(f'{x:.2f}' for x in full.rms_mm)})")
    rows = holdout_table(views, full, a.max_out, a.min_out)
    print(f"{'held out':10s} {'RMS mm':>7s} {'same,7':>7s} {'ratio':>6s} {'|dT| mm':>8s} "
          f"{'drot deg':>8s} {'mahal':>6s} {'undet':>5s} {'warned':>6s}")
    for r in rows:
        if "error" in r:
            print(f"{r['held_out']:10s} error: {r['error']}")
            continue
        print(f"{r['held_out']:10s} {r['rms']:7.2f} {r['in_sample_same']:7.2f} {r['ratio']:6.2f} "
              f"{r['dT']:8.1f} {r['drot_deg']:8.2f} {r['mahal']:6.1f} {r['undetermined']!s:>5s} "
              f"{r['warned']!s:>6s}")
    for k in sorted({r["k"] for r in rows}):
        ok = [r for r in rows if r["k"] == k and "error" not in r]
        det = [r for r in ok if not r["undetermined"]]
        if not ok:
            continue
        rat = np.array([r["ratio"] for r in ok])
        print(f"leave-{k}-out: {len(ok)} splits; held-out RMS median "
              f"{np.median([r['rms'] for r in ok]):.2f} mm, max {max(r['rms'] for r in ok):.2f}; "
              f"ratio median {np.median(rat):.2f}, max {rat.max():.2f}; "
              f"> 1.25x: {int(np.sum(rat > 1.25))}; undetermined {len(ok) - len(det)}; "
              f"determined with ratio > 1.25: {sum(r['ratio'] > 1.25 for r in det)}; "
              f"mahal > 3 (determined): {sum(r['mahal'] > 3 for r in det)}")
    print(f"CPU {time.process_time() - t0:.1f} s")
    if a.csv:
        import pandas as pd

        pd.DataFrame(rows).to_csv(a.csv, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
