"""Writing world files (format: :mod:`dsg_gym.world`): build a :class:`~dsg_gym.world.World` from a trained
field, encode it as safetensors + JSON (no pickle) and write it atomically (temp file + ``os.replace``)."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from safetensors.numpy import save as st_save

from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import (
    FORMAT_NAME,
    FORMAT_VERSION,
    GAUSSIAN_FIELDS,
    META_KEY,
    OPTIONAL_FIELDS,
    Cameras,
    World,
    WorldObject,
    transform_gaussians,
)
from train_world.capture.format import atomic_write_bytes

__all__ = ["build_world", "encode_world", "write_world"]


def _add_set(arrays: dict[str, np.ndarray], prefix: str, g: GaussianSet) -> None:
    for f in GAUSSIAN_FIELDS:
        arrays[f"{prefix}/{f}"] = np.ascontiguousarray(getattr(g, f))
    for f in OPTIONAL_FIELDS:
        v = getattr(g, f)
        if v is not None:
            arrays[f"{prefix}/{f}"] = np.ascontiguousarray(v)


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, (dict, MappingProxyType)):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def encode_world(world: World) -> bytes:
    """The bytes of a world file (deterministic for a given world)."""
    arrays: dict[str, np.ndarray] = {}
    _add_set(arrays, "gaussians/background", world.background)
    for oid in world.object_ids:
        _add_set(arrays, f"gaussians/object_{oid}", world.objects[oid].gaussians)
    for s, P in world.poses.items():
        if "/" in s:
            raise ValueError(f"state name {s!r} must not contain '/'")
        arrays[f"poses/{s}"] = np.ascontiguousarray(P, dtype=np.float64)
    for s, cam in world.cameras.items():
        arrays[f"cameras/{s}/viewmats"] = np.ascontiguousarray(cam.viewmats, dtype=np.float32)
        arrays[f"cameras/{s}/Ks"] = np.ascontiguousarray(cam.Ks, dtype=np.float32)
    arrays["classifier/weight"] = np.ascontiguousarray(world.classifier_weight, dtype=np.float32)
    arrays["classifier/bias"] = np.ascontiguousarray(world.classifier_bias, dtype=np.float32)
    doc = {
        "objects": [
            {"id": oid, "name": world.objects[oid].name, "class": i + 1}
            for i, oid in enumerate(world.object_ids)
        ],
        "num_classes": world.num_objects + 1,
        "states": list(world.poses),
        "cameras": {
            s: {"width": c.width, "height": c.height, "count": len(c)} for s, c in world.cameras.items()
        },
        "units": world.units,
        "metadata": _jsonable(world.metadata),
    }

    def encode(d: dict) -> bytes:
        full = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, **d}
        return st_save(arrays, metadata={META_KEY: json.dumps(full)})

    probe = encode({**doc, "sha256": ""})
    (hlen,) = struct.unpack("<Q", probe[:8])
    digest = hashlib.sha256(probe[8 + hlen :]).hexdigest()
    return encode({**doc, "sha256": digest})


def write_world(path: str | Path, world: World) -> Path:
    """Encode ``world`` and write it atomically to ``path``; returns the path."""
    p = Path(path)
    if p.parent and not p.parent.exists():
        p.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(p, encode_world(world))
    return p


def build_world(
    gaussians: GaussianSet,
    classes: np.ndarray,
    object_ids: tuple[int, ...],
    object_names: tuple[str, ...],
    poses: dict[str, np.ndarray],
    reference_state: str,
    cameras: dict[str, Cameras],
    classifier_weight: np.ndarray,
    classifier_bias: np.ndarray,
    units: str,
    metadata: dict[str, Any],
) -> World:
    """Split trained Gaussians (world frame of ``reference_state``) by class: class 0 is background, class
    ``i >= 1`` is object ``object_ids[i-1]``, moved into its own frame by ``inv(poses[reference_state][i-1])``.
    ``labels`` of every Gaussian become its object id (0 for the background)."""
    classes = np.asarray(classes, dtype=np.int64)
    ids = np.array((0,) + tuple(object_ids), dtype=np.int32)
    g = GaussianSet(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        gaussians.sh,
        gaussians.features,
        ids[classes],
        gaussians.opacity_logits,
        gaussians.log_scales,
    )
    ref = np.asarray(poses[reference_state], dtype=np.float64)
    objects = {}
    for i, (oid, name) in enumerate(zip(object_ids, object_names)):
        sub = g.subset(classes == i + 1)
        objects[int(oid)] = WorldObject(name, transform_gaussians(sub, np.linalg.inv(ref[i])))
    return World(
        background=g.subset(classes == 0),
        objects=MappingProxyType(objects),
        poses=MappingProxyType({s: np.asarray(P, dtype=np.float64) for s, P in poses.items()}),
        cameras=MappingProxyType(dict(cameras)),
        classifier_weight=np.asarray(classifier_weight, dtype=np.float32),
        classifier_bias=np.asarray(classifier_bias, dtype=np.float32),
        metadata=MappingProxyType({"reference_state": reference_state, **metadata}),
        units=units,
        format_version=FORMAT_VERSION,
    )
