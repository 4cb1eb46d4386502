"""``collect()``: roll a policy out for N episodes and write one Minari dataset, resumably."""

from __future__ import annotations

import json
import math
import re
import shutil
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import atomic_write_bytes, remove_partial
from .episodes import collect_episodes
from .policies import policy_name
from .rollout import VECTORIZATIONS, CollectError, EpisodeRecord
from .writer import IMAGE_ENCODINGS, ShardStore, combine_shards, env_spec_for

__all__ = ["WORK_DIR", "CollectResult", "CollectSettingsError", "collect", "default_dataset_id"]

#: hidden folder under the output root that holds unfinished runs
WORK_DIR = ".dsg-collect"
RUN_FORMAT = "dsg-collect-run"
RUN_VERSION = 1
#: settings a resumed run must share with the run it continues
_FIXED = ("env_id", "env_kwargs", "policy", "seed", "max_episode_steps", "image_encoding", "data_format",
          "dataset_id")  # fmt: skip


@dataclass(frozen=True)
class CollectResult:
    """What :func:`collect` did. ``path``: the dataset folder (``path / "data"`` is Minari's data folder);
    ``new_episodes`` / ``new_transitions`` / ``seconds``: this call only; ``success_rate``: all episodes."""

    path: Path
    dataset_id: str
    episodes: int
    transitions: int
    success_rate: float
    new_episodes: int
    new_transitions: int
    seconds: float

    @property
    def transitions_per_second(self) -> float:
        return self.new_transitions / self.seconds if self.seconds > 0 else float("nan")


def _slug(s: str) -> str:
    return re.sub(r"[^-_\w]+", "_", s).strip("_") or "x"


def default_dataset_id(env_id: str, policy: str) -> str:
    """``<env name>/<policy>-v0``, e.g. ``dsgworld/expert-v0`` (lower case, Minari's id syntax)."""
    env = env_id.split(":")[-1].split("/")[-1]
    env = re.sub(r"-v\d+$", "", env).lower()
    pol = policy.split(":")[-1].split(".")[-1] if ":" in policy else policy
    return f"{_slug(env)}/{_slug(pol).lower()}-v0"


class CollectSettingsError(CollectError):
    """Settings that cannot run (bad env kwargs, unknown policy, an existing output): nothing was written."""


def _check_env_and_policy(env_id: str, env_kwargs: dict, max_episode_steps, policy) -> None:
    """Build one env and the policy from the settings, so that a bad setting fails before any run state exists."""
    from .policies import PolicyError, policy_factory
    from .rollout import make_env

    try:
        env = make_env(env_id, env_kwargs, max_episode_steps)
    except Exception as e:  # any failure of the env's constructor is the settings' fault
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise CollectSettingsError(
            f"cannot make {env_id} with env kwargs {json.dumps(env_kwargs)}: {msg}"
        ) from e
    try:
        policy_factory(policy, env)
    except PolicyError as e:
        raise CollectSettingsError(str(e)) from e
    finally:
        env.close()


class _RunLock:
    """An exclusive lock on one dataset's run (``filelock``; ``OUT/.dsg-collect-<dataset>.lock``), held for the
    whole run; a second run is refused with the holder's process, host and start time (written beside the lock)."""

    def __init__(self, path: Path):
        self.path, self.info = Path(path), Path(f"{path}.json")

    def __enter__(self):
        import os
        import socket

        from filelock import FileLock, Timeout

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.lock = FileLock(str(self.path))
        try:
            self.lock.acquire(timeout=0)
        except Timeout:
            try:
                h = json.loads(self.info.read_text())
                who = f"process {h['pid']} on {h['host']} since {h['started']}"
            except (OSError, ValueError, KeyError):
                who = "another process"
            raise CollectSettingsError(
                f"{self.path.parent} is in use by another dsg-collect run of this dataset ({who}); wait "
                "for it to finish, or stop it first"
            ) from None
        holder = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        }
        atomic_write_bytes(self.info, json.dumps(holder).encode())
        return self

    def __exit__(self, *exc):
        self.info.unlink(missing_ok=True)
        self.lock.release()  # the empty lock file stays: removing it could let two later runs lock two files


def _positive(name: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise CollectSettingsError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


class _Progress:
    def __init__(self, enabled: bool, total: int, done: int, successes: int):
        self.bar = None
        self.total_done, self.succ = done, successes
        self.transitions, self.t0, self.shown = 0, time.monotonic(), 0.0
        if enabled:
            from tqdm.auto import tqdm

            self.bar = tqdm(total=total, initial=done, unit="episode", desc="collect", dynamic_ncols=True)

    def episode(self, rec: EpisodeRecord) -> None:
        self.set_done(self.total_done + 1, self.succ + int(rec.success))

    def set_done(self, done: int, successes: int) -> None:
        if self.bar is not None and done > self.total_done:
            self.bar.update(done - self.total_done)
        self.total_done, self.succ = done, successes
        self._postfix(force=True)

    def steps(self, n: int) -> None:
        if self.transitions == 0:
            self.t0 = time.monotonic()  # rates exclude env start-up
        self.transitions += n
        self._postfix()

    def _postfix(self, force: bool = False) -> None:
        now = time.monotonic()
        if self.bar is None or (not force and now - self.shown < 0.5):
            return
        self.shown = now
        rate = self.transitions / max(now - self.t0, 1e-9)
        sr = self.succ / self.total_done if self.total_done else float("nan")
        self.bar.set_postfix_str(f"rollout {rate:.0f} env steps/s, success {sr:.0%}", refresh=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


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
    interrupted run (same settings; ``episodes`` may grow); ``overwrite=True`` discards an unfinished run and
    replaces an existing dataset. ``backend="ray"`` spreads the episodes over ``ray_workers`` Ray tasks
    (see :mod:`dsg_gym.collect.ray_backend`). Raises :class:`CollectError` (finished episodes are kept);
    ``KeyboardInterrupt`` also keeps them.
    """
    t0 = time.monotonic()
    episodes = _positive("episodes", episodes)
    num_envs = _positive("num_envs", num_envs)
    if vectorization not in VECTORIZATIONS:
        raise CollectSettingsError(f"vectorization must be one of {VECTORIZATIONS}, got {vectorization!r}")
    shard_episodes = _positive("shard_episodes", shard_episodes)
    if max_episode_steps is not None:
        max_episode_steps = _positive("max_episode_steps", max_episode_steps)
    if image_encoding not in IMAGE_ENCODINGS:
        raise CollectSettingsError(f"image_encoding must be one of {IMAGE_ENCODINGS}, got {image_encoding!r}")
    if backend not in ("local", "ray"):
        raise CollectSettingsError(f"backend must be 'local' or 'ray', got {backend!r}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
        raise CollectSettingsError(f"seed must be an integer >= 0, got {seed!r}")
    env_kwargs = dict(env_kwargs or {})
    try:
        env_kwargs = json.loads(json.dumps(env_kwargs))  # JSON-safe (it is recorded and compared on resume)
    except (TypeError, ValueError) as e:
        raise CollectSettingsError(f"env_kwargs must be JSON-serialisable: {e}") from None
    pname = policy_name(policy)
    dataset_id = dataset_id or default_dataset_id(env_id, pname)
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        parse_dataset_id(dataset_id)
    except ValueError as e:
        raise CollectSettingsError(str(e)) from None

    _check_env_and_policy(env_id, env_kwargs, max_episode_steps, policy)  # before anything is written
    out = Path(out)
    target = out / dataset_id
    work = out / WORK_DIR / dataset_id.replace("/", "__")
    with _RunLock(out / f".dsg-collect-{dataset_id.replace('/', '__')}.lock"):
        return _collect_locked(
            out, target, work, t0, env_id=env_id, env_kwargs=env_kwargs, policy=policy, pname=pname,
            episodes=episodes, num_envs=num_envs, vectorization=vectorization, seed=seed, dataset_id=dataset_id,
            max_episode_steps=max_episode_steps, image_encoding=image_encoding, resume=resume, overwrite=overwrite,
            shard_episodes=shard_episodes, flush_seconds=flush_seconds, backend=backend, ray_workers=ray_workers,
            ray_address=ray_address, keep_shards=keep_shards, progress=progress, data_format=data_format,
        )  # fmt: skip


def _collect_locked(out, target, work, t0, *, env_id, env_kwargs, policy, pname, episodes, num_envs, vectorization,
                    seed, dataset_id, max_episode_steps, image_encoding, resume, overwrite, shard_episodes,
                    flush_seconds, backend, ray_workers, ray_address, keep_shards, progress,
                    data_format) -> CollectResult:  # fmt: skip
    """:func:`collect` once the output's lock is held."""
    settings: dict[str, Any] = {
        "format": RUN_FORMAT, "format_version": RUN_VERSION, "env_id": env_id, "env_kwargs": env_kwargs,
        "policy": pname, "seed": None if seed is None else int(seed), "episodes": episodes,
        "max_episode_steps": max_episode_steps, "image_encoding": image_encoding, "data_format": data_format,
        "dataset_id": dataset_id,
    }  # fmt: skip
    if overwrite:
        shutil.rmtree(work, ignore_errors=True)
    elif target.exists():
        if resume and (target / "data" / "metadata.json").exists():
            meta = json.loads((target / "data" / "metadata.json").read_text())
            info = meta.get("dsg_collect", {})
            have = int(meta.get("total_episodes", 0))
            if have != episodes:
                raise CollectSettingsError(
                    f"{target} is a finished dataset of {have} episodes and --resume only continues unfinished "
                    f"runs; to have {episodes} episodes, run again with --episodes {episodes} --overwrite (the "
                    f"same seed gives the same first {min(have, episodes)} episodes) or use another --dataset-id"
                )
            return CollectResult(target, dataset_id, have, int(meta.get("total_steps", 0)),
                                 float(info.get("success_rate", math.nan)), 0, 0, time.monotonic() - t0)  # fmt: skip
        raise CollectSettingsError(
            f"{target} already exists; pass overwrite=True (--overwrite) to replace it"
        )

    run_file = work / "run.json"
    if run_file.exists():
        if not resume:
            raise CollectSettingsError(
                f"an unfinished run is in {work}; pass resume=True (--resume) to continue it or overwrite=True "
                "(--overwrite) to start again"
            )
        try:
            old = json.loads(run_file.read_text())
        except (OSError, ValueError) as e:
            raise CollectError(f"unreadable {run_file}: {e}") from e
        if seed is None:
            settings["seed"] = old.get("seed")
        diff = [k for k in _FIXED if old.get(k) != settings[k]]
        if diff:
            detail = ", ".join(f"{k}: {old.get(k)!r} -> {settings[k]!r}" for k in diff)
            raise CollectSettingsError(
                f"cannot resume {work}: settings differ ({detail}); run with the recorded settings, or "
                "--overwrite to start again"
            )
    else:
        if settings["seed"] is None:
            settings["seed"] = int(np.random.SeedSequence().entropy % (2**63))
        work.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(run_file, json.dumps(settings, indent=1, sort_keys=True).encode())
    if not isinstance(policy, str):
        settings = {**settings, "policy": policy}  # the object itself runs; its name is what is recorded

    store = ShardStore(work / "shards")
    store.clean()
    remove_partial(target.parent, target.name)
    done = store.done()
    todo = [e for e in range(episodes) if e not in done]
    succ0 = sum(int(s.successes[j]) for s, j in done.values() if s.indices[j] < episodes)
    bar = _Progress(progress, episodes, episodes - len(todo), succ0)
    stats = {"episodes": 0, "transitions": 0}
    try:
        if todo and backend == "local":
            stats = collect_episodes(
                settings,
                todo,
                store.root,
                num_envs=num_envs,
                vectorization=vectorization,
                shard_episodes=shard_episodes,
                flush_seconds=flush_seconds,
                on_episode=bar.episode,
                on_steps=bar.steps,
            )
        elif todo:
            from .ray_backend import collect_ray

            stats = collect_ray(settings, todo, store.root, workers=ray_workers, address=ray_address,
                                num_envs=num_envs, shard_episodes=shard_episodes, flush_seconds=flush_seconds,
                                progress=bar, total=episodes)  # fmt: skip
    finally:
        bar.close()

    done = store.done()
    order = list(range(episodes))
    steps = sum(int(done[e][0].steps[done[e][1]]) for e in order)
    succ = sum(int(done[e][0].successes[done[e][1]]) for e in order)
    meta = {
        "algorithm_name": pname,
        "description": f"{pname} policy rolled out in {env_id} by dsg-collect",
        "dsg_collect": {**{k: v for k, v in settings.items() if k != "policy"}, "policy": pname,
                        "success_rate": succ / episodes, "episode_seeds": [int(done[e][0].seeds[done[e][1]])
                                                                            for e in order]},
    }  # fmt: skip
    spec = env_spec_for(env_id, env_kwargs, max_episode_steps)
    aside = None
    if target.exists():  # overwrite: keep the old dataset until the new one is in place
        aside = target.parent / f".{target.name}.old-{time.time_ns()}"
        target.rename(aside)
    try:
        combine_shards(store, order, target, dataset_id=dataset_id, env_spec=spec,
                       jpeg=image_encoding == "jpeg", data_format=data_format, metadata=meta)  # fmt: skip
    except BaseException:
        if aside is not None and not target.exists():
            aside.rename(target)
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)
    if not keep_shards:
        shutil.rmtree(work, ignore_errors=True)
        for d in (work.parent,):
            try:
                d.rmdir()  # only if empty
            except OSError:
                pass
    return CollectResult(target, dataset_id, episodes, steps, succ / episodes, stats["episodes"],
                         stats["transitions"], time.monotonic() - t0)  # fmt: skip
