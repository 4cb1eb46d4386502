"""Checks of a world file's safetensors header (:mod:`dsg_gym.world`): the tensor table and the ``dsg_world``
JSON document's fields, each failure a ``ValueError`` naming the tensor or the field (the reader turns it into a
:class:`dsg_gym.world.WorldFormatError` naming the file)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["DTYPES", "MAX_IMAGE_SIZE", "check_doc", "tensor_entry"]

#: safetensors dtype names the reader accepts
DTYPES = {"F32": np.float32, "F64": np.float64, "I32": np.int32, "I64": np.int64, "U8": np.uint8}


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def tensor_entry(name: str, info: Any) -> tuple[type, tuple[int, ...], int, int]:
    """``(dtype, shape, start, end)`` of a safetensors header entry; ValueError naming the tensor."""
    if not isinstance(info, dict):
        raise ValueError(f"tensor {name!r}: header entry must be an object, got {type(info).__name__}")
    dtype, shape, offsets = info.get("dtype"), info.get("shape"), info.get("data_offsets")
    if not isinstance(dtype, str) or dtype not in DTYPES:
        raise ValueError(f"tensor {name!r} has unsupported dtype {dtype!r} (one of {sorted(DTYPES)})")
    if not isinstance(shape, list) or len(shape) > 8 or not all(_is_int(n) and n >= 0 for n in shape):
        raise ValueError(f"tensor {name!r}: shape must be a list of at most 8 sizes >= 0, got {shape!r}")
    if (
        not isinstance(offsets, list)
        or len(offsets) != 2
        or not all(_is_int(o) for o in offsets)
        or not 0 <= offsets[0] <= offsets[1]
    ):
        raise ValueError(
            f"tensor {name!r}: data_offsets must be [start, end] with 0 <= start <= end, got {offsets!r}"
        )
    size = int(np.dtype(DTYPES[dtype]).itemsize) * math.prod(shape)
    if offsets[1] - offsets[0] != size:
        raise ValueError(
            f"tensor {name!r}: shape {shape} of {dtype} needs {size} bytes, data_offsets hold {offsets[1] - offsets[0]}"
        )
    return DTYPES[dtype], tuple(shape), offsets[0], offsets[1]


#: the largest capture image side a world file may declare (pixels)
MAX_IMAGE_SIZE = 1 << 16


def check_doc(doc: dict) -> dict:
    """The JSON document's fields the reader uses, type-checked; ValueError naming the field."""
    objects = doc.get("objects")
    if not isinstance(objects, list):
        raise ValueError(f"header field 'objects' must be a list, got {_kind(objects)}")
    ids = set()
    for i, o in enumerate(objects):
        if not isinstance(o, dict):
            raise ValueError(f"header field 'objects[{i}]' must be an object, got {_kind(o)}")
        oid, name = o.get("id"), o.get("name")
        if not _is_int(oid) or not 1 <= oid < 2**31 or oid in ids:
            raise ValueError(
                f"header field 'objects[{i}].id' must be a new integer in [1, 2^31), got {_kind(oid)}"
            )
        if not isinstance(name, str):
            raise ValueError(f"header field 'objects[{i}].name' must be a string, got {_kind(name)}")
        ids.add(oid)
    states = doc.get("states")
    if not isinstance(states, list) or not all(isinstance(s, str) for s in states):
        raise ValueError(f"header field 'states' must be a list of strings, got {_kind(states)}")
    cameras = doc.get("cameras")
    if not isinstance(cameras, dict):
        raise ValueError(f"header field 'cameras' must be an object, got {_kind(cameras)}")
    for s, c in cameras.items():
        for key in ("width", "height"):
            v = c.get(key) if isinstance(c, dict) else None
            if not _is_int(v) or not 1 <= v <= MAX_IMAGE_SIZE:
                raise ValueError(
                    f"header field 'cameras.{s}.{key}' must be an integer in [1, {MAX_IMAGE_SIZE}], got {_kind(v)}"
                )
    if not isinstance(doc.get("metadata", {}), dict):
        raise ValueError(f"header field 'metadata' must be an object, got {_kind(doc.get('metadata'))}")
    if not isinstance(doc.get("units", ""), str):
        raise ValueError(f"header field 'units' must be a string, got {_kind(doc.get('units'))}")
    return doc


def _kind(v: Any) -> str:
    """A short description of a JSON value for an error message."""
    text = repr(v) if isinstance(v, (int, float, str, type(None))) else type(v).__name__
    return text if len(text) <= 40 else text[:37] + "..."
