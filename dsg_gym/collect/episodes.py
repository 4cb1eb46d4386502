"""``collect_episodes``: run some episodes of a collection run and write them as shards. The local backend
(:func:`dsg_gym.collect.run.collect`) and each Ray worker (:mod:`dsg_gym.collect.ray_backend`) call it."""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from .policies import PolicyError, policy_factory, policy_name
from .rollout import CollectError, EpisodeRecord, make_env, make_vector_env, rollout
from .writer import ShardStore

__all__ = ["collect_episodes"]


def collect_episodes(
    settings: Mapping[str, Any],
    indices: Sequence[int],
    shard_root: Path,
    *,
    num_envs: int = 1,
    vectorization: str = "auto",
    shard_episodes: int = 16,
    flush_seconds: float = 30.0,
    on_episode: Callable[[EpisodeRecord], None] | None = None,
    on_steps: Callable[[int], None] | None = None,
    on_write: Callable[[float], None] | None = None,
) -> dict[str, float]:
    """Run the episodes ``indices`` of a run (``settings``: see :func:`collect`'s ``run.json``) in a vector
    env of ``num_envs`` (``vectorization`` as :func:`~dsg_gym.collect.rollout.make_vector_env`) and write them as
    shards under ``shard_root``: a shard every ``shard_episodes`` finished episodes or ``flush_seconds``, and
    whatever is finished when the run stops for any reason (error, ``KeyboardInterrupt``). ``on_write(s)`` is
    called after each shard write with the seconds it took; ``on_steps(n)`` after each vector step with the
    steps taken, and ``on_steps(0)`` when the rollout starts. Used by the local backend and by each Ray worker.

    Returns ``{"episodes", "transitions", "rollout_seconds", "write_seconds"}``: ``rollout_seconds`` is the
    time in :func:`~dsg_gym.collect.rollout.rollout` (resets, policy and env steps) less the shard writes done
    meanwhile, ``write_seconds`` the time of all shard writes."""
    s = settings
    store = ShardStore(shard_root)
    template = make_env(s["env_id"], s["env_kwargs"], s["max_episode_steps"])
    pending: list[EpisodeRecord] = []
    last = [time.monotonic()]
    stats: dict[str, float] = {"episodes": 0, "transitions": 0, "rollout_seconds": 0.0, "write_seconds": 0.0}

    def flush() -> None:
        if pending:
            t = time.monotonic()
            store.write(pending, observation_space=template.observation_space, action_space=template.action_space,
                        dataset_id=s["dataset_id"], data_format=s["data_format"])  # fmt: skip
            pending.clear()
            dt = time.monotonic() - t
            stats["write_seconds"] += dt
            if on_write is not None:
                on_write(dt)
        last[0] = time.monotonic()

    def episode(rec: EpisodeRecord) -> None:
        pending.append(rec)
        stats["episodes"] += 1
        stats["transitions"] += len(rec)
        if on_episode is not None:
            on_episode(rec)
        if len(pending) >= shard_episodes or time.monotonic() - last[0] >= flush_seconds:
            flush()

    envs = None
    ok = False
    try:
        try:
            make_policy = policy_factory(s["policy"], template)
        except PolicyError as e:
            raise CollectError(str(e)) from e
        envs = make_vector_env(s["env_id"], s["env_kwargs"], num_envs, s["max_episode_steps"], vectorization)
        t0, w0 = time.monotonic(), stats["write_seconds"]
        if on_steps is not None:
            on_steps(0)  # the rollout starts: its rate counts from here, as ``rollout_seconds`` does
        try:
            rollout(envs, indices, s["seed"], make_policy, episode, on_steps=on_steps,
                    policy_label=f"policy {policy_name(s['policy'])!r}")  # fmt: skip
        finally:
            stats["rollout_seconds"] = time.monotonic() - t0 - (stats["write_seconds"] - w0)
        ok = True
    finally:
        try:
            flush()  # keep every finished episode, whatever stopped the run
        finally:
            if envs is not None:
                envs.close(**({} if ok or num_envs == 1 else {"terminate": True}))
            template.close()
    return stats
