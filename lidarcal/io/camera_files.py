"""The camera files ``--camera`` reads (``lidarcal planes``, ``laser-plane``, ``report``).

- ``camera.json``: the keys of dataset.json's ``camera`` block (``K``, ``dist``,
  ``image_size``), as ``lidarcal intrinsics`` and ``lidarcal import --views`` write it;
- an OpenCV FileStorage file (``.yml``, ``.yaml``, ``.xml``) as OpenCV's calibration sample
  writes it: ``camera_matrix`` (or ``cameraMatrix``, ``K``), ``distortion_coefficients`` (or
  ``dist_coeffs``, ``distCoeffs``, ``D``), ``image_width``, ``image_height``;
- a ROS ``camera_info`` YAML as ``camera_calibration`` writes it (``ost.yaml``):
  ``camera_matrix: {rows, cols, data}``, ``distortion_model`` (``plumb_bob`` or
  ``rational_polynomial``), ``distortion_coefficients``, ``image_width``, ``image_height``.

Every file ends as the same validated :class:`CameraModel` (:func:`parse_camera`): OpenCV's
pinhole model with k1, k2, p1, p2, k3 (rational terms k4-k6 must be 0; a fisheye model is
refused, naming the file and what to do). Both YAML forms are read by ``cv2.FileStorage``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .dataset import CameraModel, DatasetError, parse_camera, read_json_object

K_KEYS = ("camera_matrix", "cameraMatrix", "K")
DIST_KEYS = ("distortion_coefficients", "dist_coeffs", "distCoeffs", "D")
YAML_SUFFIXES = (".yml", ".yaml", ".xml")
FIX = ("give the camera.json of `lidarcal intrinsics`, an OpenCV calibration file "
       "(camera_matrix, distortion_coefficients, image_width, image_height) or a ROS "
       "camera_info YAML")


def pinhole_from_ros(K: np.ndarray, D: np.ndarray, model: str, size: list[int]
                     ) -> tuple[dict | None, str | None]:
    """A ROS CameraInfo's calibration as the ``camera`` block (``K``, ``dist``,
    ``image_size``), or None and why not. ``plumb_bob`` D = (k1, k2, t1, t2, k3) and
    ``rational_polynomial`` (k1, k2, t1, t2, k3, k4, k5, k6) are OpenCV's order; lidarcal's
    model holds k1, k2, p1, p2, k3, so k4-k6 must be 0; ``equidistant`` (fisheye) and other
    models are not OpenCV's pinhole model."""
    K = np.asarray(K, float).reshape(3, 3)
    D = np.asarray(D, float).reshape(-1)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or min(size) <= 0:
        return None, f"no calibration (K {K.tolist()}, size {size})"
    if model in ("plumb_bob", "rational_polynomial") or (model == "" and not D.any()):
        if D.size > 5 and np.any(D[5:] != 0):
            return None, (f"{model} distortion with k4..k6 = {D[5:8].tolist()}; lidarcal's "
                          "camera model has k1, k2, p1, p2, k3 only")
        dist = np.zeros(5)
        dist[: min(D.size, 5)] = D[:5]
        return {"K": K.tolist(), "dist": dist.tolist(), "image_size": [int(s) for s in size]}, None
    what = "equidistant (fisheye)" if model in ("equidistant", "fisheye") else repr(model)
    return None, (f"distortion model {what} is not OpenCV's pinhole model that lidarcal uses "
                  "(plumb_bob, rational_polynomial)")


def _node_array(node) -> np.ndarray | None:
    """A FileStorage node as numbers: an ``!!opencv-matrix``, a ROS ``{rows, cols, data}``
    map, or a plain sequence; None when it is none of these."""
    if node.empty():
        return None
    if node.isMap() and not node.getNode("dt").empty():  # an !!opencv-matrix
        return np.asarray(node.mat(), float).ravel()
    seq = node.getNode("data") if node.isMap() else node
    if not seq.isSeq():
        return None
    return np.array([seq.at(i).real() for i in range(seq.size())], float)


def _first(fs, keys: tuple[str, ...]) -> np.ndarray | None:
    for k in keys:
        a = _node_array(fs.getNode(k))
        if a is not None:
            return a
    return None


def read_opencv_yaml(path: Path) -> CameraModel:
    """An OpenCV FileStorage or ROS camera_info file (module docstring) as a camera."""
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:  # SystemError: the binding's wrapper of a parse error
        cause = e.__cause__ or e
        msg = str(cause).strip().splitlines()[-1] if str(cause).strip() else "unreadable"
        msg = msg.rpartition(" error: ")[2] or msg  # without OpenCV's source path
        raise DatasetError(path, f"not a YAML/XML file OpenCV can read ({msg}); {FIX}") from None
    try:
        if not fs.isOpened():
            raise DatasetError(path, f"cannot be opened as YAML/XML; {FIX}")
        K, D = _first(fs, K_KEYS), _first(fs, DIST_KEYS)
        w, h = fs.getNode("image_width"), fs.getNode("image_height")
        model = fs.getNode("distortion_model")
        model = model.string() if not model.empty() and model.isString() else ""
        size = [int(w.real()), int(h.real())] if not (w.empty() or h.empty()) else None
    finally:
        fs.release()
    if K is None or K.size != 9:
        raise DatasetError(path, f"no 3x3 camera matrix (one of {', '.join(K_KEYS)}); {FIX}")
    if size is None:
        raise DatasetError(path, "no image_width and image_height (the photos' size the camera "
                                 f"matrix belongs to); add them; {FIX}")
    block, why = pinhole_from_ros(K, np.zeros(5) if D is None else D, model or "plumb_bob", size)
    if block is None:
        raise DatasetError(path, f"{why}; calibrate the camera with `lidarcal intrinsics` "
                                 "(it writes camera.json)")
    cam = parse_camera(block, path)
    return CameraModel(cam.K, cam.dist, cam.image_size, source=str(path))


def read_camera_file(path: str | Path) -> CameraModel:
    """The camera of ``--camera``: camera.json, an OpenCV FileStorage file or a ROS
    camera_info YAML (module docstring), validated by :func:`parse_camera`."""
    path = Path(path)
    if path.suffix.lower() in YAML_SUFFIXES:
        if not path.is_file():
            raise DatasetError(path, f"missing camera file; {FIX}")
        return read_opencv_yaml(path)
    raw = read_json_object(path, f"missing camera file; {FIX}", FIX,
                           f" (K, dist, image_size); {FIX}")
    cam = parse_camera(raw, path)
    return CameraModel(cam.K, cam.dist, cam.image_size, source=str(path), rms_px=raw.get("rms_px"))
