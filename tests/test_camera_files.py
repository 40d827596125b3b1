"""``--camera`` files from other tools (lidarcal.io.camera_files): OpenCV's calibration YAML,
ROS camera_calibration's camera_info YAML, and camera.json, read into one validated camera."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lidarcal.io.bag_views import camera_from_info
from lidarcal.io.camera_files import read_camera_file
from lidarcal.io.dataset import DatasetError

REPO = Path(__file__).resolve().parents[1]
TAPAS = REPO / "data" / "real_tapas"
LIDARCAL = Path(sys.executable).with_name("lidarcal")


def ros_yaml(K: np.ndarray, D: list[float], size: tuple[int, int], model: str = "plumb_bob") -> str:
    """A camera_info YAML as ROS's camera_calibration writes it (ost.yaml)."""
    P = np.hstack([K, np.zeros((3, 1))])
    return (f"image_width: {size[0]}\nimage_height: {size[1]}\ncamera_name: narrow_stereo\n"
            f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {K.ravel().tolist()}\n"
            f"distortion_model: {model}\n"
            f"distortion_coefficients:\n  rows: 1\n  cols: {len(D)}\n  data: {list(D)}\n"
            f"rectification_matrix:\n  rows: 3\n  cols: 3\n  data: {np.eye(3).ravel().tolist()}\n"
            f"projection_matrix:\n  rows: 3\n  cols: 4\n  data: {P.ravel().tolist()}\n")


def tapas_camera() -> dict:
    return json.loads((TAPAS / "camera.json").read_text())


def test_opencv_sample_yaml_reads_its_published_camera() -> None:
    """OpenCV's left_intrinsics.yml (``!!opencv-matrix`` nodes): fx = fy 535.9157, cx 342.2832,
    cy 235.5708, five coefficients, 640 x 480, exactly as the file holds them."""
    cam = read_camera_file(REPO / "tests" / "data" / "opencv_left" / "left_intrinsics.yml")
    assert cam.image_size == (640, 480)
    assert np.allclose(cam.K, [[535.915733961632, 0, 342.28315473308373],
                               [0, 535.915733961632, 235.57082909788173], [0, 0, 1]], atol=1e-9)
    assert np.allclose(cam.dist, [-2.6637260909660682e-01, -3.8588898922304653e-02,
                                  1.7831947042852964e-03, -2.8122100441115472e-04,
                                  2.3839153080878486e-01])


@pytest.mark.parametrize("model,D", [("plumb_bob", [0.1, -0.2, 0.001, 0.002, 0.05]),
                                     ("rational_polynomial", [0.1, -0.2, 0.001, 0.002, 0.05, 0, 0, 0])])
def test_ros_camera_info_yaml_equals_the_camera_json(tmp_path: Path, model: str, D: list) -> None:
    """A ROS camera_info YAML holding the numbers of a camera.json reads as that camera."""
    K = np.array([[646.3, 0.2, 312.5], [0, 645.7, 245.0], [0, 0, 1]])
    p = tmp_path / "ost.yaml"
    p.write_text(ros_yaml(K, D, (640, 480), model))
    cam = read_camera_file(p)
    assert np.allclose(cam.K, K) and np.allclose(cam.dist, D[:5]) and cam.image_size == (640, 480)
    assert cam.source == str(p)


@pytest.mark.parametrize("text,says", [
    ("fisheye", "equidistant (fisheye)"),
    ("rational", "k4..k6"),
    ("nosize", "image_width and image_height"),
    ("nok", "no 3x3 camera matrix"),
    ("transposed", "transposed"),
    ("garbage", "OpenCV can read"),
])
def test_bad_camera_yaml_names_the_file(tmp_path: Path, text: str, says: str) -> None:
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    good = ros_yaml(K, [0.0] * 5, (640, 480))
    body = {"fisheye": ros_yaml(K, [0.1, 0.01, 0, 0], (640, 480), "equidistant"),
            "rational": ros_yaml(K, [0.1, -0.2, 0, 0, 0, 0.3, 0, 0], (640, 480), "rational_polynomial"),
            "nosize": "\n".join(good.splitlines()[2:]) + "\n",
            "nok": good.replace("camera_matrix:", "intrinsics:"),
            "transposed": ros_yaml(K.T.copy(), [0.0] * 5, (640, 480)),
            "garbage": "camera_matrix: [1, 2\n  : : :\n"}[text]
    p = tmp_path / "camera.yaml"
    p.write_text(body)
    with pytest.raises(DatasetError) as e:
        read_camera_file(p)
    assert str(p) in str(e.value) and says in str(e.value)


def test_bag_camera_info_and_the_yaml_agree() -> None:
    """The bag import's CameraInfo mapping and the YAML reader share one rule
    (:func:`lidarcal.io.camera_files.pinhole_from_ros`): the same numbers give the same block."""
    from types import SimpleNamespace
    K = np.array([[646.3, 0, 312.5], [0, 645.7, 245.0], [0, 0, 1]])
    roi = SimpleNamespace(width=0, height=0)
    msg = SimpleNamespace(k=K.ravel(), d=np.array([0.1, -0.2, 0.001, 0.002, 0.05, 0, 0, 0]),
                          distortion_model="rational_polynomial", width=640, height=480,
                          binning_x=0, binning_y=0, roi=roi)
    block, why = camera_from_info(msg, "/camera/camera_info")
    assert why is None and np.allclose(block["K"], K) and block["image_size"] == [640, 480]
    msg.distortion_model = "equidistant"
    block, why = camera_from_info(msg, "/camera/camera_info")
    assert block is None and "/camera/camera_info" in why and "fisheye" in why


def test_planes_cli_with_a_ros_yaml_camera_matches_camera_json(tmp_path: Path) -> None:
    """`lidarcal planes` on the real TAPAS views with the recording's camera given as a ROS
    camera_info YAML gives the same pose as with its camera.json; a fisheye YAML: exit 2, one
    line naming it, no output folder."""
    c = tapas_camera()
    y = tmp_path / "ost.yaml"
    y.write_text(ros_yaml(np.asarray(c["K"], float), c["dist"], tuple(c["image_size"])))
    outs = {}
    for name, cam in (("json", TAPAS / "camera.json"), ("yaml", y)):
        out = tmp_path / name
        p = subprocess.run([str(LIDARCAL), "planes", str(TAPAS), "--camera", str(cam), "--out",
                            str(out)], check=False, capture_output=True, text=True)
        assert p.returncode == 0, p.stderr
        outs[name] = json.loads((out / "extrinsics.json").read_text())
    assert np.allclose(outs["json"]["R"], outs["yaml"]["R"], atol=1e-9)
    assert np.allclose(outs["json"]["T_mm"], outs["yaml"]["T_mm"], atol=1e-6)
    bad = tmp_path / "fish.yaml"
    bad.write_text(ros_yaml(np.asarray(c["K"], float), [0.1, 0.01, 0, 0], (640, 480), "equidistant"))
    p = subprocess.run([str(LIDARCAL), "planes", str(TAPAS), "--camera", str(bad), "--out",
                        str(tmp_path / "bad")], check=False, capture_output=True, text=True)
    assert p.returncode == 2 and str(bad) in p.stderr and len(p.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "bad").exists()
