"""``DSGWorldGoal-v0``: ``DSGWorld-v0`` with the goal-conditioned observation of hindsight relabelling.

The observation is a ``Dict`` of

| key | space | meaning |
| --- | --- | --- |
| ``observation`` | ``Dict`` | ``DSGWorld-v0``'s observation without ``goal`` (what ``obs`` selects) |
| ``achieved_goal`` | ``Box(low, high, (K * 7,), float64)`` | the object poses ``x y z qw qx qy qz``, flattened |
| ``desired_goal`` | ``Box(low, high, (K * 7,), float64)`` | the goal poses, flattened |

Actions, kwargs, reward, success and ``info`` are ``DSGWorld-v0``'s. :meth:`DSGWorldGoalEnv.compute_reward`
gives the env's reward for any achieved and desired goals, batched or single, so a relabelled transition gets
the reward the env would have given: ``-(mean position error + rotation_weight * mean rotation error)``,
``success_bonus`` on success, minus ``collision_penalty`` where ``info["collision"]`` is true.

Learners that take no nested ``Dict`` (Stable-Baselines3) wrap the env in :class:`FlattenGoalObservation`,
which turns ``observation`` into a flat ``Box`` of its non-pixel entries::

    env = FlattenGoalObservation(gym.make("DSGWorldGoal-v0", width=32, height=32, max_episode_steps=50))
    SAC("MultiInputPolicy", env, replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={"copy_info_dict": True}).learn(1000)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..poses import quat_normalize
from .dsg_world import DSGWorldEnv

__all__ = ["GOAL_ENV_ID", "PIXEL_KEYS", "DSGWorldGoalEnv", "FlattenGoalObservation", "goal_rewards"]

GOAL_ENV_ID = "DSGWorldGoal-v0"
#: observation entries that are images
PIXEL_KEYS = ("rgb", "mask", "depth")


def _collisions(info, shape: tuple[int, ...]) -> np.ndarray:
    """``info["collision"]`` as a bool array of ``shape``: ``info`` a dict (one value for all), a sequence or
    array of dicts (one per row), or ``None``; a missing entry counts as no collision."""
    if info is None:
        return np.zeros(shape, bool)
    if isinstance(info, Mapping):
        return np.broadcast_to(np.asarray(bool(info.get("collision", False))), shape)
    flat = [bool(i.get("collision", False)) if isinstance(i, Mapping) else False for i in np.ravel(info)]
    if len(flat) != int(np.prod(shape)):
        raise ValueError(f"compute_reward: {len(flat)} infos for {int(np.prod(shape))} goals")
    return np.array(flat, bool).reshape(shape)


def goal_rewards(achieved, desired, info, k: int, params) -> tuple[np.ndarray, np.ndarray]:
    """``(reward, success)`` of ``DSGWorld-v0`` for flattened poses ``achieved`` and ``desired``
    ``[..., k * 7]``, each ``[...]`` (float64, bool); ``params`` a :class:`~dsg_gym.envs.tasks.TaskParams`.
    Computed with the same operations as the env's own reward, so the numbers are the same."""
    a = np.asarray(achieved, dtype=np.float64)
    g = np.asarray(desired, dtype=np.float64)
    if a.shape != g.shape or a.ndim < 1 or a.shape[-1] != k * 7:
        raise ValueError(f"compute_reward: goals must both be [..., {k * 7}], got {a.shape} and {g.shape}")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(g))):
        raise ValueError("compute_reward: goals contain NaN or Inf")
    a = a.reshape(a.shape[:-1] + (k, 7))
    g = g.reshape(g.shape[:-1] + (k, 7))
    d = a[..., :3] - g[..., :3]
    pe = np.sqrt(np.add.reduce(d * d, axis=-1))
    c = np.abs(np.add.reduce(quat_normalize(a[..., 3:7]) * quat_normalize(g[..., 3:7]), axis=-1))
    re = 2.0 * np.arccos(np.clip(c, 0.0, 1.0))
    success = np.all(pe <= params.position_tolerance, axis=-1) & np.all(
        re <= params.rotation_tolerance, axis=-1
    )
    reward = -(pe.mean(axis=-1) + params.rotation_weight * re.mean(axis=-1))
    reward = reward + np.where(success, params.success_bonus, 0.0)
    reward = reward - np.where(_collisions(info, success.shape), params.collision_penalty, 0.0)
    return reward, success


class DSGWorldGoalEnv(DSGWorldEnv):
    """``DSGWorldGoal-v0`` (see the module docstring): ``DSGWorldEnv`` with the observation ``{observation,
    achieved_goal, desired_goal}`` and ``compute_reward`` / ``compute_terminated`` / ``compute_truncated``;
    the kwargs are ``DSGWorldEnv``'s."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        inner = {key: s for key, s in self.observation_space.spaces.items() if key != "goal"}
        g = self.observation_space["goal"]
        flat = spaces.Box(g.low.reshape(-1), g.high.reshape(-1), (self.K * 7,), np.float64)
        self.observation_space = spaces.Dict(
            {"observation": spaces.Dict(inner), "achieved_goal": flat, "desired_goal": flat}
        )

    def _observe(self, rendered=None) -> dict[str, Any]:
        obs = super()._observe(rendered)
        goal = obs.pop("goal")
        return {
            "observation": obs,
            "achieved_goal": self._poses.reshape(-1).copy(),
            "desired_goal": goal.reshape(-1),
        }

    def compute_reward(self, achieved_goal, desired_goal, info) -> np.ndarray | float:
        """The env's reward for reaching ``achieved_goal`` when ``desired_goal`` is the goal: flattened poses
        ``[K*7]`` (a float back) or ``[..., K*7]`` (an array ``[...]`` back). ``info``: the step's info dict, a
        sequence of them (one per row) or ``None``; its ``collision`` entry subtracts ``collision_penalty``."""
        reward, _ = goal_rewards(achieved_goal, desired_goal, info, self.K, self.task.params)
        return float(reward) if reward.ndim == 0 else reward

    def compute_terminated(self, achieved_goal, desired_goal, info) -> np.ndarray | bool:
        """Success: every object within the position and rotation tolerances (``terminated``), as above."""
        _, success = goal_rewards(achieved_goal, desired_goal, info, self.K, self.task.params)
        return bool(success) if success.ndim == 0 else success

    def compute_truncated(self, achieved_goal, desired_goal, info) -> np.ndarray | bool:
        """Always false: truncation comes from the step count alone."""
        shape = np.shape(achieved_goal)[:-1]
        return False if shape == () else np.zeros(shape, bool)


class FlattenGoalObservation(gym.ObservationWrapper):
    """``DSGWorldGoal-v0`` with ``observation`` as one flat float64 ``Box``: the listed entries of the inner
    observation, flattened and concatenated in order (default: every non-pixel entry, i.e. ``poses``). For
    learners that take no nested ``Dict`` spaces, such as Stable-Baselines3's ``MultiInputPolicy``;
    ``compute_reward`` and the other goal methods stay reachable through ``get_wrapper_attr``."""

    def __init__(self, env: gym.Env, keys: Sequence[str] | None = None):
        super().__init__(env)
        space = env.observation_space
        inner = space.spaces.get("observation") if isinstance(space, spaces.Dict) else None
        if not isinstance(inner, spaces.Dict):
            raise ValueError("FlattenGoalObservation: the env's observation has no Dict entry 'observation'")
        keys = tuple(k for k in inner.spaces if k not in PIXEL_KEYS) if keys is None else tuple(keys)
        bad = [k for k in keys if k not in inner.spaces]
        if not keys or bad:
            raise ValueError(
                f"FlattenGoalObservation: keys {list(keys)} must be entries of the observation "
                f"{list(inner.spaces)} (observe 'poses' for a non-pixel entry)"
            )
        self.keys = keys
        size = sum(int(np.prod(inner.spaces[k].shape)) for k in keys)
        self.observation_space = spaces.Dict(
            {
                "observation": spaces.Box(-np.inf, np.inf, (size,), np.float64),
                "achieved_goal": space.spaces["achieved_goal"],
                "desired_goal": space.spaces["desired_goal"],
            }
        )

    def observation(self, observation):
        inner = observation["observation"]
        flat = np.concatenate([np.asarray(inner[k], np.float64).reshape(-1) for k in self.keys])
        return {
            "observation": flat,
            "achieved_goal": observation["achieved_goal"],
            "desired_goal": observation["desired_goal"],
        }
