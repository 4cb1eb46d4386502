"""Frames to files: animated GIF (pillow, always there) and MP4 (H.264, needs the ``video`` extra).

    from dsg_gym.video import write_gif, write_mp4
    write_gif(frames, "episode.gif", fps=10)     # frames: uint8 [H, W, 3] arrays (or one [T, H, W, 3] array)
    write_mp4(frames, "episode.mp4", fps=10)     # pip install 'dsg-gym[video]'

Both write atomically (:mod:`dsg_gym.io.atomic`) and give the same bytes for the same frames. The ``video``
extra (``moviepy``, which brings ``imageio-ffmpeg`` and its own ffmpeg binary) is also what Gymnasium's
``RecordVideo`` wrapper needs. MP4 frames are padded with black to even sizes (H.264 in yuv420p needs them).
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .io.atomic import atomic_path

__all__ = ["VIDEO_EXTRA_HINT", "mp4_available", "views_side_by_side", "write_gif", "write_mp4"]

VIDEO_EXTRA_HINT = "install the video extra: pip install 'dsg-gym[video]'"


def mp4_available() -> bool:
    """Whether MP4 can be written here (the ``video`` extra is installed)."""
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        return False
    return True


def views_side_by_side(rgb) -> np.ndarray:
    """Frames of one episode's ``rgb`` observations: ``[T, H, W, 3]`` as they are, or ``[T, V, H, W, 3]``
    (V cameras) with the views side by side, ``[T, H, V * W, 3]``."""
    a = np.asarray(rgb)
    if a.ndim == 5:
        return np.concatenate(list(np.moveaxis(a, 1, 0)), axis=2)
    if a.ndim != 4:
        raise ValueError(f"views_side_by_side: expected [T, H, W, 3] or [T, V, H, W, 3], got shape {a.shape}")
    return a


def _frames(frames, what: str) -> list[np.ndarray]:
    """The frames as a list of equal-size uint8 ``[H, W, 3]`` arrays (``ValueError`` naming the problem)."""
    if isinstance(frames, np.ndarray) and frames.ndim == 4:
        frames = list(frames)
    out = []
    for i, f in enumerate(frames if isinstance(frames, Iterable) else ()):
        a = np.asarray(f)
        if a.dtype != np.uint8 or a.ndim != 3 or a.shape[2] != 3 or 0 in a.shape:
            raise ValueError(f"{what}: frame {i} must be a uint8 [H, W, 3] array, got {a.dtype} {a.shape}")
        if out and a.shape != out[0].shape:
            raise ValueError(f"{what}: frame {i} is {a.shape}, frame 0 is {out[0].shape}; frames must match")
        out.append(np.ascontiguousarray(a))
    if not out:
        raise ValueError(f"{what}: no frames (give uint8 [H, W, 3] arrays)")
    return out


def _fps(fps, what: str) -> float:
    if isinstance(fps, bool) or not isinstance(fps, (int, float, np.integer, np.floating)):
        raise ValueError(f"{what}: fps must be a number > 0, got {fps!r}")
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"{what}: fps must be a finite number > 0, got {fps!r}")
    return float(fps)


def write_gif(frames, path: str | os.PathLike, fps: float = 10.0, loop: bool = True) -> Path:
    """Write ``frames`` (uint8 ``[H, W, 3]`` each) as an animated GIF at ``fps`` (each frame shown ``1/fps``
    s, rounded to GIF's 10 ms steps); ``loop``: repeat forever. Colours are reduced to one 256-colour palette
    made from all frames, so nothing flickers between frames. Returns the path."""
    from PIL import Image

    frames = _frames(frames, "write_gif")
    fps = _fps(fps, "write_gif")
    duration = max(10, int(round(100.0 / fps)) * 10)
    # one palette for the whole clip: quantise a tall image of (up to 16 evenly spaced) frames
    pick = np.unique(np.linspace(0, len(frames) - 1, min(16, len(frames))).round().astype(int))
    palette = Image.fromarray(np.concatenate([frames[i] for i in pick], axis=0)).quantize(
        256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE
    )
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    path = Path(path)
    with atomic_path(path, suffix=".gif") as tmp:
        images[0].save(
            tmp,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=duration,
            loop=0 if loop else None,
            optimize=False,
            disposal=1,
        )
    return path


def write_mp4(frames, path: str | os.PathLike, fps: float = 10.0, quality: float = 7.0) -> Path:
    """Write ``frames`` (uint8 ``[H, W, 3]`` each) as an H.264 MP4 at ``fps``; ``quality`` 0..10 (10 best).
    Needs the ``video`` extra (``ModuleNotFoundError`` saying how to install it). Returns the path."""
    frames = _frames(frames, "write_mp4")
    fps = _fps(fps, "write_mp4")
    if not 0.0 <= float(quality) <= 10.0:
        raise ValueError(f"write_mp4: quality must lie in [0, 10], got {quality!r}")
    try:
        import imageio_ffmpeg
    except ImportError:
        raise ModuleNotFoundError(
            f"write_mp4: writing MP4 needs imageio-ffmpeg; {VIDEO_EXTRA_HINT}"
        ) from None
    h, w = frames[0].shape[:2]
    ph, pw = h + h % 2, w + w % 2
    path = Path(path)
    with atomic_path(path, suffix=".mp4") as tmp:
        writer = imageio_ffmpeg.write_frames(
            str(tmp), (pw, ph), fps=fps, quality=float(quality), codec="libx264", macro_block_size=1,
            ffmpeg_log_level="error",
            output_params=["-fflags", "+bitexact", "-flags:v", "+bitexact", "-map_metadata", "-1"],
        )  # fmt: skip
        writer.send(None)
        try:
            for f in frames:
                if (ph, pw) != (h, w):
                    f = np.pad(f, ((0, ph - h), (0, pw - w), (0, 0)))
                writer.send(f)
        finally:
            writer.close()
    return path
