"""The camera side of a simulated dataset against its truth.json: corners, intrinsics, board planes.

Three tables, each against truth (the true camera and the true board poses of truth.json):

1. corners: detected chessboard corners against the true projections, on board.png (both
   boards of the V) and on the intrinsics photos: RMS (px) and bias (mean dx, dy, px) of the
   corners ``calibrate`` uses ("lidarcal final": ``find_v_boards`` with the true camera,
   ``calibrate_intrinsics``), of lidarcal's detector (and the saddle points of :func:`lidarcal.corners.saddle_corners`
   from its corners, the V boards' sub-pixel candidate) beside plain OpenCV
   (``findChessboardCorners`` + ``cornerSubPix`` with fixed windows;
   ``findChessboardCornersSB`` with and without ``CALIB_CB_ACCURACY``);
2. intrinsics: ``calibrate_intrinsics`` (what ``lidarcal intrinsics`` and ``calibrate`` use)
   beside plain ``cv2.calibrateCamera`` on the same photos: ray direction error over the
   image (mean, max, deg) and fx, fy, cx, cy errors (px);
3. board planes: normal (deg) and distance (mm) errors of the V boards from board.png by the
   homography (eqs. 2-3), solvePnP (iterative, from IPPE or from the homography),
   ``solvePnPRefineLM`` / ``VVS``, with the estimated camera (``calibrate``'s: the photos
   plus the V's boards) and with the true camera.

    .venv/bin/python scripts/camera_truth.py /tmp/w37 [/tmp/w39 ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from lidarcal.board import find_v_boards, plane_from_pose, pose_from_homography, pose_pnp
from lidarcal.camera import calibrate_intrinsics, project_points
from lidarcal.corners import detect_chessboard, saddle_corners
from lidarcal.evaluate import (
    plane_error,
    ray_direction_error_deg,
    truth_board_planes,
    truth_camera,
)
from lidarcal.io.dataset import CameraModel, load_dataset, read_image
from lidarcal.pipeline import camera_for

CRIT = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4)


def true_intrinsics_corners(truth: dict, cam: CameraModel, k: int, pattern: tuple[int, int],
                            sq: float) -> np.ndarray:
    """True pixel positions of intrinsics view ``k``'s inner corners (OpenCV row order)."""
    v = truth["intrinsics_views"][k]
    R, T = np.asarray(v["R"], float), np.asarray(v["T_mm"], float)
    cols, rows = pattern
    jj, ii = np.mgrid[0:rows, 0:cols]
    P = T + np.outer(ii.ravel() * sq, R[:, 0]) + np.outer(jj.ravel() * sq, R[:, 1])
    return project_points(cam, P)


def match_error(det: np.ndarray | None, true_px: np.ndarray) -> np.ndarray | None:
    """Detected minus true corner (N, 2), each detection matched to its nearest true corner."""
    if det is None:
        return None
    det = np.asarray(det, float).reshape(-1, 2)
    d = np.linalg.norm(det[:, None] - true_px[None], axis=2)
    return det - true_px[np.argmin(d, axis=1)]


def detectors(pattern: tuple[int, int]) -> dict:
    """name -> function(gray) -> corners (N, 2) or None."""
    pat = tuple(pattern)

    def classic(gray):
        ok, c = cv2.findChessboardCorners(gray, pat, flags=cv2.CALIB_CB_ADAPTIVE_THRESH
                                          | cv2.CALIB_CB_NORMALIZE_IMAGE)
        return c if ok else None

    def classic_subpix(w):
        def f(gray):
            c = classic(gray)
            return None if c is None else cv2.cornerSubPix(gray, c, (w, w), (-1, -1), CRIT)
        return f

    def sb(flags):
        def f(gray):
            ok, c = cv2.findChessboardCornersSB(gray, pat, flags=flags)
            return c if ok else None
        return f

    def sb_subpix(w):
        def f(gray):
            c = sb(0)(gray)
            return None if c is None else cv2.cornerSubPix(gray, c, (w, w), (-1, -1), CRIT)
        return f

    def saddles(gray):
        c = detect_chessboard(gray, pat)
        return None if c is None else saddle_corners(gray, c, pat)

    out = {"lidarcal": lambda g: detect_chessboard(g, pat), "lidarcal saddles": saddles}
    for w in (3, 5, 11):
        out[f"classic+subpix{w}"] = classic_subpix(w)
    out["SB"] = sb(0)
    out["SB+ACCURACY"] = sb(cv2.CALIB_CB_ACCURACY)
    out["SB+EXH+ACC"] = sb(cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY)
    for w in (5, 11):
        out[f"SB+subpix{w}"] = sb_subpix(w)
    return out


def mask_other(gray: np.ndarray, cam: CameraModel, outline_mm: np.ndarray) -> np.ndarray:
    """board.png with one board's whole rectangle painted white (to detect the other alone)."""
    poly = project_points(cam, np.asarray(outline_mm, float))
    c = poly.mean(0)
    poly = c + 1.08 * (poly - c)
    out = gray.copy()
    cv2.fillPoly(out, [np.round(poly).astype(np.int32)], int(np.percentile(gray, 95)))
    return out


def corner_table(path: Path, truth: dict, ds) -> pd.DataFrame:
    tcam = truth_camera(truth, ds.image_size)
    rows = []
    # board.png: each board alone (the other painted over), true corners from truth
    gray = cv2.cvtColor(read_image(ds.board_image), cv2.COLOR_BGR2GRAY) \
        if read_image(ds.board_image).ndim == 3 else read_image(ds.board_image)
    pat_v = ds.v_board.pattern_size
    for b in range(2):
        img = mask_other(gray, tcam, truth["boards"][1 - b]["outline_mm"])
        tp = project_points(tcam, np.asarray(truth["boards"][b]["inner_corners_mm"], float))
        for name, f in detectors(pat_v).items():
            e = match_error(f(img), tp)
            rows.append({"image": "board.png", "view": b, "method": name, "err": e})
    # what calibrate uses: find_v_boards' corners (sharpest + point symmetry), true camera
    for v in find_v_boards(read_image(ds.board_image, ds.image_size), ds.v_board, tcam):
        tb = [project_points(tcam, np.asarray(b["inner_corners_mm"], float))
              for b in truth["boards"]]
        k = int(np.argmin([np.linalg.norm(t.mean(0) - v.corners_px.mean(0)) for t in tb]))
        rows.append({"image": "board.png", "view": k, "method": "lidarcal final",
                     "err": match_error(v.corners_px, tb[k])})
    if ds.intrinsics_board is not None and truth.get("intrinsics_views"):
        pat_i = ds.intrinsics_board.pattern_size
        # what calibrate uses: calibrate_intrinsics' corners (sharpest + point symmetry)
        res = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board, ds.image_size)
        for p, q in zip(res.files_used, res.image_points):
            k = list(ds.intrinsics_images()).index(p)
            tp = true_intrinsics_corners(truth, tcam, k, pat_i, ds.intrinsics_board.square_mm)
            rows.append({"image": "intrinsics", "view": k, "method": "lidarcal final",
                         "err": match_error(q, tp)})
        for k, p in enumerate(ds.intrinsics_images()):
            img = read_image(p)
            g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
            tp = true_intrinsics_corners(truth, tcam, k, pat_i, ds.intrinsics_board.square_mm)
            for name, f in detectors(pat_i).items():
                rows.append({"image": "intrinsics", "view": k, "method": name,
                             "err": match_error(f(g), tp)})
    out = []
    for (image, method), grp in pd.DataFrame(rows).groupby(["image", "method"], sort=False):
        errs = [e for e in grp.err if e is not None]
        E = np.vstack(errs) if errs else np.full((1, 2), np.nan)
        out.append({"dataset": path.name, "image": image, "method": method,
                    "found": f"{len(errs)}/{len(grp)}",
                    "rms_px": float(np.sqrt(np.mean(np.sum(E ** 2, 1)))),
                    "bias_x": float(E[:, 0].mean()), "bias_y": float(E[:, 1].mean()),
                    "p95_px": float(np.percentile(np.linalg.norm(E, axis=1), 95))})
    return pd.DataFrame(out)


def camera_row(name: str, cam: CameraModel, tcam: CameraModel, extra: str = "") -> dict:
    ray = ray_direction_error_deg(cam, tcam)
    d = cam.K - tcam.K
    return {"method": name, "ray_mean_deg": ray.mean(), "ray_max_deg": ray.max(),
            "fx": d[0, 0], "fy": d[1, 1], "cx": d[0, 2], "cy": d[1, 2], "note": extra}


def intrinsics_table(path: Path, truth: dict, ds) -> tuple[pd.DataFrame, CameraModel]:
    tcam = truth_camera(truth, ds.image_size)
    res = calibrate_intrinsics(ds.intrinsics_images(), ds.intrinsics_board, ds.image_size)
    rows = [camera_row("lidarcal intrinsics (photos)", res.camera, tcam,
                       f"k3 {'fixed' if res.flags & cv2.CALIB_FIX_K3 else 'free'} "
                       f"rms {res.camera.rms_px:.3f}")]
    cam_v, intr_v = camera_for(ds)
    rows.append(camera_row("lidarcal calibrate (photos + V)", cam_v, tcam,
                           f"extra views {len(intr_v.extra_views)}"))
    obj = ds.intrinsics_board.object_points().astype(np.float32)
    for label, det in (("cv2 classic+subpix11", detectors(ds.intrinsics_board.pattern_size)
                        ["classic+subpix11"]), ("cv2 on lidarcal corners", None)):
        pts = []
        for k, p in enumerate(ds.intrinsics_images()):
            if det is None:
                if p in res.files_used:
                    pts.append(res.image_points[list(res.files_used).index(p)])
                continue
            img = read_image(p)
            g = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY) if img.ndim == 3 else img
            c = det(g)
            if c is not None:
                pts.append(c.reshape(-1, 2))
        for flags, fl in ((0, "k3 free"), (cv2.CALIB_FIX_K3, "k3 fixed")):
            rms, K, dist, *_ = cv2.calibrateCamera([obj] * len(pts),
                                                   [q.reshape(-1, 1, 2).astype(np.float32)
                                                    for q in pts], ds.image_size, None, None,
                                                   flags=flags)
            d5 = np.zeros(5)
            d5[:5] = np.asarray(dist, float).ravel()[:5]
            cam = CameraModel(K, d5, ds.image_size)
            rows.append(camera_row(f"{label}, {fl}", cam, tcam, f"rms {rms:.3f}"))
    df = pd.DataFrame(rows)
    df.insert(0, "dataset", path.name)
    return df, cam_v


def plane_table(path: Path, truth: dict, ds, cam_est: CameraModel | None) -> pd.DataFrame:
    tcam = truth_camera(truth, ds.image_size)
    TB = truth_board_planes(truth)
    obj = ds.v_board.object_points()
    img = read_image(ds.board_image)
    rows = []
    cams = {"true camera": tcam}
    if cam_est is not None:
        cams["estimated camera"] = cam_est
    for cname, cam in cams.items():
        views = find_v_boards(img, ds.v_board, cam)
        for b, v in enumerate(views):
            c = v.corners_px
            R_h, T_h = pose_from_homography(cam, c, obj)
            K, dist = np.asarray(cam.K, float), np.asarray(cam.dist, float)
            _ok, rv_i, tv_i = cv2.solvePnP(obj, c, K, dist, flags=cv2.SOLVEPNP_IPPE)
            poses = {"homography": (R_h, T_h), "IPPE": (cv2.Rodrigues(rv_i)[0], tv_i.ravel()),
                     "PnP iter from H": pose_pnp(cam, c, obj, R_h, T_h),
                     "PnP iter from IPPE": pose_pnp(cam, c, obj)}
            rv, tv = cv2.Rodrigues(R_h)[0], T_h.reshape(3, 1).copy()
            rv_lm, tv_lm = cv2.solvePnPRefineLM(obj, c, K, dist, rv.copy(), tv.copy())
            poses["RefineLM from H"] = (cv2.Rodrigues(rv_lm)[0], tv_lm.ravel())
            rv_v, tv_v = cv2.solvePnPRefineVVS(obj, c, K, dist, rv.copy(), tv.copy())
            poses["RefineVVS from H"] = (cv2.Rodrigues(rv_v)[0], tv_v.ravel())
            for m, (R, T) in poses.items():
                pl = plane_from_pose(R, T)
                t = min(TB, key=lambda q: plane_error(pl, q)["normal_deg"])
                e = plane_error(pl, t)
                rows.append({"dataset": path.name, "camera": cname, "board": b, "method": m,
                             "normal_deg": e["normal_deg"], "offset_mm": e["offset_mm"]})
    return pd.DataFrame(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", type=Path, nargs="+")
    ap.add_argument("--skip", default="", help="comma list of tables to skip: corners,intrinsics,planes")
    args = ap.parse_args()
    skip = set(filter(None, args.skip.split(",")))
    pd.set_option("display.width", 220)
    pd.set_option("display.max_rows", 500)
    C, I, P = [], [], []
    for path in args.datasets:
        truth = json.loads((path / "truth.json").read_text())
        ds = load_dataset(path)
        if "corners" not in skip:
            C.append(corner_table(path, truth, ds))
            print(C[-1].round(4).to_string(index=False), flush=True)
        cam = ds.camera
        if ds.camera is None and "intrinsics" not in skip:
            df, cam = intrinsics_table(path, truth, ds)
            I.append(df)
            print(df.round(4).to_string(index=False), flush=True)
        elif ds.camera is None:
            cam = camera_for(ds)[0]
        if "planes" not in skip:
            P.append(plane_table(path, truth, ds, cam))
            print(P[-1].round(4).to_string(index=False), flush=True)
    if len(P) > 1:
        allp = pd.concat(P)
        print(allp.groupby(["camera", "method"])[["normal_deg", "offset_mm"]].mean().round(4))


if __name__ == "__main__":
    main()
