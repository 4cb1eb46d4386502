"""``collect()``: roll a policy out for N episodes and write one Minari dataset, resumably.

Order of work: check every setting and build one env and the policy (:mod:`.settings`; a bad setting
changes nothing on disk), take the dataset's lock (:mod:`.lock`), set up the run's state (:mod:`.state`:
new, continued or extended), collect the missing episodes as shards (:mod:`.episodes`, :mod:`.ray_backend`),
combine them into the dataset (:mod:`.writer`) and remove the shards.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..io.atomic import remove_partial
from .episodes import collect_episodes
from .lock import RunLock
from .progress import Progress
from .rollout import CollectError, CollectSettingsError
from .settings import check_env_and_policy, check_settings, default_dataset_id
from .state import discard_work, prepare_run
from .writer import combine_shards, env_spec_for

__all__ = ["WORK_DIR", "CollectResult", "CollectSettingsError", "collect", "default_dataset_id"]

#: hidden folder under the output root that holds unfinished runs
WORK_DIR = ".dsg-collect"


@dataclass(frozen=True)
class CollectResult:
    """What :func:`collect` did. ``path``: the dataset folder (``path / "data"`` is Minari's data folder);
    ``episodes`` / ``transitions`` / ``success_rate``: the whole dataset; ``new_episodes`` /
    ``new_transitions`` / ``seconds``: this call only, ``seconds`` from start to end (env start-up and
    dataset writes included); ``rollout_seconds``: this call's time in the rollout (resets, policy and env
    steps; shard writes excluded; on Ray the longest task's)."""

    path: Path
    dataset_id: str
    episodes: int
    transitions: int
    success_rate: float
    new_episodes: int
    new_transitions: int
    seconds: float
    rollout_seconds: float = math.nan

    @property
    def transitions_per_second(self) -> float:
        """New transitions per second of the whole call (start-up and dataset writes included)."""
        return self.new_transitions / self.seconds if self.seconds > 0 else math.nan

    @property
    def episodes_per_second(self) -> float:
        """New episodes per second of the whole call (start-up and dataset writes included)."""
        return self.new_episodes / self.seconds if self.seconds > 0 else math.nan

    @property
    def rollout_steps_per_second(self) -> float:
        """New env steps (transitions) per second of rollout time: the speed of policy and env alone."""
        return self.new_transitions / self.rollout_seconds if self.rollout_seconds > 0 else math.nan


def collect(
    out,
    *,
    env_id: str = "DSGWorld-v0",
    env_kwargs: Mapping[str, Any] | None = None,
    policy: str | Callable = "random",
    episodes: int = 10,
    num_envs: int = 1,
    vectorization: str = "auto",
    seed: int | None = None,
    dataset_id: str | None = None,
    max_episode_steps: int | None = None,
    image_encoding: str = "raw",
    resume: bool = False,
    overwrite: bool = False,
    shard_episodes: int = 16,
    flush_seconds: float = 30.0,
    backend: str = "local",
    ray_workers: int | None = None,
    ray_address: str | None = None,
    keep_shards: bool = False,
    progress: bool = False,
    data_format: str = "hdf5",
) -> CollectResult:
    """Roll ``policy`` out for ``episodes`` episodes and write the Minari dataset ``out/<dataset_id>``.

    ``out`` is a Minari datasets root: ``MINARI_DATASETS_PATH=out`` then ``minari.load_dataset(dataset_id)``
    (default id ``<env>/<policy>-v0``, e.g. ``dsgworld/expert-v0``). ``policy``: ``"random"``, ``"expert"``,
    ``"module:callable"`` or a callable ``obs -> action``. ``num_envs`` > 1 runs the env's own vector env (one process;
    ``DSGWorld-v0`` has one) or, for ``vectorization="async"`` or an env without one, an ``AsyncVectorEnv``; the
    episodes are the same either way.
    ``seed``: base seed (episode ``e`` resets with :func:`~dsg_gym.collect.rollout.episode_seed`; ``None``:
    a random one, recorded). ``image_encoding``: ``"raw"`` (lossless, default) or ``"jpeg"`` (Minari's lossy
    JPEG for uint8 RGB). Finished episodes are kept in shards while running; ``resume=True`` continues an
    interrupted run (same settings; ``episodes`` may grow) or adds episodes to a finished dataset (same
    settings, more ``episodes``: the result equals an uninterrupted run of all of them); ``overwrite=True``
    discards an unfinished run and replaces an existing dataset. ``backend="ray"`` spreads the episodes over
    ``ray_workers`` Ray tasks (see :mod:`dsg_gym.collect.ray_backend`).

    One run per dataset at a time: the run holds the dataset's lock (:mod:`dsg_gym.collect.lock`) throughout.
    Raises :class:`CollectSettingsError` when the run is refused before it starts (a bad setting, an env that
    cannot be built from ``env_kwargs``, an existing dataset or unfinished run, the lock held by another run):
    nothing on disk changed. Other :class:`CollectError` s stop a started run; its finished episodes are kept,
    as on ``KeyboardInterrupt``.
    """
    t0 = time.monotonic()
    settings = check_settings(
        out, env_id=env_id, env_kwargs=env_kwargs, policy=policy, episodes=episodes, seed=seed,
        dataset_id=dataset_id, max_episode_steps=max_episode_steps, image_encoding=image_encoding,
        data_format=data_format, num_envs=num_envs, vectorization=vectorization, shard_episodes=shard_episodes,
        backend=backend,
    )  # fmt: skip
    check_env_and_policy(env_id, settings["env_kwargs"], settings["max_episode_steps"], policy)
    out = Path(out)
    dataset_id = settings["dataset_id"]
    target = out / dataset_id
    work = out / WORK_DIR / dataset_id.replace("/", "__")
    with RunLock(target):
        state = prepare_run(target, work, settings, resume=resume, overwrite=overwrite)
        settings = state.settings
        if state.finished is not None:  # resume of a finished dataset with the requested episodes
            meta = state.finished
            _remove_if_empty(work.parent)
            return CollectResult(target, dataset_id, int(meta["total_episodes"]), int(meta.get("total_steps", 0)),
                                 float(meta["dsg_collect"].get("success_rate", math.nan)), 0, 0,
                                 time.monotonic() - t0)  # fmt: skip
        run = {**settings, "policy": policy}  # the policy object itself runs; its name is what is recorded
        stats = _collect_missing(run, state.store, t0, num_envs=int(num_envs), vectorization=vectorization,
                                 shard_episodes=int(shard_episodes), flush_seconds=flush_seconds, backend=backend,
                                 ray_workers=ray_workers, ray_address=ray_address, progress=progress)  # fmt: skip
        return _finish(target, work, settings, state.store, stats, t0, keep_shards=keep_shards)


def _collect_missing(run: dict[str, Any], store, t0: float, *, num_envs, vectorization, shard_episodes,
                     flush_seconds, backend, ray_workers, ray_address, progress) -> dict[str, float]:  # fmt: skip
    """Collect the run's episodes that no shard holds yet; returns the collection's stats."""
    store.clean()
    episodes = run["episodes"]
    done = store.done()
    todo = [e for e in range(episodes) if e not in done]
    succ0 = sum(int(s.successes[j]) for e, (s, j) in done.items() if e < episodes)
    bar = Progress(progress, episodes, episodes - len(todo), succ0, t0)
    stats: dict[str, float] = {"episodes": 0, "transitions": 0, "rollout_seconds": 0.0, "write_seconds": 0.0}
    try:
        if todo and backend == "local":
            stats = collect_episodes(run, todo, store.root, num_envs=num_envs, vectorization=vectorization,
                                     shard_episodes=shard_episodes, flush_seconds=flush_seconds,
                                     on_episode=bar.episode, on_steps=bar.steps, on_write=bar.wrote)  # fmt: skip
        elif todo:
            from .ray_backend import collect_ray

            stats = collect_ray(run, todo, store.root, workers=ray_workers, address=ray_address,
                                num_envs=num_envs, shard_episodes=shard_episodes, flush_seconds=flush_seconds,
                                progress=bar, total=episodes)  # fmt: skip
    finally:
        bar.close()
    return stats


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:  # not empty (other datasets' runs), or not there
        pass


def _finish(target: Path, work: Path, settings: dict[str, Any], store, stats, t0: float, *,
            keep_shards: bool) -> CollectResult:  # fmt: skip
    """Combine the shards into the dataset ``target`` (replacing what is there) and remove the work folder."""
    pname, env_id, episodes = settings["policy"], settings["env_id"], settings["episodes"]
    done = store.done()
    order = list(range(episodes))
    missing = [e for e in order if e not in done]
    if missing:
        raise CollectError(
            f"{len(missing)} episodes are still missing (first {missing[:5]}); re-run with --resume"
        )
    recs = [(s.seeds[j], s.steps[j], s.successes[j]) for s, j in (done[e] for e in order)]
    steps = sum(int(r[1]) for r in recs)
    succ = sum(int(r[2]) for r in recs)
    meta = {
        "algorithm_name": pname,
        "description": f"{pname} policy rolled out in {env_id} by dsg-collect",
        "dsg_collect": {**settings, "success_rate": succ / episodes, "episode_seeds": [int(r[0]) for r in recs],
                        "episode_steps": [int(r[1]) for r in recs],
                        "episode_success": [bool(r[2]) for r in recs]},
    }  # fmt: skip
    spec = env_spec_for(env_id, settings["env_kwargs"], settings["max_episode_steps"])
    remove_partial(target.parent, target.name)
    combine_shards(store, order, target, dataset_id=settings["dataset_id"], env_spec=spec,
                   jpeg=settings["image_encoding"] == "jpeg", data_format=settings["data_format"], metadata=meta,
                   replace=True)  # fmt: skip
    if not keep_shards:
        discard_work(work)
        _remove_if_empty(work.parent)
    return CollectResult(target, settings["dataset_id"], episodes, steps, succ / episodes, int(stats["episodes"]),
                         int(stats["transitions"]), time.monotonic() - t0,
                         float(stats["rollout_seconds"]))  # fmt: skip
