"""``DSGWorld-v0``'s own vector env: N envs in one process, stepped and rendered as one batch."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from . import MAX_EPISODE_STEPS
from .dsg_world import DSGWorldEnv

__all__ = ["DSGWorldVectorEnv"]


class DSGWorldVectorEnv(VectorEnv):
    """N ``DSGWorld-v0`` envs in one process (``gymnasium.make_vec("DSGWorld-v0", num_envs=N,
    vectorization_mode="vector_entry_point")``).

    The envs share one world, one physics proxy and one background render per camera; each step checks the
    whole batch of actions first (a bad row raises ``ValueError`` naming the env, and nothing changes), moves
    every env's objects, then re-renders every env's changed tiles in one batch
    (:class:`dsg_gym.batch_renderer.BatchSceneRenderer`). Given the same seeds and actions the observations,
    rewards, flags and infos equal those of N single envs in ``gymnasium.vector.SyncVectorEnv``, bit for bit.

    ## Arguments

    | kwarg | default | meaning |
    | --- | --- | --- |
    | ``num_envs`` | (required) | N >= 1 |
    | ``max_episode_steps`` | 200 | truncation, as ``gymnasium.make``'s ``TimeLimit`` (``None``: never) |
    | ``autoreset_mode`` | ``NEXT_STEP`` | ``AutoresetMode.NEXT_STEP`` (Gymnasium's default: the step after an episode ends resets that env and ignores its action), ``AutoresetMode.DISABLED`` (an ended env is reset by ``reset(options={"reset_mask": mask})``; until then it steps on) or ``AutoresetMode.SAME_STEP`` (reset at once; ``infos["final_obs"]`` (an object array of observation dicts) and ``infos["final_info"]`` (batched like ``infos``) hold the last observation and info, as in Gymnasium's vector envs) |
    | any other | | :class:`~dsg_gym.envs.dsg_world.DSGWorldEnv`'s kwargs, the same for every env (``incremental`` is ignored: the batch always renders incrementally, which gives the same images) |

    Spaces: ``single_observation_space`` / ``single_action_space`` are the env's; the batched spaces have a leading
    N axis. ``infos``: each key of the env's ``info`` batched to ``[N, ...]`` with its ``_key`` mask;
    ``penetrating_pairs`` and ``out_of_bounds`` vary in length and are object arrays of the envs' arrays.
    ``render()`` returns a tuple of N ``rgb_array`` frames.
    """

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int, max_episode_steps: int | None = MAX_EPISODE_STEPS,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP, **kwargs):  # fmt: skip
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer))
            or max_episode_steps < 1
        ):  # fmt: skip
            raise ValueError(
                f"max_episode_steps must be None or a positive integer, got {max_episode_steps!r}"
            )
        try:
            autoreset_mode = AutoresetMode(autoreset_mode)
        except ValueError:
            raise ValueError(
                f"autoreset_mode must be NEXT_STEP, SAME_STEP or DISABLED, got {autoreset_mode!r}"
            ) from None
        kwargs.pop("incremental", None)
        first = DSGWorldEnv(**kwargs)
        self.envs = [first] + [first._sibling() for _ in range(int(num_envs) - 1)]
        self.num_envs = int(num_envs)
        self.max_episode_steps = None if max_episode_steps is None else int(max_episode_steps)
        self.autoreset_mode = autoreset_mode
        self.metadata = {**self.metadata, "autoreset_mode": autoreset_mode}
        self.render_mode = first.render_mode
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(first.observation_space, self.num_envs)
        self.action_space = batch_space(first.action_space, self.num_envs)
        self._batch = None
        self._elapsed = np.zeros(self.num_envs, np.int64)
        self._autoreset = np.zeros(self.num_envs, bool)
        self._started = False

    # ------------------------------------------------------------------ rendering
    @property
    def batch_renderer(self):
        """The batch renderer of the observations (created on first use)."""
        if self._batch is None:
            from ..batch_renderer import BatchSceneRenderer

            self._batch = BatchSceneRenderer(self.envs[0].renderer, self.num_envs)
        return self._batch

    def _observe(self, fresh: np.ndarray) -> dict[str, np.ndarray]:
        first = self.envs[0]
        want = {k: k in first.obs_keys for k in ("rgb", "mask", "depth")}
        obs: dict[str, np.ndarray] = {}
        if any(want.values()):
            poses = np.stack([e._poses for e in self.envs])
            out = self.batch_renderer.render(poses, rgb=want["rgb"], mask=want["mask"], depth=want["depth"],
                                             fresh=fresh)  # fmt: skip
            for key in ("rgb", "mask", "depth"):
                if want[key]:
                    img = getattr(out, key)
                    obs[key] = img if first._multi else img[:, 0]
        if "poses" in first.obs_keys:
            obs["poses"] = np.stack([e._poses for e in self.envs])
        obs["goal"] = np.stack([e._goal for e in self.envs])
        return obs

    def render(self) -> tuple[np.ndarray, ...] | None:
        """Each env's ``render()`` frame (one view renderer shared by all)."""
        if self.render_mode is None:
            return None
        frames = [self.envs[0].render()]
        for e in self.envs[1:]:
            e._view_renderer = self.envs[0]._view_renderer
            frames.append(e.render())
        return tuple(frames)

    # ------------------------------------------------------------------ episodes
    def _infos(self, infos: Sequence[dict[str, Any] | None]) -> dict[str, Any]:
        """Gymnasium's vector ``infos`` of the envs' ``info`` dicts (``None``: that env has none, its ``_key``
        masks are False and its rows zero)."""
        have = np.array([i is not None for i in infos])
        first = next(i for i in infos if i is not None)
        out: dict[str, Any] = {}
        for key, v0 in first.items():
            if key in ("penetrating_pairs", "out_of_bounds"):
                arr = np.full(len(infos), None, dtype=object)
            else:
                v0 = np.asarray(v0)
                arr = np.zeros((len(infos),) + v0.shape, v0.dtype)
            for j, info in enumerate(infos):
                if info is not None:
                    arr[j] = info[key]
            out[key] = arr
            out["_" + key] = have.copy()
        return out

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        """Reset the envs: ``seed`` an int (env i gets ``seed + i``, as Gymnasium's vector envs), a list of N
        seeds or ``None``; ``options`` go to every reset env, except ``reset_mask`` (bool ``[N]``: reset only these
        envs, the others keep their episode; as Gymnasium's vector envs). Every option is checked before any env
        changes. ``infos`` hold the reset envs' info (``_key`` masks False for the others)."""
        if seed is None:
            seeds = [None] * self.num_envs
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"reset: {len(seeds)} seeds for {self.num_envs} envs")
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, bool)))
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(
                f"reset: reset_mask must be a bool array of shape ({self.num_envs},), got {mask!r}"
            )
        if not self._started and not mask.all():
            raise ValueError("reset: the first reset must reset every env (no reset_mask)")
        todo = [int(i) for i in np.flatnonzero(mask)]
        infos: list[dict[str, Any] | None] = [None] * self.num_envs
        if (
            todo
        ):  # the first env to reset checks the options before any env changes; a bad option raises there
            for i in todo:
                infos[i] = self.envs[i]._start_episode(seeds[i], options or None)
        self._elapsed[mask] = 0
        self._autoreset[mask] = False
        self._started = True
        return self._observe(mask.copy()), (self._infos(infos) if todo else {})

    def _check_actions(self, actions) -> np.ndarray:
        try:
            a = np.asarray(actions)
        except (TypeError, ValueError):
            raise ValueError(f"actions must be numeric, got {type(actions).__name__}") from None
        want = self.action_space.shape
        if a.shape != want:
            raise ValueError(f"actions have shape {a.shape}, expected {want} (num_envs, action size)")
        for i, env in enumerate(self.envs):
            if self._autoreset[i] and self.autoreset_mode == AutoresetMode.NEXT_STEP:
                continue  # this env resets and ignores its action
            try:
                checked = env._check_action(a[i])
                if env.action_mode == "absolute":
                    env._target(checked)
            except ValueError as e:
                raise ValueError(f"env {i}: {e}") from None
        return a

    def step(self, actions):
        if not self._started:
            from gymnasium.error import ResetNeeded

            raise ResetNeeded("call reset() before step()")
        a = self._check_actions(actions)
        n = self.num_envs
        rewards = np.zeros(n, np.float64)
        terms, truncs = np.zeros(n, bool), np.zeros(n, bool)
        fresh = np.zeros(n, bool)
        infos: list[dict[str, Any]] = [{}] * n
        for i, env in enumerate(self.envs):
            if self._autoreset[i] and self.autoreset_mode == AutoresetMode.NEXT_STEP:
                infos[i] = env._start_episode(None, None)
                self._elapsed[i] = 0
                fresh[i] = True
                continue
            rewards[i], terms[i], truncs[i], infos[i] = env._transition(a[i])
            self._elapsed[i] += 1
            if self.max_episode_steps is not None and self._elapsed[i] >= self.max_episode_steps:
                truncs[i] = True
        done = terms | truncs
        extra: dict[str, Any] = {}
        if self.autoreset_mode == AutoresetMode.SAME_STEP and done.any():
            last = self._observe(fresh)
            final_obs = np.full(n, None, dtype=object)
            for i in np.flatnonzero(done):
                final_obs[i] = {k: v[i] for k, v in last.items()}
            final_info = self._infos([info if d else None for info, d in zip(infos, done)])
            for i in np.flatnonzero(done):
                infos[i] = self.envs[i]._start_episode(None, None)
                self._elapsed[i] = 0
            extra = {"final_obs": final_obs, "_final_obs": done.copy(), "final_info": final_info,
                     "_final_info": done.copy()}  # fmt: skip
            fresh = done.copy()
        obs = self._observe(fresh)
        self._autoreset = done if self.autoreset_mode != AutoresetMode.SAME_STEP else np.zeros(n, bool)
        return obs, rewards, terms, truncs, {**self._infos(infos), **extra}

    def close_extras(self, **kwargs):
        for e in self.envs:
            e.close()
        self._batch = None
