"""Stable-Baselines3 on ``DSGWorld-v0``'s own vector env (needs the ``rl`` extra: ``pip install dsg-gym[rl]``).

```python
from stable_baselines3 import PPO
from dsg_gym.envs.sb3 import DSGWorldSB3VecEnv

venv = DSGWorldSB3VecEnv(num_envs=16, width=64, height=64, obs=("rgb", "poses"))
PPO("MultiInputPolicy", venv, n_steps=64).learn(10_000)
```

SB3's ``VecEnv`` resets an env within the step that ends its episode; the adapter runs
:class:`~dsg_gym.envs.dsg_world_vector.DSGWorldVectorEnv` with ``AutoresetMode.SAME_STEP`` and passes the last
observation as ``info["terminal_observation"]`` and ``info["TimeLimit.truncated"]`` as SB3 expects.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv

from .dsg_world_vector import DSGWorldVectorEnv

__all__ = ["DSGWorldSB3VecEnv"]


class DSGWorldSB3VecEnv(VecEnv):
    """``num_envs`` ``DSGWorld-v0`` envs as one Stable-Baselines3 ``VecEnv``; other kwargs go to every env
    (:class:`~dsg_gym.envs.dsg_world.DSGWorldEnv`; ``max_episode_steps`` defaults to 200 as ``gymnasium.make``)."""

    def __init__(self, num_envs: int, **kwargs):
        kwargs["autoreset_mode"] = AutoresetMode.SAME_STEP
        self.venv = DSGWorldVectorEnv(num_envs, **kwargs)
        self._actions: np.ndarray | None = None
        super().__init__(
            self.venv.num_envs, self.venv.single_observation_space, self.venv.single_action_space
        )

    def _split_infos(self, infos: dict[str, Any]) -> list[dict[str, Any]]:
        keys = [k for k in infos if not k.startswith("_") and k not in ("final_obs", "final_info")]
        return [{k: infos[k][i] for k in keys if infos["_" + k][i]} for i in range(self.num_envs)]

    def reset(self):
        seeds = None if all(s is None for s in self._seeds) else list(self._seeds)
        options = self._options[0] if self._options and self._options[0] else None
        obs, infos = self.venv.reset(seed=seeds, options=options)
        self.reset_infos = self._split_infos(infos)
        self._reset_seeds()
        self._reset_options()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        obs, rewards, terms, truncs, infos = self.venv.step(self._actions)
        out = self._split_infos(infos)
        dones = terms | truncs
        for i in np.flatnonzero(dones):
            fin = infos["final_info"]
            out[i] = {k: fin[k][i] for k in fin if not k.startswith("_")}
            out[i]["terminal_observation"] = infos["final_obs"][i]
            out[i]["TimeLimit.truncated"] = bool(truncs[i] and not terms[i])
        return obs, rewards.astype(np.float32), dones, out

    def close(self) -> None:
        self.venv.close()

    def _indices(self, indices) -> list[int]:
        return list(self._get_indices(indices))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self.venv.envs[i], attr_name) for i in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        for i in self._indices(indices):
            setattr(self.venv.envs[i], attr_name, value)

    def env_method(self, method_name: str, *args, indices=None, **kwargs) -> list[Any]:
        return [getattr(self.venv.envs[i], method_name)(*args, **kwargs) for i in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        frames = self.venv.render()
        return list(frames) if frames is not None else [None] * self.num_envs
