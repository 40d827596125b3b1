"""Point-cloud files: PLY (binary, default), PCD (binary), VTP and CSV, written atomically.

A cloud is ``N`` points (mm) and named per-point attributes (1-D arrays of
length ``N``), e.g. ``range_mm``, ``psi_deg``, ``angle_deg``, ``intensity``.
The format is chosen by the file suffix:

``.ply``
    Binary little-endian PLY written with ``plyfile``: one ``vertex`` element,
    properties ``x y z`` (float32, mm) then every attribute (float64; integer
    attributes int32). Opens in CloudCompare, Open3D, MeshLab, ParaView.
``.pcd``
    PCL's PCD v0.7, ``DATA binary`` (no common Python writer exists, so this
    module holds a small one, :func:`write_pcd`, and its reader
    :func:`read_pcd`): header ``FIELDS x y z <attributes>``, ``SIZE``/``TYPE``
    4/F for x y z, 8/F for float attributes, 4/I for integer ones, ``WIDTH N``,
    ``HEIGHT 1`` (unorganised), ``VIEWPOINT 0 0 0 1 0 0 0``, then the points as
    packed little-endian records. Opens in PCL, Open3D, CloudCompare.
``.vtp``
    VTK XML PolyData (pyvista), binary; points float64, attributes as point data.
``.csv``
    Header ``x_mm,y_mm,z_mm,<attributes>``, one row per point.

Every writer writes a temporary file next to the target and renames it, so a
file is never half-written.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from .dataset import write_atomic

FORMATS = (".ply", ".pcd", ".vtp", ".csv")


def _check(points: np.ndarray, attributes: Mapping[str, np.ndarray]) -> tuple[np.ndarray, dict]:
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"Expected points with shape (N, 3), got {pts.shape}")
    attrs = {}
    for name, a in attributes.items():
        a = np.asarray(a)
        if a.shape != (len(pts),):
            raise ValueError(f"attribute {name!r}: expected shape ({len(pts)},), got {a.shape}")
        if not name.isidentifier():
            raise ValueError(f"attribute name {name!r} must be an identifier (letters, digits, _)")
        attrs[name] = a.astype(np.int32) if a.dtype.kind in "iub" else a.astype(np.float64)
    return pts, attrs


def _records(points: np.ndarray, attrs: dict, xyz_dtype: str = "<f4") -> np.ndarray:
    dt = [("x", xyz_dtype), ("y", xyz_dtype), ("z", xyz_dtype)]
    dt += [(k, "<i4" if v.dtype.kind == "i" else "<f8") for k, v in attrs.items()]
    rec = np.empty(len(points), dtype=dt)
    rec["x"], rec["y"], rec["z"] = points.T
    for k, v in attrs.items():
        rec[k] = v
    return rec


def write_ply(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] = {}) -> Path:
    """Binary little-endian PLY (plyfile): ``vertex`` with x y z (float32, mm) and the attributes."""
    from plyfile import PlyData, PlyElement

    pts, attrs = _check(points, attributes)
    el = PlyElement.describe(_records(pts, attrs), "vertex")
    ply = PlyData([el], text=False, byte_order="<",
                  comments=["lidarcal point cloud, units mm and degrees"])
    return write_atomic(path, lambda p: ply.write(str(p)))


def write_pcd(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] = {}) -> Path:
    """PCL PCD v0.7, ``DATA binary``, unorganised (HEIGHT 1); see the module docstring."""
    pts, attrs = _check(points, attributes)
    rec = _records(pts, attrs)
    names = rec.dtype.names
    size = [str(rec.dtype[n].itemsize) for n in names]
    typ = ["I" if rec.dtype[n].kind == "i" else "F" for n in names]
    header = ("# .PCD v0.7 - Point Cloud Data file format (lidarcal, mm)\n"
              "VERSION 0.7\n"
              f"FIELDS {' '.join(names)}\nSIZE {' '.join(size)}\nTYPE {' '.join(typ)}\n"
              f"COUNT {' '.join('1' for _ in names)}\nWIDTH {len(rec)}\nHEIGHT 1\n"
              "VIEWPOINT 0 0 0 1 0 0 0\n"
              f"POINTS {len(rec)}\nDATA binary\n")

    def write(p: Path) -> None:
        with open(p, "wb") as f:
            f.write(header.encode("ascii"))
            f.write(rec.tobytes())

    return write_atomic(path, write)


def write_vtp(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] = {}) -> Path:
    """VTK XML PolyData via pyvista (binary), attributes as point data."""
    import pyvista as pv

    pts, attrs = _check(points, attributes)
    poly = pv.PolyData(pts)
    for k, v in attrs.items():
        poly.point_data[k] = v
    return write_atomic(path, lambda p: poly.save(str(p), binary=True))


def write_csv(path: str | os.PathLike, points: np.ndarray, attributes: Mapping[str, np.ndarray] = {}) -> Path:
    """CSV with header ``x_mm,y_mm,z_mm,<attributes>`` (pandas)."""
    import pandas as pd

    pts, attrs = _check(points, attributes)
    df = pd.DataFrame({"x_mm": pts[:, 0], "y_mm": pts[:, 1], "z_mm": pts[:, 2], **attrs})
    return write_atomic(path, lambda p: df.to_csv(p, index=False, float_format="%.6f"))


WRITERS = {".ply": write_ply, ".pcd": write_pcd, ".vtp": write_vtp, ".csv": write_csv}


def write_cloud(path: str | os.PathLike, points: np.ndarray,
                attributes: Mapping[str, np.ndarray] = {}) -> Path:
    """Write a cloud in the format named by the suffix of ``path`` (.ply, .pcd, .vtp, .csv)."""
    suffix = Path(path).suffix.lower()
    if suffix not in WRITERS:
        raise ValueError(f"{path}: unknown point-cloud format {suffix!r}; use one of {', '.join(FORMATS)}")
    return WRITERS[suffix](path, points, attributes)


# --------------------------------------------------------------------------- readers


def read_pcd(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a PCD v0.7 file with ``DATA binary`` or ``ascii``: points (N, 3) and attributes."""
    raw = Path(path).read_bytes()
    head: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = raw.index(b"\n", pos)
        line = raw[pos:end].decode("ascii").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        head[key.upper()] = vals
        if key.upper() == "DATA":
            break
    names = head["FIELDS"]
    kinds = {("F", "4"): "<f4", ("F", "8"): "<f8", ("I", "4"): "<i4", ("U", "4"): "<u4",
             ("I", "2"): "<i2", ("U", "1"): "u1", ("I", "1"): "i1", ("U", "2"): "<u2"}
    dt = np.dtype([(n, kinds[(t, s)]) for n, t, s in zip(names, head["TYPE"], head["SIZE"], strict=True)])
    n = int(head["POINTS"][0])
    mode = head["DATA"][0]
    if mode == "binary":
        rec = np.frombuffer(raw, dtype=dt, count=n, offset=pos)
    elif mode == "ascii":
        rec = np.loadtxt(raw[pos:].decode("ascii").splitlines(), dtype=dt, ndmin=1)
    else:
        raise ValueError(f"{path}: PCD DATA {mode!r} is not supported (binary or ascii)")
    pts = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float)
    return pts, {k: np.asarray(rec[k]) for k in names if k not in ("x", "y", "z")}


def read_cloud(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Read a cloud written by :func:`write_cloud` (plyfile / pyvista / :func:`read_pcd` / pandas)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        from plyfile import PlyData

        v = PlyData.read(str(path))["vertex"].data
        pts = np.column_stack([v["x"], v["y"], v["z"]]).astype(float)
        return pts, {k: np.asarray(v[k]) for k in v.dtype.names if k not in ("x", "y", "z")}
    if suffix == ".pcd":
        return read_pcd(path)
    if suffix == ".vtp":
        import pyvista as pv

        poly = pv.read(str(path))
        return np.asarray(poly.points, float), {k: np.asarray(poly.point_data[k]) for k in poly.point_data}
    if suffix == ".csv":
        import pandas as pd

        df = pd.read_csv(path)
        pts = df[["x_mm", "y_mm", "z_mm"]].to_numpy(float)
        return pts, {k: df[k].to_numpy() for k in df.columns if k not in ("x_mm", "y_mm", "z_mm")}
    raise ValueError(f"{path}: unknown point-cloud format {suffix!r}; use one of {', '.join(FORMATS)}")
