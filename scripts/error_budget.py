"""Per-step error budget of ``lidarcal calibrate`` against a simulated dataset's truth.json.

Walks section 1 step by step at every position and compares each estimate with the truth:
the board planes (eqs. 1-3), the laser plane (eq. 4), E and alpha (section 1.3), the scan's
vertex and lines in the LiDAR frame (eqs. 7-12), the single-shot pose (eqs. 13-14), and the
pose functions (paper, rigid, joint). Then it swaps truth in for the camera side (truth board
planes "B", truth laser plane "L", both "BL") and refits the samples and the rigid pose
function, which splits the pose function's error into the camera side's share and the scan's
floor; and it prints the Cramer-Rao bound of the V fit (:func:`lidarcal.evaluate.v_fit_crlb`)
next to the samples' true centre error.

    .venv/bin/python scripts/error_budget.py /tmp/w37            # camera as the dataset has it
    .venv/bin/python scripts/error_budget.py /tmp/w37 --true-camera   # truth.json's camera

``--true-camera`` writes a linked copy of the dataset with truth.json's camera block in
dataset.json (the intrinsics' share is the difference of the two runs).

``--white-noise N`` (issue 13) tests the scan side for a systematic error: it prints the
range errors of the returns the V split keeps against the truth (their mean, spread, the
chi-square of the per-segment means against white noise, and by incidence), then refits the
rigid pose function with the true camera side ("BL") from N copies of the scans in which every
kept return is replaced by its true range plus white noise of the injected sigma, and prints
where the rendered scans' value falls among them (a systematic scan error would put it far
above the white-noise spread).

    .venv/bin/python scripts/error_budget.py /tmp/wj_w7 --white-noise 40
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd


def with_true_camera(path: Path, tmp: Path) -> Path:
    """A copy of the dataset (files linked) whose dataset.json holds truth.json's camera."""
    out = tmp / path.name
    out.mkdir()
    for f in path.iterdir():
        if f.name != "dataset.json":
            (out / f.name).symlink_to(f.resolve())
    ds = json.loads((path / "dataset.json").read_text())
    ds["camera"] = json.loads((path / "truth.json").read_text())["camera"]
    (out / "dataset.json").write_text(json.dumps(ds, indent=1))
    return out


def step_table(res, truth: dict, scans: dict) -> pd.DataFrame:
    from lidarcal.evaluate import (
        angle_between_deg,
        match_planes,
        plane_error,
        pose_error,
        truth_board_planes,
        truth_laser_plane,
        truth_lines,
        truth_poses,
        v_fit_crlb,
    )
    from lidarcal.io.dataset import read_scan
    from lidarcal.scan import scan_points

    tp, TB = truth_poses(truth), truth_board_planes(truth)
    sigma = float(truth["noise"]["range_noise_mm"])
    rows = []
    for p in res.positions:
        cl, ll, P = p.camera_lines, p.lidar_lines, tp[p.index]
        Et, lt, alpha_t = truth_lines(truth, p.index, match_planes(list(cl.board_planes), TB))
        lpe = plane_error(cl.laser_plane, truth_laser_plane(P))
        El_t = P.R.T @ (Et - P.T)
        pairs = list(p.pose.info["pairs"])
        l_lid = np.array([ll.l1, ll.l2])[pairs]
        lt_l = (P.R.T @ lt.T).T
        dl = [min(a, 180 - a) for a in (angle_between_deg(np.r_[l_lid[k], 0], lt_l[k])
                                        for k in range(2))]
        ang, rng = read_scan(scans[p.index], res.dataset.lidar)
        pts = scan_points(ang, rng)
        bound = v_fit_crlb(pts[p.segments.first], pts[p.segments.second], ll.line1.normal,
                           (ll.line1.offset, ll.line2.offset), ll.alpha, ll.sign, sigma)
        e = pose_error(p.pose, P)
        rows.append({"index": p.index, "laser_deg": lpe["normal_deg"], "laser_mm": lpe["offset_mm"],
                     "E_cam_mm": float(np.linalg.norm(cl.E - Et)),
                     "alpha_mdeg": 1e3 * np.degrees(cl.alpha - alpha_t),
                     "E_lidar_mm": float(np.linalg.norm(ll.E - El_t[:2])),
                     "lines_deg": float(np.mean(dl)), "crlb_centre_mm": bound["centre_rms_mm"],
                     "centre_mm": e["centre_mm"], "z_axis_deg": e["z_axis_deg"],
                     "x_axis_deg": e["x_axis_deg"]})
    return pd.DataFrame(rows)


def oracle_table(res, truth: dict, scans: dict) -> pd.DataFrame:
    """Rigid pose function refitted with truth swapped in on the camera side."""
    from lidarcal.evaluate import (
        match_planes,
        pose_error,
        truth_board_planes,
        truth_laser_plane,
        truth_poses,
    )
    from lidarcal.geometry import intersect_planes, unit
    from lidarcal.io.dataset import read_scan
    from lidarcal.pose import single_shot_pose
    from lidarcal.scan import fit_v_lines, scan_points
    from lidarcal.turntable import fit_paper, fit_rigid

    tp, TB = truth_poses(truth), truth_board_planes(truth)
    rows = []
    for mode in ("estimate", "B", "L", "BL"):
        S, psi = [], []
        for p in res.positions:
            cl = p.camera_lines
            boards = ([TB[k] for k in match_planes(list(cl.board_planes), TB)] if "B" in mode
                      else list(cl.board_planes))
            L = truth_laser_plane(tp[p.index]) if "L" in mode else cl.laser_plane
            E = intersect_planes(boards[0], boards[1], L)
            l = np.array([unit(np.cross(b.normal, L.normal)) for b in boards])
            l *= np.sign(np.sum(l * cl.l, axis=1))[:, None]
            alpha = float(np.arccos(np.clip(l[0] @ l[1], -1, 1)))
            ang, rng = read_scan(scans[p.index], res.dataset.lidar)
            pts = scan_points(ang, rng)
            ll = fit_v_lines(pts[p.segments.first], pts[p.segments.second], alpha)
            S.append(single_shot_pose(l, E, alpha, ll, res.dataset.lidar.z_axis_hint))
            psi.append(p.psi_deg)
        psi = np.array(psi)
        rigid = fit_rigid(psi, S, init=fit_paper(psi, S))
        fe = pd.DataFrame([pose_error(rigid.pose(a), tp[p.index])
                           for a, p in zip(psi, res.positions)])
        se = np.mean([pose_error(s, tp[p.index])["centre_mm"] for s, p in zip(S, res.positions)])
        rows.append({"camera side": mode, "samples_centre_mm": se,
                     **{f"rigid_{k}": v for k, v in fe.mean().items()}})
    return pd.DataFrame(rows)


def _bl_camera(p, truth: dict):
    """Truth's camera side at one position in the estimate's board order: E, rays l, alpha."""
    from lidarcal.evaluate import match_planes, truth_board_planes, truth_lines

    return truth_lines(truth, p.index, match_planes(list(p.camera_lines.board_planes),
                                                    truth_board_planes(truth)))


def range_error_table(res, truth: dict, scans: dict) -> tuple[dict, pd.DataFrame]:
    """Range errors (measured - true, mm) of the kept returns: summary and by incidence."""
    from scipy import stats

    from lidarcal.evaluate import scan_range_errors, segment_boards, truth_scan_line
    from lidarcal.io.dataset import read_scan

    sigma = float(truth["noise"]["range_noise_mm"])
    err, inc, chi2, k, slopes = [], [], 0.0, 0, []
    for p in res.positions:
        ang, rng = read_scan(scans[p.index], res.dataset.lidar)
        for beams, board in zip((p.segments.first, p.segments.second), segment_boards(truth, p)):
            r = scan_range_errors(truth_scan_line(truth, p.index, board), ang[beams], rng[beams])
            err.append(r["error_mm"])
            inc.append(r["incidence_deg"])
            chi2 += (r["error_mm"].mean() * np.sqrt(len(beams)) / sigma) ** 2
            k += 1
            # tilt: slope of the error from the fold (x = -1) to the outer end (x = +1)
            x = np.linspace(1.0, -1.0, len(beams)) if len(slopes) % 2 == 0 else \
                np.linspace(-1.0, 1.0, len(beams))
            slopes.append((x @ r["error_mm"] / (x @ x), sigma / np.sqrt(x @ x)))
    e, i = np.concatenate(err), np.concatenate(inc)
    summary = {"n": len(e), "mean_mm": e.mean(), "sem_mm": e.std() / np.sqrt(len(e)),
               "std_mm": e.std(), "injected_sigma_mm": sigma, "segments": k,
               "chi2_segment_means": chi2, "chi2_p_value": float(stats.chi2.sf(chi2, k))}
    b, sb = np.array(slopes).T
    summary.update(tilt_mean_mm=float(np.mean(b)), tilt_sem_mm=float(np.sqrt(np.sum(sb ** 2)) / k),
                   chi2_tilts=float(np.sum((b / sb) ** 2)),
                   chi2_tilts_p_value=float(stats.chi2.sf(np.sum((b / sb) ** 2), k)))
    bins = pd.cut(i, np.arange(0.0, 91.0, 10.0), right=False)
    table = pd.DataFrame({"error_mm": e, "incidence": bins}).groupby("incidence", observed=True)
    return summary, table.error_mm.agg(["count", "mean", "std"])


def white_noise_floor(res, truth: dict, scans: dict, n: int, seed: int = 0,
                      camera: str = "truth") -> dict:
    """The rigid pose function's mean true centre error with the true camera side (``camera=
    "truth"``, "BL") or the estimated one (``"estimate"``), from the rendered scans and from
    ``n`` copies whose kept returns read true range + white noise."""
    from lidarcal.evaluate import pose_error, segment_boards, truth_poses, truth_scan_line
    from lidarcal.io.dataset import read_scan
    from lidarcal.pose import single_shot_pose
    from lidarcal.scan import fit_v_lines, scan_points
    from lidarcal.turntable import fit_paper, fit_rigid

    tp = truth_poses(truth)
    sigma = float(truth["noise"]["range_noise_mm"])
    hint = res.dataset.lidar.z_axis_hint
    setup = []
    for p in res.positions:
        ang, rng = read_scan(scans[p.index], res.dataset.lidar)
        segs = []
        for beams, board in zip((p.segments.first, p.segments.second), segment_boards(truth, p)):
            line = truth_scan_line(truth, p.index, board)
            th = np.radians(ang[beams])
            b = np.column_stack([np.cos(th), np.sin(th)])
            segs.append((b, scan_points(ang, rng)[beams], line.offset / (b @ line.normal)))
        cl = p.camera_lines
        setup.append((p, _bl_camera(p, truth) if camera == "truth" else (cl.E, cl.l, cl.alpha),
                      segs))
    psi = np.array([p.psi_deg for p in res.positions])

    def rigid_error(noise: np.random.Generator | None) -> float:
        S = []
        for p, (E, l, alpha), segs in setup:
            pts = [q if noise is None else b * (r + noise.normal(0.0, sigma, len(r)))[:, None]
                   for b, q, r in segs]
            S.append(single_shot_pose(l, E, alpha, fit_v_lines(pts[0], pts[1], alpha), hint))
        rigid = fit_rigid(psi, S, init=fit_paper(psi, S))
        return float(np.mean([pose_error(rigid.pose(a), tp[p.index])["centre_mm"]
                              for a, (p, _, _) in zip(psi, setup)]))

    rendered = rigid_error(None)
    rs = np.random.default_rng(seed)
    white = np.array([rigid_error(rs) for _ in range(n)])
    return {"rendered_mm": rendered, "white_mean_mm": white.mean(),
            "white_median_mm": float(np.median(white)), "white_min_mm": white.min(),
            "white_max_mm": white.max(), "rendered_percentile": 100 * np.mean(white < rendered)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--true-camera", action="store_true")
    ap.add_argument("--white-noise", type=int, default=0, metavar="N",
                    help="also test the scan side for a systematic error against N white-noise copies")
    args = ap.parse_args()
    from lidarcal.evaluate import (
        match_planes,
        plane_error,
        pose_error,
        truth_board_planes,
        truth_poses,
    )
    from lidarcal.io.dataset import load_dataset
    from lidarcal.pipeline import calibrate

    pd.set_option("display.width", 200)
    with tempfile.TemporaryDirectory() as tmp:
        path = with_true_camera(args.dataset, Path(tmp)) if args.true_camera else args.dataset
        truth = json.loads((path / "truth.json").read_text())
        res = calibrate(path, method="joint", workers=1)
        scans = {p.index: p.scan for p in load_dataset(path).positions}
        print(f"{args.dataset}: camera from {res.camera.source}, {len(res.positions)} positions")
        TB = truth_board_planes(truth)
        bp = res.positions[0].camera_lines.board_planes
        for k, (b, m) in enumerate(zip(bp, match_planes(list(bp), TB))):
            e = plane_error(b, TB[m])
            print(f"board {k}: normal {e['normal_deg']:.4f} deg, offset {e['offset_mm']:.4f} mm")
        st = step_table(res, truth, scans)
        print("per step, mean of the absolute errors over positions:")
        print(st.drop(columns="index").abs().mean().round(4).to_string())
        print(f"alpha signed mean {st.alpha_mdeg.mean():.2f} mdeg, std {st.alpha_mdeg.std():.2f}")
        tp = truth_poses(truth)
        for name, model in res.models.items():
            fe = pd.DataFrame([pose_error(q, tp[i]) for i, q in res.fitted(model).items()])
            print(f"{name:6s} pose function mean: " +
                  ", ".join(f"{k} {v:.4f}" for k, v in fe.mean().items()))
        print(oracle_table(res, truth, scans).round(4).to_string(index=False))
        if args.white_noise:
            summary, by_inc = range_error_table(res, truth, scans)
            print("kept returns' range errors against truth: " +
                  ", ".join(f"{k} {v:.4g}" for k, v in summary.items()))
            print(by_inc.round(3).to_string())
            for cam in ("truth", "estimate"):
                floor = white_noise_floor(res, truth, scans, args.white_noise, camera=cam)
                print(f"rigid pose function, {cam} camera side: " +
                      ", ".join(f"{k} {v:.4g}" for k, v in floor.items()))


if __name__ == "__main__":
    main()
