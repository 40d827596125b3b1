"""Which returns the board's measured margins drop or add, per view of a real pairs folder.

``lidarcal planes`` is run twice on the folder (default data/real_tapas): with the board's margins
measured in the photos (the default) and with the margin assumed (``--assumed-margin``). Per view
the beams taken as the board by one fit and not the other are listed with, in the board frame of
the fit with the assumed margin (eq. 1, the camera's board pose), how far beyond the printed
pattern they fall, how far beyond the measured edge (pattern + margin) and their distance from the
board plane: ``edge`` (within 12 mm of the measured edge: the beam's footprint on the edge, or the
pose's own error along the board) or ``beyond`` (what stands in line with the board past its edge:
TAPAS's aluminium stand and its brackets). With ``--png DIR`` every view's photo is drawn with its
returns: green taken by both fits, red only with the assumed margin, blue only with the measured
one, grey neither. The two poses' difference is printed in the assumed fit's sigmas.

    .venv/bin/python scripts/margin_beams.py [DIR] [--png DIR]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lidarcal.degeneracy import pose_difference
from lidarcal.io.pairs import board_spec
from lidarcal.overlay import project_returns
from lidarcal.planes import run_planes
from lidarcal.planes_wall import pattern_extent
from lidarcal.scan import scan_points

#: Returns within this of the measured edge are the edge's (a few beams at 0.25 deg and ~1 m).
EDGE_MM = 12.0


def beam_table(v, R: np.ndarray, T: np.ndarray, beams: np.ndarray, margin_uv: np.ndarray
               ) -> list[dict]:
    """Per beam: its board-frame ``(u, v)`` mapped by ``(R, T)``, mm beyond the printed pattern
    and beyond the measured edge, distance from the board plane, and its kind."""
    p = scan_points(v.angle_deg[beams], v.range_mm[beams])
    X = np.column_stack([p, np.zeros(len(p))]) @ R.T + T
    uv = (X - v.board.T) @ v.board.R[:, :2]
    lo, hi, _ = pattern_extent(v.board.board)
    out_pat = np.maximum(lo - uv, uv - hi)  # per axis, mm beyond the pattern (< 0: inside)
    beyond = np.max(out_pat - margin_uv, axis=1)
    dist = v.board.plane.distance(X)
    return [{"beam": int(b), "range_mm": float(v.range_mm[b]), "u": float(q[0]), "v": float(q[1]),
             "beyond_pattern_mm": float(np.max(o)), "beyond_edge_mm": float(e),
             "plane_mm": float(d), "kind": "inside" if e <= 0 else "edge" if e <= EDGE_MM
             else "beyond"} for b, q, o, e, d in zip(beams, uv, out_pat, beyond, dist)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", nargs="?", default=str(ROOT / "data" / "real_tapas"))
    ap.add_argument("--png", type=Path, default=None)
    a = ap.parse_args(argv)
    folder = Path(a.folder)
    board = board_spec(folder)
    old = run_planes(folder, folder / "camera.json", board, assumed_margin=True)
    new = run_planes(folder, folder / "camera.json", board)
    bm = new.board_margins
    print(f"margins measured: u {bm['u_mm']} +- {bm['sigma_u_mm']} mm, v {bm['v_mm']} +- "
          f"{bm['sigma_v_mm']} mm; {bm['fallback'] or 'both axes measured'}")
    d6 = pose_difference(new.R, new.T, old.R, old.T)
    sd = np.sqrt(np.diag(old.uncertainty.covariance))
    print(f"pose change: |dT| {np.linalg.norm(d6[3:]):.2f} mm (dT {np.round(d6[3:], 2)}), "
          f"drot {np.degrees(np.linalg.norm(d6[:3])):.3f} deg; per parameter in the assumed fit's "
          f"sigmas {np.round(np.abs(d6) / sd, 2)}; RMS {old.total_rms_mm:.2f} -> "
          f"{new.total_rms_mm:.2f} mm")
    for va, vn, ra, rn in zip(old.views, new.views, old.rms_mm, new.rms_mm):
        if va.board is None:
            continue
        g = np.array([bm["u_mm"] or np.inf, bm["v_mm"] or np.inf])
        g = g if va.board.board.inner_corners == board.inner_corners else g[::-1]
        print(f"{va.name}: {len(va.beams)} -> {len(vn.beams)} board returns, RMS "
              f"{ra:.2f} -> {rn:.2f} mm")
        for label, beams in (("dropped", np.setdiff1d(va.beams, vn.beams)),
                             ("added", np.setdiff1d(vn.beams, va.beams))):
            rows = beam_table(va, old.R, old.T, beams, g)
            for kind in ("inside", "edge", "beyond"):
                k = [r for r in rows if r["kind"] == kind]
                if not k:
                    continue
                be = [r["beyond_edge_mm"] for r in k]
                pl = [r["plane_mm"] for r in k]
                print(f"  {label} {len(k):3d} {kind:6s} beams {k[0]['beam']}-{k[-1]['beam']}: "
                      f"{min(be):6.1f} to {max(be):6.1f} mm beyond the measured edge, "
                      f"{min(pl):6.1f} to {max(pl):5.1f} mm from the board plane")
        if a.png is not None:
            a.png.mkdir(parents=True, exist_ok=True)
            pair = next(p for p in old.pairs if p.name == va.name)
            img = cv2.imread(str(pair.image_path))
            px, _, ok = project_returns(old.camera, old.R, old.T, va.angle_deg, va.range_mm)
            for b in np.flatnonzero(ok):
                c = ((0, 200, 0) if b in va.beams and b in vn.beams else (0, 0, 255)
                     if b in va.beams else (255, 0, 0) if b in vn.beams else (128, 128, 128))
                cv2.circle(img, tuple(np.rint(px[b]).astype(int).tolist()), 2, c, -1)
            cv2.imwrite(str(a.png / f"margin_beams_{va.name}.png"), img)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
