"""The runtime world model: a static background plus rigid objects made of 3D Gaussians.

A :class:`WorldModel` holds the background :class:`~dsg_gym.gaussians.GaussianSet` (world frame), one set per
movable object in that object's own frame, the table (resting surface) bounds, the capture cameras and the
captured object poses of each state. :meth:`WorldModel.compose` places the objects at any poses (the paper's
``W_GS``): every object Gaussian's mean is moved by the object's pose and its rotation pre-multiplied by the
pose's rotation, in float64 with renormalised quaternions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .cameras import Cameras
from .gaussians import GaussianSet
from .poses import as_poses7, pose7_to_matrix
from .world import compositing, load_world, splat_options
from .world import transform_gaussians as _transform_matrix

__all__ = ["TableBounds", "WORKSPACE_HEIGHT", "Workspace", "WorldModel", "WorldModelError"]

#: height of the workspace above the table top, metres (:class:`Workspace`)
WORKSPACE_HEIGHT = 0.5


class WorldModelError(ValueError):
    """A world that cannot be used; the message names the file or the field."""


@dataclass(frozen=True)
class TableBounds:
    """The resting surface: ``xmin <= x <= xmax``, ``ymin <= y <= ymax`` at height ``z`` (its top)."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    z: float = 0.0

    def __post_init__(self) -> None:
        vals = (self.xmin, self.xmax, self.ymin, self.ymax, self.z)
        if not all(np.isfinite(v) for v in vals) or self.xmin >= self.xmax or self.ymin >= self.ymax:
            raise WorldModelError(f"TableBounds: invalid bounds {vals}")

    @property
    def center(self) -> np.ndarray:
        return np.array([0.5 * (self.xmin + self.xmax), 0.5 * (self.ymin + self.ymax), self.z])

    @property
    def size(self) -> tuple[float, float]:
        return (self.xmax - self.xmin, self.ymax - self.ymin)


@dataclass(frozen=True)
class Workspace:
    """The box the objects stay in: x and y within the table's bounds, z from the table top up to
    :data:`WORKSPACE_HEIGHT` above it (``lo``, ``hi``: its corners).

    An object is inside when its origin (the position of its pose) lies in the box and its collision hull stays
    within the box's x/y range and below its top, each by at most ``tol``. A hull that reaches below the table
    top touches or penetrates the table: that is a collision, not a workspace violation."""

    lo: tuple[float, float, float]
    hi: tuple[float, float, float]

    @classmethod
    def above(cls, table: TableBounds, height: float = WORKSPACE_HEIGHT) -> Workspace:
        """The workspace of ``table``: its x/y bounds, from its top up to ``height`` metres above it."""
        return cls((table.xmin, table.ymin, table.z), (table.xmax, table.ymax, table.z + float(height)))

    def outside(
        self, origins: np.ndarray, hull_lo: np.ndarray, hull_hi: np.ndarray, tol: float
    ) -> np.ndarray:
        """``[K]`` bool: objects outside the box, from their origins and hulls' lower / upper corners ``[K,3]``."""
        lo, hi = np.array(self.lo), np.array(self.hi)
        return (
            np.any(origins < lo, axis=1)
            | np.any(origins > hi, axis=1)
            | np.any(hull_lo[:, :2] < lo[:2] - tol, axis=1)
            | np.any(hull_hi[:, :2] > hi[:2] + tol, axis=1)
            | (hull_hi[:, 2] > hi[2] + tol)
        )

    def problem(self, origin: np.ndarray, hull_lo: np.ndarray, hull_hi: np.ndarray, tol: float) -> str | None:
        """What takes one object out of the box (``None`` when it is inside), as :meth:`outside` decides."""
        for i, axis in enumerate("xyz"):
            what = (
                "the table's bounds"
                if i < 2
                else f"the table top to {self.hi[2] - self.lo[2]:.4g} m above it"
            )
            bound = f"the workspace's {axis} range [{self.lo[i]:.4g}, {self.hi[i]:.4g}] ({what})"
            if not self.lo[i] <= origin[i] <= self.hi[i]:
                return f"its position {axis} = {origin[i]:.6g} is outside {bound}"
            if (i < 2 and hull_lo[i] < self.lo[i] - tol) or hull_hi[i] > self.hi[i] + tol:
                reach = hull_lo[i] if hull_lo[i] < self.lo[i] - tol and i < 2 else hull_hi[i]
                return f"its collision hull reaches {axis} = {reach:.4g}, outside {bound}"
        return None


@dataclass(frozen=True, eq=False)
class WorldModel:
    """Background + objects of a Gaussian world (see the module docstring).

    ``objects[k]`` (object id ``object_ids[k]``, name ``object_names[k]``) is in its own frame; ``states`` maps a
    state name to ``[K,4,4]`` float64 world-from-object poses (e.g. the two captured states ``state1`` and
    ``state2``); ``metadata`` is free-form JSON-like data (its ``source`` says where the world came from).
    """

    background: GaussianSet
    objects: tuple[GaussianSet, ...]
    object_names: tuple[str, ...]
    table: TableBounds
    cameras: Cameras
    states: Mapping[str, np.ndarray] = field(default_factory=dict)
    object_ids: tuple[int, ...] = ()
    metadata: Mapping[str, Any] = field(default_factory=dict)
    name: str = "world"

    def __post_init__(self) -> None:
        objs = tuple(self.objects)
        k = len(objs)
        if k < 1:
            raise WorldModelError("WorldModel: needs at least one object")
        if any(not isinstance(o, GaussianSet) or o.num == 0 for o in objs):
            raise WorldModelError("WorldModel: every object must be a non-empty GaussianSet")
        if not isinstance(self.background, GaussianSet):
            raise WorldModelError("WorldModel: background must be a GaussianSet")
        widths = {o.num_features for o in objs} | {self.background.num_features}
        if len(widths) != 1:
            raise WorldModelError(f"WorldModel: feature widths differ between sets: {sorted(widths)}")
        if len(self.object_names) != k:
            raise WorldModelError(f"WorldModel: {len(self.object_names)} names for {k} objects")
        ids = tuple(int(i) for i in self.object_ids) or tuple(range(1, k + 1))
        if len(ids) != k or len(set(ids)) != k:
            raise WorldModelError(f"WorldModel: object ids {ids} are not {k} distinct values")
        states = {}
        for name, poses in dict(self.states).items():
            p = np.asarray(poses, dtype=np.float64)
            try:
                p7 = as_poses7(p, k, f"WorldModel.states[{name!r}]")
            except ValueError as e:
                raise WorldModelError(str(e)) from None
            states[str(name)] = pose7_to_matrix(p7)
        put = lambda n, v: object.__setattr__(self, n, v)  # noqa: E731  (frozen)
        put("objects", objs)
        put("object_names", tuple(str(n) for n in self.object_names))
        put("object_ids", ids)
        put("states", states)
        put("metadata", dict(self.metadata))

    # ------------------------------------------------------------------ properties
    @property
    def num_objects(self) -> int:
        return len(self.objects)

    @property
    def rasterize_mode(self) -> str:
        """The splat mode the world was trained in ("classic" or "antialiased", ``metadata["rasterize_mode"]``);
        every renderer of the world must use it."""
        return str(self.metadata.get("rasterize_mode", "classic"))

    @property
    def splat_options(self) -> dict[str, Any]:
        """Renderer keyword arguments the world was trained with (:attr:`dsg_gym.world.World.splat_options`)."""
        return splat_options(self.metadata)

    @property
    def compositing(self) -> str:
        """How the world composites background and objects ("sorted" or "layers",
        :attr:`dsg_gym.world.World.compositing`); every renderer of the world must use it."""
        return compositing(self.metadata)

    @property
    def workspace(self) -> Workspace:
        """The box the objects stay in (:class:`Workspace`: the table's x/y bounds, from its top up to
        :data:`WORKSPACE_HEIGHT` above it)."""
        return Workspace.above(self.table)

    @property
    def num_gaussians(self) -> int:
        return self.background.num + sum(o.num for o in self.objects)

    def without_features(self) -> WorldModel:
        """The same world without per-Gaussian identity features (``features`` become ``[N, 0]``; everything
        else is shared, not copied). The runtime never reads them: masks come from object labels, and the
        renderer composites only RGB, one-hot labels and depth. ``DSGWorld-v0`` loads world files this way."""
        if self.background.num_features == 0 and all(o.num_features == 0 for o in self.objects):
            return self

        def strip(g: GaussianSet) -> GaussianSet:
            return dataclasses.replace(g, features=np.zeros((g.num, 0), np.float32))

        return dataclasses.replace(
            self, background=strip(self.background), objects=tuple(strip(o) for o in self.objects)
        )

    def state_poses(self, name: str) -> np.ndarray:
        """``[K,4,4]`` float64 copy of a captured state's poses; ValueError for an unknown state."""
        if name not in self.states:
            raise WorldModelError(f"unknown state {name!r}; this world has {sorted(self.states)}")
        return self.states[name].copy()

    # ------------------------------------------------------------------ composing
    def compose(self, poses) -> GaussianSet:
        """The whole scene with object ``k`` at ``poses[k]`` (``[K,7]`` or ``[K,4,4]``), as one set:
        background first, then the objects in order; ``labels`` are 0 for the background and ``k + 1`` for
        object ``k``."""
        p7 = as_poses7(poses, self.num_objects, "poses")
        sets = [dataclasses.replace(self.background, labels=np.zeros(self.background.num, np.int32))]
        for k, (obj, p) in enumerate(zip(self.objects, p7, strict=True)):
            sets.append(transform_gaussians(obj, p, label=k + 1))
        return GaussianSet.concat([s.without_encodings() for s in sets])

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_world(cls, world: Any) -> WorldModel:
        """Adapter from the world-file reader's ``World`` (:func:`dsg_gym.world.load_world`).

        Reads ``background``, ``objects`` ({id: (name, GaussianSet in the object frame)}), the per-state poses,
        the capture cameras and ``metadata``; table bounds come from the metadata (``table.bounds`` as in a
        capture's ``scene.json``) or, if absent, are derived from the geometry (:func:`derive_table_bounds`).
        """
        try:
            items = sorted(dict(world.objects).items())
            ids = tuple(int(i) for i, _ in items)
            names = tuple(str(v[0]) for _, v in items)
            sets = tuple(v[1] for _, v in items)
            if not isinstance(world.background, GaussianSet) or not all(
                isinstance(g, GaussianSet) for g in sets
            ):
                raise WorldModelError("world background/objects are not GaussianSets")
            meta = dict(getattr(world, "metadata", {}) or {})
            states = _world_states(world)
            cams = _world_cameras(world, meta)
        except (AttributeError, TypeError, KeyError) as e:
            raise WorldModelError(f"world object lacks a field the runtime needs: {e}") from None
        table = _table_from_metadata(meta)
        if table is None:
            table = derive_table_bounds(world.background, sets, states)
        return cls(
            background=world.background,
            objects=sets,
            object_names=names,
            table=table,
            cameras=cams,
            states=states,
            object_ids=ids,
            metadata=meta,
            name=str(meta.get("name", getattr(world, "name", "world"))),
        )

    @classmethod
    def load(cls, path: str | Path) -> WorldModel:
        """Load a world file; any failure is a :class:`WorldModelError` (a ``ValueError``) naming the path."""
        p = Path(path)
        if not p.exists():
            raise WorldModelError(f"{p}: world file does not exist")
        try:
            world = load_world(p)
        except Exception as e:  # the reader's own errors, whatever their type, become one clear message
            raise WorldModelError(f"{p}: cannot load world file: {e}") from None
        try:
            return cls.from_world(world)
        except WorldModelError as e:
            raise WorldModelError(f"{p}: {e}") from None


def transform_gaussians(gs: GaussianSet, pose7: np.ndarray, label: int | None = None) -> GaussianSet:
    """``gs`` moved by the rigid pose ``pose7`` (:func:`dsg_gym.world.transform_gaussians`: float64 math,
    renormalised quaternions, SH rotated with the Gaussians), float32 centres, encodings dropped."""
    m = pose7_to_matrix(np.asarray(pose7, dtype=np.float64))
    out = _transform_matrix(gs, m, label=label)
    return dataclasses.replace(
        out, means=out.means.astype(np.float32), quats=out.quats.astype(np.float32)
    ).without_encodings()


def derive_table_bounds(
    background: GaussianSet, objects: Sequence[GaussianSet], states: Mapping[str, np.ndarray]
) -> TableBounds:
    """Table bounds when a world file has none: the top is where the objects rest (the mean over the captured
    states of each object's lowest Gaussian), the x/y range the 2nd..98th percentile of background Gaussians
    within 1.5 cm of that height and within 1.5 m of the objects."""
    if not states:
        raise WorldModelError("cannot derive table bounds: the world has no captured object poses")
    lows, centres = [], []
    for poses in states.values():
        for obj, pose in zip(objects, poses, strict=True):
            pts = obj.means.astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
            lows.append(pts[:, 2].min())
            centres.append(pose[:3, 3])
    z = float(np.mean(lows))
    c = np.mean(centres, axis=0)
    bg = background.means.astype(np.float64)
    near = (np.abs(bg[:, 2] - z) < 0.015) & (np.linalg.norm(bg[:, :2] - c[:2], axis=1) < 1.5)
    if near.sum() < 10:
        raise WorldModelError("cannot derive table bounds: no background surface at the objects' height")
    lo = np.percentile(bg[near, :2], 2, axis=0)
    hi = np.percentile(bg[near, :2], 98, axis=0)
    return TableBounds(float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]), z)


def _table_from_metadata(meta: Mapping[str, Any]) -> TableBounds | None:
    t = meta.get("table")
    if not isinstance(t, Mapping) or "bounds" not in t:
        return None
    try:
        b = np.asarray(t["bounds"], dtype=np.float64)
    except (TypeError, ValueError, OverflowError, RecursionError):
        b = None
    if b is None or b.shape != (2, 3):
        raise WorldModelError(
            f"metadata table.bounds: expected [[x0, y0, z], [x1, y1, z]] numbers, got {_short(t['bounds'])}"
        )
    top = t.get("top_z", b[0, 2])
    if isinstance(top, bool) or not isinstance(top, (int, float, np.floating)):
        raise WorldModelError(f"metadata table.top_z: expected a number, got {_short(top)}")
    try:
        z = float(top)
    except OverflowError:
        raise WorldModelError(f"metadata table.top_z: expected a finite number, got {_short(top)}") from None
    return TableBounds(float(b[0, 0]), float(b[1, 0]), float(b[0, 1]), float(b[1, 1]), z)


def _short(v: Any) -> str:
    text = repr(v) if isinstance(v, (int, float, str, type(None))) else type(v).__name__
    return text if len(text) <= 40 else text[:37] + "..."


def _world_states(world: Any) -> dict[str, np.ndarray]:
    for attr in ("state_poses", "poses", "states"):
        v = getattr(world, attr, None)
        if isinstance(v, Mapping):
            return {str(n): np.asarray(p, dtype=np.float64) for n, p in v.items()}
    return {}


def _world_cameras(world: Any, meta: Mapping[str, Any]) -> Cameras:
    """The capture cameras: the reader's ``{state: Cameras}`` concatenated (reference state first; states
    with another image size are skipped), or a single camera set."""
    cams = getattr(world, "cameras", None)
    try:
        if not isinstance(cams, Mapping):
            src = cams if cams is not None else world
            return Cameras(np.asarray(src.viewmats), np.asarray(src.Ks), src.width, src.height)
        if not cams:
            raise WorldModelError("world has no capture cameras")
        ref = meta.get("reference_state")
        order = sorted(cams, key=lambda s: (s != ref, str(s)))
        first = cams[order[0]]
        same = [cams[s] for s in order if (cams[s].width, cams[s].height) == (first.width, first.height)]
        return Cameras(
            np.concatenate([np.asarray(c.viewmats, dtype=np.float64) for c in same]),
            np.concatenate([np.asarray(c.Ks, dtype=np.float64) for c in same]),
            first.width,
            first.height,
        )
    except WorldModelError:
        raise
    except ValueError as e:  # the cameras' own validation
        raise WorldModelError(str(e)) from None
