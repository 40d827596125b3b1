"""Typst helpers of the report: escaping, numbers, tables, the template, compiling."""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path

import numpy as np

from ..io.dataset import write_atomic


def esc(s: object) -> str:
    """Plain text as a typst string expression (no markup), breakable after / _ - ."""
    t = str(s).replace("\\", "\\\\").replace('"', '\\"').replace("\n", " ")
    for ch in "/_-.,":
        t = t.replace(ch, ch + "\u200b")
    return '#"' + t + '"'


def fnum(x: object, nd: int = 3, sign: bool = False) -> str:
    """A number for a table cell ("--" for missing)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return "--"
    if not math.isfinite(v):
        return "--"
    s = f"{v:+.{nd}f}" if sign else f"{v:.{nd}f}"
    return s.replace("-", "\u2212")


def vec(v, nd: int = 3) -> str:
    return "(" + ", ".join(fnum(x, nd) for x in np.asarray(v, dtype=float).ravel()) + ")"


def typst_table(header: list[str], rows: list[list[str]], align: str | list[str] | None = None,
                size: str = "8pt", columns: str | None = None, header_rows: list[str] | None = None,
                hlines: tuple[int, ...] = ()) -> str:
    """A typst table; cells are typst markup. Long tables break across pages with the header
    repeated. ``hlines``: body row numbers before which a thicker rule is drawn."""
    n = len(header)
    if align is None:
        align = ["left"] + ["right"] * (n - 1)
    elif isinstance(align, str):
        align = [align] * n
    cols = columns or f"({', '.join(['auto'] * n)})"
    parts = [f"#small(size: {size})[#table(columns: {cols}, align: ({', '.join(align)},),"]
    hdr = ""
    if header_rows:
        hdr += ", ".join(header_rows) + ", "
    hdr += ", ".join(f"[{h}]" for h in header)
    parts.append(f"  table.header({hdr}),")
    for k, r in enumerate(rows):
        if k in hlines:
            parts.append("  table.hline(stroke: 0.9pt),")
        if len(r) != n:
            r = list(r) + [""] * (n - len(r))
        parts.append("  " + ", ".join(f"[{c}]" for c in r) + ",")
    parts.append(")]")
    return "\n".join(parts) + "\n"


def _template() -> str:
    return resources.files(__package__).joinpath("template.typ").read_text()


def compile_typst(source_path: Path, out_pdf: Path, root: Path | None = None) -> Path:
    """Compile a .typ file to ``out_pdf`` atomically (temporary file in the same folder, rename)."""
    import typst

    return write_atomic(out_pdf, lambda tmp: typst.compile(
        str(source_path), output=str(tmp), root=str(root or source_path.parent)), ".tmp")
