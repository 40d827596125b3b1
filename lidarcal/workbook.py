"""The workbook on any dataset: run the numbered notebooks on it and typeset one PDF.

``lidarcal workbook DATASET --out workbook.pdf`` executes ``notebooks/NN_*.ipynb``
in order with papermill (a fresh kernel per notebook, a per-cell timeout), each
with its ``parameters`` cell set to ``DATASET = "<absolute path>"``, into a
temporary folder (the notebooks in the repository are never touched). Each
executed notebook is converted to typst by pandoc (``pypandoc-binary``:
markdown, LaTeX math -> typst math, code cells, text outputs and PNG images);
the pieces are joined under a title page (the dataset, its positions and
turntable range, a table of the notebooks) with a table of contents, and typst
compiles the PDF (written to a temporary file, then renamed).

The rule for a notebook of the workbook: a file ``NN_name.ipynb`` whose first
code cell is tagged ``parameters`` and assigns ``DATASET`` (a path relative to
the notebook folder, the bundled ``../data/paper_rig`` by default, so nbval and
JupyterLab run it as it is); every cell that needs ``truth.json`` runs under
``if truth is not None:``.

Cell tags: ``remove-cell`` drops a cell, ``hide-input`` keeps only its outputs.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import struct
import subprocess
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from .io.dataset import Dataset, DatasetError, load_dataset

if TYPE_CHECKING:
    import pandas as pd

ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
TAG = re.compile(r"\\tag\{([^}]*)\}")
IMAGE = re.compile(r'image\("([^"]+)"\)')
EMPTY_CODE = re.compile(r"```[a-z0-9]*\s*```\n?")
#: Assumed resolution of notebook PNGs without a pHYs chunk (matplotlib inline: 100 dpi).
DEFAULT_DPI = 100.0
#: Text width of the page (A4 minus the template's 1.8 cm margins), pt.
TEXT_WIDTH_PT = 595.3 - 2 * 51.0
#: The name of the parameter every numbered notebook takes.
PARAMETER = "DATASET"
#: Per-cell timeout (s): the slowest cell of the bundled workbook (the small Monte Carlo
#: study of notebook 07) takes a few minutes on a shared two-core machine.
DEFAULT_TIMEOUT_S = 900


def default_notebook_dir() -> Path:
    """The repository's ``notebooks/`` folder (beside the package)."""
    return Path(__file__).resolve().parent.parent / "notebooks"


# ------------------------------------------------------------------ the dataset, summarised


@dataclass(frozen=True)
class DatasetSummary:
    """What a reader of the workbook needs to know about its dataset first."""

    name: str
    n_positions: int
    psi_min_deg: float
    psi_max_deg: float
    psi_step_deg: float  # median spacing of the sorted angles
    camera: str  # "dataset.json" or "intrinsics/ (N views)"
    truth: bool
    measurements: int

    def line(self) -> str:
        """One line: ``NAME: N positions, psi A to B deg (step S deg)``."""
        return (f"{self.name}: {self.n_positions} positions, psi {self.psi_min_deg:g} to "
                f"{self.psi_max_deg:g} deg (step {self.psi_step_deg:g} deg)")


def summarise_dataset(ds: Dataset) -> DatasetSummary:
    """The positions, turntable range, camera source and truth of a dataset (no images read)."""
    import numpy as np

    from .turntable import unwrap_angles_deg

    # as calibrate reads them: one sweep where a controller wraps at 360 deg
    psi = np.sort(unwrap_angles_deg([p.psi_deg for p in ds.positions]))
    step = float(np.median(np.diff(psi))) if len(psi) > 1 else 0.0
    cam = "dataset.json" if ds.camera is not None \
        else f"intrinsics/ ({len(ds.intrinsics_images())} views)"
    return DatasetSummary(ds.root.name, len(psi), round(float(psi[0]), 4), round(float(psi[-1]), 4),
                          round(step, 4), cam, (ds.root / "truth.json").is_file(),
                          len(ds.measurements))


def dataset_summary(ds: Dataset) -> pd.DataFrame:
    """:func:`summarise_dataset` as a two-column table for a notebook."""
    import pandas as pd

    s = summarise_dataset(ds)
    rows = [("dataset", str(ds.root)), ("positions", s.n_positions),
            ("turntable angle psi (deg)", f"{s.psi_min_deg:g} to {s.psi_max_deg:g}"),
            ("psi span (deg)", f"{s.psi_max_deg - s.psi_min_deg:g}"),
            ("psi step (deg, median)", f"{s.psi_step_deg:g}"), ("camera from", s.camera),
            ("measurement sweeps", s.measurements),
            ("truth.json", "yes (simulated)" if s.truth else "no (truth comparisons skipped)")]
    return pd.DataFrame(rows, columns=["item", "value"]).set_index("item")


def shown_position(ds: Dataset, camera, boards, rho: float | None = None):
    """The position a notebook shows step by step (sections 1.3-1.4): the first of
    positions.csv that ``calibrate`` solves (:func:`lidarcal.pipeline.solve_position`, with
    the dataset's reflectance ratio ``rho``; a failure is one that ``calibrate`` would skip,
    :func:`~lidarcal.pipeline.solve_safe`). A recorded dataset's first position may be one
    that ``calibrate`` skips. Returns the position and one line per position passed over."""
    from .pipeline import solve_safe

    passed_over = []
    for pos in ds.positions:
        got = solve_safe((pos, camera, boards, ds.lidar, rho))
        if not isinstance(got, DatasetError):
            return pos, passed_over
        passed_over.append(f"position {pos.index} passed over: {got}")
    raise DatasetError(ds.root / "positions.csv", "no position gives both a laser plane from its "
                                                  "stripes and the V in its scan; run lidarcal "
                                                  "check on the dataset")


# ------------------------------------------------------------------ notebooks


def find_notebooks(folder: Path, select: Sequence[str] | None = None) -> list[Path]:
    """The numbered notebooks ``NN_*.ipynb`` of ``folder``, in order; ``select`` keeps those whose
    number (``"01"`` or ``"1"``) or stem is listed."""
    folder = Path(folder)
    books = sorted(p for p in folder.glob("[0-9][0-9]_*.ipynb") if p.is_file())
    if not books:
        raise DatasetError(folder, "holds no numbered notebooks (NN_name.ipynb); pass the "
                                   "workbook's notebooks folder with --notebook-dir")
    if select:
        want = {s.strip() for s in select if s.strip()}
        keep = [p for p in books if p.stem[:2] in want or p.stem in want
                or str(int(p.stem[:2])) in want]
        found = {p.stem[:2] for p in keep} | {p.stem for p in keep} | \
            {str(int(p.stem[:2])) for p in keep}
        missing = sorted(want - found)
        if missing:
            raise DatasetError(folder, f"no notebook numbered {', '.join(missing)}; it holds "
                                       f"{', '.join(p.stem for p in books)}")
        books = keep
    return books


#: What a numbered notebook runs on (its metadata ``lidarcal.input``): ``dataset``, a turntable
#: dataset folder (docs/dataset-format.md; the default), or ``view-pairs``, a folder of photo +
#: scan pairs with camera.json (the one-board method, ``lidarcal planes``, notebook 08).
INPUT_KINDS = ("dataset", "view-pairs")


def notebook_input(path: Path) -> str:
    """The input kind a numbered notebook is written for (see :data:`INPUT_KINDS`)."""
    import nbformat

    kind = nbformat.read(path, as_version=4).metadata.get("lidarcal", {}).get("input", "dataset")
    if kind not in INPUT_KINDS:
        raise DatasetError(path, f"metadata lidarcal.input is {kind!r}; expected one of "
                                 f"{', '.join(INPUT_KINDS)}")
    return kind


def input_kind(folder: Path) -> str:
    """``dataset`` for a folder with dataset.json, ``view-pairs`` for photo + scan pairs with
    camera.json (checked by reading the pairs); otherwise a one-line error naming the folder."""
    folder = Path(folder)
    if (folder / "dataset.json").is_file() or not (folder / "camera.json").is_file():
        return "dataset"  # load_dataset names what is missing
    from .io.pairs import read_view_pairs

    read_view_pairs(folder)
    return "view-pairs"


def summary_line(folder: Path, kind: str) -> tuple[str, str]:
    """The workbook's subtitle and one-line description of its input."""
    if kind == "dataset":
        s = summarise_dataset(load_dataset(folder))
        return s.name, s.line()
    from .io.pairs import BOARD_JSON, board_spec, read_view_pairs

    line = f"{Path(folder).name}: {len(read_view_pairs(folder))} photo + scan pairs (one flat board"
    if (Path(folder) / BOARD_JSON).is_file():
        b = board_spec(folder)
        line += f", {b.inner_corners[0]} x {b.inner_corners[1]} inner corners, {b.square_mm:g} mm squares"
    return Path(folder).name, line + ")"


def check_parameters_cell(nb, path: Path) -> None:
    """A workbook notebook has a code cell tagged ``parameters`` that assigns ``DATASET``."""
    for cell in nb.cells:
        if cell.cell_type == "code" and "parameters" in cell.get("metadata", {}).get("tags", []):
            if re.search(rf"^\s*{PARAMETER}\s*=", cell.source, flags=re.MULTILINE):
                return
            break
    raise DatasetError(path, f"has no code cell tagged 'parameters' assigning {PARAMETER}; "
                             "every workbook notebook must take its dataset from one")


def _kernel_manager(workdir: Path, kernel_log):
    """A kernel manager whose kernel writes its own log (not the cells' output, which goes to
    the notebook) to the open file ``kernel_log`` instead of our stderr, and talks over unix sockets in
    ``workdir`` where those exist (POSIX: no TCP ports for a local kernel)."""
    from jupyter_client.manager import AsyncKernelManager

    class LocalKernelManager(AsyncKernelManager):
        def __init__(self, **kw):
            super().__init__(**kw)
            if os.name == "posix":
                self.transport = "ipc"
                self.ip = str(workdir / "kernel")

        async def start_kernel(self, **kw):
            kw.setdefault("stderr", kernel_log)
            return await super().start_kernel(**kw)

    return LocalKernelManager


def _cell_name(path: Path, executed: Path, index: int) -> str:
    """``code cell K (id ID)`` of the notebook ``path`` for the failed cell of its executed copy
    (the cell with the error output: the copy also holds papermill's parameters and error
    banner cells, so ``index``, papermill's, is only the fallback)."""
    import nbformat

    try:
        cid = next(c.get("id") for c in nbformat.read(executed, as_version=4).cells
                   if any(o.get("output_type") == "error" for o in c.get("outputs", [])))
        code = [c.get("id") for c in nbformat.read(path, as_version=4).cells
                if c.cell_type == "code"]
        return f"code cell {code.index(cid) + 1} (id {cid})"
    except (OSError, StopIteration, ValueError, KeyError):
        return f"cell {index + 1} of the executed notebook"


def _log_tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return "; kernel log: " + " | ".join(text[-lines:]) if text else ""


def execute_notebook(path: Path, out: Path, dataset: Path | None, timeout: int) -> None:
    """Run one notebook with papermill: fresh kernel, ``DATASET`` injected (with ``dataset``
    None the notebook runs on its own default), working directory = the notebook's folder,
    matplotlib inline; the executed copy is written to ``out``.

    Raises :class:`DatasetError` naming the notebook and the failing cell.
    """
    import nbformat
    import papermill as pm

    if dataset is not None:
        check_parameters_cell(nbformat.read(path, as_version=4), path)
    log = out.with_suffix(".kernel.log")
    old = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    pm_log = logging.getLogger("papermill")
    level = pm_log.level
    pm_log.setLevel(logging.ERROR)  # papermill's notes (e.g. "Black is not installed") are not errors
    try:
        with open(log, "ab") as kernel_log:
            pm.execute_notebook(str(path), str(out),
                                parameters={} if dataset is None else {PARAMETER: str(dataset)},
                                kernel_name="python3", language="python", cwd=str(path.parent),
                                progress_bar=False,
                                log_output=False, execution_timeout=timeout,
                                request_save_on_cell_execute=False,
                                kernel_manager_class=_kernel_manager(out.parent, kernel_log))
    except pm.PapermillExecutionError as e:
        msg = " ".join(ANSI.sub("", str(e.evalue)).split())[:500]
        on = "" if dataset is None else f" with {PARAMETER} = '{dataset}'"
        raise DatasetError(path, f"{_cell_name(path, out, e.cell_index)} raised {e.ename}: {msg}; "
                                 "run this notebook "
                                 f"in JupyterLab (make lab){on} to see it") from None
    except RuntimeError as e:  # the kernel died or did not start
        raise DatasetError(path, f"the kernel failed ({e}){_log_tail(log)}") from None
    except TimeoutError as e:
        raise DatasetError(path, f"a cell ran longer than {timeout} s ({e}); raise --timeout") \
            from None
    finally:
        pm_log.setLevel(level)
        if old is None:
            os.environ.pop("MPLBACKEND", None)
        else:
            os.environ["MPLBACKEND"] = old


def prepare(nb):
    """Apply cell tags, drop the default ``parameters`` cell when papermill injected one, turn
    ``\\tag{n}`` into a visible number, strip ANSI colour codes."""
    injected = any("injected-parameters" in c.get("metadata", {}).get("tags", []) for c in nb.cells)
    cells = []
    for cell in nb.cells:
        tags = set(cell.get("metadata", {}).get("tags", []))
        if "remove-cell" in tags or (injected and "parameters" in tags):
            continue
        if cell.cell_type == "markdown":
            cell.source = TAG.sub(lambda m: r"\qquad (" + m.group(1) + ")", cell.source)
        if cell.cell_type == "code":
            if "hide-input" in tags:
                cell.source = ""
            for out in cell.get("outputs", []):
                if "text" in out:
                    out["text"] = ANSI.sub("", out["text"])
                if "traceback" in out:
                    out["traceback"] = [ANSI.sub("", t) for t in out["traceback"]]
        cells.append(cell)
    nb.cells = cells
    return nb


def png_width_pt(path: Path) -> float | None:
    """Display width of a PNG (pt) from its pixel width and pHYs resolution."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        return None
    width = struct.unpack(">I", data[16:20])[0]
    dpi = DEFAULT_DPI
    i = data.find(b"pHYs")
    if i > 0:
        ppux, _, unit = struct.unpack(">IIB", data[i + 4:i + 13])
        if unit == 1 and ppux > 0:
            dpi = ppux * 0.0254
    return width / dpi * 72.0


def to_typst(ipynb: Path, workdir: Path) -> str:
    """pandoc ipynb -> typst body (media extracted into ``workdir/media``), images sized."""
    import pypandoc

    pandoc = pypandoc.get_pandoc_path()
    res = subprocess.run([pandoc, "-f", "ipynb", "-t", "typst", "--wrap=preserve",
                          "--extract-media=media", str(ipynb.resolve())],
                         cwd=workdir, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        raise RuntimeError(f"{ipynb.name}: pandoc failed: {res.stderr.strip()}")
    body = EMPTY_CODE.sub("", res.stdout)  # hide-input cells leave an empty code block

    def sized(m: re.Match) -> str:
        w = png_width_pt(workdir / m.group(1))
        w = TEXT_WIDTH_PT if w is None else min(w, TEXT_WIDTH_PT)
        return f'image("{m.group(1)}", width: {w:.1f}pt)'

    return IMAGE.sub(sized, body)


def _esc(s: str) -> str:
    return '#"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _typst_source(parts: list[str], listing: list[tuple[str, str, float]], title: str,
                  subtitle: str, about: str) -> str:
    from importlib import resources

    tpl = resources.files("lidarcal.report").joinpath("template.typ").read_text()
    created = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    rows = ", ".join(f"[{_esc(n)}], [{s}], [{d:.1f} s]" for n, s, d in listing)
    head = [
        tpl,
        # pandoc's typst writer relies on these names from its default template
        "#let horizontalrule = line(start: (25%, 0%), end: (75%, 0%))\n",
        # symbols pandoc 3 still writes that newer typst renamed (\\cap, \\partial)
        "#let sect = sym.inter\n#let diff = sym.partial\n",
        (f"#show: lidarcal-doc.with(title: [{_esc(title)}], subtitle: [{_esc(subtitle)}], "
         f"footer-left: [{_esc(title)} -- {_esc(created)}], chapter-breaks: false)\n"),
        "#show figure.where(kind: table): set figure.caption(position: top)\n",
        "#set table(stroke: 0.4pt + luma(160))\n",
        (f'#align(center)[#v(3cm) #text(22pt, weight: "bold")[{_esc(title)}] \\ #v(0.5em) '
         "#text(11pt)[Liu, Jiang, Jia, Qu: Pose determination of 2D LiDAR on uniaxial turntable] "
         f"\\ #v(0.8em) #text(11pt)[{_esc(about)}] "
         f"\\ #v(0.3em) #text(10pt)[{_esc(created)}]]\n"),
        ("#v(1cm)\n#small(size: 9pt)[#table(columns: (1fr, auto, auto), align: (left, left, right),"
         f" table.header([notebook], [outputs], [time]), {rows})]\n"),
        "#pagebreak()\n#outline(depth: 2, indent: auto)\n",
    ]
    return "\n".join(head + parts)


def build(notebooks: Sequence[Path], out_pdf: Path, *, dataset: Path | None = None,
          execute: bool = True, timeout: int = DEFAULT_TIMEOUT_S, keep: Path | None = None,
          title: str = "lidarcal workbook", log: Callable[[str], None] = print) -> Path:
    """Execute the ``notebooks`` on ``dataset`` (or take them as stored with ``execute=False``),
    convert and typeset them as one PDF; returns its path."""
    import nbformat

    from .report import compile_typst

    kind = input_kind(dataset) if dataset is not None else None
    described = summary_line(dataset, kind) if dataset is not None else None
    work = Path(tempfile.mkdtemp(prefix="lidarcal_workbook_"))
    try:
        parts, listing = [], []
        for path in notebooks:
            t0 = time.perf_counter()
            done = work / path.name
            if execute:
                log(f"executing {path.name}")
                execute_notebook(path, done, None if dataset is None else Path(dataset).resolve(),
                                 timeout)
                nb = nbformat.read(done, as_version=4)
            else:
                nb = nbformat.read(path, as_version=4)
            nbformat.write(prepare(nb), done)
            body = to_typst(done, work)
            if not re.search(r"^= ", body, flags=re.MULTILINE):
                body = f"= {_esc(path.stem)}\n\n" + body
            parts.append(f"// ---- {path.name}\n#pagebreak(weak: true)\n{body}\n")
            listing.append((path.name, "executed" if execute else "as stored",
                            time.perf_counter() - t0))
        subtitle, about = described or (Path(notebooks[0]).parent.name, "notebooks as stored")
        typ = work / "workbook.typ"
        typ.write_text(_typst_source(parts, listing, title, subtitle, about))
        if keep is not None:
            shutil.copytree(work, keep, dirs_exist_ok=True)
        return compile_typst(typ, Path(out_pdf), root=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def write_workbook(dataset: str | os.PathLike, out_pdf: str | os.PathLike, *,
                   notebook_dir: str | os.PathLike | None = None,
                   select: Sequence[str] | None = None, timeout: int = DEFAULT_TIMEOUT_S,
                   keep: str | os.PathLike | None = None,
                   log: Callable[[str], None] = print) -> Path:
    """``lidarcal workbook``: the numbered notebooks written for ``dataset``'s kind (a turntable
    dataset: 01-07; photo + scan pairs: 08; :data:`INPUT_KINDS`) run on it, as one PDF."""
    root = Path(dataset)
    kind = input_kind(root)
    if kind == "dataset":
        root = load_dataset(root).root  # bad input fails here, before any kernel starts
    books = find_notebooks(Path(notebook_dir) if notebook_dir else default_notebook_dir(), select)
    other = [b for b in books if notebook_input(b) != kind]
    if select and other:
        raise DatasetError(root, f"{', '.join(b.name for b in other)} runs on another kind of "
                                 f"input than this {kind} folder; leave it out of --notebooks")
    books = [b for b in books if b not in other]
    if not books:
        raise DatasetError(root, f"no numbered notebook runs on a {kind} folder")
    return build(books, Path(out_pdf), dataset=root, timeout=timeout,
                 keep=None if keep is None else Path(keep), log=log)
