"""Vectorised rollouts: one Gymnasium vector env, one episode per slot at a time, per-episode buffers.

Episodes are numbered ``0 .. N-1``; episode ``e`` always starts from ``reset(seed=episode_seed(base, e))``
and the built-in policies are re-seeded with the same number, so an episode's data depends only on
``(base seed, e, policy)``: not on the number of envs, the order episodes finish in, interruptions or the
machine that ran it (Ray workers).

The vector env runs with ``autoreset_mode=DISABLED``: when a slot's episode ends (``terminated`` or
``truncated``) the loop resets exactly that slot (``options={"reset_mask": ...}``) with the next episode's
seed, so every stored episode has ``T`` actions/rewards and ``T + 1`` observations (reset observation
first, the final observation last) and no transition ever crosses an episode boundary. Slots without work
left are stepped with zero actions and ignored.
"""

from __future__ import annotations

import copy
import functools
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import gymnasium as gym
import numpy as np

__all__ = [
    "DEFAULT_INFO_KEYS",
    "CollectError",
    "CollectSettingsError",
    "EpisodeRecord",
    "episode_seed",
    "make_env",
    "make_vector_env",
    "rollout",
]

#: ``info`` entries stored with every step (those the env provides; fixed shapes within an episode)
DEFAULT_INFO_KEYS = ("success", "collision", "rejected", "position_errors", "rotation_errors")


class CollectError(RuntimeError):
    """Collection stopped: a bad policy, a bad action, an env failure or an unusable output folder. Episodes
    finished before the error are kept (see :func:`dsg_gym.collect.collect`)."""


class CollectSettingsError(CollectError):
    """A run refused before it starts (bad settings, an existing output, a run in progress on the same
    dataset): nothing on disk was changed."""


def episode_seed(base_seed: int, index: int) -> int:
    """The reset seed of episode ``index`` of a run with ``base_seed`` (a 63-bit integer)."""
    state = np.random.SeedSequence([int(base_seed), int(index)]).generate_state(2, np.uint32)
    return int((int(state[0]) << 31) ^ int(state[1]))


@dataclass
class EpisodeRecord:
    """One finished episode: ``T`` steps, observations ``[T + 1, ...]`` per key, infos ``[T + 1, ...]``."""

    index: int
    seed: int
    observations: dict[str, np.ndarray] | np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    infos: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.rewards)

    @property
    def success(self) -> bool:
        """Ended by termination (the task's success for ``DSGWorld-v0``), or ``info["success"]`` at the end."""
        if "success" in self.infos:
            return bool(self.infos["success"][-1])
        return bool(self.terminations[-1]) if len(self) else False


def make_env(env_id: str, env_kwargs: Mapping[str, Any], max_episode_steps: int | None) -> gym.Env:
    """``gymnasium.make(env_id, **env_kwargs)`` with ``dsg_gym`` registered (also in spawned workers)."""
    import dsg_gym  # noqa: F401  (registers DSGWorld-v0)

    kw = dict(env_kwargs)
    if max_episode_steps is not None:
        kw["max_episode_steps"] = int(max_episode_steps)  # gymnasium.make: the TimeLimit
    return gym.make(env_id, **kw)


VECTORIZATIONS = ("auto", "own", "async")


def make_vector_env(
    env_id: str,
    env_kwargs: Mapping[str, Any],
    num_envs: int,
    max_episode_steps: int | None = None,
    vectorization: str = "auto",
) -> gym.vector.VectorEnv:
    """A vector env with autoreset disabled: a ``SyncVectorEnv`` for one env; for more, the env's own vector env
    (one process, e.g. ``DSGWorld-v0``'s batch of envs) when it has one (``"auto"``, ``"own"``), else an
    ``AsyncVectorEnv`` (subprocesses, shared memory; ``"async"``). Every choice gives the same episodes."""
    if vectorization not in VECTORIZATIONS:
        raise ValueError(f"vectorization must be one of {VECTORIZATIONS}, got {vectorization!r}")
    import dsg_gym  # noqa: F401  (registers DSGWorld-v0)

    fn = functools.partial(make_env, env_id, dict(env_kwargs), max_episode_steps)
    mode = gym.vector.AutoresetMode.DISABLED
    if num_envs == 1:
        return gym.vector.SyncVectorEnv([fn], autoreset_mode=mode)
    own = env_id in gym.registry and gym.registry[env_id].vector_entry_point is not None
    if vectorization == "own" and not own:
        raise ValueError(f"{env_id} has no vector env of its own; use vectorization 'async'")
    if own and vectorization != "async":
        kw = dict(env_kwargs)
        if max_episode_steps is not None:
            kw["max_episode_steps"] = int(max_episode_steps)
        return gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                            autoreset_mode=mode, **kw)  # fmt: skip
    return gym.vector.AsyncVectorEnv([fn] * num_envs, shared_memory=True, autoreset_mode=mode)


def _slot(tree, i: int):
    if isinstance(tree, Mapping):
        return {k: _slot(v, i) for k, v in tree.items()}
    if isinstance(tree, tuple):
        return tuple(_slot(v, i) for v in tree)
    return np.array(tree[i], copy=True)


def _stack(items: list):
    first = items[0]
    if isinstance(first, Mapping):
        return {k: _stack([it[k] for it in items]) for k in first}
    if isinstance(first, tuple):
        return tuple(_stack([it[j] for it in items]) for j in range(len(first)))
    return np.stack(items)


def _slot_info(info: Mapping[str, Any], i: int, keys: Sequence[str]) -> dict[str, np.ndarray]:
    out = {}
    for k in keys:
        if k in info and bool(np.asarray(info.get("_" + k, np.ones(i + 1, bool)))[i]):
            v = np.asarray(info[k][i])
            if v.dtype != object:
                out[k] = v.copy()
    return out


class _Buffer:
    def __init__(self, index: int, seed: int, obs, info: dict[str, np.ndarray]):
        self.index, self.seed = index, seed
        self.obs, self.infos = [obs], [info]
        self.actions: list[np.ndarray] = []
        self.rewards: list[float] = []
        self.terms: list[bool] = []
        self.truncs: list[bool] = []

    def add(self, action, obs, reward, term, trunc, info) -> None:
        self.actions.append(action)
        self.obs.append(obs)
        self.rewards.append(reward)
        self.terms.append(bool(term))
        self.truncs.append(bool(trunc))
        self.infos.append(info)

    def record(self) -> EpisodeRecord:
        keys = set(self.infos[0])
        infos = {}
        for k in sorted(keys):
            vals = [inf.get(k) for inf in self.infos]
            if any(v is None for v in vals) or len({(v.shape, v.dtype) for v in vals}) != 1:
                continue  # an entry that is not present (with one shape) at every step is not stored
            infos[k] = np.stack(vals)
        return EpisodeRecord(
            index=self.index,
            seed=self.seed,
            observations=_stack(self.obs),
            actions=np.stack(self.actions),
            rewards=np.asarray(self.rewards, dtype=np.float64),
            terminations=np.asarray(self.terms, dtype=bool),
            truncations=np.asarray(self.truncs, dtype=bool),
            infos=infos,
        )


def _check_action(action, space: gym.spaces.Box, where: str) -> np.ndarray:
    try:
        a = np.asarray(action)
        if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
            raise TypeError(f"not numeric ({a.dtype})")
        a = a.astype(space.dtype)
    except (TypeError, ValueError) as e:
        raise CollectError(
            f"{where}: the policy returned a bad action ({type(action).__name__}: {e})"
        ) from None
    if a.shape != space.shape:
        raise CollectError(
            f"{where}: the policy returned an action of shape {a.shape}, expected {space.shape}"
        )
    if not np.all(np.isfinite(a)):
        raise CollectError(f"{where}: the policy returned an action with NaN or Inf: {a}")
    if np.any(a < space.low) or np.any(a > space.high):
        raise CollectError(
            f"{where}: the policy returned an action outside the action space [{space.low.min()}, "
            f"{space.high.max()}] (max |a| = {np.abs(a).max():.6g}); clip it in the policy"
        )
    return a


def rollout(
    envs: gym.vector.VectorEnv,
    indices: Iterable[int],
    base_seed: int,
    make_policy: Callable[[], Callable],
    on_episode: Callable[[EpisodeRecord], None],
    *,
    on_steps: Callable[[int], None] | None = None,
    info_keys: Sequence[str] = DEFAULT_INFO_KEYS,
    policy_label: str = "policy",
) -> int:
    """Run the episodes ``indices`` in ``envs`` (made by :func:`make_vector_env`), calling ``on_episode``
    with each finished :class:`EpisodeRecord` (in the order they finish) and ``on_steps(n)`` after every
    vector step with the number of transitions it added. Returns the number of transitions.

    A policy that raises, or returns an action that is not in the action space (wrong shape, NaN/Inf,
    outside the bounds), and an env that raises stop the run with :class:`CollectError`; episodes passed to
    ``on_episode`` before that stay valid. ``KeyboardInterrupt`` propagates unchanged.
    """
    space = envs.single_action_space
    if not isinstance(space, gym.spaces.Box):
        raise CollectError(f"only Box action spaces are supported, got {space}")
    n = envs.num_envs
    queue = deque(int(e) for e in indices)
    policies = [make_policy() for _ in range(n)]
    bufs: list[_Buffer | None] = [None] * n
    total = 0

    def assign(mask: np.ndarray) -> list[int | None]:
        seeds: list[int | None] = [None] * n
        for i in np.flatnonzero(mask):
            if queue:
                e = queue.popleft()
                seeds[i] = episode_seed(base_seed, e)
                bufs[i] = _Buffer(e, seeds[i], None, {})
            else:
                bufs[i] = None
                seeds[i] = 0  # idle slot: any valid episode, never recorded
        return seeds

    def start(mask: np.ndarray, obs, info) -> None:
        for i in np.flatnonzero(mask):
            b = bufs[i]
            if b is None:
                continue
            b.obs, b.infos = [_slot(obs, i)], [_slot_info(info, i, info_keys)]
            reset = getattr(policies[i], "reset", None)
            if callable(reset):
                try:
                    reset(b.seed)
                except Exception as e:
                    raise CollectError(
                        f"{policy_label}.reset raised at episode {b.index}: {type(e).__name__}: {e}"
                    ) from e

    mask = np.ones(n, dtype=bool)
    seeds = assign(mask)
    try:
        obs, info = envs.reset(seed=seeds)
    except Exception as e:
        raise CollectError(f"env reset failed: {type(e).__name__}: {e}") from e
    start(mask, obs, info)
    while any(b is not None for b in bufs):
        actions = np.zeros((n, *space.shape), dtype=space.dtype)
        for i, b in enumerate(bufs):
            if b is None:
                continue
            where = f"episode {b.index} step {len(b.actions)}"
            try:
                a = policies[i](copy.deepcopy(b.obs[-1]))  # the stored observation stays intact
            except (KeyboardInterrupt, CollectError):
                raise
            except Exception as e:
                raise CollectError(f"{where}: {policy_label} raised {type(e).__name__}: {e}") from e
            actions[i] = _check_action(a, space, where)
        try:
            obs, rew, term, trunc, info = envs.step(actions)
        except Exception as e:
            raise CollectError(f"env step failed: {type(e).__name__}: {e}") from e
        done = np.zeros(n, dtype=bool)
        stepped = 0
        for i, b in enumerate(bufs):
            if b is None:
                continue
            b.add(
                actions[i].copy(),
                _slot(obs, i),
                float(rew[i]),
                term[i],
                trunc[i],
                _slot_info(info, i, info_keys),
            )
            stepped += 1
            if term[i] or trunc[i]:
                done[i] = True
                on_episode(b.record())
        total += stepped
        if on_steps is not None:
            on_steps(stepped)
        if done.any():
            seeds = assign(done)
            try:
                obs, info = envs.reset(seed=seeds, options={"reset_mask": done})
            except Exception as e:
                raise CollectError(f"env reset failed: {type(e).__name__}: {e}") from e
            start(done, obs, info)
    return total
