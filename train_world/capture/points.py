"""A capture's sparse 3D points: the static background's structure-from-motion points, to start training from.

``dsg-capture`` triangulates the background (the objects are masked out of its features) and writes those
points, in the capture's table frame, to ``points3d.ply`` beside ``scene.json``, which names the file under
``"points": {"path": "points3d.ply", "kind": "sfm", "count": N}``. Training on a capture without depth maps
starts from them (as 3D Gaussian Splatting starts from COLMAP's points), so the walls and floor that the random
points in the table box never reach get Gaussians from the first step.

The file is a binary little-endian PLY with one ``vertex`` element of float ``x, y, z`` and uchar ``red,
green, blue``: what nerfstudio's ``ply_file_path`` and most point-cloud tools read. :func:`read_points_ply`
reads that layout and any other whose vertex properties are scalars (extra properties are skipped, ascii
too); anything else is a :class:`~train_world.capture.files.CaptureError` naming the file.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from train_world.capture.files import CaptureError
from train_world.capture.format import atomic_write_bytes

__all__ = ["POINTS_FILE", "capture_points", "point_colours", "read_points_ply", "write_points_ply"]

#: the file name ``dsg-capture`` writes beside ``scene.json``
POINTS_FILE = "points3d.ply"

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def write_points_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray) -> None:
    """Write points ``xyz [N,3]`` (float, written as float32) with colours ``rgb [N,3]`` uint8 (atomically)."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb).reshape(-1, 3)
    if len(rgb) != len(xyz) or rgb.dtype != np.uint8 or not np.isfinite(xyz).all():
        raise ValueError(
            f"write_points_ply: need finite xyz [N,3] and uint8 rgb [N,3], got {xyz.shape}, {rgb.dtype}"
        )
    rec = np.empty(
        len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("r", "u1"), ("g", "u1"), ("b", "u1")]
    )
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["r"], rec["g"], rec["b"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", "comment dsg-capture background points (table frame)",
         f"element vertex {len(xyz)}", "property float x", "property float y", "property float z",
         "property uchar red", "property uchar green", "property uchar blue", "end_header"]
    )  # fmt: skip
    atomic_write_bytes(path, (header + "\n").encode("ascii") + rec.tobytes())


def read_points_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Points ``[N,3]`` float64 and colours ``[N,3]`` float32 in [0, 1] (grey 0.5 without colour properties)
    of a point PLY (module docstring)."""
    path = Path(path)
    fix = "write it again with dsg-capture, or remove it and its 'points' entry from scene.json"
    try:
        data = path.read_bytes()
    except OSError as e:
        raise CaptureError(f"{path}: cannot read the point cloud ({e.strerror or e})") from e
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise CaptureError(f"{path}: not a PLY file (no 'ply' ... 'end_header' header); {fix}")
    body_start = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, count, props, element = None, None, [], None
    for line in lines[1:]:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format" and len(parts) >= 2:
            fmt = parts[1]
        elif parts[0] == "element" and len(parts) == 3:
            element = parts[1]
            if element == "vertex":
                count = int(parts[2]) if parts[2].isdigit() else -1
            elif count is not None:
                break  # elements after the vertices are not needed
        elif parts[0] == "property" and element == "vertex":
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:
                raise CaptureError(f"{path}: vertex property {' '.join(parts[1:])!r} is not a scalar; {fix}")
            props.append((parts[2], _PLY_TYPES[parts[1]]))
    names = [n for n, _ in props]
    if count is None or count < 0 or not {"x", "y", "z"} <= set(names):
        raise CaptureError(f"{path}: no vertex element with x, y, z properties; {fix}")
    if fmt == "ascii":
        text = data[body_start:].decode("ascii", errors="replace").split()
        if len(text) < count * len(props):
            raise CaptureError(f"{path}: {count} vertices announced, fewer written; {fix}")
        table = np.asarray(text[: count * len(props)], dtype=np.float64).reshape(count, len(props))
        col = {n: table[:, i] for i, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        if len(data) - body_start < count * dtype.itemsize:
            raise CaptureError(f"{path}: {count} vertices announced, the file is shorter; {fix}")
        rec = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
        col = {n: rec[n].astype(np.float64) for n in names}
    else:
        raise CaptureError(f"{path}: PLY format {fmt!r} is not ascii or binary; {fix}")
    xyz = np.stack([col["x"], col["y"], col["z"]], 1)
    if not np.isfinite(xyz).all():
        raise CaptureError(f"{path}: a point has a non-finite coordinate; {fix}")
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([col["red"], col["green"], col["blue"]], 1) / 255.0
    else:
        rgb = np.full((count, 3), 0.5)
    return xyz, np.clip(rgb, 0.0, 1.0).astype(np.float32)


def capture_points(root: str | Path, scene: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The points a capture's ``scene.json`` (``scene``, read from ``root``) names under ``"points"``, or None
    when it names none. CaptureError for an entry that is not ``{"path": <file inside the capture>}``."""
    entry = scene.get("points")
    if entry is None:
        return None
    src = Path(root) / "scene.json"
    if not isinstance(entry, Mapping) or not isinstance(entry.get("path"), str):
        raise CaptureError(
            f"{src}: 'points' must be an object with a 'path' string, e.g. {{\"path\": \"{POINTS_FILE}\"}}"
        )
    root = Path(root).resolve()
    path = (root / entry["path"]).resolve()
    if root not in path.parents:
        raise CaptureError(
            f"{src}: points path {entry['path']!r} leaves the capture folder; give a path inside it"
        )
    return read_points_ply(path)


def point_colours(
    points: np.ndarray, images: list[np.ndarray], world_to_camera: list[np.ndarray], K: np.ndarray
) -> np.ndarray:
    """Colour ``[N,3]`` uint8 of each point: the per-channel median over the views it projects into (in front
    of the camera, inside the image; ``images`` uint8 ``[H,W,3]``, OpenCV ``world_to_camera [4,4]``, one
    pinhole ``K``); grey (128) for a point no view sees."""
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    samples = [[] for _ in range(len(P))]
    for img, w2c in zip(images, world_to_camera):
        c = P @ w2c[:3, :3].T + w2c[:3, 3]
        z = c[:, 2]
        ok = z > 1e-9
        u = np.floor(K[0, 0] * c[:, 0] / np.where(ok, z, 1) + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * c[:, 1] / np.where(ok, z, 1) + K[1, 2]).astype(np.int64)
        h, w = img.shape[:2]
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        for i in np.flatnonzero(ok):
            samples[i].append(img[v[i], u[i], :3])
    out = np.full((len(P), 3), 128, np.uint8)
    for i, s in enumerate(samples):
        if s:
            out[i] = np.median(np.asarray(s), axis=0).round().astype(np.uint8)
    return out
