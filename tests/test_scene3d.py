"""pyvista scenes render off screen in a fresh process without a display (no X warning)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = textwrap.dedent("""
    import sys
    import numpy as np
    from lidarcal import scene3d
    from lidarcal.geometry import Pose, rotation_about_axis

    R0 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    poses = [Pose(rotation_about_axis(np.array([1.0, 0, 0]), np.radians(a)) @ R0,
                  np.array([50.0, 150.0, 100.0])) for a in (-10, 0, 10)]
    g = np.stack(np.meshgrid(np.arange(5) * 20.0, np.arange(4) * 20.0), -1).reshape(-1, 2)
    board = np.column_stack([g[:, 0] - 200, g[:, 1] - 50, 1200 + 0.5 * g[:, 0]])
    K = np.array([[1000.0, 0, 400], [0, 1000.0, 300], [0, 0, 1]])
    p = scene3d.rig_plotter(poses, [board], None, (np.zeros(3), np.array([1.0, 0, 0])), K=K,
                            image_size=(800, 600), aperture_deg=(-35, 35))
    scene3d.scene_figure_png(p, sys.argv[1])
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(2000, 3)) * [100, 100, 2] + [0, 0, 1500]
    p = scene3d.sweep_plotter(pts, pts[:, 0], "x_mm", disc=(np.array([0, 0, 1500.0]),
                              np.array([0, 0, 1.0]), 140.0))
    img = scene3d.screenshot(p, sys.argv[2])
    fig = scene3d.rig_figure(poses, [board], None, None)
    print(img.shape, type(fig).__name__)
""")


def test_scenes_render_headless(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY",
                                                            "VTK_DEFAULT_OPENGL_WINDOW")}
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(tmp_path / "rig.png"), str(tmp_path / "sweep.png")],
                       capture_output=True, text=True, env=env, cwd=ROOT, check=False, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "Figure" in r.stdout
    assert "bad X server" not in r.stderr and "WARN" not in r.stderr, r.stderr
    import matplotlib.image as mpimg

    for name in ("rig.png", "sweep.png"):
        img = mpimg.imread(tmp_path / name)[..., :3]
        assert img.shape[0] > 100 and img.shape[1] > 100
        # something was drawn: a good share of pixels is not the white background, in colour
        drawn = np.any(img < 0.9, axis=-1)
        assert 0.01 < drawn.mean() < 0.9, drawn.mean()
        assert np.ptp(img[drawn], axis=0).max() > 0.3
