"""lidarcal: pose of a 2D LiDAR on a single-axis turntable, calibrated against a camera.

Implements Liu, Jiang, Jia, Qu, "Pose determination of 2D LiDAR on uniaxial
turntable" (J. Electronic Measurement and Instrumentation), step by step.
"""

__version__ = "0.1.0"


def load_calibration(path, model: str = "poses"):
    """Read a ``calibration.json``; see :func:`lidarcal.api.load_calibration`."""
    from .api import load_calibration as _load

    return _load(path, model)


__all__ = ["__version__", "load_calibration"]
