"""Semi-real laser photos (lidarcal.synthetic.semireal) through `lidarcal laser-plane`:
plane error against the truth (deg, mm), rms, photos used, CPU seconds; one line per kind.

    .venv/bin/python scripts/semireal_laser.py OUT_DIR [KIND ...] [-v]

KIND: a key of lidarcal.synthetic.semireal.KINDS (default: all), or simN / simjpegN: the
rendered photos of lidarcal.synthetic.laserphotos (seed N; 14 photos, one where the laser
misses the board, one overexposed). ``sigma``: the bootstrap sigma of the normal and of
``d`` that `lidarcal laser-plane` reports, beside the true error of ``d``.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from lidarcal.geometry import Plane
from lidarcal.io.dataset import BoardSpec, DatasetError
from lidarcal.laserplane import laser_plane, read_camera_json
from lidarcal.synthetic.laserphotos import LaserPhotoConfig, write_laser_photos
from lidarcal.synthetic.semireal import KINDS, write_semireal_photos

REAL = Path(__file__).resolve().parents[1] / "data" / "real_tapas"


def main(out: Path, kinds: list[str], verbose: bool = False) -> None:
    for kind in kinds or list(KINDS):
        folder = out / kind
        if not (folder / "truth.json").exists():
            if kind.startswith("sim"):  # the rendered photos: simN, simjpegN (seed N)
                seed = int(kind.lstrip("simjpeg"))
                cfg = LaserPhotoConfig(jpeg_quality=90 if "jpeg" in kind else None)
                write_laser_photos(folder, seed=seed, n_photos=16, cfg=cfg, miss=(14,),
                                   overexposed=(15,))
            else:
                write_semireal_photos(REAL, folder, kind)
        t = json.loads((folder / "truth.json").read_text())
        n = np.asarray(t["laser_plane"]["normal"])
        d = t["laser_plane"]["d_mm"]
        c0 = time.process_time()
        m0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        try:
            r = laser_plane(folder, BoardSpec(tuple(t["pattern"]), t["square_mm"]),
                            read_camera_json(folder / "camera.json"))
        except DatasetError as e:
            print(f"{kind:9s} error: {e}", flush=True)
            continue
        cpu = time.process_time() - c0
        ang = np.degrees(np.arccos(min(1.0, abs(r.plane.normal @ n))))
        # offset: the truth plane's distance at the used points' centroid
        used = [p for p in r.photos if p.used]
        cen = np.vstack([p.points_mm for p in used]).mean(0)
        off = abs(n @ cen - d)
        dd = abs(r.plane.d - d * np.sign(r.plane.normal @ n))
        print(f"{kind:9s} {ang:.3f} deg {off:.3f} mm rms {r.rms_mm:.3f} mm used "
              f"{len(used)}/{len(r.photos)} sigma {r.sigma_normal_deg:.3f} deg "
              f"{r.sigma_d_mm:.3f} mm (|d error| {dd:.3f} mm) cpu {cpu:.1f} s maxrss "
              f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB "
              f"(before {m0 / 1024:.0f})", flush=True)
        truth = Plane.from_normal_point(n, n * d)
        for p in r.photos:
            if not p.used:
                print(f"    {p.name}: {p.problem}")
            elif verbose:
                e = truth.distance(p.points_mm)
                print(f"    {p.name}: {len(e)} points, to the true plane rms "
                      f"{np.sqrt(np.mean(e ** 2)):.3f} max {np.abs(e).max():.2f} mm, "
                      f"stripe rms {p.rms_px:.2f} px")


if __name__ == "__main__":
    args = [a for a in sys.argv[2:] if a != "-v"]
    main(Path(sys.argv[1]), args, "-v" in sys.argv[2:])
