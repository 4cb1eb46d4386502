"""Recording episodes of ``DSGWorld-v0`` for USD playback, and the episode file format.

``RecordEpisode`` wraps an env and records, per step, the object poses (read from the env's own state, so
``poses`` need not be an observation), the reward and the action, with :class:`dsg_gym.usd.EpisodeRecorder`
at ``fps = env.metadata["render_fps"]``::

    env = RecordEpisode(gym.make("DSGWorld-v0"), folder="episodes")   # folder: optional auto-save
    env.reset(seed=0)
    for _ in range(20):
        env.step(env.action_space.sample())
    env.save("ep.npz")                                 # or env.episode() -> dsg_gym.usd.Episode
    # dsg-export WORLD --episode ep.npz --out ep.usdc

Episode file (``.npz``, written atomically by :func:`save_episode`, read by :func:`load_episode` with
``allow_pickle=False``):

============  ==================  ================================================================
key           shape / dtype       meaning
============  ==================  ================================================================
``fps``       [] float64          playback rate (USD ``timeCodesPerSecond``), > 0
``poses``     [T,K,4,4] float64   object-to-world pose of each object after ``t`` steps (T >= 1)
``rewards``   [T-1] float64       optional: reward received on reaching state ``t + 1``
``actions``   [T-1,A] float64     optional: action applied in state ``t`` (clipped to the action space, as the env does)
============  ==================  ================================================================
"""

from __future__ import annotations

import io
import os
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np

from ..io.atomic import atomic_write_bytes
from ..usd.episode import Episode, EpisodeRecorder

__all__ = ["EpisodeFileError", "RecordEpisode", "load_episode", "save_episode", "EPISODE_KEYS"]

EPISODE_KEYS = ("fps", "poses", "rewards", "actions")


class EpisodeFileError(ValueError):
    """An episode file that cannot be read or written; the message names the file."""


def _episode_path(path) -> Path:
    p = Path(path)
    if p.suffix == "":
        p = p.with_name(p.name + ".npz")
    if p.suffix != ".npz":
        raise EpisodeFileError(f"{p}: an episode file must end in .npz")
    return p


def save_episode(path, episode: Episode) -> Path:
    """Write ``episode`` as an ``.npz`` episode file (``.npz`` appended when ``path`` has no suffix), atomically
    (:mod:`dsg_gym.io.atomic`); returns the path."""
    if not isinstance(episode, Episode):
        raise EpisodeFileError(f"save_episode: expected an Episode, got {type(episode).__name__}")
    p = _episode_path(path)
    arrays = {"fps": np.float64(episode.fps), "poses": np.ascontiguousarray(episode.poses, np.float64)}
    if episode.rewards is not None:
        arrays["rewards"] = np.ascontiguousarray(episode.rewards, np.float64)
    if episode.actions is not None:
        arrays["actions"] = np.ascontiguousarray(episode.actions, np.float64)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return atomic_write_bytes(p, buf.getvalue())


def load_episode(path) -> Episode:
    """Read and validate an episode file; :class:`EpisodeFileError` (a ``ValueError``) naming the file for a
    missing, truncated or non-npz file, pickled arrays, missing ``fps``/``poses`` or wrong shapes."""
    p = Path(path)
    if not p.is_file():
        raise EpisodeFileError(f"{p}: episode file does not exist")
    try:
        npz = np.load(p, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise EpisodeFileError(f"{p}: not a readable .npz episode file ({e})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise EpisodeFileError(f"{p}: not an .npz episode file (it holds a single array)")
    with npz:
        missing = [k for k in ("fps", "poses") if k not in npz.files]
        if missing:
            raise EpisodeFileError(f"{p}: episode file lacks {missing} (it has {sorted(npz.files)})")
        try:
            data = {k: npz[k] for k in EPISODE_KEYS if k in npz.files}
        except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise EpisodeFileError(f"{p}: not a readable .npz episode file ({e})") from None
    fps = data["fps"]
    if fps.shape != () or fps.dtype.kind not in "fiu":
        raise EpisodeFileError(
            f"{p}: 'fps' must be a numeric scalar, got shape {fps.shape}, dtype {fps.dtype}"
        )
    actions = data.get("actions")
    if actions is not None and actions.ndim != 2:
        raise EpisodeFileError(f"{p}: 'actions' must be [T-1, A], got shape {actions.shape}")
    try:
        return Episode(float(fps), data["poses"], data.get("rewards"), actions)
    except ValueError as e:
        raise EpisodeFileError(f"{p}: {e}") from None


def env_poses(env: gym.Env) -> np.ndarray:
    """The current object poses ``[K, 7]`` (``x y z qw qx qy qz``) of a (wrapped) ``DSGWorldEnv``, a copy."""
    base = env.unwrapped
    if not hasattr(type(base), "poses"):
        raise TypeError(
            f"RecordEpisode: {type(base).__name__} does not expose object poses (not a DSGWorldEnv?)"
        )
    return np.array(base.poses, dtype=np.float64, copy=True)


class RecordEpisode(gym.Wrapper):
    """Records poses (from the env state), rewards and actions of each episode (see the module docstring).

    Args:
        env: a ``DSGWorld-v0`` env (possibly wrapped, e.g. by ``gymnasium.make``'s ``TimeLimit``).
        folder: if given, every finished episode (``terminated`` or ``truncated``) is saved there as
            ``episode_NNNNNN.npz`` (and listed in :attr:`saved`).
        fps: playback rate; default ``env.metadata["render_fps"]``.
    """

    def __init__(self, env: gym.Env, folder: str | os.PathLike | None = None, fps: float | None = None):
        super().__init__(env)
        fps = env.metadata.get("render_fps") if fps is None else fps
        if fps is None:
            raise ValueError("RecordEpisode: the env has no metadata['render_fps']; pass fps=")
        self.recorder = EpisodeRecorder(float(fps))
        Episode(float(fps), np.eye(4)[None, None])  # validates fps now, not at the first episode()
        self.fps = float(fps)
        self.folder = None if folder is None else Path(folder)
        self.saved: list[Path] = []
        self._episodes = 0
        self._finished = False

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.recorder.reset(env_poses(self.env))
        self._finished = False
        self._episodes += 1
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)  # raises on a bad action
        applied = np.asarray(action, dtype=np.float64).reshape(-1)
        space = self.env.action_space
        if isinstance(space, gym.spaces.Box):  # the env clips to its Box: record what it applied
            applied = np.clip(applied, space.low.reshape(-1), space.high.reshape(-1))
        self.recorder.step(env_poses(self.env), reward=float(reward), action=applied)
        if (terminated or truncated) and not self._finished:
            self._finished = True
            if self.folder is not None:
                self.saved.append(self.save(self.folder / f"episode_{self._episodes - 1:06d}.npz"))
        return obs, reward, terminated, truncated, info

    def episode(self) -> Episode:
        """The current episode (or the last one, after it finished), as a :class:`dsg_gym.usd.Episode`."""
        if len(self.recorder) == 0:
            raise ValueError("RecordEpisode.episode: nothing recorded yet (call reset() first)")
        return self.recorder.episode()

    def save(self, path) -> Path:
        """Write :meth:`episode` as an ``.npz`` episode file (atomic); returns the path."""
        return save_episode(path, self.episode())
