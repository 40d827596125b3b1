"""A documented command is a tested command.

(a) Every ``lidarcal <subcommand>`` shown in README.md and docs/*.md (code blocks and inline
code) must have an end-to-end test that runs it as a whole process; :data:`TESTED_BY` maps each
subcommand to its test in this file. A new subcommand (documented or not) adds its entry here.
(b) The README's command block (section "Command line") is run line by line through the
installed ``lidarcal``, in subprocesses, on small real files: a 6-position simulated rig, the
bundled dataset's first 6 positions with its disc sweeps, the bundled camera views and
OpenCV's sample photos; each line's exit status and the files it writes are checked.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from lidarcal.cli import COMMANDS

REPO = Path(__file__).resolve().parents[1]
BUNDLED = REPO / "data" / "paper_rig"
LIDARCAL = shutil.which("lidarcal", path=str(Path(sys.executable).parent)) or "lidarcal"

# subcommand -> the test that runs it end to end in a subprocess: a test of this file, or
# ``test_<module>.py::test_name`` for one beside it
TESTED_BY = {
    "simulate": "test_readme_command_block",
    "intrinsics": "test_intrinsics_on_real_photos",
    "calibrate": "test_readme_command_block",
    "pose": "test_readme_command_block",
    "measure": "test_readme_command_block",
    "report": "test_readme_command_block",
    "cloud": "test_cloud.py::test_cli_cloud_one_sweep_and_all",
    "import": "test_bag.py::test_ros1_raw_images_cli",
    # a documented mode of a subcommand: its command lines run by their own test
    "import --views": "test_bag_views.py::test_import_views_cli_then_planes",
    "check": "test_check.py::test_readme_own_rig_commands",
    "workbook": "test_workbook.py::test_workbook_runs_on_an_unseen_dataset_without_truth",
    "planes": "test_planes.py::test_readme_commands_run",
    "overlay": "test_planes.py::test_readme_commands_run",
    "laser-plane": "test_laserplane.py::test_cli_writes_the_plane",
}

_CODE = re.compile(r"```[^\n]*\n(.*?)```|`([^`\n]+)`", re.DOTALL)
_COMMAND = re.compile(r"(?:^|[\s/;&|(])lidarcal[ \t]+(?:--?[\w-]+[ \t]+)*([a-z][\w-]*)",
                      re.MULTILINE)


def documents() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def documented_subcommands(text: str) -> set[str]:
    """The subcommands of every ``lidarcal ...`` command in the code of a Markdown text."""
    code = "\n".join(a or b for a, b in _CODE.findall(text))
    return set(_COMMAND.findall(code))


def readme_command_block() -> list[str]:
    """The command lines of the first code block of the README's "Command line" section."""
    text = (REPO / "README.md").read_text()
    section = text.split("\n## Command line", 1)[1].split("\n## ", 1)[0]
    block = section.split("```", 2)[1].split("\n", 1)[1]
    lines = [ln.split("#", 1)[0].strip() for ln in block.splitlines()]
    return [ln for ln in lines if ln]


def test_extraction_finds_commands_and_only_commands():
    text = ("```bash\nlidarcal calibrate DATA --out X   # note\n.venv/bin/lidarcal pose c.json\n"
            "python -m lidarcal measure D\nimport lidarcal\ncal = lidarcal.load_calibration(p)\n```\n"
            "Run `lidarcal --debug report D` or `lidarcal --debug ...`; **lidarcal** calibrates.")
    assert documented_subcommands(text) == {"calibrate", "pose", "measure", "report"}


def test_every_documented_command_has_an_end_to_end_test():
    documented = {}
    for doc in documents():
        for sub in documented_subcommands(doc.read_text()):
            documented.setdefault(sub, doc.name)
    assert {"simulate", "calibrate", "report"} <= set(documented)  # the extraction works
    unknown = {s: d for s, d in documented.items() if s not in COMMANDS}
    assert not unknown, f"documented but not a lidarcal subcommand: {unknown}"
    untested = sorted(set(documented) - set(TESTED_BY))
    assert not untested, f"documented without an end-to-end test (add to TESTED_BY): {untested}"
    assert set(COMMANDS) <= set(TESTED_BY), sorted(set(COMMANDS) - set(TESTED_BY))
    for sub, test in TESTED_BY.items():
        assert _is_test(test), f"{sub}: {test} is not a test"


def test_documented_modes_are_in_the_docs():
    # a TESTED_BY entry "SUBCOMMAND --FLAG" names a mode some document shows on a command line
    text = "\n".join(doc.read_text() for doc in documents())
    for key in (k for k in TESTED_BY if " " in k):
        sub, flag = key.split(" ", 1)
        assert sub in COMMANDS, key
        assert re.search(rf"lidarcal {sub}\b[^\n`]* {re.escape(flag)}\b", text), key


def _is_test(ref: str) -> bool:
    """Whether ``name`` (a test of this file) or ``file.py::name`` (a file beside it) exists."""
    if "::" not in ref:
        return callable(globals().get(ref))
    file, name = ref.split("::")
    source = (Path(__file__).parent / file).read_text()
    return re.search(rf"^def {re.escape(name)}\(", source, re.MULTILINE) is not None


def lidarcal(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([LIDARCAL, *map(str, args)], capture_output=True, text=True, cwd=cwd,
                          check=False)


def _bundled_with_sweeps(dst: Path, n: int) -> Path:
    """The bundled dataset's first ``n`` positions and its disc sweeps (files referenced)."""
    from conftest import bundled_dataset

    return bundled_dataset(dst, n, link=("board.png", "measure"))


def _pose_errors(poses: list[dict], truth: dict):
    from lidarcal.evaluate import pose_errors
    from lidarcal.geometry import Pose

    return pose_errors({p["index"]: Pose.from_dict(p) for p in poses}, truth)


def test_readme_command_block(tmp_path):
    """Each line of the README's command block, as written, with its placeholders bound:
    OUT (simulate) -> a new 6-position rig without sweeps; DATASET -> the bundled dataset's
    first 6 positions with its 10 disc sweeps; OUT -> an output folder; PHOTOS/ -> the
    bundled camera views; relative paths land in a scratch folder."""
    lines = readme_command_block()
    sim, data, out = tmp_path / "sim", _bundled_with_sweeps(tmp_path / "data", 6), tmp_path / "out"
    truth = json.loads((BUNDLED / "truth.json").read_text())
    ran = []
    for line in lines:
        argv = shlex.split(line)
        assert argv[0] == "lidarcal", line
        sub = argv[1]
        bound = [str(data) if t == "DATASET" else str(BUNDLED / "intrinsics") if t == "PHOTOS/"
                 else t.replace("OUT", str(sim if sub == "simulate" else out), 1)
                 if t.startswith("OUT") else t for t in argv[1:]]
        if sub == "simulate":
            bound += ["--positions", "6", "--no-sweeps"]  # small: the command, not the study
        p = lidarcal(*bound, cwd=tmp_path)
        assert p.returncode == 0, (line, p.stderr)
        assert "error:" not in p.stderr and "Traceback" not in p.stderr, (line, p.stderr)
        CHECKS[sub](bound, p, tmp_path, out, truth)
        ran.append(sub)
    assert set(ran) >= {s for s, t in TESTED_BY.items() if t == "test_readme_command_block"}, ran


def _check_simulate(argv, p, cwd, out, truth):
    from lidarcal.io.dataset import load_dataset

    ds = load_dataset(argv[1])
    assert len(ds.positions) == 6 and ds.camera is not None
    t = ds.truth()
    assert t is not None and len(t["poses"]) == 6
    assert all(pos.stripe_image.is_file() and pos.scan.is_file() for pos in ds.positions)


def _check_intrinsics(argv, p, cwd, out, truth):
    """camera.json against the bundled truth: fx, fy to 0.05 %, principal point to 2 px (as in
    test_camera; OpenCV's own 1-sigma on these 12 views is ~0.8 px in f, ~1.3 px in cx)."""
    cam = json.loads((cwd / argv[argv.index("-o") + 1]).read_text())
    K, Kt = np.array(cam["K"]), np.array(truth["camera"]["K"])
    assert cam["source"] == "intrinsics" and cam["image_size"] == truth["camera"]["image_size"]
    assert abs(K[0, 0] / Kt[0, 0] - 1) < 5e-4 and abs(K[1, 1] / Kt[1, 1] - 1) < 5e-4
    assert np.hypot(K[0, 2] - Kt[0, 2], K[1, 2] - Kt[1, 2]) < 2.0
    assert "views used 12 of 12" in p.stdout


def _check_calibrate(argv, p, cwd, out, truth):
    """Six positions over 1.25 deg: single-shot accuracy holds (bars as test_cli's 4-position
    rig), the axis is weak and the run says so."""
    cal = json.loads((out / "calibration.json").read_text())
    method = argv[argv.index("--method") + 1] if "--method" in argv else "joint"
    assert cal["format"] == "lidarcal-calibration/1" and cal["method"] == method
    assert [s["index"] for s in cal["samples"]] == list(range(6)) and not cal["skipped"]
    err = _pose_errors(cal["poses"], truth)
    assert err.centre_mm.mean() < 1.0 and err.z_axis_deg.mean() < 0.03 \
        and err.x_axis_deg.mean() < 0.08, err
    assert "positions span only" in p.stderr
    if "--fit-planes" in argv:
        # the refined planes stay near the camera's (corners 0.03 px; measured shifts 0.0001-
        # 0.0002 deg and 0.001 mm) and the fit's own plane-shift check stays silent
        assert len(cal["boards_joint"]) == 2
        for fitted, cam in zip(cal["boards_joint"], cal["boards"]):
            cos = abs(np.dot(fitted["normal"], cam["pnp"]["normal"]))
            assert np.degrees(np.arccos(min(cos, 1.0))) < 0.01
            assert abs(fitted["d_mm"] - cam["pnp"]["d_mm"]) < 0.1
        assert not any("moved the board planes" in w for w in cal["warnings"])
    else:
        assert "boards_joint" not in cal


def _check_pose(argv, p, cwd, out, truth):
    """The printed R and T are the calibration's pose function at each angle."""
    from lidarcal.api import load_calibration

    cal = load_calibration(argv[1])
    psis = [float(v) for v in argv[argv.index("--psi") + 1:]]
    blocks = p.stdout.split("psi ")[1:]
    assert len(blocks) == len(psis)
    for psi, block in zip(psis, blocks):
        T = np.array(block.split("T_mm = [")[1].split("]")[0].split(), float)
        R = np.array(block.split("R =\n")[1].split("T_mm")[0].replace("[", " ").replace("]", " ")
                     .split(), float).reshape(3, 3)
        pose = cal.pose(psi)
        assert np.allclose(T, pose.T, atol=1e-5) and np.allclose(R, pose.R, atol=1e-6)


def _check_measure(argv, p, cwd, out, truth):
    """All 10 discs of 140 mm; a 6-position calibration measures them to within 1 mm (the
    paper's mean absolute error was 2.77 mm); with ``--reference`` the named discs calibrate
    the edge model (``source`` "reference") and are marked, without it the prior is used."""
    m = json.loads((out / "measurements.json").read_text())
    assert m["format"] == "lidarcal-measurements/1" and len(m["measurements"]) == 10
    assert all(abs(r["error_mm"]) < 1.0 for r in m["measurements"]), m["measurements"]
    refs = argv[argv.index("--reference") + 1:] if "--reference" in argv else []
    assert m["edge_model"]["source"] == ("reference" if refs else "prior")
    assert m["edge_model"]["references"] == refs
    assert [r["name"] for r in m["measurements"] if r["reference"]] == refs
    for r in m["measurements"]:  # the documented formula, D = D_half - 2 k u s
        assert np.isclose(r["edge_spacing_mm"], r["beam_spacing_mm"] * r["rim_stretch"])
        assert np.isclose(r["diameter_mm"], r["diameter_half_mm"]
                          - 2 * m["edge_model"]["k"] * r["edge_spacing_mm"])


def _check_check(argv, p, cwd, out, truth):
    """Every detection succeeds (exit 0, checked by the caller); the contact sheet is written
    in the current folder as ``<dataset name>-check.png``."""
    sheet = cwd / f"{Path(argv[1]).name}-check.png"
    assert sheet.is_file() and sheet.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", p.stdout


def _check_cloud(argv, p, cwd, out, truth):
    """The sweep's cloud in the camera frame: the returns inside the true disc's rim (less
    3 mm) lie on its true plane (median distance under 3 mm: 1 mm range noise, a 6-position
    calibration), and the attributes are the documented ones."""
    from lidarcal.io.clouds import read_cloud

    name = argv[argv.index("--sweep") + 1]
    pts, attrs = read_cloud(cwd / argv[argv.index("--out") + 1])
    assert {"range_mm", "psi_deg", "angle_deg"} <= set(attrs) and len(pts) > 1000
    disc = next(d for d in truth["measurements"] if d["name"] == name)
    c, n = np.array(disc["center_mm"]), np.array(disc["normal"])
    rel = pts - c
    along = rel @ n
    radial = np.linalg.norm(rel - np.outer(along, n), axis=1)
    on_disc = radial < disc["diameter_mm"] / 2 - 3.0
    near = on_disc & (np.abs(along) < 20.0)
    assert near.sum() > 500, near.sum()
    assert np.median(np.abs(along[near])) < 3.0, np.median(np.abs(along[near]))


def _check_report(argv, p, cwd, out, truth):
    pdf = cwd / argv[argv.index("--out") + 1]
    data = pdf.read_bytes()
    assert data.startswith(b"%PDF") and len(data) > 20_000
    assert not list(pdf.parent.glob(f".{pdf.name}*"))  # no temporary file left behind


CHECKS = {"simulate": _check_simulate, "intrinsics": _check_intrinsics,
          "calibrate": _check_calibrate, "pose": _check_pose, "measure": _check_measure,
          "check": _check_check, "cloud": _check_cloud, "report": _check_report}


def test_intrinsics_on_real_photos(tmp_path, opencv_photos):
    """OpenCV's real sample photos (13 views, 9x6): exit 0, camera.json written, K as OpenCV's
    own tutorial recipe (findChessboardCorners + cornerSubPix + calibrateCamera) to 0.5 %
    (the tolerance of test_camera's detector comparison); a view without the board is named
    in a warning and not used."""
    import cv2

    photos = opencv_photos
    folder = tmp_path / "photos"
    folder.mkdir()
    for ph in photos:
        shutil.copy(ph, folder / ph.name)
    cv2.imwrite(str(folder / "zz_blank.png"), np.full((480, 640), 128, np.uint8))
    p = lidarcal("intrinsics", folder, "--pattern", "9x6", "--square-mm", "25", "-o",
                 tmp_path / "cam" / "camera.json", cwd=tmp_path)
    assert p.returncode == 0, p.stderr
    assert f"views used {len(photos)} of {len(photos) + 1}" in p.stdout
    assert p.stderr.count("warning: ") == 1 and "zz_blank.png" in p.stderr
    cam = json.loads((tmp_path / "cam" / "camera.json").read_text())
    assert cam["image_size"] == [640, 480] and cam["rms_px"] < 0.5
    objp = np.zeros((54, 3), np.float32)
    objp[:, :2] = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 25.0
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.001)
    img = []
    for ph in photos:
        g = cv2.imread(str(ph), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(g, (9, 6), None)
        assert ok, ph
        img.append(cv2.cornerSubPix(g, c, (5, 5), (-1, -1), crit))
    _, K_cv, _, _, _ = cv2.calibrateCamera([objp] * len(img), img, (640, 480), None, None)
    K = np.array(cam["K"])
    assert abs(K[0, 0] / K_cv[0, 0] - 1) < 5e-3 and abs(K[1, 1] / K_cv[1, 1] - 1) < 5e-3
    assert np.hypot(K[0, 2] - K_cv[0, 2], K[1, 2] - K_cv[1, 2]) < 5.0
