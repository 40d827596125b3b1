"""Build the executed workbook as one PDF (a thin caller of :mod:`lidarcal.workbook`).

    python scripts/workbook.py NOTEBOOK_DIR OUT_PDF [--dataset DIR] [--no-execute]
                               [--timeout S] [--keep DIR]

With ``--dataset`` this is ``lidarcal workbook DIR --out OUT_PDF --notebook-dir
NOTEBOOK_DIR``: every numbered notebook runs on that dataset (its ``parameters``
cell set by papermill). Without it the notebooks run as they are (their own
default dataset); ``--no-execute`` typesets their stored outputs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from lidarcal.workbook import ANSI, DEFAULT_TIMEOUT_S, build, find_notebooks


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("notebooks", type=Path, help="folder of numbered notebooks")
    ap.add_argument("out", type=Path, help="output PDF")
    ap.add_argument("--dataset", type=Path, default=None, help="run the notebooks on this dataset")
    ap.add_argument("--no-execute", action="store_true", help="use the stored outputs")
    ap.add_argument("--timeout", type=int, default=DEFAULT_TIMEOUT_S, help="per-cell timeout, s")
    ap.add_argument("--keep", type=Path, default=None, help="copy the typst source here")
    a = ap.parse_args(argv)
    try:
        path = build(find_notebooks(a.notebooks), a.out, dataset=a.dataset,
                     execute=not a.no_execute, timeout=a.timeout, keep=a.keep,
                     log=lambda m: print(m, file=sys.stderr))
    except Exception as e:  # noqa: BLE001  (one line, like the CLI)
        msg = " ".join(ANSI.sub("", str(e)).split())
        print(f"error: {type(e).__name__}: {msg[:2000]}", file=sys.stderr)
        return 1
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
