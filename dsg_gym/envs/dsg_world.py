"""``DSGWorld-v0``: rearrange the objects of a Gaussian world; splat-rendered observations."""

from __future__ import annotations

import copy
import dataclasses
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..assets import world_path
from ..cameras import Cameras
from ..physics import SETTLE_TOLERANCE
from ..poses import as_poses7, axis_angle_to_quat, matrix_to_pose7, quat_multiply, quat_normalize, yaw_to_quat
from ..world_model import WorldModel
from .checks import (
    check_action,
    check_goal,
    check_start,
    positive_int,
    real_array,
    resolve_cameras,
    settle_checked,
)
from .goal_overlay import check_render_goal, overlay_goal
from .tasks import RearrangementTask, TaskParams

__all__ = ["DSGWorldEnv", "DEFAULT_WORLD", "GEOMETRY_WORLD", "load_default_world"]

#: the bundled world: DSG-World trained on the synthetic ``two_blocks`` capture (how to reproduce it:
#: docs/environment.md, "The bundled world")
DEFAULT_WORLD = world_path("two_blocks_dsg.dsgworld")
#: the geometry world of the same scene (Gaussians sampled on the MuJoCo geoms: the ideal reconstruction;
#: ``python -m train_world.cli.geom_world``), used by tests and as a reference
GEOMETRY_WORLD = world_path("default_geom.dsgworld")
_REBUILD = "docs/environment.md, 'The bundled world', gives the commands that rebuild it"
OBS_KEYS = ("rgb", "mask", "depth", "poses")
ACTION_MODES = ("delta", "se3", "absolute")
COLLISION_MODES = ("reject", "settle", "ignore")
RESET_OPTIONS = ("start", "goal")
ABSOLUTE_Z_SPAN = 0.3  # metres above the table top that absolute actions' z spans
_WORLD_CACHE: dict[str, WorldModel] = {}


def load_default_world() -> WorldModel:
    """The bundled world (cached per process). If the asset is missing or unreadable this raises a
    ValueError naming it (``dsg_gym`` never imports ``train_world``; docs/environment.md, "The bundled world", has the
    commands that rebuild it)."""
    key = str(DEFAULT_WORLD)
    if key not in _WORLD_CACHE:
        try:
            _WORLD_CACHE[key] = WorldModel.load(DEFAULT_WORLD).without_features()
        except ValueError as e:
            raise ValueError(f"the bundled world does not load ({e}); {_REBUILD}") from e
    return _WORLD_CACHE[key]


def _resolve_world(world) -> WorldModel:
    if world is None:
        return load_default_world()
    if isinstance(world, WorldModel):
        return world
    if isinstance(world, (str, Path)):
        key = str(Path(world).resolve())
        if key not in _WORLD_CACHE:
            # WorldModelError (a ValueError) names the file; identity features are never used at runtime
            _WORLD_CACHE[key] = WorldModel.load(world).without_features()
        return _WORLD_CACHE[key]
    raise ValueError(f"world must be None, a path or a WorldModel, got {type(world).__name__}")


class DSGWorldEnv(gym.Env):
    """Goal-conditioned rearrangement in a 3D Gaussian world model (``DSGWorld-v0``).

    The objects of a DSG world (a static Gaussian background plus rigid Gaussian objects) are moved by the
    actions; observations are splat renders (RGB, object-id masks, depth) from one or more cameras and the
    object poses; a MuJoCo proxy (convex hulls of the objects' Gaussians on a table box) keeps moves
    physically sensible. Rendering is incremental: only the 16x16 image tiles an object touches before or
    after its move are recomposited, bit-identical to a full render.

    ## Arguments (``gymnasium.make("DSGWorld-v0", **kwargs)``)

    | kwarg | default | meaning |
    | --- | --- | --- |
    | ``world`` | ``None`` | ``None`` (the bundled world: DSG-World trained on the ``two_blocks`` capture), a world file path (loaded without its per-Gaussian identity features, which the runtime never uses: masks come from object labels), or a ``WorldModel`` (used as given) |
    | ``width``, ``height`` | 128, 128 | observation image size (pixels) |
    | ``cameras`` | ``None`` | ``None`` = capture camera 0; an int (capture camera index); a look-at dict ``{"eye", "target", "up"?, "fovy_deg"?}``; or a **list** of these for V views (images get a leading V axis) |
    | ``obs`` | ``("rgb", "mask", "poses")`` | any of ``rgb``, ``mask``, ``depth``, ``poses``; only these are rendered (``goal`` is always included) |
    | ``action_mode`` | ``"delta"`` | ``"delta"``, ``"se3"`` or ``"absolute"`` (see Action space) |
    | ``collision`` | ``"reject"`` | ``"reject"``: a move that interpenetrates or leaves the workspace is undone for the objects involved (``info["rejected"]``); ``"settle"``: moves that leave the workspace are undone, then MuJoCo lets every object fall and come to rest; when they cannot rest inside the workspace without interpenetrating deeper than 2 mm (``physics.SETTLE_TOLERANCE``) the whole move is undone; ``"ignore"``: moves that stay in the workspace are accepted (collisions are still reported in ``info``) |
    | ``max_translation`` | 0.02 | metres per step at action 1 (``delta``, ``se3``) |
    | ``max_rotation`` | 0.2 | radians per step at action 1 (``delta``: yaw, ``se3``: axis-angle norm per component) |
    | ``task`` | ``TaskParams()`` | tolerances and reward weights (:class:`~dsg_gym.envs.tasks.TaskParams` or a dict of its fields) |
    | ``incremental`` | ``True`` | incremental rendering (``False``: full render every step; the same images with ``tail_stride`` 0) |
    | ``render_mode`` | ``None`` | ``"rgb_array"``: ``render()`` returns uint8 ``(render_height, render_width * V, 3)`` |
    | ``render_width``, ``render_height`` | 256, 256 | size of ``render()`` images |
    | ``render_goal`` | ``False`` | ``render()`` frames also show each object at its goal pose as a translucent, outlined ghost (observations never do) |
    | ``background_color`` | ``(0, 0, 0)`` | RGB in [0, 1] behind all Gaussians |
    | ``render_settings`` | ``RenderSettings()`` | renderer speed/accuracy knobs (:class:`~dsg_gym.scene_renderer.RenderSettings` or a dict of its fields: ``alpha_min`` 2/255, ``t_min`` 1e-3, ``sh_degree`` ``None``: the point ``benchmarks/pareto.py`` recommends; ``tail_stride`` 64: background tail tables behind the objects, within the ``t_min`` cut-off's reach of the exact merge; ``{"alpha_min": 1/255, "t_min": 1e-4, "tail_stride": 0}`` renders exactly like the training renderer) |
    | ``max_episode_steps`` | ``None`` | internal truncation (``gymnasium.make`` adds a ``TimeLimit`` of 200 steps anyway) |

    ## Action space

    ``Box(-1, 1, (K * n,), float32)`` for K objects, ``n`` numbers per object (object k owns entries
    ``[k*n, (k+1)*n)``). Values are clipped to [-1, 1]; NaN/Inf, a wrong shape or a dtype other than bool, int or
    float (complex, object, string) raise ``ValueError``.

    | ``action_mode`` | n | per object | scaling |
    | --- | --- | --- | --- |
    | ``delta`` | 4 | ``dx, dy, dz, dyaw`` in the world frame | ``max_translation`` m, ``max_rotation`` rad |
    | ``se3`` | 6 | ``dx, dy, dz`` and an axis-angle ``rx, ry, rz`` (world frame, applied about the object origin) | same |
    | ``absolute`` | 7 | target ``x, y, z, qw, qx, qy, qz`` | x/y span the table bounds, z spans ``[table, table + 0.3 m]``; the quaternion is normalised (zero: ``ValueError``) |

    An object whose action entries are all zero (``delta``/``se3``) does not move (and is not re-rendered).

    ## Observation space (``Dict``)

    | key | space | meaning |
    | --- | --- | --- |
    | ``rgb`` | ``Box(0, 255, (H, W, 3), uint8)`` | splat-rendered colour |
    | ``mask`` | ``Box(0, K, (H, W), uint8)`` | object id per pixel (0 = background, k = object k) |
    | ``depth`` | ``Box(0, inf, (H, W), float32)`` | expected z-depth in metres (0 where nothing is hit) |
    | ``poses`` | ``Box(low, high, (K, 7), float64)`` | object poses ``x, y, z, qw, qx, qy, qz`` (unit quaternion, ``qw >= 0``); x, y, z within the workspace, quaternion parts within [-1, 1] |
    | ``goal`` | ``Box(low, high, (K, 7), float64)`` | goal poses, same layout and bounds |

    With a list of V cameras the image entries get a leading ``V`` axis. The workspace
    (:attr:`~dsg_gym.world_model.WorldModel.workspace`) is the box over the table's x/y bounds from its top to 0.5 m
    above it; no object leaves it in any collision mode (its origin stays in the box, its collision hull within the
    table's x/y bounds and below the box's top).

    ## Episodes

    ``reset(seed=..., options=...)`` samples a valid start and goal (:mod:`dsg_gym.envs.tasks`); ``options``
    may give ``start`` and/or ``goal`` as a captured state's name (e.g. ``"state1"``, ``"state2"``) or poses
    ``[K,7]`` / ``[K,4,4]``; other keys raise ``ValueError``, as do given poses outside the workspace or, per
    collision mode, interpenetrating (``reject`` refuses such a start, ``settle`` settles it, ``ignore`` accepts
    it; ``reject`` and ``settle`` refuse such a goal). Reward: dense, from the pose error (see
    :mod:`~dsg_gym.envs.tasks`). ``terminated`` on success (all objects within the position and rotation
    tolerances); ``truncated`` after ``max_episode_steps``. ``info``: ``success``, ``position_errors``,
    ``rotation_errors`` (``[K]``), ``collision`` (the requested move interpenetrated or left the workspace),
    ``rejected`` (``[K]`` bool: moves undone), ``penetrating_pairs``, ``out_of_bounds``, ``settled``.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        world=None,
        width: int = 128,
        height: int = 128,
        cameras=None,
        obs: Sequence[str] = ("rgb", "mask", "poses"),
        action_mode: str = "delta",
        collision: str = "reject",
        max_translation: float = 0.02,
        max_rotation: float = 0.2,
        task: TaskParams | Mapping[str, Any] | None = None,
        incremental: bool = True,
        render_mode: str | None = None,
        render_width: int = 256,
        render_height: int = 256,
        background_color=(0.0, 0.0, 0.0),
        max_episode_steps: int | None = None,
        render_settings=None,
        render_goal: bool = False,
    ):
        super().__init__()
        from ..physics import PhysicsProxy  # MuJoCo; the renderer (numba) is imported below

        self.width, self.height = positive_int("width", width), positive_int("height", height)
        self.render_width = positive_int("render_width", render_width)
        self.render_height = positive_int("render_height", render_height)
        if isinstance(obs, str):
            obs = (obs,)
        obs = tuple(obs)
        bad = [o for o in obs if o not in OBS_KEYS]
        if bad or not obs or len(set(obs)) != len(obs):
            raise ValueError(f"obs must be distinct entries of {OBS_KEYS}, got {obs}")
        self.obs_keys = obs
        if action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
        if collision not in COLLISION_MODES:
            raise ValueError(f"collision must be one of {COLLISION_MODES}, got {collision!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(
                f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}"
            )
        for name, v in (("max_translation", max_translation), ("max_rotation", max_rotation)):
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        if max_episode_steps is not None:
            max_episode_steps = positive_int("max_episode_steps", max_episode_steps)
        bgc = np.asarray(background_color, dtype=np.float64)
        if bgc.shape != (3,) or not np.all(np.isfinite(bgc)) or bgc.min() < 0 or bgc.max() > 1:
            raise ValueError(f"background_color must be 3 numbers in [0, 1], got {background_color!r}")
        from ..scene_renderer import RenderSettings

        if render_settings is None:
            render_settings = RenderSettings()
        elif isinstance(render_settings, Mapping):
            known = [f.name for f in dataclasses.fields(RenderSettings)]
            bad = set(render_settings) - set(known)
            if bad:
                raise ValueError(f"render_settings: unknown keys {sorted(bad)} ({', '.join(known)})")
            render_settings = RenderSettings(**render_settings)
        elif not isinstance(render_settings, RenderSettings):
            raise ValueError(
                f"render_settings must be a RenderSettings or a dict, got {type(render_settings).__name__}"
            )
        self.render_settings = render_settings
        if isinstance(task, Mapping):
            task = TaskParams(**task)
        elif task is not None and not isinstance(task, TaskParams):
            raise ValueError(f"task must be a TaskParams or a dict of its fields, got {type(task).__name__}")

        self.world = _resolve_world(world)
        self.cameras, self._multi = resolve_cameras(cameras, self.world.cameras, self.width, self.height)
        self.action_mode, self.collision = action_mode, collision
        self.max_translation, self.max_rotation = float(max_translation), float(max_rotation)
        self.incremental = bool(incremental)
        self.render_mode, self.render_goal = render_mode, check_render_goal(render_goal)
        self.background_color = tuple(float(c) for c in bgc)
        self.max_episode_steps = max_episode_steps
        self.physics = PhysicsProxy(self.world)
        ref = next(iter(self.world.states.values()), None)
        ref_q = (
            matrix_to_pose7(ref)[:, 3:]
            if ref is not None
            else np.tile([1.0, 0, 0, 0], (self.world.num_objects, 1))
        )
        self.task = RearrangementTask(self.physics, ref_q, task)
        self.K = self.world.num_objects

        n = {"delta": 4, "se3": 6, "absolute": 7}[action_mode]
        self._n = n
        self.action_space = spaces.Box(-1.0, 1.0, (self.K * n,), np.float32)
        v = len(self.cameras)
        lead = (v,) if self._multi else ()
        hw = lead + (self.height, self.width)
        space: dict[str, spaces.Space] = {}
        if "rgb" in obs:
            space["rgb"] = spaces.Box(0, 255, hw + (3,), np.uint8)
        if "mask" in obs:
            space["mask"] = spaces.Box(0, self.K, hw, np.uint8)
        if "depth" in obs:
            space["depth"] = spaces.Box(0.0, np.inf, hw, np.float32)
        ws = self.physics.workspace
        low = np.tile([*ws.lo, -1.0, -1.0, -1.0, -1.0], (self.K, 1))
        high = np.tile([*ws.hi, 1.0, 1.0, 1.0, 1.0], (self.K, 1))
        if "poses" in obs:
            space["poses"] = spaces.Box(low, high, (self.K, 7), np.float64)
        space["goal"] = spaces.Box(low, high, (self.K, 7), np.float64)
        self.observation_space = spaces.Dict(space)

        self._renderer = None
        self._view_renderer = None
        self._poses: np.ndarray | None = None
        self._goal: np.ndarray | None = None
        self._steps = 0
        self._closed = False

    # ------------------------------------------------------------------ rendering
    def _make_renderer(self, cams: Cameras):
        from ..scene_renderer import SceneRenderer

        w = self.world
        return SceneRenderer(
            w.background, list(w.objects), cams.viewmats, cams.Ks, cams.width, cams.height,
            background_color=self.background_color, **w.splat_options, compositing=w.compositing,
            **self.render_settings.kwargs(),
        )  # fmt: skip

    @property
    def renderer(self):
        """The observation renderer (created on first use)."""
        if self._renderer is None:
            self._renderer = self._make_renderer(self.cameras)
        return self._renderer

    def _observe(self, rendered=None) -> dict[str, np.ndarray]:
        """The observation; ``rendered``: this env's images (``RenderOutput`` of its V cameras) when a batch
        renderer made them, else they are rendered here."""
        obs: dict[str, np.ndarray] = {}
        want = {k: k in self.obs_keys for k in ("rgb", "mask", "depth")}
        if any(want.values()):
            out = rendered
            if out is None:
                out = self.renderer.render(
                    self._poses, rgb=want["rgb"], mask=want["mask"], depth=want["depth"],
                    incremental=self.incremental,
                )  # fmt: skip
            for key in ("rgb", "mask", "depth"):
                if want[key]:
                    img = getattr(out, key)
                    obs[key] = img if self._multi else img[0]
        if "poses" in self.obs_keys:
            obs["poses"] = self._poses.copy()
        obs["goal"] = self._goal.copy()
        return obs

    def render(self):
        """``rgb_array``: uint8 ``(render_height, render_width * V, 3)`` of the current state (V views side by
        side); ``None`` without a render mode."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None
        if self._poses is None:
            raise gym.error.ResetNeeded("call reset() before render()")
        if self._view_renderer is None:
            c = self.cameras
            sx, sy = self.render_width / c.width, self.render_height / c.height
            ks = c.Ks.copy()
            ks[:, 0] *= sx
            ks[:, 1] *= sy
            self._view_renderer = self._make_renderer(
                Cameras(c.viewmats, ks, self.render_width, self.render_height)
            )
        out = self._view_renderer.render(self._poses, rgb=True, mask=False, depth=False)
        rgb = overlay_goal(self, out.rgb) if self.render_goal else out.rgb
        return np.concatenate(list(rgb), axis=1)

    # ------------------------------------------------------------------ episodes
    def _pose_option(self, name: str, value) -> np.ndarray:
        if isinstance(value, str):
            if value not in self.world.states:
                raise ValueError(
                    f"options[{name!r}]: unknown state {value!r}; this world has {sorted(self.world.states)}"
                )
            return matrix_to_pose7(self.world.states[value])
        return as_poses7(real_array(value, f"options[{name!r}]"), self.K, f"options[{name!r}]")

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        info = self._start_episode(seed, options)
        return self._observe(), info

    def _start_episode(self, seed, options) -> dict[str, Any]:
        """``reset`` without the observation: checks ``options``, seeds, samples the start and goal; the info."""
        if options is not None and not isinstance(options, Mapping):
            raise ValueError(f"options must be a dict, got {type(options).__name__}")
        options = dict(options or {})
        unknown = sorted(set(options) - set(RESET_OPTIONS))
        if unknown:
            raise ValueError(f"unknown reset options {unknown}; expected any of {RESET_OPTIONS}")
        start = self._pose_option("start", options["start"]) if options.get("start") is not None else None
        goal = self._pose_option("goal", options["goal"]) if options.get("goal") is not None else None
        report, settled = None, False
        if start is not None:  # outside the workspace or (per collision mode) overlapping: ValueError
            start, report, settled = check_start(self.physics, start, self.collision)
        if goal is not None:
            check_goal(self.physics, goal, self.collision)
        super().reset(seed=seed)
        rng = self.np_random
        if start is None:
            start = self.task.sample_configuration(rng)
        if goal is None:
            goal = self.task.sample_goal(rng, start)
        self._poses, self._goal, self._steps = start, goal, 0
        if report is None:
            report = self.physics.check(start, distance=False)
        return self._info(np.zeros(self.K, bool), report, collided=False, settled=settled)

    def _info(self, rejected, report, collided: bool, settled: bool, errors=None) -> dict[str, Any]:
        pe, re = self.task.errors(self._poses, self._goal) if errors is None else errors
        p = self.task.params
        return {
            "success": bool(np.all(pe <= p.position_tolerance) and np.all(re <= p.rotation_tolerance)),
            "position_errors": pe,
            "rotation_errors": re,
            "collision": bool(collided),
            "rejected": rejected,
            "penetrating_pairs": np.array(report.penetrating, dtype=np.int64).reshape(-1, 2),
            "out_of_bounds": np.array(report.out_of_bounds, dtype=np.int64),
            "settled": bool(settled),
        }

    # ------------------------------------------------------------------ actions
    def _check_action(self, action) -> np.ndarray:
        """The action as ``[K, n]`` float64 in [-1, 1] (:func:`~dsg_gym.envs.checks.check_action`)."""
        return check_action(action, self.action_space.shape, self.K, self._n)

    def _target(self, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidate poses ``[K,7]`` and which objects the action moves."""
        p = self._poses.copy()
        if self.action_mode == "absolute":
            ws = self.physics.workspace
            lo = np.array(ws.lo)
            hi = np.array([ws.hi[0], ws.hi[1], ws.lo[2] + ABSOLUTE_Z_SPAN])
            q = a[:, 3:7]
            if np.any(np.linalg.norm(q, axis=1) < 1e-6):
                raise ValueError("absolute action: a target quaternion is zero")
            p[:, :3] = lo + 0.5 * (a[:, :3] + 1.0) * (hi - lo)
            p[:, 3:] = quat_normalize(q)
            moved = np.any(p != self._poses, axis=1)
            return p, moved
        moved = np.any(a != 0.0, axis=1)
        idx = np.flatnonzero(moved)
        if idx.size == 0:
            return p, moved
        p[idx, :3] += self.max_translation * a[idx, :3]
        if self.action_mode == "delta":
            dq = yaw_to_quat(self.max_rotation * a[idx, 3])
        else:
            dq = axis_angle_to_quat(self.max_rotation * a[idx, 3:6])
        p[idx, 3:] = quat_normalize(quat_multiply(dq, p[idx, 3:]))
        return p, moved

    @property
    def poses(self) -> np.ndarray:
        """Current object poses ``[K, 7]`` (``x y z qw qx qy qz``, float64), a copy; after ``reset``."""
        if self._poses is None:
            raise gym.error.ResetNeeded("call reset() before reading poses")
        return self._poses.copy()

    @property
    def goal(self) -> np.ndarray:
        """Goal poses ``[K, 7]`` of the current episode, a copy; after ``reset``."""
        if self._goal is None:
            raise gym.error.ResetNeeded("call reset() before reading the goal")
        return self._goal.copy()

    def step(self, action):
        reward, terminated, truncated, info = self._transition(action)
        return self._observe(), reward, terminated, truncated, info

    def _transition(self, action) -> tuple[float, bool, bool, dict[str, Any]]:
        """``step`` without the observation: ``(reward, terminated, truncated, info)``; a bad action raises
        ``ValueError`` before anything changes."""
        if self._poses is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        a = self._check_action(action)
        cand, moved = self._target(a)  # may raise ValueError; nothing changed yet
        rejected = np.zeros(self.K, dtype=bool)
        report = self.physics.check(cand, distance=False)
        collided = not report.ok
        settled = False
        if self.collision == "reject":
            cand, rejected, report = self._reject(cand, moved, report, bounds_only=False)
        elif self.collision == "settle":
            cand, rejected, report = self._reject(cand, moved, report, bounds_only=True)
            if moved.any():
                rest = settle_checked(self.physics, cand)
                if rest is None:  # no rest in the workspace without penetrating (e.g. pushed off): undo all
                    cand, rejected = self._poses, moved.copy()
                    report = self.physics.check(cand, tol=SETTLE_TOLERANCE, distance=False)
                else:
                    (cand, report), settled = rest, True
        else:  # ignore: collisions stay, leaving the workspace does not
            cand, rejected, report = self._reject(cand, moved, report, bounds_only=True)
        self._poses = cand
        self._steps += 1
        errors = self.task.errors(self._poses, self._goal)
        reward, success = self.task.reward(self._poses, self._goal, collided, errors)
        truncated = self.max_episode_steps is not None and self._steps >= self.max_episode_steps
        info = self._info(rejected, report, collided, settled, errors)
        return reward, success, bool(truncated and not success), info

    def _reject(self, cand, moved, report, bounds_only: bool):
        """Undo the moves of the moved objects involved in a violation until the configuration is valid."""
        prev = self._poses
        rejected = np.zeros(self.K, dtype=bool)
        for _ in range(self.K + 1):
            bad = set(report.out_of_bounds)
            if not bounds_only:
                bad |= set(report.objects_in_collision())
            bad = [k for k in sorted(bad) if moved[k] and not rejected[k]]
            if not bad:
                break
            cand = cand.copy()
            cand[bad] = prev[bad]
            rejected[bad] = True
            report = self.physics.check(cand, distance=False)
        return cand, rejected, report

    def _sibling(self) -> DSGWorldEnv:
        """Another env on the same world, cameras, physics proxy and spaces with its own episode state and
        random generator (the vector env's members; the proxy holds no state between calls)."""
        other = copy.copy(self)
        other._renderer = other._view_renderer = None
        other._poses = other._goal = None
        other._steps = 0
        other._np_random = other._np_random_seed = None
        return other

    def close(self):
        self._renderer = None
        self._view_renderer = None
        self._closed = True
        super().close()
