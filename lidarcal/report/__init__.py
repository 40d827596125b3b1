"""The PDF calibration report (in the spirit of Kalibr's report).

Numbers come from ``calibration.json`` / ``measurements.json`` only, so the
report always agrees with the files: when no calibration is given the
pipeline is run and its output written to a temporary folder first, then read
back like any other. Figures that need images (corners, stripes, scan lines,
disc cloud) re-run only those steps, on one representative position.

The document is typst source (tables + PNG figures) compiled with the
``typst`` Python binding; :func:`build_report_source` gives the source
without compiling it (tests compare its numbers with the JSON files).

Split by concern: :mod:`.inputs` (what the report shows), :mod:`.tables` (the
numbers: the paper's Tables 1 and 2), :mod:`.markup` (typst helpers, the template,
compiling), :mod:`.figures`, :mod:`.sections` and :mod:`.build` (the whole document).
"""

from .build import build_report_source, write_report
from .figures import FIG_DPI
from .inputs import ReportInputs, gather_inputs
from .markup import compile_typst, esc, fnum, typst_table, vec
from .tables import (
    COMPARISON_COLUMNS,
    DECIMALS,
    PAPER_REFERENCE_MM,
    PAPER_TABLE1,
    PAPER_TABLE2,
    PAPER_TABLE2_MEAN,
    axes_table,
    comparison,
    comparisons,
    edge_model_text,
    model_poses,
    table1,
    table2,
    uncertainty_summary,
)

__all__ = ["COMPARISON_COLUMNS", "DECIMALS", "FIG_DPI", "PAPER_REFERENCE_MM", "PAPER_TABLE1",
           "PAPER_TABLE2", "PAPER_TABLE2_MEAN", "ReportInputs", "axes_table", "build_report_source",
           "comparison", "comparisons", "compile_typst", "edge_model_text", "esc", "fnum", "gather_inputs",
           "model_poses", "table1", "table2", "typst_table", "uncertainty_summary", "vec",
           "write_report"]
