"""Scale-out collection on Ray (optional extra ``pip install 'dsg-gym[ray]'``).

The episodes still to collect are split into contiguous blocks, one Ray task per block (``num_cpus`` =
envs per task). Each task builds its own env(s) and policy and writes its own shard datasets (Minari data
folders, the same format as the local backend) into the run's shard folder; the driver shows progress by
watching that folder and combines all shards into the final dataset when every task is done. Because an
episode's data depends only on (seed, episode index, policy), the result equals a local run bit for bit.

The output folder must be visible to every worker under the same path: a local folder for a single-machine
Ray instance (``ray.init(num_cpus=2)``), a shared file system on a cluster (``address="auto"``). A failed task
stops the run with :class:`~dsg_gym.collect.rollout.CollectError`; the shards every task finished are kept
and ``resume=True`` collects only what is missing (on either backend).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from .episodes import collect_episodes
from .rollout import CollectError
from .writer import ShardStore

__all__ = ["collect_ray", "import_ray"]


def import_ray():
    try:
        import ray
    except ImportError as e:
        raise CollectError(
            "backend 'ray' needs Ray: pip install 'dsg-gym[ray]' (or pip install 'ray>=2.9')"
        ) from e
    return ray


def _run_block(settings: Mapping[str, Any], indices: list[int], shard_root: str, num_envs: int,
               shard_episodes: int, flush_seconds: float) -> dict[str, int]:  # fmt: skip
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    import numba

    # the task holds num_envs CPUs: a single env renders on that many threads (with more envs the rendering
    # happens in the vector env's worker processes, single-threaded; dsg_gym.splat.threads)
    numba.set_num_threads(max(1, min(num_envs, numba.config.NUMBA_NUM_THREADS)))
    return collect_episodes(settings, indices, Path(shard_root), num_envs=num_envs, shard_episodes=shard_episodes,
                            flush_seconds=flush_seconds)  # fmt: skip


def _blocks(todo: Sequence[int], n: int) -> list[list[int]]:
    n = max(1, min(n, len(todo)))
    size, extra = divmod(len(todo), n)
    out, start = [], 0
    for i in range(n):
        stop = start + size + (i < extra)
        out.append([int(e) for e in todo[start:stop]])
        start = stop
    return out


def collect_ray(
    settings: Mapping[str, Any],
    todo: Sequence[int],
    shard_root: Path,
    *,
    workers: int | None = None,
    address: str | None = None,
    num_envs: int = 1,
    shard_episodes: int = 16,
    flush_seconds: float = 30.0,
    progress=None,
    total: int | None = None,
) -> dict[str, int]:
    """Collect the episodes ``todo`` with Ray tasks writing shards under ``shard_root``.

    Connects to a running Ray instance (``address``, or one already initialised in this process) or starts
    a local one with ``workers`` CPUs (default: all). ``workers`` tasks (default: the cluster's CPUs /
    ``num_envs``) each run ``num_envs`` envs. Returns ``{"episodes", "transitions", "rollout_seconds",
    "write_seconds"}`` as :func:`~dsg_gym.collect.episodes.collect_episodes` does, ``rollout_seconds`` being
    the longest task's (the tasks run side by side).
    """
    ray = import_ray()
    started = False
    if not ray.is_initialized():
        kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False, "logging_level": "ERROR"}
        if address is None:
            kw["num_cpus"] = workers
        ray.init(address=address, **kw)
        started = True
    try:
        cpus = int(ray.cluster_resources().get("CPU", 1))
        n = workers if workers is not None else max(1, cpus // max(num_envs, 1))
        task = ray.remote(num_cpus=num_envs, max_retries=0)(_run_block)
        refs = [
            task.remote(dict(settings), block, str(shard_root), num_envs, shard_episodes, flush_seconds)
            for block in _blocks(todo, n)
        ]
        store = ShardStore(shard_root)
        stats: dict[str, float] = {
            "episodes": 0,
            "transitions": 0,
            "rollout_seconds": 0.0,
            "write_seconds": 0.0,
        }
        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=len(pending), timeout=1.0)
                for r in ready:
                    try:
                        got = ray.get(r)
                    except Exception as e:
                        cause = getattr(e, "cause", None) or e
                        raise CollectError(f"a Ray worker failed: {type(cause).__name__}: {cause}") from e
                    stats["episodes"] += got["episodes"]
                    stats["transitions"] += got["transitions"]
                    stats["write_seconds"] += got["write_seconds"]
                    # the tasks roll out side by side: the run's rollout time is the longest task's
                    stats["rollout_seconds"] = max(stats["rollout_seconds"], got["rollout_seconds"])
                if progress is not None:
                    done = store.done()
                    succ = sum(int(s.successes[j]) for s, j in done.values())
                    progress.set_done(min(len(done), total or len(done)), succ)
        except BaseException:
            for r in pending:
                ray.cancel(r, force=True)
            raise
        return stats
    finally:
        if started:
            ray.shutdown()
            time.sleep(0.1)
