"""The on-disk state of a collection run, set up once the run's lock is held.

Three cases, decided from what is in the output folder and from ``resume`` / ``overwrite``:

- a **new run** (nothing there, or ``overwrite``): the work folder starts empty with a fresh ``run.json``;
- the **continuation** of an unfinished run (``run.json`` and at least one finished shard, ``resume``): the
  settings must match ``run.json``; ``episodes`` may change;
- the **extension** of a finished dataset (``resume`` with more ``episodes`` than it holds): the settings must
  match those recorded in the dataset; the dataset becomes the run's first shard
  (:meth:`~dsg_gym.collect.writer.ShardStore.adopt`) and only the episodes after it are collected, so the
  result equals an uninterrupted run of all the episodes.

A work folder without finished episodes holds nothing worth keeping: any command starts afresh there. A
work folder is removed by renaming it to a hidden temporary first (:func:`discard_work`), so a run killed
meanwhile leaves it whole or gone, never a shard without its data.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import TMP_TAG, atomic_write_bytes, remove_partial
from .rollout import CollectSettingsError, EpisodeRecord, episode_seed
from .settings import RUN_FORMAT, RUN_VERSION
from .writer import ShardStore

__all__ = ["FIXED", "RunState", "discard_work", "finished_dataset", "prepare_run"]

#: settings a continued or extended run must share with what it continues
FIXED = ("env_id", "env_kwargs", "policy", "seed", "max_episode_steps", "image_encoding", "data_format",
         "dataset_id")  # fmt: skip


@dataclass
class RunState:
    """``settings``: the run's (seed resolved); ``store``: its shards; ``finished``: the metadata of the
    dataset when it already holds exactly the requested episodes (nothing to do)."""

    settings: dict[str, Any]
    store: ShardStore
    finished: dict[str, Any] | None = None


def discard_work(work: Path) -> None:
    """Remove the work folder ``work`` (the caller holds the run's lock): renamed to a hidden temporary, then
    deleted; a temporary left by a killed run is deleted by the next :func:`prepare_run`."""
    work = Path(work)
    if work.exists():
        gone = work.parent / f".{work.name}{TMP_TAG}{os.getpid()}-discarded-{uuid.uuid4().hex[:8]}"
        os.replace(work, gone)
        shutil.rmtree(gone, ignore_errors=True)


def _diff(old: dict, new: dict) -> str:
    return ", ".join(f"{k}: {old.get(k)!r} -> {new[k]!r}" for k in FIXED if old.get(k) != new[k])


def finished_dataset(target: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(metadata, metadata["dsg_collect"])`` of the finished dataset folder ``target``."""
    path = Path(target) / "data" / "metadata.json"
    try:
        meta = json.loads(path.read_text())
        info = meta["dsg_collect"]
        int(meta["total_episodes"])
        if not isinstance(info, dict):
            raise TypeError("dsg_collect is not a mapping")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise CollectSettingsError(
            f"{target} is not a dataset written by dsg-collect ({type(e).__name__}: {e}); pass --overwrite to "
            "replace it or choose another --dataset-id"
        ) from None
    return meta, info


def _episode_records(target: Path, info: dict, have: int) -> tuple[list[int], list[bool]]:
    """Per-episode steps and successes of a finished dataset: recorded in its metadata, else read back."""
    steps, succ = info.get("episode_steps"), info.get("episode_success")
    if isinstance(steps, list) and isinstance(succ, list) and len(steps) == len(succ) == have:
        return [int(v) for v in steps], [bool(v) for v in succ]
    import minari

    ds = minari.MinariDataset(Path(target) / "data")
    steps, succ = [], []
    for ep in ds.iterate_episodes():
        infos = {"success": ep.infos["success"]} if ep.infos and "success" in ep.infos else {}
        rec = EpisodeRecord(0, 0, {}, ep.actions, ep.rewards, ep.terminations, ep.truncations, infos)
        steps.append(len(rec))
        succ.append(rec.success)
    return steps, succ


def _extension(target: Path, settings: dict[str, Any]) -> tuple[dict[str, Any] | None, int, dict | None]:
    """Check the finished dataset ``target`` against ``settings`` (its seed is taken when ``settings`` has
    none): ``(metadata, episodes it holds, per-episode records to adopt or None when nothing is to add)``."""
    meta, info = finished_dataset(target)
    if settings["seed"] is None:
        settings["seed"] = info.get("seed")
    diff = _diff(info, settings)
    if diff:
        raise CollectSettingsError(
            f"cannot add episodes to {target}: settings differ ({diff}); run with its settings, or pass "
            "--overwrite to replace it"
        )
    have, want = int(meta["total_episodes"]), settings["episodes"]
    if have == want:
        return meta, have, None
    if have > want:
        raise CollectSettingsError(
            f"{target} already holds {have} episodes, more than --episodes {want}; --resume never removes "
            f"episodes: pass --overwrite to write a {want}-episode dataset"
        )
    if settings["image_encoding"] != "raw":
        raise CollectSettingsError(
            f"cannot add episodes to {target}: its images are JPEG-encoded and would be encoded a second time; "
            f"pass --overwrite to collect all {want} episodes"
        )
    seeds = info.get("episode_seeds")
    if seeds != [episode_seed(settings["seed"], e) for e in range(have)]:
        raise CollectSettingsError(
            f"cannot add episodes to {target}: its recorded episode seeds do not follow its base seed; pass "
            "--overwrite to replace it"
        )
    steps, succ = _episode_records(target, info, have)
    return meta, have, {"seeds": seeds, "steps": steps, "successes": succ}


def _never_shrink(target: Path, settings: dict[str, Any]) -> None:
    """Refuse to replace a finished dataset of this run's settings by one with fewer episodes (a run that
    ended its combining but not its clean-up, resumed with a smaller ``episodes``)."""
    if not target.exists():
        return
    try:
        meta, info = finished_dataset(target)
    except CollectSettingsError:
        return  # not this run's dataset: it is being replaced (--overwrite)
    have = int(meta["total_episodes"])
    if not _diff(info, settings) and have > settings["episodes"]:
        raise CollectSettingsError(
            f"{target} already holds {have} episodes, more than --episodes {settings['episodes']}; --resume "
            f"never removes episodes: pass --overwrite to write a {settings['episodes']}-episode dataset"
        )


def prepare_run(
    target: Path, work: Path, settings: dict[str, Any], *, resume: bool, overwrite: bool
) -> RunState:
    """Set up the work folder ``work`` of the run that writes the dataset folder ``target`` (see the module
    docstring); the caller holds the run's lock. Raises :class:`CollectSettingsError` (nothing changed) when
    the run must not start."""
    settings = dict(settings)
    remove_partial(work.parent, work.name)  # a work folder a killed run was discarding
    run_file = work / "run.json"
    store = ShardStore(work / "shards")
    adopt = None
    if overwrite:
        pass  # a new run; the dataset is replaced at the end
    elif run_file.exists() and store.shards():
        if not resume:
            raise CollectSettingsError(
                f"an unfinished run of this dataset is in {work}; pass --resume to continue it or --overwrite "
                "to start again"
            )
        try:
            old = json.loads(run_file.read_text())
            if old.get("format") != RUN_FORMAT or old.get("format_version") != RUN_VERSION:
                raise ValueError(f"not a {RUN_FORMAT} version {RUN_VERSION} file")
        except (OSError, ValueError, AttributeError) as e:
            raise CollectSettingsError(
                f"unreadable {run_file} ({e}); pass --overwrite to start again"
            ) from None
        if settings["seed"] is None:
            settings["seed"] = old.get("seed")
        diff = _diff(old, settings)
        if diff:
            raise CollectSettingsError(
                f"cannot resume the run in {work}: settings differ ({diff}); run with the recorded settings, or "
                "pass --overwrite to start again"
            )
        _never_shrink(target, settings)
        atomic_write_bytes(run_file, json.dumps(settings, indent=1, sort_keys=True).encode())
        return RunState(settings, store)
    elif target.exists():
        if not resume:
            raise CollectSettingsError(
                f"{target} already exists; pass --overwrite to replace it, or --resume with more --episodes to "
                "add episodes to it"
            )
        meta, _, adopt = _extension(target, settings)
        if adopt is None:
            return RunState(settings, store, finished=meta)
    # a new run or an extension: whatever the work folder holds has no finished episodes of this run
    discard_work(work)
    if settings["seed"] is None:
        settings["seed"] = int(np.random.SeedSequence().entropy % (2**63))
    work.mkdir(parents=True, exist_ok=True)
    if adopt is not None:
        store.adopt(target / "data", **adopt)
    atomic_write_bytes(run_file, json.dumps(settings, indent=1, sort_keys=True).encode())
    return RunState(settings, store)
