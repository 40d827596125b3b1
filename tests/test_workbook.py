"""The workbook on any dataset: the notebooks' parameters cell, and ``lidarcal workbook`` end to end
on a small simulated rig that has no truth.json and no stored camera (calibrated from its
intrinsics photos), with fewer positions and another turntable range than the bundled rig."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import nbformat
import numpy as np
import pytest

from lidarcal.io.dataset import DatasetError, load_dataset
from lidarcal.workbook import (
    PARAMETER,
    check_parameters_cell,
    default_notebook_dir,
    find_notebooks,
    summarise_dataset,
)

REPO = Path(__file__).resolve().parents[1]
NOTEBOOKS = sorted((REPO / "notebooks").glob("[0-9][0-9]_*.ipynb"))


def lidarcal(*args, cwd=None, timeout=None):
    return subprocess.run([sys.executable, "-m", "lidarcal", *map(str, args)], capture_output=True,
                          text=True, cwd=cwd, timeout=timeout, check=False)


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem[:2])
def test_every_notebook_takes_its_dataset_from_one_parameters_cell(path):
    """The rule for workbook notebooks: one code cell tagged 'parameters', before any other code,
    assigning DATASET a path relative to the notebook, to a dataset bundled in data/ (01-07: the
    paper rig); no other cell names that folder; every use of the truth is guarded."""
    nb = nbformat.read(path, as_version=4)
    check_parameters_cell(nb, path)
    code = [c for c in nb.cells if c.cell_type == "code"]
    tagged = [c for c in code if "parameters" in c.metadata.get("tags", [])]
    assert len(tagged) == 1 and code[0] is tagged[0]
    m = re.search(rf'^{PARAMETER} = "([^"]+)"', tagged[0].source, flags=re.MULTILINE)
    default = (path.parent / m.group(1)).resolve() if m else None
    assert default is not None and default.is_dir() and default.parent == REPO / "data"
    for c in code[1:]:
        assert m.group(1) not in c.source and "truth.json" not in c.source, c.id
        if "truth[" in c.source:  # every use of the truth is guarded
            assert "truth is not None" in c.source, (path.name, c.id)
    assert all(c.get("id") for c in nb.cells) and not any(c.get("outputs") for c in code)


def test_find_notebooks_selects_by_number(tmp_path):
    books = find_notebooks(default_notebook_dir(), ["01", "5"])
    assert [p.stem[:2] for p in books] == ["01", "05"]
    with pytest.raises(DatasetError, match="no notebook numbered 99"):
        find_notebooks(default_notebook_dir(), ["99"])
    with pytest.raises(DatasetError, match="holds no numbered notebooks"):
        find_notebooks(tmp_path)
    nbformat.write(nbformat.v4.new_notebook(), tmp_path / "01_x.ipynb")
    with pytest.raises(DatasetError, match="no code cell tagged 'parameters' assigning DATASET"):
        check_parameters_cell(nbformat.read(tmp_path / "01_x.ipynb", as_version=4), tmp_path)


def test_summary_gives_the_datasets_own_range(small_dataset):
    s = summarise_dataset(load_dataset(small_dataset))
    rows = (small_dataset / "positions.csv").read_text().splitlines()[1:]
    psi = sorted(float(r.split(",")[1]) for r in rows)
    assert (s.n_positions, s.psi_min_deg, s.psi_max_deg) == (len(psi), psi[0], psi[-1])
    assert s.psi_step_deg == pytest.approx(np.median(np.diff(psi)))
    assert s.truth and s.camera == "dataset.json"
    assert f"psi {psi[0]:g} to {psi[-1]:g} deg" in s.line()


@pytest.fixture(scope="module")
def unseen_dataset(tmp_path_factory) -> Path:
    """A paper-like rig seen by no other test: 6 positions 2 deg apart (10 deg, the bundled rig
    has 87 over 21.5 deg), two disc sweeps, the camera only as 10 intrinsics photos, no truth."""
    from lidarcal.synthetic import get_rig, simulate

    rig = get_rig("paper").with_(n_positions=6, psi_step_deg=2.0, camera_in_dataset=False,
                                 n_discs=2, n_intrinsics_views=10)
    out = simulate(tmp_path_factory.mktemp("unseen") / "unseen_rig", seed=23, rig=rig)
    (out / "truth.json").unlink()
    meta = json.loads((out / "dataset.json").read_text())
    assert "camera" not in meta and len(list((out / "intrinsics").glob("*.png"))) == 10
    return out


def test_workbook_runs_on_an_unseen_dataset_without_truth(unseen_dataset, tmp_path):
    """Every notebook, on a dataset without truth.json: exit 0, no error output, >= 12 pages,
    and the PDF shows this dataset's turntable range (not the bundled rig's)."""
    pypdf = pytest.importorskip("pypdf")
    s = summarise_dataset(load_dataset(unseen_dataset))
    out = tmp_path / "wb" / "workbook.pdf"
    r = lidarcal("workbook", unseen_dataset, "--out", out, "--timeout", 600, timeout=1800)
    assert r.returncode == 0, r.stderr
    assert r.stderr == "", r.stderr
    assert f"wrote {out}" in r.stdout
    reader = pypdf.PdfReader(out)
    assert len(reader.pages) >= 12
    text = "\n".join(p.extract_text() for p in reader.pages)
    for needle in (s.line(), f"{s.psi_min_deg:g} to {s.psi_max_deg:g}", str(unseen_dataset)):
        assert needle in text, needle
    bundled = summarise_dataset(load_dataset(REPO / "data" / "paper_rig"))
    assert f"{bundled.psi_min_deg:g} to {bundled.psi_max_deg:g}" not in text
    assert "intrinsics/ (10 views)" in text  # the camera came from the photos
    for word in ("Traceback", "Error:", "Exception"):
        assert word not in text, word
    assert not list(out.parent.glob(".*.tmp"))  # written atomically


def test_workbook_bad_input_is_one_line(tmp_path):
    r = lidarcal("workbook", tmp_path / "nope", "--out", tmp_path / "x.pdf")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert r.stderr.startswith("error: ") and "not a dataset folder" in r.stderr
    r = lidarcal("workbook", REPO / "data" / "paper_rig", "--out", tmp_path / "x.pdf",
                 "--notebooks", "42")
    assert r.returncode == 2 and "no notebook numbered 42" in r.stderr
    assert not (tmp_path / "x.pdf").exists()


def test_a_failing_notebook_is_one_line_naming_it_and_its_cell(small_dataset, tmp_path):
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_code_cell('DATASET = "../data/paper_rig"', metadata={"tags": ["parameters"]}),
                nbformat.v4.new_code_cell("from pathlib import Path\nassert Path(DATASET).is_dir()"),
                nbformat.v4.new_code_cell("raise ValueError('no V in scan 3')")]
    nbformat.write(nb, tmp_path / "01_fails.ipynb")
    r = lidarcal("workbook", small_dataset, "--out", tmp_path / "x.pdf", "--notebook-dir", tmp_path)
    assert r.returncode == 2, r.stderr
    line, = r.stderr.strip().splitlines()
    assert line.startswith(f"error: {tmp_path / '01_fails.ipynb'}: code cell 3 (id ")
    assert "raised ValueError: no V in scan 3; run this notebook in JupyterLab (make lab)" in line
    assert str(small_dataset) in line and not (tmp_path / "x.pdf").exists()


def test_notebooks_are_chosen_by_their_input_kind(tmp_path):
    """A turntable dataset runs 01-07; notebook 08 (photo + scan pairs) is not run on it, and
    naming it for a dataset is a one-line error."""
    from lidarcal.workbook import input_kind, notebook_input

    kinds = {p.stem[:2]: notebook_input(p) for p in NOTEBOOKS}
    assert kinds["08"] == "view-pairs" and all(k == "dataset" for n, k in kinds.items() if n < "08")
    assert input_kind(REPO / "data" / "paper_rig") == "dataset"
    assert input_kind(REPO / "data" / "real_tapas") == "view-pairs"
    from lidarcal.workbook import summary_line

    assert summary_line(REPO / "data" / "real_tapas", "view-pairs")[1] == \
        "real_tapas: 7 photo + scan pairs (one flat board, 8 x 5 inner corners, 100 mm squares)"
    r = lidarcal("workbook", REPO / "data" / "paper_rig", "--out", tmp_path / "x.pdf",
                 "--notebooks", "08")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "08_real_data" in r.stderr
    assert not (tmp_path / "x.pdf").exists()


@pytest.mark.parametrize("notebooks", ["01,02,03,04,05,06"])
def test_workbook_runs_without_sweeps_or_truth(dataset_copy, tmp_path, notebooks):
    """Notebooks 01-06 on a 4-position dataset with no measurement sweeps (no 'measurements', no
    measure/) and no truth.json: the disc notebook says so in its output instead of failing, and
    no cell writes to stderr (no warnings in the PDF)."""
    pypdf = pytest.importorskip("pypdf")
    (dataset_copy / "truth.json").unlink()
    meta = json.loads((dataset_copy / "dataset.json").read_text())
    meta.pop("measurements", None)
    (dataset_copy / "dataset.json").write_text(json.dumps(meta))
    assert not (dataset_copy / "measure").exists()
    out = tmp_path / "wb.pdf"
    r = lidarcal("workbook", dataset_copy, "--out", out, "--notebooks", notebooks, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stderr == "", r.stderr
    text = "\n".join(p.extract_text() for p in pypdf.PdfReader(out).pages)
    assert "this dataset lists no measurement sweeps" in text
    for word in ("Traceback", "Error:", "Exception", "Warning:"):
        assert word not in text, word


def test_the_shown_position_passes_over_a_broken_first_one(dataset_copy):
    """Notebook 03 shows the first position whose stripes and V are found: a blank first stripe
    image is passed over with the reason (calibrate would skip it too)."""
    import cv2

    from lidarcal.board import find_v_boards
    from lidarcal.io.dataset import read_image
    from lidarcal.pipeline import camera_for
    from lidarcal.workbook import shown_position

    ds = load_dataset(dataset_copy)
    camera, _ = camera_for(ds)
    views = find_v_boards(read_image(ds.board_image, camera.image_size), ds.v_board, camera)
    pos, passed = shown_position(ds, camera, views)
    assert pos.index == ds.positions[0].index and passed == []
    cv2.imwrite(str(ds.positions[0].stripe_image), np.zeros(camera.image_size[::-1], np.uint8))
    pos, passed = shown_position(ds, camera, views)
    assert pos.index == ds.positions[1].index
    assert len(passed) == 1 and passed[0].startswith(f"position {ds.positions[0].index} passed over")
