"""Recorded episodes: object poses per step (plus optional rewards and actions) for USD playback.

``poses[t]`` is the state after ``t`` steps (``poses[0]`` right after reset); ``actions[t]`` and
``rewards[t]`` (``t < T - 1``) are the action taken in state ``t`` and the reward received on
reaching state ``t + 1``. ``EpisodeRecorder`` collects them step by step::

    rec = EpisodeRecorder(fps=env_fps)
    rec.reset(poses0)                       # [K, 4, 4] object-to-world, or [K, 7] x y z qw qx qy qz
    rec.step(poses1, reward=r, action=a)    # after each env.step
    episode = rec.episode()
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dsg_gym.poses import check_rigid, quat_to_rotmat

__all__ = ["Episode", "EpisodeRecorder"]


@dataclass(frozen=True, eq=False)
class Episode:
    """``fps`` (> 0; one time code per step), ``poses [T, K, 4, 4]`` float64 object-to-world with
    ``T >= 1``, optional ``rewards [T - 1]`` and ``actions [T - 1, ...]`` (numeric). Validated on
    construction; ``ValueError`` names the field."""

    fps: float
    poses: np.ndarray
    rewards: np.ndarray | None = None
    actions: np.ndarray | None = None

    def __post_init__(self) -> None:
        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731  (frozen)
        try:
            fps = float(self.fps)
        except (TypeError, ValueError):
            raise ValueError(f"Episode.fps: expected a number, got {self.fps!r}") from None
        if not math.isfinite(fps) or fps <= 0:
            raise ValueError(f"Episode.fps: must be finite and > 0, got {self.fps!r}")
        put("fps", fps)
        poses = np.asarray(self.poses)
        if poses.ndim != 4 or poses.shape[2:] != (4, 4) or poses.shape[0] < 1:
            raise ValueError(f"Episode.poses: expected shape [T >= 1, K, 4, 4], got {poses.shape}")
        put("poses", check_rigid("Episode.poses", poses))
        t = poses.shape[0]
        for name in ("rewards", "actions"):
            value = getattr(self, name)
            if value is None:
                continue
            arr = np.asarray(value)
            if arr.dtype.kind not in "fiub":
                raise ValueError(f"Episode.{name}: expected a numeric array, got dtype {arr.dtype}")
            arr = np.asarray(arr, dtype=np.float64)
            if name == "rewards" and arr.shape != (t - 1,):
                raise ValueError(f"Episode.rewards: expected shape ({t - 1},) for {t} poses, got {arr.shape}")
            if name == "actions" and (arr.ndim < 1 or arr.shape[0] != t - 1):
                raise ValueError(
                    f"Episode.actions: expected shape ({t - 1}, ...) for {t} poses, got {arr.shape}"
                )
            if not np.isfinite(arr).all():
                raise ValueError(f"Episode.{name}: contains non-finite values")
            put(name, arr)

    @property
    def num_steps(self) -> int:
        """T, the number of recorded states (time codes 0 .. T - 1)."""
        return int(self.poses.shape[0])

    @property
    def num_objects(self) -> int:
        """K."""
        return int(self.poses.shape[1])


def _as_matrices(poses) -> np.ndarray:
    """``[K, 4, 4]`` float64 copy of ``poses`` given as ``[K, 4, 4]`` matrices or ``[K, 7]`` pose
    vectors ``x, y, z, qw, qx, qy, qz`` (the env's observation layout; quaternions renormalised)."""
    p = np.array(poses, dtype=np.float64, copy=True)
    if p.ndim == 2 and p.shape[1] == 7:
        if not np.isfinite(p).all() or (np.linalg.norm(p[:, 3:], axis=1) == 0).any():
            raise ValueError("EpisodeRecorder: [K, 7] poses must be finite with non-zero quaternions")
        m = np.tile(np.eye(4), (p.shape[0], 1, 1))
        m[:, :3, :3] = quat_to_rotmat(p[:, 3:])
        m[:, :3, 3] = p[:, :3]
        return m
    if p.ndim != 3 or p.shape[1:] != (4, 4):
        raise ValueError(f"EpisodeRecorder: poses must be [K, 4, 4] or [K, 7], got shape {p.shape}")
    return p


class EpisodeRecorder:
    """Collects poses/rewards/actions step by step; ``episode()`` returns an ``Episode``. Poses may
    be ``[K, 4, 4]`` matrices or ``[K, 7]`` vectors ``x, y, z, qw, qx, qy, qz``."""

    def __init__(self, fps: float) -> None:
        self.fps = fps
        self._poses: list[np.ndarray] = []
        self._rewards: list[float] = []
        self._actions: list[np.ndarray] = []
        self._has_actions: bool | None = None

    def __len__(self) -> int:
        return len(self._poses)

    def reset(self, poses) -> None:
        """Start a new episode with the initial object poses ``[K, 4, 4]``."""
        self._poses = [_as_matrices(poses)]
        self._rewards, self._actions, self._has_actions = [], [], None

    def step(self, poses, reward: float = 0.0, action=None) -> None:
        """Append the poses after one step, the reward received and (optionally) the action."""
        if not self._poses:
            raise ValueError("EpisodeRecorder.step: call reset() first")
        has = action is not None
        if self._has_actions is not None and has != self._has_actions:
            raise ValueError("EpisodeRecorder.step: give an action on every step or on none")
        self._has_actions = has
        self._poses.append(_as_matrices(poses))
        self._rewards.append(float(reward))
        if has:
            self._actions.append(np.array(action, dtype=np.float64, copy=True))

    def episode(self) -> Episode:
        """The episode recorded since the last ``reset`` (validated)."""
        if not self._poses:
            raise ValueError("EpisodeRecorder.episode: nothing recorded (call reset() first)")
        shapes = {p.shape for p in self._poses}
        if len(shapes) != 1:
            raise ValueError(f"EpisodeRecorder: pose arrays of different shapes {sorted(shapes)}")
        actions = np.stack(self._actions) if self._has_actions else None
        return Episode(self.fps, np.stack(self._poses), np.asarray(self._rewards, np.float64), actions)
