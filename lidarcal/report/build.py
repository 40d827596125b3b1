"""The whole report: typst source from the sections, compiled to PDF."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path

from .. import __version__
from ..io.dataset import Dataset
from .figures import _Detail, _detail, _Figures
from .inputs import ReportInputs, gather_inputs
from .markup import _template, compile_typst, esc
from .sections import (
    _intrinsics_section,
    _provenance_section,
    _section1,
    _section2,
    _section3,
    _skipped_section,
    _summary_section,
)
from .tables import comparisons, table1, table2


def build_report_source(inp: ReportInputs, folder: str | os.PathLike, figures: bool = True) -> str:
    """The report's typst source; figures are written as PNG files into ``folder``.

    ``figures=False`` leaves the figures (and the re-run of section 1 they need)
    out: the tables only, fast.

    Every number in the tables is computed from ``inp.cal`` / ``inp.meas``
    (the JSON files) by :func:`table1` and :func:`table2`.
    """
    folder = Path(folder)
    fig = _Figures(folder, inp.notes, enabled=figures)
    cal = inp.cal
    cmp = comparisons(cal, inp.truth)
    t1 = table1(cal, inp.truth)
    t2, t2sum = table2(inp.meas, inp.truth)
    det = _detail(inp) if figures else _Detail()
    import matplotlib

    matplotlib.use("Agg", force=False)
    body = [
        _intrinsics_section(inp, det, fig),
        _section1(inp, det, fig),
        _section2(inp, fig, t1, cmp),
        _section3(inp, fig, t2, t2sum),
    ]
    prov = _provenance_section(inp)
    tail = _skipped_section(inp)
    summary = _summary_section(inp, t1, t2sum)  # last: collects the notes
    name = inp.dataset.root.name
    title = "lidarcal calibration report"
    head = [_template(),
            (f'#show: lidarcal-doc.with(title: [{title}], subtitle: [{esc(name)}], '
            f'footer-left: [lidarcal {esc(__version__)} -- {esc(inp.created)}])\n'),
            (f"#align(center)[#text(20pt, weight: \"bold\")[{title}] \\ "
            f"#v(0.3em) #text(12pt)[dataset {esc(name)}] \\ #text(9pt)[Liu, Jiang, Jia, Qu: "
            "Pose determination of 2D LiDAR on uniaxial turntable (JEMI)]]\n"),
            summary, prov,
            "#pagebreak()\n#outline(depth: 2, indent: auto)\n"]
    return "\n".join(head + body + [tail])


def write_report(dataset: str | os.PathLike | Dataset, out_pdf: str | os.PathLike,
                 calibration: str | os.PathLike | None = None,
                 measurements: str | os.PathLike | None = None,
                 command: str | None = None, keep_source: str | os.PathLike | None = None) -> Path:
    """Write the PDF calibration report of ``dataset`` to ``out_pdf``.

    With ``calibration=None`` the pipeline is run first (and the dataset's
    measurement sweeps measured); otherwise the given ``calibration.json`` (and
    ``measurements.json``, if given) are shown as they are. ``keep_source``:
    a folder to copy the typst source and figures into (for debugging).
    """
    work = Path(tempfile.mkdtemp(prefix="lidarcal_report_"))
    try:
        inp = gather_inputs(dataset, calibration, measurements, command, workdir=work / "json")
        src = build_report_source(inp, work)
        typ = work / "report.typ"
        typ.write_text(src)
        if keep_source is not None:
            shutil.copytree(work, keep_source, dirs_exist_ok=True)
        return compile_typst(typ, Path(out_pdf), root=work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
