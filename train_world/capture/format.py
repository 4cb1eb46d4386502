"""Writing the capture layout on disk (used by ``dsg-synth`` and ``dsg-import``); see docs/captures.md.

::

    OUT/scene.json                 objects, per-state object poses, table bounds, units, generator, seed
    OUT/<state>/transforms.json    intrinsics + frames [{file_path, mask_path, depth_path, transform_matrix}]
    OUT/<state>/images/NNNN.png    RGB
    OUT/<state>/masks/NNNN.png     uint8 object ids (0 = background, 1..K objects)
    OUT/<state>/depth/NNNN.png     uint16 millimetres (0 = no depth)

Everything is deterministic: PNGs are encoded with a fixed zlib level and no timestamps, JSON keeps insertion
order, and a whole capture is written into a hidden sibling folder that is renamed into place at the end, so
a crash never leaves half a capture at ``OUT``.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from dsg_gym.io.atomic import atomic_dir, atomic_write_bytes

__all__ = [
    "DEPTH_SCALE",
    "depth_to_png_units",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "atomic_write_bytes",
    "atomic_write_json",
    "encode_png",
    "frame_entry",
    "staged_directory",
    "transforms_header",
]

FORMAT_NAME = "dsg-capture"
FORMAT_VERSION = 1
#: metres per depth-PNG unit (depth PNGs hold uint16 millimetres; 0 means "no depth")
DEPTH_SCALE = 0.001
PNG_COMPRESS_LEVEL = 1


def depth_to_png_units(depth_m: np.ndarray) -> np.ndarray:
    """Metres ``[...]`` -> uint16 ``DEPTH_SCALE`` units (millimetres) of a depth PNG; 0 (no depth) where the
    depth is not finite, rounds to <= 0 or lies beyond 65.535 m."""
    d = np.asarray(depth_m, dtype=np.float64)
    units = np.rint(np.where(np.isfinite(d), d, 0.0) * (1.0 / DEPTH_SCALE))  # 1000.0 exactly
    units[(units <= 0) | (units > np.iinfo(np.uint16).max)] = 0
    return units.astype(np.uint16)


def encode_png(array: np.ndarray, compress_level: int = PNG_COMPRESS_LEVEL) -> bytes:
    """Encode uint8 [H,W,3] (RGB), uint8 [H,W] (grey/ids) or uint16 [H,W] (depth) as PNG bytes,
    deterministically."""
    a = np.ascontiguousarray(array)
    if a.dtype == np.uint16 and a.ndim == 2:
        img = Image.fromarray(a.astype("<u2", copy=False))  # mode I;16
    elif a.dtype == np.uint8 and (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (3, 4))):
        img = Image.fromarray(a)
    else:
        raise ValueError(f"encode_png: unsupported array dtype {a.dtype} shape {a.shape}")
    buf = io.BytesIO()
    img.save(buf, format="PNG", compress_level=int(compress_level), optimize=False)
    return buf.getvalue()


def _is_scalar(v: object) -> bool:
    return v is None or isinstance(v, bool | int | float | str)


def json_text(obj: object, indent: int = 0) -> str:
    """Indented JSON where lists of scalars stay on one line (so 4x4 matrices read as four rows).

    Insertion order is kept; NaN/inf are refused.
    """
    pad = "  " * indent
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [f"{pad}  {json.dumps(str(k))}: {json_text(v, indent + 1)}" for k, v in obj.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(obj, list | tuple):
        if all(_is_scalar(v) for v in obj):
            return json.dumps(list(obj), allow_nan=False)
        rows = [f"{pad}  {json_text(v, indent + 1)}" for v in obj]
        return "[\n" + ",\n".join(rows) + f"\n{pad}]"
    return json.dumps(obj, allow_nan=False)


def atomic_write_json(path: str | os.PathLike, obj: object) -> None:
    """Write ``obj`` as indented JSON (:func:`json_text`, trailing newline) atomically."""
    atomic_write_bytes(path, (json_text(obj) + "\n").encode("utf-8"))


@contextlib.contextmanager
def staged_directory(out: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty hidden sibling folder of ``out``; on success it is renamed to ``out``.

    Refuses (``FileExistsError``) when ``out`` exists and is not empty, unless ``overwrite``. On error the
    staged folder is removed and ``out`` is left untouched.
    """
    out = Path(out).absolute()
    if out.exists() and not overwrite and (not out.is_dir() or any(out.iterdir())):
        raise FileExistsError(f"{out}: already exists; pass --overwrite (overwrite=True) to replace it")
    with atomic_dir(out, replace=True) as stage:
        yield stage


def transforms_header(width: int, height: int, fx: float, fy: float, cx: float, cy: float) -> dict:
    """Global intrinsics block of a ``transforms.json`` (nerfstudio keys plus Blender's
    ``camera_angle_x``)."""
    return {
        "camera_model": "OPENCV",
        "w": int(width),
        "h": int(height),
        "fl_x": float(fx),
        "fl_y": float(fy),
        "cx": float(cx),
        "cy": float(cy),
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "camera_angle_x": float(2.0 * np.arctan(0.5 * width / fx)),
        "camera_angle_y": float(2.0 * np.arctan(0.5 * height / fy)),
        "depth_unit_scale_factor": DEPTH_SCALE,
        "camera_convention": "transform_matrix: camera-to-world, OpenGL axes (x right, y up, looks -z)",
    }


def frame_entry(
    file_path: str, c2w_gl: np.ndarray, mask_path: str | None = None, depth_path: str | None = None
) -> dict:
    """One ``frames`` entry; paths are relative to the folder holding ``transforms.json``."""
    entry: dict = {"file_path": file_path}
    if mask_path is not None:
        entry["mask_path"] = mask_path
    if depth_path is not None:
        entry["depth_path"] = depth_path
    entry["transform_matrix"] = matrix_to_list(c2w_gl)
    return entry


def matrix_to_list(mat: np.ndarray) -> list[list[float]]:
    """A 4x4 matrix as nested lists of Python floats (exact float64 repr in JSON)."""
    return [[float(x) for x in row] for row in np.asarray(mat, dtype=np.float64)]


def view_file_stem(index: int, count: int) -> str:
    """Zero-padded stem for view ``index`` of ``count`` (at least 4 digits)."""
    return f"{index:0{max(4, len(str(max(count - 1, 0))))}d}"


def write_state_views(
    state_dir: Path,
    c2w_gl: Sequence[np.ndarray],
    width: int,
    height: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    images: Sequence[bytes],
    masks: Sequence[bytes] | None = None,
    depths: Sequence[bytes] | None = None,
) -> None:
    """Write one state's encoded PNGs plus its ``transforms.json`` under ``state_dir``."""
    n = len(c2w_gl)
    frames = []
    for i in range(n):
        stem = view_file_stem(i, n)
        img_rel = f"images/{stem}.png"
        atomic_write_bytes(state_dir / img_rel, images[i])
        mask_rel = depth_rel = None
        if masks is not None:
            mask_rel = f"masks/{stem}.png"
            atomic_write_bytes(state_dir / mask_rel, masks[i])
        if depths is not None:
            depth_rel = f"depth/{stem}.png"
            atomic_write_bytes(state_dir / depth_rel, depths[i])
        frames.append(frame_entry(img_rel, c2w_gl[i], mask_rel, depth_rel))
    doc = transforms_header(width, height, fx, fy, cx, cy)
    doc["frames"] = frames
    atomic_write_json(state_dir / "transforms.json", doc)
