"""Build the executed workbook: every numbered notebook, run and typeset as one PDF.

    python scripts/workbook.py NOTEBOOK_DIR OUT_PDF [--no-execute] [--timeout S] [--keep DIR]

Notebooks ``NOTEBOOK_DIR/[0-9][0-9]_*.ipynb`` are executed in order with
nbclient (working directory = the notebook folder, matplotlib inline), or, with
``--no-execute``, taken as they are (already-executed copies). Each is
converted to typst by pandoc (``pypandoc-binary``: markdown, LaTeX math ->
typst math, code cells, text outputs and PNG images), the pieces are joined
under a title page with a table of contents and page numbers, and typst
compiles the PDF (written to a temporary file, then renamed).

Cell tags: ``remove-cell`` drops a cell, ``hide-input`` keeps only its outputs.
"""

from __future__ import annotations

import argparse
import copy
import os
import re
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")
TAG = re.compile(r"\\tag\{([^}]*)\}")
IMAGE = re.compile(r'image\("([^"]+)"\)')
EMPTY_CODE = re.compile(r"```[a-z0-9]*\s*```\n?")
#: Assumed resolution of notebook PNGs without a pHYs chunk (matplotlib inline: 100 dpi).
DEFAULT_DPI = 100.0
#: Text width of the page (A4 minus the template's 1.8 cm margins), pt.
TEXT_WIDTH_PT = 595.3 - 2 * 51.0


def find_notebooks(folder: Path) -> list[Path]:
    return sorted(p for p in Path(folder).glob("[0-9][0-9]_*.ipynb") if p.is_file())


def execute(nb, folder: Path, timeout: int, allow_errors: bool):
    """Run a notebook in ``folder`` with the inline matplotlib backend; returns the executed copy."""
    import nbclient

    nb = copy.deepcopy(nb)
    old = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    try:
        client = nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                         allow_errors=allow_errors,
                                         resources={"metadata": {"path": str(folder)}})
        client.execute()
    finally:
        if old is None:
            os.environ.pop("MPLBACKEND", None)
        else:
            os.environ["MPLBACKEND"] = old
    return nb


def prepare(nb):
    """Apply cell tags, turn ``\\tag{n}`` into a visible number, strip ANSI colour codes."""
    cells = []
    for cell in nb.cells:
        tags = set(cell.get("metadata", {}).get("tags", []))
        if "remove-cell" in tags:
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


def build(folder: Path, out_pdf: Path, execute_notebooks: bool = True, timeout: int = 900,
          allow_errors: bool = False, keep: Path | None = None, title: str = "lidarcal workbook",
          log=print) -> Path:
    """Execute (optionally), convert and typeset the numbered notebooks of ``folder``."""
    import nbformat

    folder = Path(folder).resolve()
    books = find_notebooks(folder)
    if not books:
        raise FileNotFoundError(f"{folder}: no numbered notebooks ([0-9][0-9]_*.ipynb)")
    work = Path(tempfile.mkdtemp(prefix="lidarcal_workbook_"))
    try:
        parts, listing = [], []
        for path in books:
            t0 = time.perf_counter()
            nb = nbformat.read(path, as_version=4)
            if execute_notebooks:
                log(f"executing {path.name}")
                nb = execute(nb, folder, timeout, allow_errors)
            nb = prepare(nb)
            tmp_nb = work / path.name
            nbformat.write(nb, tmp_nb)
            body = to_typst(tmp_nb, work)
            if not re.search(r"^= ", body, flags=re.MULTILINE):
                body = f"= {_esc(path.stem)}\n\n" + body
            parts.append(f"// ---- {path.name}\n#pagebreak(weak: true)\n{body}\n")
            dt = time.perf_counter() - t0
            listing.append((path.name, "executed" if execute_notebooks else "as stored", dt))
        template = (Path(__file__).resolve().parent.parent / "lidarcal" / "report" / "template.typ")
        try:
            from importlib import resources

            tpl = resources.files("lidarcal.report").joinpath("template.typ").read_text()
        except (ModuleNotFoundError, FileNotFoundError):
            tpl = template.read_text()
        created = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
        rows = ", ".join(f"[{_esc(n)}], [{s}], [{d:.1f} s]" for n, s, d in listing)
        head = [
            tpl,
            # pandoc's typst writer relies on these names from its default template
            "#let horizontalrule = line(start: (25%, 0%), end: (75%, 0%))\n",
            # symbols pandoc 3 still writes that newer typst renamed (\\cap, \\partial)
            "#let sect = sym.inter\n#let diff = sym.partial\n",
            (f"#show: lidarcal-doc.with(title: [{_esc(title)}], subtitle: [{_esc(folder.name)}], "
            f"footer-left: [{_esc(title)} -- {_esc(created)}], chapter-breaks: false)\n"),
            "#show figure.where(kind: table): set figure.caption(position: top)\n",
            "#set table(stroke: 0.4pt + luma(160))\n",
            (f'#align(center)[#v(3cm) #text(22pt, weight: "bold")[{_esc(title)}] \\ #v(0.5em) '
            "#text(11pt)[Liu, Jiang, Jia, Qu: Pose determination of 2D LiDAR on uniaxial turntable] "
            f"\\ #v(0.3em) #text(10pt)[{_esc(created)}]]\n"),
            ("#v(1cm)\n#small(size: 9pt)[#table(columns: (1fr, auto, auto), align: (left, left, right),"
            f" table.header([notebook], [outputs], [time]), {rows})]\n"),
            "#pagebreak()\n#outline(depth: 2, indent: auto)\n",
        ]
        typ = work / "workbook.typ"
        typ.write_text("\n".join(head + parts))
        if keep is not None:
            shutil.copytree(work, keep, dirs_exist_ok=True)
        sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
        from lidarcal.report import compile_typst

        return compile_typst(typ, Path(out_pdf), root=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("notebooks", type=Path, help="folder of numbered notebooks")
    ap.add_argument("out", type=Path, help="output PDF")
    ap.add_argument("--no-execute", action="store_true", help="use the stored outputs")
    ap.add_argument("--allow-errors", action="store_true", help="keep going past failing cells")
    ap.add_argument("--timeout", type=int, default=900, help="per-cell timeout, s")
    ap.add_argument("--keep", type=Path, default=None, help="copy the typst source here")
    a = ap.parse_args(argv)
    try:
        path = build(a.notebooks, a.out, not a.no_execute, a.timeout, a.allow_errors, a.keep,
                     log=lambda m: print(m, file=sys.stderr))
    except Exception as e:  # noqa: BLE001  (one line, like the CLI)
        msg = " ".join(ANSI.sub("", str(e)).split())
        print(f"error: {type(e).__name__}: {msg[:2000]}", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
