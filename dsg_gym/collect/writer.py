"""Minari datasets from :class:`~dsg_gym.collect.rollout.EpisodeRecord` s: shards, combination, atomic writes.

Storage facts (Minari 0.5.4, ``data_format="hdf5"``): every array leaf of an episode is an HDF5 dataset of
the exact dtype and values given, **except** "image spaces" (``Box`` uint8, 2 or 3 dims, both of the first two
>= 32, low 0 and high 255, e.g. ``rgb``): with ``jpeg_encoding=True`` (Minari's default) each frame of those is
stored as a JPEG (lossy) and decoded on read. ``mask`` (high = K) and multi-camera images (4 dims) never
qualify. This module passes ``jpeg_encoding=False`` unless JPEG is asked for, so RGB is stored raw and read
back bit for bit. :func:`minari.combine_datasets` does not pass ``jpeg_encoding`` on (the combined dataset
would JPEG the images again), so shards are combined here, episode by episode, with Minari's own storage API.

Layout of a run with output root ``OUT`` (a Minari datasets root: ``MINARI_DATASETS_PATH=OUT``):

```
OUT/<dataset_id>/data/{metadata.json, main_data.hdf5}     the finished dataset (minari.load_dataset(dataset_id))
OUT/.dsg-collect/<dataset_id, '/' -> '__'>/run.json       while running: the run's settings (resume checks them)
OUT/.dsg-collect/<...>/shards/shard-<first>-<uid>/         finished episodes, each shard a Minari data folder
```

Every folder is written as a hidden temporary sibling and renamed into place, so a crash leaves either a
complete shard / dataset or none (temporaries are removed on the next run). Extending a finished dataset
makes it the run's first shard (:meth:`ShardStore.adopt`: hard links, no copy), so the dataset can be
replaced at the end while its episodes stay safe in the shard.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import os
import shutil
import uuid
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym

from ..io.atomic import atomic_dir, remove_partial
from .rollout import CollectError, EpisodeRecord

__all__ = [
    "IMAGE_ENCODINGS",
    "ShardInfo",
    "ShardStore",
    "combine_shards",
    "env_spec_for",
    "to_episode_buffer",
    "write_storage",
]

IMAGE_ENCODINGS = ("raw", "jpeg")


def _minari():
    try:
        import minari
        from minari.dataset.minari_storage import MinariStorage
    except ImportError as e:  # pragma: no cover - minari is a dependency
        raise CollectError(
            f"data collection needs minari with HDF5 support: pip install 'minari[hdf5]' ({e})"
        ) from e
    return minari, MinariStorage


def _jpeg_kw(jpeg: bool) -> dict[str, bool]:
    _, storage_cls = _minari()
    if "jpeg_encoding" in inspect.signature(storage_cls.new).parameters:
        return {"jpeg_encoding": bool(jpeg)}
    if jpeg:
        raise CollectError("the installed minari has no JPEG option (images are always stored raw)")
    return {}  # older minari: raw arrays only


def env_spec_for(env_id: str, env_kwargs: Mapping[str, Any], max_episode_steps: int | None):
    """The ``EnvSpec`` recorded in the dataset (so ``dataset.recover_environment()`` works); ``None`` if the
    id is not registered."""
    import dsg_gym  # noqa: F401

    try:
        spec = gym.spec(env_id)
    except gym.error.Error:
        return None
    kw = {**spec.kwargs, **dict(env_kwargs)}
    steps = spec.max_episode_steps if max_episode_steps is None else int(max_episode_steps)
    return dataclasses.replace(spec, kwargs=kw, max_episode_steps=steps)


def to_episode_buffer(rec: EpisodeRecord, episode_id: int | None = None):
    from minari.data_collector.episode_buffer import EpisodeBuffer

    return EpisodeBuffer(
        id=episode_id,
        seed=int(rec.seed),
        observations=rec.observations,
        actions=rec.actions,
        rewards=rec.rewards,
        terminations=rec.terminations,
        truncations=rec.truncations,
        infos=dict(rec.infos) or None,
    )


def write_storage(
    data_path: Path,
    buffers: Iterable,
    *,
    observation_space: gym.Space,
    action_space: gym.Space,
    env_spec,
    dataset_id: str,
    jpeg: bool = False,
    data_format: str = "hdf5",
    metadata: Mapping[str, Any] | None = None,
) -> int:
    """Create a Minari data folder at ``data_path`` (must not hold a dataset) from ``EpisodeBuffer`` s;
    returns the number of episodes. ``metadata`` entries are added to Minari's ``metadata.json``."""
    minari, storage_cls = _minari()
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*env_spec is not serializable.*")
        storage = storage_cls.new(
            data_path, observation_space=observation_space, action_space=action_space, env_spec=env_spec,
            data_format=data_format, **_jpeg_kw(jpeg),
        )  # fmt: skip
    storage.update_metadata(
        {"dataset_id": dataset_id, "minari_version": minari.__version__, **(metadata or {})}
    )
    n = 0
    for buf in buffers:
        storage.update_episodes([buf])
        n += 1
    return n


@dataclass(frozen=True)
class ShardInfo:
    path: Path
    indices: tuple[int, ...]
    seeds: tuple[int, ...]
    steps: tuple[int, ...]
    successes: tuple[bool, ...]


class ShardStore:
    """Finished episodes of one run: ``root/shard-*/`` Minari data folders (raw images, any order)."""

    def __init__(self, root: Path):
        self.root = Path(root)

    def write(self, records: Sequence[EpisodeRecord], *, observation_space, action_space, dataset_id: str,
              data_format: str = "hdf5") -> Path:  # fmt: skip
        """Write ``records`` as one new shard (atomically); returns its folder."""
        self.root.mkdir(parents=True, exist_ok=True)
        first = min(r.index for r in records)
        target = self.root / f"shard-{first:08d}-{uuid.uuid4().hex[:8]}"
        meta = {
            "dsg_collect_shard": {
                "episode_indices": [int(r.index) for r in records],
                "episode_seeds": [int(r.seed) for r in records],
                "episode_steps": [len(r) for r in records],
                "episode_success": [bool(r.success) for r in records],
            }
        }
        with atomic_dir(target) as tmp:
            write_storage(
                tmp, (to_episode_buffer(r) for r in records), observation_space=observation_space,
                action_space=action_space, env_spec=None, dataset_id=dataset_id, jpeg=False,
                data_format=data_format, metadata=meta,
            )  # fmt: skip
        return target

    def adopt(self, data_path: Path, *, seeds: Sequence[int], steps: Sequence[int],
              successes: Sequence[bool]) -> Path:  # fmt: skip
        """Make the Minari data folder ``data_path`` of a finished dataset (episodes ``0 .. n-1``, with these
        ``seeds``, ``steps`` and ``successes``) a shard of this run, atomically and without copying: its data
        files are hard-linked (copied where the file system cannot link) and its ``metadata.json`` gets the
        shard's records. The dataset folder may then be replaced (not modified) without touching the shard."""
        data_path = Path(data_path)
        n = len(seeds)
        if not n or len(steps) != n or len(successes) != n:
            raise CollectError(f"cannot adopt {data_path}: per-episode records of different lengths")
        meta = json.loads((data_path / "metadata.json").read_text())
        meta["dsg_collect_shard"] = {
            "episode_indices": list(range(n)),
            "episode_seeds": [int(v) for v in seeds],
            "episode_steps": [int(v) for v in steps],
            "episode_success": [bool(v) for v in successes],
        }
        self.root.mkdir(parents=True, exist_ok=True)
        target = self.root / f"shard-{0:08d}-{uuid.uuid4().hex[:8]}"
        with atomic_dir(target) as tmp:
            for src in sorted(data_path.rglob("*")):
                dst = tmp / src.relative_to(data_path)
                if src.is_dir():
                    dst.mkdir(parents=True, exist_ok=True)
                elif src != data_path / "metadata.json":
                    dst.parent.mkdir(parents=True, exist_ok=True)
                    try:
                        os.link(src, dst)
                    except OSError:
                        shutil.copy2(src, dst)
            (tmp / "metadata.json").write_text(json.dumps(meta))
        return target

    def shards(self) -> list[ShardInfo]:
        """The complete shards, sorted by folder name (temporaries of interrupted writes are ignored)."""
        out = []
        if not self.root.is_dir():
            return out
        for p in sorted(self.root.iterdir()):
            if p.name.startswith(".") or not p.is_dir():
                continue
            try:
                meta = json.loads((p / "metadata.json").read_text())["dsg_collect_shard"]
                out.append(ShardInfo(p, tuple(meta["episode_indices"]), tuple(meta["episode_seeds"]),
                                     tuple(meta["episode_steps"]), tuple(meta["episode_success"])))  # fmt: skip
            except (OSError, ValueError, KeyError) as e:
                raise CollectError(
                    f"unreadable shard {p}: {e}; delete it to collect its episodes again"
                ) from e
        return out

    def done(self) -> dict[int, tuple[ShardInfo, int]]:
        """``episode index -> (shard, position in the shard)`` of every finished episode."""
        out: dict[int, tuple[ShardInfo, int]] = {}
        for s in self.shards():
            for j, e in enumerate(s.indices):
                out.setdefault(int(e), (s, j))
        return out

    def clean(self) -> None:
        remove_partial(self.root)


def combine_shards(
    store: ShardStore,
    indices: Sequence[int],
    target: Path,
    *,
    dataset_id: str,
    env_spec,
    jpeg: bool,
    data_format: str = "hdf5",
    metadata: Mapping[str, Any] | None = None,
    replace: bool = False,
) -> Path:
    """Write the episodes ``indices`` (in that order; all must be finished) from the shards as one Minari
    dataset folder ``target`` (``target/data/...``), atomically; ``replace``: an existing ``target`` is
    replaced once the new folder is complete. Returns ``target``."""
    _, storage_cls = _minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer

    done = store.done()
    missing = [e for e in indices if e not in done]
    if missing:
        raise CollectError(f"cannot combine: {len(missing)} episodes are not finished (first {missing[:5]})")
    opened: dict[Path, Any] = {}

    def storage(s: ShardInfo):
        if s.path not in opened:
            opened[s.path] = storage_cls.read(s.path)
        return opened[s.path]

    first = storage(done[indices[0]][0]) if indices else None
    if first is None:
        raise CollectError("cannot combine: no episodes")

    def buffers():
        for e in indices:
            s, j = done[e]
            ep = next(iter(storage(s).get_episodes([j])))
            yield EpisodeBuffer(
                id=None, seed=int(s.seeds[j]), observations=ep["observations"], actions=ep["actions"],
                rewards=ep["rewards"], terminations=ep["terminations"], truncations=ep["truncations"],
                infos=ep.get("infos") or None,
            )  # fmt: skip

    with atomic_dir(Path(target), replace=replace) as tmp:
        write_storage(
            tmp / "data", buffers(), observation_space=first.observation_space, action_space=first.action_space,
            env_spec=env_spec, dataset_id=dataset_id, jpeg=jpeg, data_format=data_format, metadata=metadata,
        )  # fmt: skip
    return Path(target)
