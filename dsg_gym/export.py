"""Export a world (and optionally a recorded episode) to USD or to standard 3DGS PLY files.

Python::

    from dsg_gym.export import export_world_usd, export_world_ply
    export_world_usd("assets/worlds/two_blocks_dsg.dsgworld", "world.usdc")          # objects at state1
    export_world_usd(world_model, "w.usda", poses="state2")       # or [K,4,4] / [K,7] / a poses file
    export_world_usd(world_model, "ep", episode="ep.npz")                              # -> ep.usdc, animated
    export_world_ply(world_model, "ply_dir")                    # background.ply + <name>.ply (object frames)
    export_world_ply(world_model, "ply_dir", poses="state1")    # objects placed in the world frame

Command line (``dsg-export``, :mod:`dsg_gym.cli.export`)::

    dsg-export WORLD --out stage.usdc|.usda [--poses state1|state2|FILE] [--episode FILE]
    dsg-export WORLD --out DIR --ply [--poses ...]

``poses`` files: ``.npy`` (one array), ``.npz`` (key ``poses``, or a single array) or ``.json`` (a list, or
an object with ``poses``), holding ``[K,4,4]`` world-from-object matrices or ``[K,7]`` ``x y z qw qx qy qz``.
Episode files: see :mod:`dsg_gym.envs.recording` (``RecordEpisode``, ``save_episode``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .poses import as_poses7, matrix_to_pose7, pose7_to_matrix
from .world_model import WorldModel, transform_gaussians

__all__ = ["export_world_usd", "export_world_ply", "load_world_model", "resolve_poses", "load_poses_file"]

POSE_FILE_SUFFIXES = (".npy", ".npz", ".json")


# ----------------------------------------------------------------------------------------- inputs
def load_world_model(world) -> WorldModel:
    """A :class:`WorldModel` from a world file path or a ``WorldModel`` (returned as is)."""
    if isinstance(world, WorldModel):
        return world
    if isinstance(world, (str, Path)):
        return WorldModel.load(world)  # WorldModelError (ValueError) names the file
    raise ValueError(f"world must be a world file path or a WorldModel, got {type(world).__name__}")


def load_poses_file(path, k: int) -> np.ndarray:
    """``[K,4,4]`` float64 poses from a ``.npy`` / ``.npz`` / ``.json`` file (see the module docstring)."""
    p = Path(path)
    if p.suffix not in POSE_FILE_SUFFIXES:
        raise ValueError(f"{p}: a poses file must end in {', '.join(POSE_FILE_SUFFIXES)}")
    if not p.is_file():
        raise ValueError(f"{p}: poses file does not exist")
    try:
        if p.suffix == ".json":
            doc = json.loads(p.read_text(encoding="utf-8"))
            arr = doc.get("poses") if isinstance(doc, dict) else doc
            if arr is None:
                raise ValueError("a JSON object needs a 'poses' entry")
            arr = np.asarray(arr, dtype=np.float64)
        else:
            data = np.load(p, allow_pickle=False)
            if isinstance(data, np.lib.npyio.NpzFile):
                with data:
                    if "poses" in data.files:
                        arr = data["poses"]
                    elif len(data.files) == 1:
                        arr = data[data.files[0]]
                    else:
                        raise ValueError(f"an .npz needs a 'poses' array (it has {sorted(data.files)})")
            else:
                arr = data
            if arr.dtype.kind not in "fiu":
                raise ValueError(f"poses must be numeric, got dtype {arr.dtype}")
    except (OSError, ValueError, EOFError, TypeError) as e:
        raise ValueError(f"{p}: cannot read poses ({e})") from None
    try:
        return _as_matrices(arr, k, "poses")
    except ValueError as e:
        raise ValueError(f"{p}: {e}") from None


def _as_matrices(value, k: int, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    p7 = as_poses7(arr, k, name)  # validates shape, finiteness, rigidity
    return arr.copy() if arr.shape == (k, 4, 4) else pose7_to_matrix(p7)


def resolve_poses(wm: WorldModel, poses) -> np.ndarray:
    """``[K,4,4]`` float64 object poses from a state name, an array (``[K,4,4]`` or ``[K,7]``) or a poses file
    path (``.npy`` / ``.npz`` / ``.json``). ``None`` means the world's reference state (``state1`` when
    present, else its first state). ``ValueError`` lists the available states for an unknown name."""
    k = wm.num_objects
    if poses is None:
        ref = wm.metadata.get("reference_state")
        first = "state1" if "state1" in wm.states else next(iter(wm.states), None)
        name = ref if ref in wm.states else first
        if name is None:
            raise ValueError("the world has no captured states; give poses explicitly")
        return wm.state_poses(name)
    if isinstance(poses, Path) or (isinstance(poses, str) and poses not in wm.states):
        s = str(poses)
        if isinstance(poses, Path) or Path(s).suffix in POSE_FILE_SUFFIXES or Path(s).exists():
            return load_poses_file(s, k)
        raise ValueError(
            f"unknown state {s!r}; this world has states {sorted(wm.states)} "
            f"(or give a .npy/.npz/.json poses file)"
        )
    if isinstance(poses, str):
        return wm.state_poses(poses)
    return _as_matrices(poses, k, "poses")


def _resolve_episode(episode, k: int):
    from .envs.recording import load_episode
    from .usd import Episode

    if episode is None:
        return None
    if isinstance(episode, (str, Path)):
        episode = load_episode(episode)
    if not isinstance(episode, Episode):
        raise ValueError(f"episode must be an Episode or an episode file path, got {type(episode).__name__}")
    if episode.num_objects != k:
        raise ValueError(f"the episode has {episode.num_objects} objects per step, the world has {k}")
    return episode


# ----------------------------------------------------------------------------------------- USD
def export_world_usd(world, out, *, poses=None, episode=None, meters_per_unit: float = 1.0) -> Path:
    """Write ``world`` (a world file path or a :class:`WorldModel`) as a USD stage (see docs/usd.md).

    ``out``: ``.usdc`` (binary, appended when ``out`` has no suffix) or ``.usda``. ``poses``: the objects'
    (untimed) poses: a state name, ``[K,4,4]`` / ``[K,7]`` array or a poses file; default the reference state,
    or the episode's first step when an ``episode`` (an :class:`~dsg_gym.usd.Episode` or an ``.npz`` episode
    file) is given, which adds time-sampled poses (``timeCodesPerSecond`` = the episode's fps, kinematic
    bodies).
    Includes the capture cameras and the table as a static collider. Returns the stage path."""
    from .usd import UsdObject, cameras_from_arrays, export_stage

    wm = load_world_model(world)
    out = Path(out)
    if out.is_dir():
        raise ValueError(f"{out}: is a folder; give a .usdc/.usda stage path (or export PLY files into it)")
    if out.suffix == "":
        out = out.with_name(out.name + ".usdc")
    if out.suffix not in (".usdc", ".usda"):
        raise ValueError(f"{out}: a USD stage must end in .usdc (binary) or .usda (text)")
    ep = _resolve_episode(episode, wm.num_objects)
    if poses is None and ep is not None:
        P = ep.poses[0]  # noqa: N806
    else:
        P = resolve_poses(wm, poses)  # noqa: N806
    objects = [UsdObject(name, g, P[k]) for k, (name, g) in enumerate(zip(wm.object_names, wm.objects))]
    c = wm.cameras
    cameras = cameras_from_arrays(c.viewmats, c.Ks, c.width, c.height)
    t = wm.table
    table = [[t.xmin, t.ymin, t.z], [t.xmax, t.ymax, t.z]]
    with _made_folder(out.parent):
        return export_stage(
            out,
            wm.background,
            objects,
            cameras,
            episode=ep,
            table_bounds=table,
            meters_per_unit=meters_per_unit,
        )


@contextlib.contextmanager
def _made_folder(folder: Path) -> Iterator[None]:
    """Create ``folder`` and its missing parents; when that or the block fails, remove those it created (if
    empty). A folder that cannot be created raises ``OSError`` naming it and the reason, in one line."""
    made = []
    p = folder
    while not p.exists() and p != p.parent:
        made.append(p)
        p = p.parent
    try:
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as e:
            why = (
                "a file of that name is in the way"
                if isinstance(e, FileExistsError)
                else e.strerror or str(e)
            )
            raise OSError(f"cannot create the folder {str(e.filename or folder)!r}: {why}") from None
        yield
    except BaseException:
        for d in made:  # deepest first
            with contextlib.suppress(OSError):
                d.rmdir()
        raise


# ----------------------------------------------------------------------------------------- PLY
def _file_stem(name: str, used: set[str], oid: int) -> str:
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", name).strip(".") or f"object_{oid}"
    if stem.lower() in used:
        stem = f"{stem}_{oid}"
    used.add(stem.lower())
    return stem


def export_world_ply(world, out_dir, *, poses=None) -> list[Path]:
    """Write the world as standard 3DGS PLY files (Inria layout, ``dsg_gym.io.write_ply``) into ``out_dir``:
    ``background.ply`` (unless the background has no Gaussians: a PLY needs at least one) and one ``<name>.ply``
    per object (names made file-safe; a clash gets ``_<id>``), each object in its own frame, or in the world frame
    placed at ``poses`` (a state name, array or poses file) when given. Object files carry a ``label`` property =
    the object id. Returns the paths, background first. When a write fails, the files and folders this call
    created are removed.

    Every array reads back bit for bit except ``scales``: the Inria layout stores float32 log-scales, which
    cannot represent every float32 scale, so a scale may come back a few float32 ulps off (relative error
    <= 3e-7); files of sets read from PLY (e.g. an imported background) are rewritten byte for byte."""
    from .io import write_ply

    wm = load_world_model(world)
    P = None if poses is None else resolve_poses(wm, poses)  # noqa: N806
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: exists and is not a folder")
    jobs = [("background", wm.background, None)] if wm.background.num else []
    used = {"background"}
    for k, (oid, name, g) in enumerate(zip(wm.object_ids, wm.object_names, wm.objects)):
        if P is not None:
            g = transform_gaussians(g, matrix_to_pose7(P[k]))
        jobs.append(
            (_file_stem(name, used, oid), dataclasses.replace(g, labels=np.full(g.num, oid, np.int32)), True)
        )
    paths: list[Path] = []
    with _made_folder(out):
        new = [not (out / f"{stem}.ply").exists() for stem, _, _ in jobs]
        try:
            for stem, g, labels in jobs:
                paths.append(write_ply(out / f"{stem}.ply", g, labels=labels))
        except BaseException:
            for p, created in zip(paths, new):
                if created:
                    p.unlink(missing_ok=True)
            raise
    return paths
