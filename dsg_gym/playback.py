"""Recorded episodes as object poses per step, from an episode file or a Minari dataset (``dsg-view``'s time
slider, :mod:`dsg_gym.episode_video`'s videos).

* an ``.npz`` episode file (:func:`dsg_gym.envs.recording.load_episode`, as ``RecordEpisode`` writes): its
  ``poses`` ``[T, K, 4, 4]``;
* a Minari dataset (``dsg-collect``'s output folder, or a dataset id found under ``MINARI_DATASETS_PATH``):
  episode ``index``'s ``poses`` observations ``[T+1, K, 7]`` (the dataset must observe ``poses``), and its
  ``goal`` when observed.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .poses import as_poses7

__all__ = ["DATASET_FPS", "Playback", "dataset_playback", "load_playback", "open_dataset"]

#: playback rate of dataset episodes (``DSGWorld-v0``'s ``render_fps``)
DATASET_FPS = 10.0


@dataclass(frozen=True)
class Playback:
    """``poses`` ``[T, K, 7]`` per step (``x y z qw qx qy qz``); ``goal`` ``[K, 7]`` or ``None``; ``fps``;
    ``source`` says where it came from."""

    poses: np.ndarray
    goal: np.ndarray | None
    fps: float
    source: str

    def __len__(self) -> int:
        return int(self.poses.shape[0])


def _checked(poses: np.ndarray, k: int, what: str) -> np.ndarray:
    poses = np.asarray(poses, np.float64)
    if poses.ndim < 3 or poses.shape[1] != k or len(poses) == 0:
        raise ValueError(f"{what}: poses of shape {poses.shape} do not hold {k} objects per step")
    return np.stack([as_poses7(p, k, f"{what}: step {t}") for t, p in enumerate(poses)])


def open_dataset(source):
    """The Minari dataset at ``source``: a folder ``dsg-collect`` wrote, or a dataset id found under
    ``MINARI_DATASETS_PATH`` (``ValueError`` naming the source otherwise)."""
    import minari

    from .collect import load

    p = Path(str(source))
    try:
        return load(p) if p.exists() else minari.load_dataset(str(source))
    except Exception as e:  # minari raises many kinds; the message names the source
        raise ValueError(f"{source}: not a readable Minari dataset or episode file ({e})") from None


def dataset_playback(ds, index: int, k: int, source: str = "dataset") -> Playback:
    """Episode ``index`` of the open Minari dataset ``ds`` (:func:`open_dataset`) for a world of ``k``
    objects: its ``poses`` observations and, when observed, its ``goal`` (``ValueError`` naming ``source``)."""
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise ValueError(f"episode index must be an integer, got {index!r}")
    n = ds.total_episodes
    if not 0 <= index < n:
        raise ValueError(f"{source}: episode index {index} out of range: the dataset has {n} episodes")
    obs = ds[int(index)].observations
    if not isinstance(obs, dict) or "poses" not in obs:
        raise ValueError(
            f"{source}: the dataset does not observe 'poses' (collect with obs including 'poses')"
        )
    what = f"{source} episode {index}"
    goal = obs.get("goal")
    goal = None if goal is None else as_poses7(np.asarray(goal)[0], k, f"{what}: goal")
    return Playback(_checked(obs["poses"], k, what), goal, DATASET_FPS, what)


def load_playback(source, k: int, index: int = 0) -> Playback:
    """The poses to play from ``source`` (see the module docstring) for a world of ``k`` objects;
    ``ValueError`` naming the source for anything unreadable, an index out of range or the wrong object count."""
    from .envs.recording import load_episode

    s = str(source)
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)):
        raise ValueError(f"episode index must be an integer, got {index!r}")
    if Path(s).suffix == ".npz":
        ep = load_episode(s)  # EpisodeFileError (a ValueError) names the file
        return Playback(_checked(ep.poses, k, s), None, float(ep.fps), s)
    return dataset_playback(open_dataset(s), index, k, s)
