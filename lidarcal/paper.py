"""The paper's published figures (Liu, Jiang, Jia, Qu, JEMI; ``docs`` and method notes): what
the workbook, the evaluation tables and the report compare with. Numbers only, no imports."""

from __future__ import annotations

#: Table 1 (the fitted pose function against its 87 single-shot samples, no truth): (mean, max).
TABLE1 = {"centre_mm": (1.12, 2.72), "z_axis_deg": (0.203, 0.455), "x_axis_deg": (0.662, 1.580)}

#: Table 2: trial, measured diameter (mm), |error| (mm) of the 140 mm aluminium disc.
TABLE2 = [(1, 137.12, 2.88), (2, 135.80, 4.20), (3, 134.89, 5.11), (4, 142.63, 2.63),
          (5, 138.48, 1.52), (6, 135.64, 4.36), (7, 141.57, 1.57), (8, 136.87, 3.13),
          (9, 139.81, 0.19), (10, 142.08, 2.08)]
TABLE2_MEAN = (138.49, 2.77)  # mean diameter, mean |error| (mm)
REFERENCE_MM = 140.0  # the disc's diameter
