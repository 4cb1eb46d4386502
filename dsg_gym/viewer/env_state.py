"""The state behind ``dsg-view``'s page: a ``DSGWorldEnv`` whose objects the page moves, without any server.

:class:`ViewerSession` holds a ``DSGWorldEnv`` in ``absolute`` action mode with ``collision="ignore"``:
every object move is one env step whose action is the objects' target poses, so the env renders what an agent
would see (RGB, object ids and depth from the chosen camera) and its physics proxy reports what is wrong with
the configuration (:class:`Verdict`): interpenetrating objects stay where they were put and are reported as
colliding; a move that would take an object out of the workspace is undone by the env, as for an agent, and
reported as out of the workspace. Positions stay within the absolute action's range (x and y over the table
bounds, z from the table top to ``ABSOLUTE_Z_SPAN`` above it).
The session also resets to a captured state or a random valid configuration, saves the configuration as a JSON
poses file, exports it as a USD stage, and plays episodes (:mod:`dsg_gym.playback`). All methods hold
one lock: the page's callbacks may call them from several threads.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..envs.dsg_world import ABSOLUTE_Z_SPAN, DSGWorldEnv
from ..export import export_world_usd, load_poses_file
from ..io.atomic import atomic_write_bytes
from ..playback import Playback, load_playback
from ..poses import as_poses7, matrix_to_pose7

__all__ = ["RANDOM", "TABLE_NAME", "ViewerSession", "Verdict"]

#: the ``reset`` start that samples a random valid configuration
RANDOM = "random"
#: the name a verdict gives the table (a pair with it: an object reaches into the table)
TABLE_NAME = "table"


@dataclass(frozen=True)
class Verdict:
    """What the physics proxy says about the last move: ``colliding`` pairs of names that interpenetrate
    (an object or ``"table"``) and the objects ``out_of_workspace`` (the move would have taken them out of the
    workspace, so the env kept them where they were); ``free`` when neither."""

    colliding: tuple[tuple[str, str], ...] = ()
    out_of_workspace: tuple[str, ...] = ()

    @property
    def free(self) -> bool:
        return not self.colliding and not self.out_of_workspace

    @property
    def status(self) -> str:
        """``"free"``, ``"colliding"``, ``"out of the workspace"`` or both joined by ``" and "``."""
        parts = (["colliding"] if self.colliding else []) + (
            ["out of the workspace"] if self.out_of_workspace else []
        )
        return " and ".join(parts) or "free"

    @property
    def text(self) -> str:
        """One line naming the objects, e.g. ``colliding: red_box + blue_cylinder``."""
        if self.free:
            return "free"
        parts = []
        if self.colliding:
            parts.append("colliding: " + ", ".join(f"{a} + {b}" for a, b in self.colliding))
        if self.out_of_workspace:
            parts.append("out of the workspace: " + ", ".join(self.out_of_workspace))
        return "; ".join(parts)


class ViewerSession:
    """A ``DSGWorldEnv`` moved by absolute poses (see the module docstring).

    Args:
        world: ``None`` (the bundled world), a world file path or a ``WorldModel``.
        camera: the capture camera whose view the observation shows.
        size: observation width = height in pixels.
        seed: seed of the first random configuration (each ``reset("random")`` takes the next one).
    """

    def __init__(self, world=None, camera: int = 0, size: int = 256, seed: int = 0):
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise ValueError(f"seed must be an integer, got {seed!r}")
        self._lock = threading.RLock()
        self._size = size
        self._seed = int(seed)
        self.env = self._make_env(world, camera)
        self.world = self.env.world
        self.camera = int(camera)
        self.names = tuple(self.world.object_names)
        self.playback: Playback | None = None
        self._obs: dict[str, np.ndarray] = {}
        self._info: dict[str, Any] = {}
        states = self.world.states
        self.reset("state1" if "state1" in states else next(iter(states), RANDOM))

    def _make_env(self, world, camera) -> DSGWorldEnv:
        return DSGWorldEnv(
            world=world, width=self._size, height=self._size, cameras=camera,
            obs=("rgb", "mask", "depth", "poses"), action_mode="absolute", collision="ignore",
        )  # fmt: skip

    # ------------------------------------------------------------------ reading
    @property
    def num_cameras(self) -> int:
        """How many capture cameras the world has (``set_camera`` takes an index below this)."""
        return len(self.world.cameras)

    def poses(self) -> np.ndarray:
        """The objects' poses ``[K, 7]`` in the env (a copy)."""
        with self._lock:
            return self.env.poses

    def goal(self) -> np.ndarray:
        """The env's goal poses ``[K, 7]`` (a copy)."""
        with self._lock:
            return self.env.goal

    def observation(self) -> dict[str, np.ndarray]:
        """The env's latest observation (``rgb``, ``mask``, ``depth``, ``poses``, ``goal``; copies)."""
        with self._lock:
            return {k: v.copy() for k, v in self._obs.items()}

    def verdict(self) -> Verdict:
        """The physics proxy's verdict on the current configuration."""
        with self._lock:
            info, n = self._info, self.names
            pairs = np.asarray(info.get("penetrating_pairs", np.zeros((0, 2), np.int64))).reshape(-1, 2)
            out = set(np.asarray(info.get("out_of_bounds", ()), np.int64).reshape(-1).tolist())
            out |= set(np.flatnonzero(np.asarray(info.get("rejected", np.zeros(len(n), bool)))).tolist())
            name = lambda i: n[int(i)] if 0 <= int(i) < len(n) else TABLE_NAME  # noqa: E731
            return Verdict(tuple((name(a), name(b)) for a, b in pairs), tuple(n[k] for k in sorted(out)))

    def object_index(self, which) -> int:
        """Index of an object given by name or index (``ValueError`` listing the objects otherwise)."""
        if isinstance(which, str):
            if which not in self.names:
                raise ValueError(f"unknown object {which!r}; this world has {list(self.names)}")
            return self.names.index(which)
        if (
            isinstance(which, (int, np.integer))
            and not isinstance(which, bool)
            and 0 <= which < len(self.names)
        ):
            return int(which)
        raise ValueError(
            f"object must be one of {list(self.names)} or an index below {len(self.names)}, got {which!r}"
        )

    # ------------------------------------------------------------------ moving
    def _action(self, poses: np.ndarray) -> np.ndarray:
        """The absolute action that asks for ``poses`` ``[K, 7]`` (the env clips it to its range)."""
        ws = self.env.physics.workspace
        lo = np.array(ws.lo, np.float64)
        hi = np.array([ws.hi[0], ws.hi[1], ws.lo[2] + ABSOLUTE_Z_SPAN])
        a = poses.copy()
        a[:, :3] = 2.0 * (poses[:, :3] - lo) / (hi - lo) - 1.0
        return a.reshape(-1)

    def set_poses(self, poses) -> Verdict:
        """Move every object to ``poses`` (``[K, 7]`` or ``[K, 4, 4]``) with one env step; the verdict."""
        p = as_poses7(poses, len(self.names), "poses")  # ValueError before anything changes
        with self._lock:
            obs, _, _, _, info = self.env.step(self._action(p))
            self._obs, self._info = obs, info
            return self.verdict()

    def set_object_pose(self, which, pose) -> Verdict:
        """Move one object (name or index) to ``pose`` (``x y z qw qx qy qz`` or a 4x4 rigid transform);
        the others stay (to rounding: the absolute action maps every pose to [-1, 1] and back). Returns the
        verdict."""
        k = self.object_index(which)
        p = as_poses7(np.asarray(pose, np.float64)[None], 1, f"pose of {self.names[k]}")[0]
        with self._lock:
            poses = self.env.poses
            poses[k] = p
            return self.set_poses(poses)

    def _restart(self, start, goal, seed=None) -> Verdict:
        opts = {"start": start, "goal": goal}
        obs, info = self.env.reset(seed=seed, options={k: v for k, v in opts.items() if v is not None})
        self._obs, self._info = obs, info
        return self.verdict()

    def reset(self, start: str = "state1") -> Verdict:
        """Start over at a captured state (its goal: the other captured state of ``state1``/``state2``, else
        a sampled one) or, with ``"random"``, at a random valid configuration and goal. The verdict."""
        with self._lock:
            if start == RANDOM:
                self._seed += 1
                return self._restart(None, None, seed=self._seed - 1)
            if not isinstance(start, str) or start not in self.world.states:
                raise ValueError(
                    f"start must be {RANDOM!r} or a state of this world {sorted(self.world.states)}"
                )
            other = {"state1": "state2", "state2": "state1"}.get(start)
            if other in self.world.states:
                return self._restart(start, other)
            return self._restart(start, None, seed=self._seed)  # a sampled goal, seeded

    def set_camera(self, camera: int) -> None:
        """Observe from capture camera ``camera`` (the configuration and goal stay)."""
        if isinstance(camera, bool) or not isinstance(camera, (int, np.integer)):
            raise ValueError(f"camera must be a capture camera index, got {camera!r}")
        with self._lock:
            env = self._make_env(self.world, int(camera))  # ValueError for an index out of range
            poses, goal = self.env.poses, self.env.goal
            self.env.close()
            self.env, self.camera = env, int(camera)
            self._restart(poses, goal)

    # ------------------------------------------------------------------ files
    def configuration(self) -> dict[str, Any]:
        """The configuration as JSON data: ``world``, ``objects`` (names), ``poses`` and ``goal`` ``[K][7]``."""
        with self._lock:
            return {
                "world": self.world.name,
                "objects": list(self.names),
                "poses": self.env.poses.tolist(),
                "goal": self.env.goal.tolist(),
            }

    def save_configuration(self, path) -> Path:
        """Write :meth:`configuration` as JSON (atomic); ``dsg-export WORLD --poses PATH`` and
        :meth:`load_configuration` read it. Returns the path."""
        p = Path(path)
        if p.suffix != ".json":
            raise ValueError(f"{p}: a configuration file must end in .json")
        text = json.dumps(self.configuration(), indent=2) + "\n"
        return atomic_write_bytes(p, text.encode("utf-8"))

    def load_configuration(self, path) -> Verdict:
        """Move the objects to the poses of a poses file (``.json`` as saved here, ``.npy`` or ``.npz``)."""
        return self.set_poses(matrix_to_pose7(load_poses_file(path, len(self.names))))

    def export_usd(self, path) -> Path:
        """Write the world with the objects at their current poses as a USD stage (``.usdc``/``.usda``,
        :func:`dsg_gym.export.export_world_usd`). Returns the path."""
        with self._lock:
            return export_world_usd(self.world, path, poses=self.env.poses)

    # ------------------------------------------------------------------ playback
    def load_episode(self, source, index: int = 0) -> int:
        """Load an episode to play (an ``.npz`` episode file or a Minari dataset and episode ``index``),
        show its first step (its goal too when the dataset has one) and return its number of steps."""
        pb = load_playback(source, len(self.names), index)
        with self._lock:
            self.playback = pb
            if pb.goal is not None:
                self._restart(pb.poses[0], pb.goal)
            else:
                self.set_poses(pb.poses[0])
            return len(pb)

    def show_step(self, t: int) -> Verdict:
        """Move the objects to step ``t`` of the loaded episode; the verdict."""
        with self._lock:
            if self.playback is None:
                raise ValueError("no episode loaded: load an episode file or a dataset episode first")
            n = len(self.playback)
            if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= t < n:
                raise ValueError(f"step must be an integer in [0, {n}), got {t!r}")
            return self.set_poses(self.playback.poses[int(t)])

    def close(self) -> None:
        with self._lock:
            self.env.close()

    def info(self) -> Mapping[str, Any]:
        """The env's latest ``info`` (a shallow copy)."""
        with self._lock:
            return dict(self._info)
