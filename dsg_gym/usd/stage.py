"""Write a Gaussian world (background + rigid objects + cameras, optionally an episode) as a USD
stage, and read it back.

Stage layout (``defaultPrim = /World``)::

    /World                              Xform
        Background                      ParticleField3DGaussianSplat (world frame)
        Objects/<name>                  Xform: translate (double3) + orient (quatd) ops = the
                                        object-to-world pose; RigidBodyAPI, MassAPI
            Splats                      ParticleField3DGaussianSplat (object frame)
            Collider                    Mesh, purpose guide: convex hull of the splat means,
                                        CollisionAPI + MeshCollisionAPI (convexHull)
        Table                           Mesh, static box collider (only with ``table_bounds``)
        Cameras/<name>                  Camera (see ``dsg_gym.usd.cameras``)
        PhysicsScene                    PhysicsScene, gravity along -upAxis, 9.81 m/s^2

Units: geometry is written as given, in the world's units; ``meters_per_unit`` and
``kilograms_per_unit`` only describe them (stage metadata). ``UsdObject.mass`` is in the stage's
mass unit; gravity is converted (``9.81 / meters_per_unit``).

With an ``Episode`` the object ops also get one time sample per step (time code ``t`` =
step ``t``), ``timeCodesPerSecond = framesPerSecond = fps``, start/end time codes ``0`` and
``T - 1``, ``physics:kinematicEnabled = true`` on every body, rewards as time samples of the
``/World.dsg:episode:reward`` attribute (at ``t + 1``) and actions as time samples of
``/World.dsg:episode:action`` (flattened ``double[]``, shape in its customData). The default
(untimed) value of each pose is ``UsdObject.pose``.

Prim names are the object / camera names when they are valid USD identifiers, otherwise the
name with invalid characters replaced by ``_``; the original is kept in the prim's customData
(``dsg:name``).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdPhysics, Vt

from dsg_gym.gaussians import GaussianSet
from dsg_gym.io.atomic import atomic_path, remove_partial
from dsg_gym.poses import check_rigid, quat_hemisphere_continuous, rotmat_to_quat
from dsg_gym.usd.cameras import UsdCamera, check_camera, read_camera, write_camera
from dsg_gym.usd.collider import MIN_THICKNESS_M, box_mesh, convex_hull_mesh, write_collider
from dsg_gym.usd.episode import Episode
from dsg_gym.usd.splats import read_splats, write_splats

__all__ = [
    "UsdObject",
    "StageObject",
    "StageContents",
    "export_stage",
    "read_stage",
    "SUFFIXES",
    "GRAVITY_M_S2",
    "TABLE_THICKNESS_M",
    "FORMAT_VERSION",
]

SUFFIXES = (".usdc", ".usda")
GRAVITY_M_S2 = 9.81
TABLE_THICKNESS_M = 0.02
FORMAT_VERSION = 1
WORLD = Sdf.Path("/World")


@dataclass(frozen=True, eq=False)
class UsdObject:
    """A rigid object: its Gaussians in its own frame, ``pose [4, 4]`` object-to-world, ``mass``."""

    name: str
    gaussians: GaussianSet
    pose: np.ndarray
    mass: float = 0.1


@dataclass(frozen=True, eq=False)
class StageObject:
    """An object read back from a stage; ``pose`` is the default-time (untimed) pose."""

    name: str
    gaussians: GaussianSet
    pose: np.ndarray
    mass: float
    kinematic: bool
    collider_vertices: np.ndarray
    collider_triangles: np.ndarray
    prim_path: str


@dataclass(frozen=True, eq=False)
class StageContents:
    """What ``read_stage`` returns. ``metadata`` holds ``metersPerUnit``, ``upAxis``,
    ``kilogramsPerUnit``, ``defaultPrim``, ``timeCodesPerSecond``, ``startTimeCode``,
    ``endTimeCode`` and the layer's ``customLayerData`` (ours under ``"dsg"``: ``exporter``,
    ``formatVersion``, ``episodeLength``)."""

    background: GaussianSet
    objects: list[StageObject]
    cameras: list[UsdCamera]
    metadata: dict
    episode: Episode | None = None
    table_vertices: np.ndarray | None = field(default=None, repr=False)


# ---------------------------------------------------------------------------------------- checks


def _check_path(path) -> Path:
    path = Path(path)
    if path.suffix not in SUFFIXES:
        raise ValueError(f"export_stage: path {str(path)!r} must end in .usdc (binary) or .usda (text)")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"export_stage: folder {str(path.parent)!r} does not exist")
    return path


def _positive(name: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"export_stage: {name} must be a number, got {value!r}") from None
    if not np.isfinite(x) or x <= 0:
        raise ValueError(f"export_stage: {name} must be finite and > 0, got {value!r}")
    return x


def _prim_names(kind: str, names: Sequence[str]) -> list[str]:
    out: list[str] = []
    for name in names:
        if not isinstance(name, str) or not name:
            raise ValueError(f"export_stage: {kind} name must be a non-empty string, got {name!r}")
        safe = name if Sdf.Path.IsValidIdentifier(name) else re.sub(r"\W", "_", name, flags=re.ASCII)
        if not Sdf.Path.IsValidIdentifier(safe):
            safe = "_" + safe
        if safe in out:
            raise ValueError(
                f"export_stage: {kind} names {name!r} and another give the same prim name {safe!r}"
            )
        out.append(safe)
    return out


def _check_objects(objects: Sequence[UsdObject]) -> list[np.ndarray]:
    poses = []
    for i, obj in enumerate(objects):
        if not isinstance(obj, UsdObject):
            raise ValueError(f"export_stage: objects[{i}] is a {type(obj).__name__}, expected UsdObject")
        if not isinstance(obj.gaussians, GaussianSet):
            raise ValueError(f"export_stage: object {obj.name!r}: gaussians must be a GaussianSet")
        pose = np.asarray(obj.pose)
        if pose.shape != (4, 4):
            raise ValueError(f"export_stage: object {obj.name!r}: pose must be [4, 4], got {pose.shape}")
        poses.append(check_rigid(f"export_stage: object {obj.name!r} pose", pose))
        _positive(f"object {obj.name!r} mass", obj.mass)
    return poses


# ---------------------------------------------------------------------------------------- writing


def _set_pose(translate_op, orient_op, pose: np.ndarray, quat: np.ndarray, time=Usd.TimeCode.Default()):  # noqa: B008  (an immutable value)
    translate_op.Set(Gf.Vec3d(*(float(x) for x in pose[:3, 3])), time)
    orient_op.Set(Gf.Quatd(float(quat[0]), Gf.Vec3d(float(quat[1]), float(quat[2]), float(quat[3]))), time)


def _build(stage: Usd.Stage, background, objects, poses, cameras, mpu, up_axis, kpu, episode, table_bounds):
    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
    UsdPhysics.SetStageKilogramsPerUnit(stage, kpu)
    world = UsdGeom.Xform.Define(stage, WORLD)
    stage.SetDefaultPrim(world.GetPrim())
    layer_data = {"exporter": "dsg-gym", "formatVersion": FORMAT_VERSION}
    up = np.array([0.0, 0.0, 1.0]) if up_axis == "Z" else np.array([0.0, 1.0, 0.0])

    scene = UsdPhysics.Scene.Define(stage, WORLD.AppendChild("PhysicsScene"))
    scene.CreateGravityDirectionAttr(Gf.Vec3f(*(0.0 - up)))
    scene.CreateGravityMagnitudeAttr(GRAVITY_M_S2 / mpu)

    write_splats(stage, WORLD.AppendChild("Background"), background)

    objects_path = WORLD.AppendChild("Objects")
    UsdGeom.Scope.Define(stage, objects_path)
    ops = []
    for i, (obj, prim_name, pose) in enumerate(
        zip(objects, _prim_names("object", [o.name for o in objects]), poses)
    ):
        path = objects_path.AppendChild(prim_name)
        xf = UsdGeom.Xform.Define(stage, path)
        translate_op = xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
        orient_op = xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
        _set_pose(translate_op, orient_op, pose, rotmat_to_quat(pose[:3, :3]))
        ops.append((translate_op, orient_op))
        prim = xf.GetPrim()
        prim.SetCustomDataByKey("dsg:name", obj.name)
        prim.SetCustomDataByKey("dsg:index", i)
        body = UsdPhysics.RigidBodyAPI.Apply(prim)
        body.CreateRigidBodyEnabledAttr(True)
        body.CreateKinematicEnabledAttr(episode is not None)
        UsdPhysics.MassAPI.Apply(prim).CreateMassAttr(float(obj.mass))
        write_splats(stage, path.AppendChild("Splats"), obj.gaussians)
        verts, tris = convex_hull_mesh(obj.gaussians.means, MIN_THICKNESS_M / mpu)
        write_collider(stage, path.AppendChild("Collider"), verts, tris, convex_hull=True)

    if table_bounds is not None:
        lo, hi = table_bounds.min(axis=0), table_bounds.max(axis=0)
        axis = int(np.argmax(up))
        lo[axis] = min(lo[axis], hi[axis] - TABLE_THICKNESS_M / mpu)
        verts, tris = box_mesh(lo, hi)
        table = write_collider(stage, WORLD.AppendChild("Table"), verts, tris, convex_hull=True)
        table.GetPrim().SetCustomDataByKey("dsg:role", "table")

    cameras_path = WORLD.AppendChild("Cameras")
    UsdGeom.Scope.Define(stage, cameras_path)
    for cam, prim_name in zip(cameras, _prim_names("camera", [c.name for c in cameras])):
        write_camera(stage, cameras_path.AppendChild(prim_name), cam)

    if episode is not None:
        _write_episode(stage, world.GetPrim(), ops, episode)
        layer_data["episodeLength"] = episode.num_steps
    stage.GetRootLayer().customLayerData = {"dsg": layer_data}


def _write_episode(stage: Usd.Stage, world: Usd.Prim, ops, episode: Episode) -> None:
    t_count = episode.num_steps
    stage.SetTimeCodesPerSecond(episode.fps)
    stage.SetFramesPerSecond(episode.fps)
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(float(t_count - 1))
    quats = quat_hemisphere_continuous(rotmat_to_quat(episode.poses[:, :, :3, :3]))  # [T, K, 4]
    for k, (translate_op, orient_op) in enumerate(ops):
        for t in range(t_count):
            _set_pose(translate_op, orient_op, episode.poses[t, k], quats[t, k], Usd.TimeCode(float(t)))
    if episode.rewards is not None and episode.rewards.size:
        attr = world.CreateAttribute("dsg:episode:reward", Sdf.ValueTypeNames.Double, custom=True)
        for t, r in enumerate(episode.rewards):
            attr.Set(float(r), Usd.TimeCode(float(t + 1)))
    if episode.actions is not None and episode.actions.size:
        attr = world.CreateAttribute("dsg:episode:action", Sdf.ValueTypeNames.DoubleArray, custom=True)
        attr.SetCustomDataByKey("dsg:shape", Vt.IntArray([int(s) for s in episode.actions.shape[1:]]))
        for t, a in enumerate(episode.actions):
            flat = Vt.DoubleArray.FromNumpy(np.ascontiguousarray(a.reshape(-1)))
            attr.Set(flat, Usd.TimeCode(float(t + 1)))


def export_stage(
    path,
    background: GaussianSet,
    objects: Sequence[UsdObject] = (),
    cameras: Sequence[UsdCamera] = (),
    *,
    meters_per_unit: float = 1.0,
    up_axis: str = "Z",
    kilograms_per_unit: float = 1.0,
    episode: Episode | None = None,
    table_bounds=None,
) -> Path:
    """Write the world as a USD stage at ``path`` (``.usdc`` binary crate or ``.usda`` text, by
    extension) and return the path. See the module docstring for the layout.

    ``table_bounds`` (optional ``[2, 3]`` min/max corners, e.g. the world's table bounds whose
    up-axis extent may be zero at the table top) adds a static box collider ``/World/Table``
    extending ``TABLE_THICKNESS_M`` below the top.

    The stage is built in memory and written atomically (:mod:`dsg_gym.io.atomic`): readers never
    see a partial file and no temporary file is left behind on failure; the temporaries of earlier exports to
    ``path`` that were killed are deleted first. Invalid input raises ``ValueError`` naming the problem (wrong
    extension, non-rigid or non-finite pose, episode shape mismatch, ...); a place USD cannot write raises
    ``OSError`` with USD's reason.
    """
    path = _check_path(path)
    if not isinstance(background, GaussianSet):
        raise ValueError(f"export_stage: background must be a GaussianSet, got {type(background).__name__}")
    objects, cameras = list(objects), list(cameras)
    poses = _check_objects(objects)
    for i, cam in enumerate(cameras):
        if not isinstance(cam, UsdCamera):
            raise ValueError(f"export_stage: cameras[{i}] is a {type(cam).__name__}, expected UsdCamera")
        check_camera(cam)
    _prim_names("object", [o.name for o in objects])
    _prim_names("camera", [c.name for c in cameras])
    mpu = _positive("meters_per_unit", meters_per_unit)
    kpu = _positive("kilograms_per_unit", kilograms_per_unit)
    if up_axis not in ("Y", "Z"):
        raise ValueError(f"export_stage: up_axis must be 'Y' or 'Z', got {up_axis!r}")
    if episode is not None:
        if not isinstance(episode, Episode):
            raise ValueError(f"export_stage: episode must be an Episode, got {type(episode).__name__}")
        if episode.num_objects != len(objects):
            raise ValueError(
                f"export_stage: episode.poses has shape {episode.poses.shape}, expected "
                f"[T, {len(objects)}, 4, 4] (one pose per object per step)"
            )
    if table_bounds is not None:
        table_bounds = np.array(table_bounds, dtype=np.float64)
        if table_bounds.shape != (2, 3) or not np.isfinite(table_bounds).all():
            raise ValueError(
                f"export_stage: table_bounds must be a finite [2, 3] array, got {table_bounds.shape}"
            )

    stage = Usd.Stage.CreateInMemory(f"dsg{path.suffix}")
    _build(stage, background, objects, poses, cameras, mpu, up_axis, kpu, episode, table_bounds)

    remove_partial(path.parent, path.name, stale_only=True)  # what killed exports to this path left behind
    with atomic_path(path, suffix=path.suffix) as tmp:  # USD picks the file format by extension
        try:
            written = stage.GetRootLayer().Export(str(tmp))
        except Tf.ErrorException as e:
            raise OSError(f"export_stage: cannot write {str(path)!r}: {_usd_reason(e)}") from None
        if not written:
            raise OSError(f"export_stage: USD could not write {str(path)!r}")
    return path


def _usd_reason(err: Exception) -> str:
    """The first message of a USD error, without USD's source locations (one line)."""
    found = re.findall(r" : '(.*)'$", str(err), flags=re.MULTILINE)
    return found[0] if found else " ".join(str(err).split())


# ---------------------------------------------------------------------------------------- reading


def _pose_at(xformable: UsdGeom.Xformable, time: Usd.TimeCode) -> np.ndarray:
    return np.array(xformable.GetLocalTransformation(time), dtype=np.float64).T.copy()


def _read_object(prim: Usd.Prim) -> StageObject:
    splats = prim.GetChild("Splats")
    collider = UsdGeom.Mesh(prim.GetChild("Collider"))
    if not splats or not collider:
        raise ValueError(f"read_stage: object {prim.GetPath()} lacks its Splats or Collider child")
    body = UsdPhysics.RigidBodyAPI(prim)
    mass = UsdPhysics.MassAPI(prim).GetMassAttr().Get()
    verts = np.array(collider.GetPointsAttr().Get(), dtype=np.float64).reshape(-1, 3)
    tris = np.array(collider.GetFaceVertexIndicesAttr().Get(), dtype=np.int32).reshape(-1, 3)
    return StageObject(
        name=str(prim.GetCustomDataByKey("dsg:name") or prim.GetName()),
        gaussians=read_splats(splats),
        pose=_pose_at(UsdGeom.Xformable(prim), Usd.TimeCode.Default()),
        mass=float(mass) if mass is not None else float("nan"),
        kinematic=bool(body.GetKinematicEnabledAttr().Get()) if body else False,
        collider_vertices=verts,
        collider_triangles=tris,
        prim_path=str(prim.GetPath()),
    )


def _read_episode(stage: Usd.Stage, object_prims: list[Usd.Prim], length: int) -> Episode:
    t_count = int(length)
    poses = np.zeros((t_count, len(object_prims), 4, 4))
    for k, prim in enumerate(object_prims):
        xf = UsdGeom.Xformable(prim)
        for t in range(t_count):
            poses[t, k] = _pose_at(xf, Usd.TimeCode(float(t)))
    world = stage.GetPrimAtPath(WORLD)
    rewards = actions = None
    reward_attr = world.GetAttribute("dsg:episode:reward")
    if reward_attr and reward_attr.GetNumTimeSamples():
        rewards = np.array([reward_attr.Get(Usd.TimeCode(float(t + 1))) for t in range(t_count - 1)])
    action_attr = world.GetAttribute("dsg:episode:action")
    if action_attr and action_attr.GetNumTimeSamples():
        shape = tuple(int(s) for s in (action_attr.GetCustomDataByKey("dsg:shape") or ()))
        actions = np.stack(
            [
                np.array(action_attr.Get(Usd.TimeCode(float(t + 1))), np.float64).reshape(shape)
                for t in range(t_count - 1)
            ]
        )
    return Episode(stage.GetTimeCodesPerSecond(), poses, rewards, actions)


def read_stage(path) -> StageContents:
    """Read a stage written by ``export_stage``: the background and object splats (float32
    arrays bit-identical to those written), object poses at the default time, cameras, stage
    metadata and, when the stage holds one, the episode (poses evaluated at time codes
    ``0 .. T - 1``). The file is read fresh (never a cached layer). ``ValueError`` when the
    stage does not have the expected layout."""
    layer = Sdf.Layer.OpenAsAnonymous(str(path))
    if layer is None:
        raise ValueError(f"read_stage: cannot open {str(path)!r} as a USD layer")
    stage = Usd.Stage.Open(layer)
    background = stage.GetPrimAtPath(WORLD.AppendChild("Background"))
    if not background:
        raise ValueError(f"read_stage: {str(path)!r} has no /World/Background")
    objects_prim = stage.GetPrimAtPath(WORLD.AppendChild("Objects"))
    object_prims = list(objects_prim.GetChildren()) if objects_prim else []
    object_prims.sort(key=lambda p: int(p.GetCustomDataByKey("dsg:index") or 0))
    cameras_prim = stage.GetPrimAtPath(WORLD.AppendChild("Cameras"))
    cameras = [read_camera(p) for p in cameras_prim.GetChildren()] if cameras_prim else []
    layer_data = dict(stage.GetRootLayer().customLayerData)
    dsg_data = dict(layer_data.get("dsg", {}))
    default_prim = stage.GetDefaultPrim()
    metadata = {
        "metersPerUnit": UsdGeom.GetStageMetersPerUnit(stage),
        "upAxis": str(UsdGeom.GetStageUpAxis(stage)),
        "kilogramsPerUnit": UsdPhysics.GetStageKilogramsPerUnit(stage),
        "defaultPrim": str(default_prim.GetPath()) if default_prim else None,
        "timeCodesPerSecond": stage.GetTimeCodesPerSecond(),
        "startTimeCode": stage.GetStartTimeCode(),
        "endTimeCode": stage.GetEndTimeCode(),
        "customLayerData": layer_data,
    }
    episode = None
    if "episodeLength" in dsg_data:
        episode = _read_episode(stage, object_prims, dsg_data["episodeLength"])
    table = UsdGeom.Mesh(stage.GetPrimAtPath(WORLD.AppendChild("Table")))
    table_vertices = np.array(table.GetPointsAttr().Get(), np.float64) if table else None
    return StageContents(
        background=read_splats(background),
        objects=[_read_object(p) for p in object_prims],
        cameras=cameras,
        metadata=metadata,
        episode=episode,
        table_vertices=table_vertices,
    )
