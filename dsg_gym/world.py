"""The world file: a trained DSG world (background + per-object Gaussians, object poses, cameras).

One safetensors file (no pickle; loads without executing code and without torch). Its header metadata has one
entry, ``dsg_world``: a JSON document with ``format = "dsg-world"``, ``format_version`` (1) and the
description below; the tensors are:

=====================================  ===================  ================================================
tensor                                 shape / dtype        meaning
=====================================  ===================  ================================================
``gaussians/background/<field>``       see GaussianSet      background Gaussians, world frame
``gaussians/object_<id>/<field>``      see GaussianSet      object ``id``'s Gaussians in the object's frame
``poses/<state>``                      [K,4,4] float64      world-from-object pose per object (rows follow
                                                            the sorted object ids) in each captured state
``cameras/<state>/viewmats``           [V,4,4] float32      capture cameras, OpenCV world-to-camera
``cameras/<state>/Ks``                 [V,3,3] float32      intrinsics (pixel centres at +0.5)
``classifier/weight``, ``/bias``       [K+1,F], [K+1] f32   identity classifier (class 0 = background)
=====================================  ===================  ================================================

``<field>`` is ``means quats scales opacities sh features labels`` and optionally ``opacity_logits
log_scales`` (the exact raw values). The JSON document lists the objects ``[{id, name, class}]``, the states,
camera sizes, units, ``metadata`` (training config, source, and the renderer options the world was trained
with: ``rasterize_mode`` "classic" or "antialiased" and ``eps2d``, see :func:`dsg_gym.splat.rasterize` and
:attr:`World.splat_options`; absent: "classic", 0.3) and a SHA-256 of the tensor bytes, so a truncated or
altered file is refused with :class:`WorldFormatError`, as is an unknown format version, a header field of the wrong
type or a tensor whose shape does not fit its bytes or its role (the message names the field or the tensor;
:mod:`dsg_gym.world_header` checks the header).

Reading: :func:`load_world` / :func:`parse_world_bytes`. Writing: :func:`encode_world` (the same world always
gives the same bytes) and :func:`write_world` (atomic); :func:`build_world` splits trained Gaussians by class
into background and objects.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np
from safetensors.numpy import save as st_save

from .cameras import Cameras
from .gaussians import GaussianSet
from .io.atomic import atomic_write_bytes, remove_partial
from .poses import quat_multiply, quat_normalize, rotmat_to_quat
from .sh_basis import rotate_sh
from .splat_options import DEFAULT_EPS2D, check_compositing, check_splat_options
from .world_header import check_doc, tensor_entry

__all__ = [
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "GAUSSIAN_FIELDS",
    "World",
    "WorldFormatError",
    "WorldObject",
    "build_world",
    "compositing",
    "encode_world",
    "load_world",
    "parse_world_bytes",
    "splat_options",
    "transform_gaussians",
    "write_world",
]

FORMAT_NAME = "dsg-world"
FORMAT_VERSION = 1
GAUSSIAN_FIELDS = ("means", "quats", "scales", "opacities", "sh", "features", "labels")
OPTIONAL_FIELDS = ("opacity_logits", "log_scales")
META_KEY = "dsg_world"  # the one safetensors metadata entry (one key: the header bytes are deterministic)


class WorldFormatError(ValueError):
    """A world file that cannot be read: truncated, corrupt, not a world file, or an unknown version."""


class WorldObject(NamedTuple):
    name: str
    gaussians: GaussianSet  # in the object's own frame


@dataclass(frozen=True, eq=False)
class World:
    """A loaded world. ``objects``: ``{id: WorldObject(name, GaussianSet in object frame)}``; ``poses``:
    ``{state: [K,4,4] float64}`` (rows follow ``object_ids``); ``cameras``: ``{state: Cameras}``
    (:class:`dsg_gym.cameras.Cameras`)."""

    background: GaussianSet
    objects: Mapping[int, WorldObject]
    poses: Mapping[str, np.ndarray]
    cameras: Mapping[str, Cameras]
    classifier_weight: np.ndarray
    classifier_bias: np.ndarray
    metadata: Mapping[str, Any] = field(default_factory=dict)
    units: str = "unknown"
    format_version: int = FORMAT_VERSION

    def __post_init__(self) -> None:
        k = len(self.objects)
        for s, P in self.poses.items():
            if P.shape != (k, 4, 4):
                raise ValueError(f"World.poses[{s!r}]: shape {P.shape}, expected ({k}, 4, 4)")
        if self.classifier_weight.ndim != 2 or self.classifier_bias.shape != (
            self.classifier_weight.shape[0],
        ):
            raise ValueError("World: classifier weight must be [K+1, F] and bias [K+1]")

    @property
    def rasterize_mode(self) -> str:
        """The splat mode the world was trained in and must be rendered in ("classic" or "antialiased")."""
        return str(self.metadata.get("rasterize_mode", "classic"))

    @property
    def splat_options(self) -> dict[str, Any]:
        """Keyword arguments every renderer of this world needs (``rasterize`` / ``SceneRenderer``): the
        ``rasterize_mode`` and 2D low-pass ``eps2d`` (px^2) it was trained with (defaults: 3DGS's)."""
        return splat_options(self.metadata)

    @property
    def compositing(self) -> str:
        """How background and objects are composited: "sorted" (one depth-sorted list, 3DGS; the default) or
        "layers" (each splatted alone and merged per pixel by expected depth: :mod:`dsg_gym.splat.layers`)."""
        return compositing(self.metadata)

    @property
    def object_ids(self) -> tuple[int, ...]:
        return tuple(sorted(self.objects))

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(self.objects[i].name for i in self.object_ids)

    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def states(self) -> tuple[str, ...]:
        return tuple(self.poses)

    def gaussians(self, state: str | None = None, poses: np.ndarray | None = None) -> GaussianSet:
        """All Gaussians in the world frame with objects placed at ``poses`` ``[K,4,4]`` (or those of
        ``state``; default: the reference state the world was trained in). ``labels`` hold object ids."""
        if poses is None:
            state = state or self.metadata.get("reference_state") or next(iter(self.poses), None)
            if state not in self.poses:
                raise KeyError(f"world has no state {state!r} (states: {list(self.poses)})")
            poses = self.poses[state]
        poses = np.asarray(poses, dtype=np.float64)
        if poses.shape != (self.num_objects, 4, 4):
            raise ValueError(f"poses must be [{self.num_objects},4,4], got {poses.shape}")
        parts = [self.background]
        for row, oid in enumerate(self.object_ids):
            g = self.objects[oid].gaussians
            parts.append(transform_gaussians(g, poses[row]))
        return GaussianSet.concat(parts).without_encodings() if len(parts) > 1 else parts[0]

    def classify(self, features: np.ndarray) -> np.ndarray:
        """Class logits ``[..., K+1]`` of identity features ``[..., F]``."""
        return features @ self.classifier_weight.T + self.classifier_bias


# ----------------------------------------------------------------------------------- moving Gaussians
def transform_gaussians(g: GaussianSet, T: np.ndarray, label: int | None = None) -> GaussianSet:
    """``g`` moved by the rigid transform ``T`` ``[4,4]``: centres and rotations (float64 arithmetic,
    renormalised quaternions; zero quaternions read as the identity) and the SH bands, rotated with the
    Gaussians so their view-dependent colour turns with them (:func:`dsg_gym.sh_basis.rotate_sh`).
    ``label``: set every Gaussian's label (None: keep). Encodings (raw logits/log-scales) are kept."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"transform must be a finite [4,4] matrix, got shape {T.shape}")
    R, t = T[:3, :3], T[:3, 3]
    means = g.means.astype(np.float64) @ R.T + t
    q = g.quats.astype(np.float64)
    q = np.where(np.linalg.norm(q, axis=1, keepdims=True) > 0, q, np.array([1.0, 0.0, 0.0, 0.0]))
    quats = quat_normalize(quat_multiply(rotmat_to_quat(R)[None], quat_normalize(q)))
    return dataclasses.replace(
        g,
        means=means.astype(g.means.dtype),
        quats=quats.astype(g.quats.dtype),
        sh=rotate_sh(g.sh, R),
        labels=g.labels if label is None else np.full(g.num, label, np.int32),
    )


# ----------------------------------------------------------------------------------- reading


def compositing(metadata: Mapping[str, Any]) -> str:
    """``metadata["compositing"]`` (absent: "sorted"); WorldFormatError when it is not one of
    :data:`dsg_gym.splat_options.COMPOSITING_MODES`."""
    try:
        return check_compositing(metadata.get("compositing", "sorted"))
    except ValueError as e:
        raise WorldFormatError(f"world metadata: {e}") from None


def splat_options(metadata: Mapping[str, Any]) -> dict[str, Any]:
    """``{"rasterize_mode", "eps2d"}`` from a world's metadata (absent: "classic", 0.3); WorldFormatError when
    they are not valid."""
    try:
        mode, eps2d = check_splat_options(
            metadata.get("rasterize_mode", "classic"), metadata.get("eps2d", DEFAULT_EPS2D)
        )
    except ValueError as e:
        raise WorldFormatError(f"world metadata: {e}") from None
    return {"rasterize_mode": mode, "eps2d": eps2d}


def _fail(src: str, msg: str) -> WorldFormatError:
    return WorldFormatError(f"{src}: {msg}")


def parse_world_bytes(data: bytes, src: str = "<bytes>") -> World:
    """Decode a world file's bytes (see the module docstring); :class:`WorldFormatError` naming the file and the
    header field or tensor on any problem."""
    if len(data) < 8:
        raise _fail(src, f"truncated world file ({len(data)} bytes)")
    (hlen,) = struct.unpack("<Q", data[:8])
    if hlen > len(data) - 8:
        raise _fail(src, f"truncated world file (header of {hlen} bytes, file has {len(data)})")
    try:
        header = json.loads(data[8 : 8 + hlen].decode("utf-8"))
        meta = header.pop("__metadata__")
    except (ValueError, KeyError, AttributeError, TypeError, RecursionError) as e:
        raise _fail(src, f"not a world file (unreadable header: {type(e).__name__}: {e})") from None
    try:
        doc = json.loads(meta[META_KEY])
    except (KeyError, TypeError, ValueError, RecursionError) as e:
        raise _fail(
            src, f"not a world file (no readable {META_KEY!r} metadata: {type(e).__name__}: {e})"
        ) from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT_NAME:
        raise _fail(
            src, f"not a world file (format {doc.get('format') if isinstance(doc, dict) else None!r})"
        )
    version = doc.get("format_version")
    if type(version) is not int or version != FORMAT_VERSION:
        raise _fail(
            src, f"unknown world format version {version!r} (this dsg_gym reads version {FORMAT_VERSION})"
        )
    body = memoryview(data)[8 + hlen :]
    try:
        table = {name: tensor_entry(name, info) for name, info in header.items()}
    except ValueError as e:
        raise _fail(src, str(e)) from None
    end = max((b for _, _, _, b in table.values()), default=0)
    if len(body) != end:
        raise _fail(
            src, f"truncated or padded world file: tensor data is {len(body)} bytes, header needs {end}"
        )
    if hashlib.sha256(body).hexdigest() != doc.get("sha256"):
        raise _fail(src, "checksum mismatch: the world file is corrupt")
    arrays: dict[str, np.ndarray] = {}
    for name, (dtype, shape, a, b) in table.items():
        arr = np.frombuffer(body[a:b], dtype=np.dtype(dtype).newbyteorder("<"))
        arrays[name] = arr.reshape(shape).astype(dtype, copy=True)
    try:
        return _build(arrays, check_doc(doc), version)
    except ValueError as e:
        raise _fail(src, str(e)) from None


def _gaussian_set(arrays: dict[str, np.ndarray], prefix: str) -> GaussianSet:
    missing = [f for f in GAUSSIAN_FIELDS if f"{prefix}/{f}" not in arrays]
    if missing:
        raise ValueError(f"missing tensor {prefix}/{missing[0]!s}")
    kw = {f: arrays[f"{prefix}/{f}"] for f in GAUSSIAN_FIELDS}
    for f in OPTIONAL_FIELDS:
        if f"{prefix}/{f}" in arrays:
            kw[f] = arrays[f"{prefix}/{f}"]
    try:
        return GaussianSet(**kw)
    except ValueError as e:
        raise ValueError(f"tensors {prefix}/*: {e}") from None


def _tensor(arrays: dict[str, np.ndarray], name: str) -> np.ndarray:
    if name not in arrays:
        raise ValueError(f"missing tensor {name}")
    return arrays[name]


def _build(arrays: dict[str, np.ndarray], doc: dict, version: int) -> World:
    objects = {}
    for o in doc["objects"]:
        objects[o["id"]] = WorldObject(o["name"], _gaussian_set(arrays, f"gaussians/object_{o['id']}"))
    poses = {s: _tensor(arrays, f"poses/{s}") for s in doc["states"]}
    cameras = {}
    for s, c in doc["cameras"].items():
        vm, ks = _tensor(arrays, f"cameras/{s}/viewmats"), _tensor(arrays, f"cameras/{s}/Ks")
        try:
            cameras[s] = Cameras(vm, ks, c["width"], c["height"])
        except ValueError as e:
            raise ValueError(f"tensors cameras/{s}/*: {e}") from None
    meta = doc.get("metadata", {})
    splat_options(meta)  # validates
    compositing(meta)
    weight, bias = _tensor(arrays, "classifier/weight"), _tensor(arrays, "classifier/bias")
    k = len(objects)
    for s, P in poses.items():
        if P.shape != (k, 4, 4):
            raise ValueError(f"tensor poses/{s}: shape {P.shape}, expected ({k}, 4, 4) for {k} objects")
    if weight.ndim != 2 or bias.shape != (weight.shape[0],):
        raise ValueError(
            f"tensors classifier/*: weight {weight.shape} must be [C, F] and bias {bias.shape} [C]"
        )
    return World(
        background=_gaussian_set(arrays, "gaussians/background"),
        objects=MappingProxyType(objects),
        poses=MappingProxyType(poses),
        cameras=MappingProxyType(cameras),
        classifier_weight=weight,
        classifier_bias=bias,
        metadata=MappingProxyType(meta),
        units=doc.get("units", "unknown"),
        format_version=version,
    )


def load_world(path: str | Path) -> World:
    """Read a world file (written by :func:`write_world`, e.g. by ``dsg-train``)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except OSError as e:
        raise WorldFormatError(f"{p}: cannot read world file ({e})") from e
    return parse_world_bytes(data, str(p))


# ----------------------------------------------------------------------------------- writing
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
    """Encode ``world`` and write it atomically (:mod:`dsg_gym.io.atomic`) to ``path`` (the temporaries of killed
    writes to ``path`` are deleted first); returns the path."""
    data = encode_world(world)
    remove_partial(Path(path).parent, Path(path).name, stale_only=True)
    return atomic_write_bytes(path, data)


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
