"""Combined perturbations: several rig, LiDAR and capture changes at once, against the truth.

The three single-perturbation sweeps each change ONE thing: ``capture_sweep.py`` (the
images), ``lidar_sweep.py`` (LiDAR, turntable, geometry) and ``rig_sweep.py`` (camera,
boards). Real datasets combine several. This script builds COMBINATIONS from their
builders (imported, not copied):

- rig parts: ``rig_sweep.VARIANTS`` (``R:name``, camera/board; each fixes the preset, paper
  or wide) and ``lidar_sweep.variants()`` (``L:name``; their changes applied to the combo's
  preset); two parts that set the same field do not combine;
- capture parts: ``capture_sweep.cases()`` (``C:name``), written over the simulated dataset
  with ``capture_sweep.write_case`` (stripe perturbations composed in order, a colour one last);
- ``B:raw|png|jpeg|lit``: the (perturbed) dataset recorded as a ROS 1 bag
  (``lidarcal.synthetic.bag.write_bag``) and read back with ``lidarcal import`` (``lit``: one
  camera topic, lights on at the first stop, as docs/ros-bags.md describes).

Per combo: simulate (``--positions`` positions over the preset's span, disc sweeps when a
part asks for them; the simulation is cached per rig in ``WORK/sim``), perturb, (record and
import), then ``lidarcal check``, ``lidarcal calibrate`` and, with sweeps, ``lidarcal measure``
in subprocesses; the row compares calibration.json with truth.json (mean/max centre error
mm, z/x axis deg, share of positions whose centre, z and x errors all lie within 2 sigma,
the worst error/sigma ratio) and classifies the outcome:

- ``good``: exit 0, every position within 2 sigma (or the worst within 3 sigma and the
  mean centre error below 1 mm);
- ``refused``: exit 2 with one ``error: FILE: ...`` line (an honest refusal);
- ``warned``: exit 0, errors beyond that, but calibration.json carries a warning saying the
  result or its sigmas are doubtful (:func:`doubting`; judge the text);
- ``SILENT``: exit 0, errors beyond 3 sigma or the mean centre error above 3 mm, no such
  warning (``good-ish``: beyond 2 sigma, within those bounds);
- ``CRASH``: any other exit status, a traceback, or exit 2 without the one-line form.

usage::

    .venv/bin/python scripts/combo_sweep.py --work /tmp/combo [--hand] [--random 40] [--seed 7]
        [--positions 12] [--only NAME ...] [--csv rows.csv] [--list]

``--hand`` runs the hand-picked plausible combos (``HAND``), ``--random N`` a seeded
sample of N random combos of 2-4 parts; ``--only`` picks combos by name (``--list``
prints them). Combos run one after the other (each ~1-2 min on a shared CPU).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import capture_sweep as cs
import lidar_sweep as ls
import rig_sweep as rs

from lidarcal.io.dataset import DatasetError
from lidarcal.synthetic import simulate
from lidarcal.synthetic.config import PAPER, WIDE, RigConfig

LIDAR = {v.name: v for v in ls.variants()}
CAPTURE = {c.name: c for c in cs.cases()}
BAGS = ("raw", "png", "jpeg", "lit")
# parts that change what the sweeps' own rows already cover alone and make no sense mixed
# (a preset or the clean copy), or that only re-write positions.csv
_SKIP_RANDOM = {"R:paper", "R:wide", "L:base", "C:clean", "L:pos150", "L:pos3", "L:pos5",
                "L:pos3_step5", "R:cam_4k", "R:v_tiny_3px", "R:v_tiny_5px",
                # ranging physics added after the seeded batches were drawn (kept out of the
                # draw so a seed names the same combos as before; HAND combines them)
                "L:incidence10", "L:incidence30", "L:scale0.2pct", "L:scale1pct",
                "L:psiscale1pct", "L:psiscale3pct"}
# capture builders, for combos the three sweeps do not list as one case
EXTRA_CAPTURE = {
    "stripes_jpeg40": cs.Case("stripes_jpeg40", stripes=cs.jpeg(40)),
    "lit60_jpeg": cs.Case("lit60_jpeg", stripes=cs.compose(cs.lights_on(60), cs.jpeg(50)),
                          board=cs.jpeg(50)),
}
CAPTURE.update(EXTRA_CAPTURE)


def all_parts() -> list[str]:
    """Every part name a combo may draw."""
    return ([f"R:{k}" for k in rs.VARIANTS] + [f"L:{k}" for k in LIDAR]
            + [f"C:{k}" for k in CAPTURE] + [f"B:{b}" for b in BAGS])


# Hand-picked combos a lab plausibly records (name -> parts).
HAND: dict[str, tuple[str, ...]] = {
    "wide_lit_jpeg_hokuyo": ("R:wide", "C:lit60_jpeg", "L:fov270", "L:quantum10"),
    "fov360_photos_blur": ("R:cam_photos", "L:fov360", "C:blur2_both"),
    "barrel_small_noise_enc": ("R:cam_barrel", "R:v_tiny_8px", "L:noise10", "L:encoder0.02"),
    "bag_lit_frames": ("R:wide", "B:lit", "C:lit30"),
    "bag_jpeg_noise": ("R:paper", "B:jpeg", "L:noise5", "C:board_noise10"),
    "vga_lit_quantum": ("R:cam_vga", "C:lit60", "L:quantum10"),
    "752_gamma_drop": ("R:cam_752", "C:gamma0.3", "L:drop20"),
    "tangential_red_spurious": ("R:cam_tangential", "C:red60", "L:spurious5"),
    "photos_disc_noise": ("R:cam_photos", "L:disc_near", "L:noise10"),
    "wide_disc_blur_sat": ("L:disc_wide", "C:sat4_bloom", "C:blur2"),
    "v9x6_upside_offset": ("R:v_9x6", "L:upside_down", "L:offset+25"),
    "far_firstecho_vig": ("R:v_far", "L:firstecho", "C:vig0.5"),
    "bag_png_fov270_wrap": ("R:wide", "B:png", "L:fov270_yaw90", "L:encoder0.02"),
    "nonsquare_tilt_hot": ("R:cam_nonsquare", "L:axis_tilt10", "C:hot500"),
    "margin_glare_rolled": ("R:v_margin_0.25", "C:board_glare", "L:rolled20"),
    # harsher stacks
    "tiny5_blur3_noise20": ("R:v_tiny_5px", "C:blur3", "L:noise20"),
    "offset_spurious_jpegbag_lit": ("L:offset+25", "L:spurious5", "B:jpeg", "C:lit120"),
    "fov360yaw_barrel_redsat": ("L:fov360_yaw180", "R:cam_barrel", "C:red120_sat"),
    "psiwrap_rawbag": ("L:psiwrap", "B:raw", "C:hot500"),
    "unsorted_pngbag_gamma": ("L:unsorted", "B:png", "C:gamma0.5"),
    "negstep_photos_gamma": ("L:negstep", "R:cam_photos", "C:gamma0.5", "L:noise10"),
    "tilt_enc_far": ("L:axis_tilt10", "L:encoder0.02", "R:v_far"),
    "pos5_lit120_noise20": ("L:pos5", "C:lit120", "L:noise20"),
    "disc_far_quantum_lit": ("L:disc_far", "L:quantum10", "C:lit60", "R:cam_photos"),
    "firstecho_div_small": ("L:firstecho", "L:divergence", "R:v_sq15"),
    "pp_off_occl_drop": ("R:cam_pp_off", "C:occl0.6", "L:drop20", "L:offset-30"),
    # the parts of bag_png_fov270_wrap (SILENT) one removed at a time
    "wide_enc": ("R:wide", "L:encoder0.02"),
    "wide_fov270yaw_enc": ("R:wide", "L:fov270_yaw90", "L:encoder0.02"),
    "paper_fov270yaw_enc": ("L:fov270_yaw90", "L:encoder0.02"),
    # its parts one at a time (combo2 round)
    "paper_enc": ("R:paper", "L:encoder0.02"),
    "paper_fov270yaw": ("R:paper", "L:fov270_yaw90"),
    "paper_fov270_enc": ("L:fov270", "L:encoder0.02"),
    # ranging physics another simulator may have (combo3 round): a range bias growing with
    # the incidence angle, a range scale (time-base) error
    "paper_incidence10": ("R:paper", "L:incidence10"),
    "wide_incidence30": ("R:wide", "L:incidence30"),
    "paper_scale0.2pct": ("R:paper", "L:scale0.2pct"),
    "wide_scale1pct": ("R:wide", "L:scale1pct"),
    "disc_scale0.2pct": ("L:disc_near", "L:scale0.2pct"),
    "fov270yaw_incidence10_lit": ("L:fov270_yaw90", "L:incidence10", "C:lit60"),
    "disc_incidence10": ("L:disc_near", "L:incidence10"),
    # an encoder (gear) scale error: the turns read 1 % / 3 % long
    "paper_psiscale1pct": ("R:paper", "L:psiscale1pct"),
    "wide_psiscale1pct": ("R:wide", "L:psiscale1pct"),
    "paper_psiscale3pct": ("R:paper", "L:psiscale3pct"),
}


def random_combos(n: int, seed: int) -> dict[str, tuple[str, ...]]:
    """``n`` seeded random combos of 2-4 parts (at most one R, two L, two C, one B part);
    combos whose parts set the same rig field are redrawn."""
    rng = np.random.default_rng(seed)
    pools = {k: [p for p in all_parts() if p.startswith(k) and p not in _SKIP_RANDOM]
             for k in ("R:", "L:", "C:", "B:")}
    caps = {"R:": 1, "L:": 2, "C:": 2, "B:": 1}
    out: dict[str, tuple[str, ...]] = {}
    tries = 0
    while len(out) < n and tries < 100 * n:
        tries += 1
        k = int(rng.integers(2, 5))
        kinds = rng.choice(["R:", "L:", "L:", "C:", "C:", "B:"], size=k, replace=True)
        if any(sum(kinds == t) > caps[t] for t in caps):
            continue
        parts = tuple(sorted({str(rng.choice(pools[t])) for t in kinds}))
        if len(parts) < 2:
            continue
        try:
            build(parts, 12)
        except ValueError:
            continue
        out[f"r{len(out):02d}_" + "+".join(p.split(":")[1] for p in parts)] = parts
    return out


@dataclass
class Combo:
    """A built combo: the rig, disc sweeps or not, positions.csv post-processing, the capture
    case (None: the images as simulated) and the bag kind (None: the folder itself)."""

    rig: RigConfig
    sweeps: bool
    post: str
    capture: cs.Case | None
    bag: str | None


def _compose_cases(cases: list[cs.Case]) -> cs.Case | None:
    """One capture case doing the cases' stripe and board perturbations in order (a colour
    frame last); at most one PNG writer and one laser colour."""
    if not cases:
        return None
    coloured = [c for c in cases if c.name.startswith(("red", "green"))]
    if len(coloured) > 1 or sum(c.writer is not None for c in cases) > 1:
        raise ValueError("two colour cases or two PNG writers")
    order = [c for c in cases if c not in coloured] + coloured
    stripes = [c.stripes for c in order if c.stripes is not None]
    boards = [c.board for c in order if c.board is not None]
    return cs.Case("+".join(c.name for c in order),
                   stripes=cs.compose(*stripes) if stripes else None,
                   board=cs.compose(*boards) if boards else None,
                   writer=next((c.writer for c in order if c.writer), None),
                   laser_colour=next((c.laser_colour for c in order if c.laser_colour), None))


def build(parts: tuple[str, ...], positions: int) -> Combo:
    """The combo of ``parts`` (see the module docstring); ValueError when they conflict."""
    rparts = [p[2:] for p in parts if p.startswith("R:")]
    lparts = [LIDAR[p[2:]] for p in parts if p.startswith("L:")]
    cparts = [CAPTURE[p[2:]] for p in parts if p.startswith("C:")]
    bparts = [p[2:] for p in parts if p.startswith("B:")]
    if len(rparts) > 2 or len(bparts) > 1:
        raise ValueError("too many R or B parts")
    bases = {rs.VARIANTS[r][0].name for r in rparts}
    bases |= {v.rig.name.split("-")[0] for v in lparts if v.rig.name.startswith("wide")}
    if len(bases) > 1:
        raise ValueError(f"presets conflict: {bases}")
    base = WIDE if bases == {"wide"} else PAPER
    changes: dict = {}
    for ch in [rs.VARIANTS[r][1] for r in rparts] + [v.changes for v in lparts]:
        clash = set(ch) & set(changes)
        if clash:
            raise ValueError(f"parts set the same fields {sorted(clash)}")
        changes.update(ch)
    posts = {v.post for v in lparts if v.post}
    if len(posts) > 1:
        raise ValueError("two positions.csv post-processings")
    sweeps = any(v.sweeps for v in lparts)
    # the preset's turntable span with fewer positions, unless a part sets the turntable
    n = changes.pop("n_positions", positions)
    step = changes.pop("psi_step_deg", base.psi_step_deg * (base.n_positions - 1) / max(n - 1, 1))
    rig = base.with_(name=f"{base.name}-combo", n_positions=n, psi_step_deg=round(step, 4), **changes)
    return Combo(rig, sweeps, posts.pop() if posts else "", _compose_cases(cparts),
                 bparts[0] if bparts else None)


def _lidarcal(*args: str, timeout: int = 1800) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "lidarcal", *args], capture_output=True, text=True,
                          check=False, timeout=timeout)


_ONE_LINE = re.compile(r"^error: .+")


def _failure(p: subprocess.CompletedProcess) -> tuple[str, str]:
    """(outcome, note) of a non-zero exit: ``refused`` for exit 2 with the one-line error form."""
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    last = lines[-1] if lines else ""
    if "Traceback" in p.stderr:
        return "CRASH", last[:200]
    if p.returncode == 2 and _ONE_LINE.match(last):
        return "refused", last[:200]
    return "CRASH", f"exit {p.returncode}: {last[:200]}"


def _simulate(work: Path, c: Combo, seed: int) -> Path:
    """The simulated dataset of the combo's rig (cached by the rig's fields and seed)."""
    key = hashlib.sha1(repr((c.rig.with_(name="x"), c.sweeps, c.post, seed)).encode()).hexdigest()[:12]
    ds = work / "sim" / key
    if not (ds / "truth.json").is_file():
        simulate(ds, seed=seed, rig=c.rig, with_sweeps=c.sweeps, overwrite=True)
        ls._post(ds, c.post, np.random.default_rng(seed))
    return ds


def _truth_for_import(folder: Path, imported: Path) -> None:
    """truth.json of the recorded folder, its poses re-indexed as ``lidarcal import`` numbered
    the positions (in recording order: each imported row gets the truth pose of the nearest
    psi_deg)."""
    truth = json.loads((folder / "truth.json").read_text())
    rows = [ln.split(",") for ln in (imported / "positions.csv").read_text().splitlines()[1:]]
    poses = []
    for r in rows:
        best = min(truth["poses"], key=lambda p: abs((p["psi_deg"] - float(r[1]) + 180.0) % 360.0 - 180.0))
        poses.append({**best, "index": int(r[0])})
    (imported / "truth.json").write_text(json.dumps({**truth, "poses": poses}))


def _routine(w: str) -> bool:
    """Warnings every dataset of a short sweep carries (they do not flag a doubtful result)."""
    return "span only" in w


# words of a warning that says the result itself is doubtful (a skipped position or a blur
# note does not: it says what was done about the input)
_DOUBT = ("sigma", "understate", "doubtful", "off by", "not told apart", "poorly determined",
          "not determined", "weak")


def doubting(warning: str) -> bool:
    """Whether ``warning`` says the calibration's result (or its sigmas) may be wrong."""
    return any(k in warning for k in _DOUBT)


def classify(row: dict) -> str:
    """good / warned / SILENT of a calibrate that exited 0 (see the module docstring)."""
    ok = row["cov2s"] >= 1.0 or (row["worst_ratio"] <= 3.0 and row["centre_mm"] < 1.0)
    if ok:
        return "good"
    if row["n_doubt"] > 0:
        return "warned"
    if row["worst_ratio"] > 3.0 or row["centre_mm"] > 3.0:
        return "SILENT"
    return "good-ish"


def run_combo(name: str, parts: tuple[str, ...], work: Path, seed: int, positions: int) -> dict:
    """Simulate, perturb, (bag round trip), check, calibrate and measure one combo: its row."""
    row: dict = {"combo": name, "parts": " ".join(parts)}
    c = build(parts, positions)
    try:
        src = _simulate(work, c, seed)
    except ValueError as exc:
        return {**row, "outcome": "sim-fail", "note": str(exc)[:200]}
    ds = work / name
    shutil.rmtree(ds, ignore_errors=True)
    if c.capture is not None:
        cs.write_case(src, ds / "folder", c.capture, seed)
    else:
        shutil.copytree(src, ds / "folder", copy_function=lambda s, d: Path(d).hardlink_to(s))
    data = ds / "folder"
    if c.bag is not None:
        from lidarcal.synthetic.bag import write_bag

        bag = ds / "rec.bag"
        kw = ({"images": "raw", "single_camera_topic": True} if c.bag == "lit"
              else {"images": c.bag})
        try:
            write_bag(data, bag, storage="rosbag1", seed=seed, sweeps=c.sweeps, rig_json=ds / "rig.json",
                      **kw)
        except DatasetError as exc:  # the folder itself is refused (as calibrate would refuse it)
            return {**row, "outcome": "refused", "note": f"recording the bag: error: {exc}"[:200]}
        p = _lidarcal("import", str(bag), "--rig", str(ds / "rig.json"), "--out", str(ds / "imported"),
                      "--no-progress")
        row["import"] = p.returncode
        if p.returncode != 0:
            row["outcome"], row["note"] = _failure(p)
            return row
        _truth_for_import(data, ds / "imported")
        data = ds / "imported"
    chk = _lidarcal("check", str(data), "--sheet", str(ds / "check.png"))
    row["check"] = chk.returncode
    if "Traceback" in chk.stderr:
        row["outcome"], row["note"] = "CRASH", "check: " + _failure(chk)[1]
        return row
    out = ds / "out"
    p = _lidarcal("calibrate", str(data), "--out", str(out), "--no-progress")
    row["cal"] = p.returncode
    if p.returncode != 0:
        row["outcome"], row["note"] = _failure(p)
        return row
    ev = cs.evaluate_case(data, out, p)
    cal = json.loads((out / "calibration.json").read_text())
    warns = [w for w in cal.get("warnings", []) if not _routine(w)]
    row.update({k: ev[k] for k in ("used", "skipped", "centre_mm", "centre_max_mm", "z_deg", "x_deg",
                                   "cov2s", "worst_ratio")})
    row["n_warn"] = len(warns)
    row["n_doubt"] = sum(doubting(w) for w in warns)
    row["outcome"] = classify(row)
    row["note"] = next((w for w in warns if doubting(w)), warns[0] if warns else "")[:200]
    if c.sweeps:
        m = _lidarcal("measure", str(data), "--calibration", str(out / "calibration.json"),
                      "--out", str(out))
        row["meas"] = m.returncode
        if m.returncode == 0:
            me = ls.measure_errors(out)
            row["meas_abs_mm"], row["meas_in2s"] = round(me["meas_abs_mm"], 3), me["meas_in2s"]
            if me["meas_in2s"] < 1.0 and row["outcome"] == "good":
                row["outcome"] = "SILENT(measure)"
        elif "Traceback" in m.stderr:
            row["outcome"], row["note"] = "CRASH", "measure: " + _failure(m)[1]
    return row


COLUMNS = ("combo", "outcome", "check", "cal", "used", "skipped", "n_warn", "n_doubt", "centre_mm", "centre_max_mm",
           "z_deg", "x_deg", "cov2s", "worst_ratio", "meas", "meas_abs_mm", "meas_in2s", "note")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("combo-work"))
    ap.add_argument("--hand", action="store_true", help="the hand-picked combos")
    ap.add_argument("--random", type=int, default=0, help="this many seeded random combos")
    ap.add_argument("--seed", type=int, default=7, help="seed of the simulations and the draw")
    ap.add_argument("--positions", type=int, default=12)
    ap.add_argument("--only", nargs="*", default=None, help="combo names (see --list)")
    ap.add_argument("--skip", type=int, default=0, help="skip the first N combos (resume)")
    ap.add_argument("--csv", type=Path, default=None)
    ap.add_argument("--list", action="store_true")
    a = ap.parse_args(argv)
    combos: dict[str, tuple[str, ...]] = {}
    if a.hand or a.only:
        combos.update(HAND)
    if a.random or a.only:
        combos.update(random_combos(a.random or 60, a.seed))
    if a.only:
        combos = {k: v for k, v in combos.items() if k in a.only}
    if a.list:
        for k, v in combos.items():
            print(f"{k:50s} {' '.join(v)}")
        return 0
    a.work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, parts in list(combos.items())[a.skip:]:
        try:
            r = run_combo(name, parts, a.work, a.seed, a.positions)
        except Exception as exc:  # noqa: BLE001  (the sweep reports and goes on)
            r = {"combo": name, "parts": " ".join(parts), "outcome": "SCRIPT", "note": repr(exc)[:200]}
        rows.append(r)
        print("  ".join(f"{k}={r[k]}" for k in COLUMNS if r.get(k, "") != ""), flush=True)
        if a.csv:
            keys = list(dict.fromkeys(["parts", *COLUMNS]))
            with a.csv.open("w", newline="") as f:
                w = csv.DictWriter(f, fieldnames=keys, extrasaction="ignore")
                w.writeheader()
                w.writerows(rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
