"""The rig simulator: a camera, a V-board and a 2D LiDAR on a turntable, with ground truth.

``simulate(out, seed, rig)`` writes a dataset folder in the contract
(``docs/dataset-format.md``) plus ``truth.json``; ``make_truth(seed, rig)``
samples the geometry only (cheap, for tests). Presets are in :data:`RIGS`:
``"paper"`` (the paper's rig), ``"wide"`` (a wide-angle, strongly distorted
camera and a different LiDAR / board) and ``"harsh"`` (the paper rig with
nuisances: speckle, ambient light, sensor noise, spurious and dropped
returns, encoder noise, more mixed pixels).

Image formation is described in :mod:`lidarcal.synthetic.render`, the LiDAR
footprint / return model in :mod:`lidarcal.synthetic.lidar`.
"""

from .config import RIGS, RigConfig, get_rig
from .lidar import beam_angles_deg, footprint_pattern, simulate_scans
from .render import RayMap, distort_normalized, undistort_pixels
from .truth import BoardTruth, DiscTrial, RigTruth, make_truth, project_points
from .writer import fmt_psi, simulate

__all__ = ["RIGS", "BoardTruth", "DiscTrial", "RayMap", "RigConfig", "RigTruth", "beam_angles_deg",
           "distort_normalized", "fmt_psi", "footprint_pattern", "get_rig", "make_truth", "project_points",
           "simulate", "simulate_scans", "undistort_pixels"]
