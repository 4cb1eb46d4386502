"""Import a standard 3DGS PLY (Inria layout, e.g. an externally trained splat scene) into a world file.

    dsg-import-ply scene.ply --out scene.dsgworld                                  # background, new world
    dsg-import-ply scene.ply --out mine.dsgworld --base assets/worlds/default_geom.dsgworld  # new background
    dsg-import-ply mug.ply --out mine.dsgworld --as object --object-name mug --base WORLD     # add an object

* ``--as background`` (default) with ``--base``: the base world's background is replaced by the PLY's
  Gaussians; its objects, states, cameras and table are kept (the table bounds are frozen into the metadata so
  they do not change with the new background). Without a base: a world with **no objects** and an orbit of
  cameras looking at the PLY's bounding box. Such a world renders (``dsg_gym.world.load_world`` +
  ``SceneRenderer``) but ``DSGWorld-v0`` needs at least one object: import one with ``--as object`` into it
  (``--base``), or use a base world that has objects.
* ``--as object``: the PLY becomes a new object (id = the largest id + 1) whose frame is the PLY's frame; its
  pose is the identity in every state of the base world. Without a base: a world with this one object, an
  empty background, a table under the object's footprint and the orbit cameras.

Identity features (``obj_dc_*``) whose width differs from the base world's are replaced by zeros of the base's
width; the classifier gets a zero row for a new object. The world file is written with
:func:`dsg_gym.world.write_world` (atomic).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from types import MappingProxyType

import numpy as np
import torch

from dsg_gym.cameras import Cameras, orbit_eyes
from dsg_gym.gaussians import GaussianSet
from dsg_gym.geometry import intrinsics_from_fov, look_at_viewmat
from dsg_gym.io import read_ply
from dsg_gym.world import World, WorldObject, load_world
from dsg_gym.world_model import WorldModel

__all__ = ["world_from_ply", "orbit_cameras", "world_from_model", "ROLES"]

ROLES = ("background", "object")


def orbit_cameras(
    means: np.ndarray,
    *,
    num_views: int = 16,
    width: int = 256,
    height: int = 256,
    fovy_deg: float = 60.0,
    up=None,
) -> Cameras:
    """``num_views`` cameras on two rings (20 and 45 degrees elevation) around the robust bounding box of
    ``means`` (1st..99th percentile), all looking at its centre from a distance at which the box's bounding
    sphere fills the vertical field of view. ``up``: the world's up axis, default the direction of least
    spread of the points (the ground normal of a typical captured scene)."""
    pts = np.asarray(means, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError("orbit_cameras: need at least one point")
    lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-3)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    core = pts[inside] if inside.sum() >= 3 else pts
    if up is None:
        if len(core) >= 3:
            _, vecs = np.linalg.eigh(np.cov((core - core.mean(0)).T))
            up = vecs[:, 0]
            if up[int(np.argmax(np.abs(up)))] < 0:
                up = -up
        else:
            up = np.array([0.0, 0.0, 1.0])
    up = np.asarray(up, dtype=np.float64)
    dist = 1.05 * radius / math.sin(math.radians(0.5 * fovy_deg))
    eyes = orbit_eyes(centre, up, dist, (math.radians(20.0), math.radians(45.0)), num_views)
    vm = look_at_viewmat(
        torch.tensor(eyes, dtype=torch.float64),
        torch.tensor(centre, dtype=torch.float64)[None],
        torch.tensor(up / np.linalg.norm(up), dtype=torch.float64)[None],
    ).numpy()
    K = intrinsics_from_fov(math.radians(fovy_deg), width, height, dtype=torch.float64).numpy()  # noqa: N806
    return Cameras(vm.astype(np.float32), np.repeat(K[None], num_views, 0).astype(np.float32), width, height)


def world_from_model(wm: WorldModel, units: str = "metres") -> World:
    """The file-level :class:`~dsg_gym.world.World` of a runtime :class:`WorldModel` (cameras under its
    reference state, table bounds kept in ``metadata["table"]``, an all-zero identity classifier)."""
    k, f = wm.num_objects, wm.background.num_features
    ref = wm.metadata.get("reference_state") or ("state1" if "state1" in wm.states else "state1")
    c = wm.cameras
    return World(
        background=wm.background,
        objects=MappingProxyType(
            {oid: WorldObject(n, g) for oid, n, g in zip(wm.object_ids, wm.object_names, wm.objects)}
        ),
        poses=MappingProxyType({s: np.asarray(p, np.float64) for s, p in wm.states.items()}),
        cameras=MappingProxyType(
            {ref: Cameras(c.viewmats.astype(np.float32), c.Ks.astype(np.float32), c.width, c.height)}
        ),
        classifier_weight=np.zeros((k + 1, f), np.float32),
        classifier_bias=np.zeros(k + 1, np.float32),
        metadata=MappingProxyType(
            {**wm.metadata, "reference_state": ref, "name": wm.name, "table": _table_meta(wm)}
        ),
        units=units,
    )


def _table_meta(wm: WorldModel) -> dict:
    t = wm.table
    return {"bounds": [[t.xmin, t.ymin, t.z], [t.xmax, t.ymax, t.z]], "top_z": t.z}


def _as_base(base) -> World | None:
    if base is None or isinstance(base, World):
        return base
    if isinstance(base, WorldModel):
        return world_from_model(base)
    if isinstance(base, (str, Path)):
        return load_world(base)  # WorldFormatError (a ValueError) names the file
    raise ValueError(
        f"base must be None, a world file path, a World or a WorldModel, got {type(base).__name__}"
    )


def _with_features(g: GaussianSet, width: int, what: str) -> GaussianSet:
    if g.num_features == width:
        return g
    if g.num_features:
        warnings.warn(
            f"{what}: its {g.num_features} identity features do not match the base world's "
            f"{width}; replaced by zeros",
            stacklevel=3,
        )
    return dataclasses.replace(g, features=np.zeros((g.num, width), np.float32))


def world_from_ply(
    ply_path,
    base=None,
    role: str = "background",
    *,
    object_name: str | None = None,
    num_views: int = 16,
    width: int = 256,
    height: int = 256,
    up=None,
    for_env: bool = False,
) -> World:
    """A world (:class:`dsg_gym.world.World`, the world-file object; ``WorldModel.from_world`` makes the
    runtime model of it, which needs at least one object) with the PLY's Gaussians as its background or as a
    new object (see the module docstring). ``base``: ``None``, a world file path, a ``World`` or a ``WorldModel``.
    PLY problems raise :class:`dsg_gym.io.PlyFormatError` (a ``ValueError``) naming the file. ``for_env``:
    refuse (``ValueError``) to make a world without objects, which ``DSGWorld-v0`` cannot use."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {ROLES}, got {role!r}")
    ply_path = Path(ply_path)
    if not ply_path.is_file():
        raise ValueError(f"{ply_path}: PLY file does not exist")
    g = read_ply(ply_path)
    if g.num == 0:
        raise ValueError(f"{ply_path}: the PLY has no Gaussians")
    b = _as_base(base)
    if for_env and role == "background" and (b is None or b.num_objects == 0):
        raise ValueError(
            "a world for DSGWorld-v0 needs at least one object: import the PLY with "
            "role='object' (--as object), or replace the background of a base world that has "
            "objects (--base WORLD)"
        )
    source = {"ply": ply_path.name, "role": role, "gaussians": g.num}

    if b is None:
        cams = orbit_cameras(g.means, num_views=num_views, width=width, height=height, up=up)
        f = g.num_features
        if role == "background":
            return World(
                background=dataclasses.replace(g, labels=np.zeros(g.num, np.int32)),
                objects=MappingProxyType({}),
                poses=MappingProxyType({}),
                cameras=MappingProxyType({"orbit": cams}),
                classifier_weight=np.zeros((1, f), np.float32),
                classifier_bias=np.zeros(1, np.float32),
                metadata=MappingProxyType(
                    {"name": ply_path.stem, "source": "ply-import", "imports": [source]}
                ),
                units="unknown",
            )
        name = object_name or ply_path.stem
        m = g.means.astype(np.float64)
        lo, hi = m.min(0), m.max(0)
        pad = max(float(np.max(hi[:2] - lo[:2])), 0.05)
        table = {
            "bounds": [[lo[0] - pad, lo[1] - pad, lo[2]], [hi[0] + pad, hi[1] + pad, lo[2]]],
            "top_z": float(lo[2]),
        }
        obj = dataclasses.replace(g, labels=np.ones(g.num, np.int32))
        return World(
            background=GaussianSet.empty(g.sh_degree, f),
            objects=MappingProxyType({1: WorldObject(name, obj)}),
            poses=MappingProxyType({"state1": np.eye(4)[None]}),
            cameras=MappingProxyType({"state1": cams}),
            classifier_weight=np.zeros((2, f), np.float32),
            classifier_bias=np.zeros(2, np.float32),
            metadata=MappingProxyType(
                {
                    "name": name,
                    "source": "ply-import",
                    "reference_state": "state1",
                    "table": table,
                    "imports": [source],
                }
            ),
            units="unknown",
        )

    meta = dict(b.metadata)
    if "table" not in meta and b.num_objects:  # freeze the base's table (deriving it would see the import)
        meta["table"] = _table_meta(WorldModel.from_world(b))
    meta["imports"] = list(meta.get("imports", [])) + [source]
    f = b.classifier_weight.shape[1]
    if role == "background":
        bg = _with_features(dataclasses.replace(g, labels=np.zeros(g.num, np.int32)), f, str(ply_path))
        return dataclasses.replace(b, background=bg, metadata=MappingProxyType(meta))
    oid = max(b.object_ids, default=0) + 1
    name = object_name or ply_path.stem
    if name in b.object_names:
        raise ValueError(
            f"the base world already has an object named {name!r} "
            f"(objects: {list(b.object_names)}); choose another object name"
        )
    obj = _with_features(dataclasses.replace(g, labels=np.full(g.num, oid, np.int32)), f, str(ply_path))
    objects = {**dict(b.objects), oid: WorldObject(name, obj)}
    poses = {s: np.concatenate([np.asarray(p, np.float64), np.eye(4)[None]]) for s, p in b.poses.items()}
    return World(
        background=b.background,
        objects=MappingProxyType(objects),
        poses=MappingProxyType(poses),
        cameras=b.cameras,
        classifier_weight=np.concatenate([b.classifier_weight, np.zeros((1, f), np.float32)]),
        classifier_bias=np.concatenate([b.classifier_bias, np.zeros(1, np.float32)]),
        metadata=MappingProxyType(meta),
        units=b.units,
    )
