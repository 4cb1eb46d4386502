"""Videos of recorded episodes: ``DSGWorld-v0``'s ``render()`` frames of the object poses an episode went through.

    from dsg_gym.episode_video import episode_frames, write_dataset_videos
    frames = episode_frames(poses, goal, env_kwargs={"cameras": [0, 5]})   # uint8 [T, H, W*V, 3]
    paths = write_dataset_videos("datasets/dsgworld/expert-v0", episodes=3)  # DIR/videos/episode_0000.mp4, ...

Rendering is a function of the poses alone, so the frames of a recorded episode are the frames ``render()`` gave
while it ran (with the goal drawn as a translucent ghost, ``render_goal``). A dataset's episodes are rendered with
the env kwargs its ``env_spec`` records (world, cameras, ``render_width`` / ``render_height``, background); they
must observe ``poses`` (``DSGWorld-v0``'s default observation does).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .playback import DATASET_FPS, dataset_playback, open_dataset
from .poses import as_poses7
from .video import mp4_available, write_gif, write_mp4

__all__ = ["VIDEO_FORMATS", "episode_frames", "write_dataset_videos"]

#: ``write_dataset_videos``'s formats: ``auto`` is ``mp4`` with the ``video`` extra, else ``gif``
VIDEO_FORMATS = ("auto", "mp4", "gif")
# kwargs of the env that renders frames which the frames do not depend on (replaced; see _frame_env)
_REPLACED = ("obs", "collision", "render_mode", "render_goal", "action_mode", "max_episode_steps")


def _frame_env(env_kwargs: Mapping[str, Any] | None, render_goal: bool):
    """A ``DSGWorldEnv`` from ``env_kwargs`` that renders frames only: no observation images, every
    configuration accepted (``collision="ignore"``)."""
    from .envs.dsg_world import DSGWorldEnv

    if env_kwargs is not None and not isinstance(env_kwargs, Mapping):
        raise ValueError(f"env_kwargs must be a dict of DSGWorld-v0 kwargs, got {type(env_kwargs).__name__}")
    kw = {k: v for k, v in dict(env_kwargs or {}).items() if k not in _REPLACED}
    return DSGWorldEnv(
        **kw, obs=("poses",), collision="ignore", render_mode="rgb_array", render_goal=bool(render_goal)
    )


def _render(env, poses: np.ndarray, goal: np.ndarray | None) -> np.ndarray:
    frames = []
    for p in poses:
        env.reset(options={"start": p, "goal": p if goal is None else goal})
        frames.append(env.render())
    return np.stack(frames)


def episode_frames(
    poses, goal=None, *, env_kwargs: Mapping[str, Any] | None = None, render_goal=None
) -> np.ndarray:
    """``render()`` frames uint8 ``[T, H, W * V, 3]`` of ``DSGWorld-v0`` made with ``env_kwargs``, the objects
    at ``poses[t]`` (``[T, K, 7]`` or ``[T, K, 4, 4]``). ``goal`` ``[K, 7]`` / ``[K, 4, 4]`` is drawn as a
    ghost when ``render_goal`` is true (``None``: when a goal is given). ``ValueError`` names a bad input (poses
    outside the workspace included)."""
    render_goal = goal is not None if render_goal is None else render_goal
    if render_goal and goal is None:
        raise ValueError("episode_frames: render_goal needs the goal poses")
    env = _frame_env(env_kwargs, bool(render_goal))
    try:
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim not in (3, 4) or len(p) == 0:
            raise ValueError(f"episode_frames: poses must be [T, K, 7] or [T, K, 4, 4], got {p.shape}")
        p = np.stack([as_poses7(x, env.K, f"episode_frames: poses[{t}]") for t, x in enumerate(p)])
        g = None if goal is None else as_poses7(goal, env.K, "episode_frames: goal")
        return _render(env, p, g)
    finally:
        env.close()


def write_dataset_videos(
    dataset,
    episodes: int = 1,
    out_dir: str | os.PathLike | None = None,
    *,
    fps: float | None = None,
    fmt: str = "auto",
    render_goal: bool = True,
) -> list[Path]:
    """Write videos of the first ``episodes`` episodes of a Minari dataset (a folder ``dsg-collect`` wrote, or
    a dataset id under ``MINARI_DATASETS_PATH``) as ``out_dir/episode_0000.mp4``, ... (default ``out_dir``:
    ``DATASET/videos`` for a folder, ``./videos`` for an id). ``fmt``: ``mp4`` (the ``video`` extra), ``gif``
    or ``auto`` (MP4 when the extra is installed, else GIF); ``fps`` defaults to the env's ``render_fps`` (10).
    Each episode's goal is drawn as a ghost when the dataset observes ``goal`` and ``render_goal``. Returns the
    paths. ``ValueError`` names a bad argument or an unreadable dataset before anything is written."""
    if isinstance(episodes, bool) or not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    if fmt not in VIDEO_FORMATS:
        raise ValueError(f"fmt must be one of {VIDEO_FORMATS}, got {fmt!r}")
    if fmt == "auto":
        fmt = "mp4" if mp4_available() else "gif"
    elif fmt == "mp4" and not mp4_available():
        from .video import VIDEO_EXTRA_HINT

        raise ModuleNotFoundError(f"MP4 videos need imageio-ffmpeg; {VIDEO_EXTRA_HINT}")
    rate = DATASET_FPS if fps is None else fps
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not (np.isfinite(rate) and rate > 0):
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    ds = open_dataset(dataset)
    spec = getattr(ds, "env_spec", None)
    if spec is None or not str(spec.entry_point).startswith("dsg_gym."):
        raise ValueError(
            f"{dataset}: the dataset was not collected from DSGWorld-v0; its frames cannot be rendered"
        )
    n = min(int(episodes), ds.total_episodes)
    folder = Path(dataset)
    out = Path(out_dir) if out_dir is not None else (folder if folder.exists() else Path(".")) / "videos"
    env = _frame_env(spec.kwargs, render_goal)
    try:
        plays = [dataset_playback(ds, i, env.K, str(dataset)) for i in range(n)]  # every check before writing
        paths = []
        for i, pb in enumerate(plays):
            env.render_goal = bool(render_goal and pb.goal is not None)
            frames = _render(env, pb.poses, pb.goal)
            write = write_mp4 if fmt == "mp4" else write_gif
            paths.append(write(frames, out / f"episode_{i:04d}.{fmt}", float(rate)))
        return paths
    finally:
        env.close()
