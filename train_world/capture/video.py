"""Photos from a video: one walk around the table per state, sampled to N sharp frames.

A photo capture's state may hold one video file (``PHOTOS/state1/<name>.mp4`` etc.) instead of ``images/``.
:func:`extract_frames` decodes it (PyAV, the ``capture`` extra), splits it into N equal stretches of time and keeps
the sharpest frame of each (the variance of the Laplacian of the grey image, the usual focus measure: motion blur
and defocus lower it), and writes them as ``images/frame_0000.jpg`` ... together with ``frames.json`` (the video,
each frame's time and sharpness). Masks are made for those frames afterwards (``masks/frame_0000.png`` ...), as for
photos. ``frames.json`` also tells structure from motion that the views are a sequence, so it matches each frame
with its neighbours instead of every pair (:mod:`train_world.capture.sfm`).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image
from scipy import ndimage

from dsg_gym.io.atomic import atomic_dir, atomic_write_bytes
from train_world.capture.photos import FRAMES_FILE, PHOTO_STATES, VIDEO_SUFFIXES, PhotoCaptureError

__all__ = [
    "FRAMES_FILE",
    "VIDEO_SUFFIXES",
    "extract_capture_frames",
    "extract_frames",
    "find_video",
    "sharpness",
]

_MEASURE_WIDTH = 320  # frames are scored at about this width: blur shows at any size, and it is fast


def find_video(state_dir: Path) -> Path | None:
    """The one video file directly in ``state_dir`` (``None`` when there is none); two are an error."""
    vids = sorted(p for p in state_dir.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if len(vids) > 1:
        raise PhotoCaptureError(
            f"{state_dir}: {len(vids)} videos ({', '.join(p.name for p in vids)}); keep one walk-around per state"
        )
    return vids[0] if vids else None


def sharpness(rgb: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image ``rgb [H, W, 3]`` uint8, scored at about 320 px wide."""
    grey = rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
    step = max(1, grey.shape[1] // _MEASURE_WIDTH)
    return float(ndimage.laplace(grey[::step, ::step]).var())


def _decode(video: Path, progress: bool):
    """(time s, rgb uint8) of every frame; PhotoCaptureError when the file does not decode."""
    try:
        import av
    except ImportError as e:
        raise PhotoCaptureError(
            "reading videos needs PyAV: pip install 'dsg-gym[capture]' (or pip install av)"
        ) from e
    from tqdm import tqdm

    try:
        with av.open(str(video)) as container:
            if not container.streams.video:
                raise PhotoCaptureError(f"{video}: no video stream; pass a video file (MP4, MOV, ...)")
            stream = container.streams.video[0]
            total = stream.frames or None
            bar = tqdm(
                total=total, desc=f"dsg-capture: reading {video.name}", unit="frame", disable=not progress
            )
            with bar:
                for frame in container.decode(stream):
                    t = float(frame.time) if frame.time is not None else float(bar.n)
                    bar.update(1)
                    yield t, frame.to_ndarray(format="rgb24")
    except PhotoCaptureError:
        raise
    except (av.error.FFmpegError, OSError, ValueError) as e:
        raise PhotoCaptureError(f"{video}: cannot decode ({e}); re-export it as H.264 MP4") from e


def extract_frames(
    state_dir: str | Path,
    n: int,
    *,
    overwrite: bool = False,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
) -> list[Path]:
    """Sample the video in ``state_dir`` to ``n`` sharp frames in ``state_dir/images`` (module docstring).

    Two passes over the video keep memory flat: the first scores every frame, the second writes the chosen ones.
    The folder appears whole or not at all; an existing ``images/`` is refused unless ``overwrite``.
    """
    state_dir = Path(state_dir)
    if isinstance(n, bool) or not isinstance(n, int) or n < 3:
        raise PhotoCaptureError(f"frames per state must be an integer >= 3, got {n!r} (about 40 works well)")
    video = find_video(state_dir) if state_dir.is_dir() else None
    if video is None:
        raise PhotoCaptureError(f"{state_dir}: no video file ({', '.join(VIDEO_SUFFIXES)}) in this folder")
    images = state_dir / "images"
    if images.exists() and not overwrite:
        raise PhotoCaptureError(f"{images}: already exists; remove it or pass --overwrite to extract again")
    times, scores = [], []
    for t, rgb in _decode(video, progress):
        times.append(t)
        scores.append(sharpness(rgb))
    if len(times) < n:
        raise PhotoCaptureError(f"{video}: {len(times)} frames, fewer than the {n} asked for; ask for fewer")
    edges = np.linspace(0, len(times), n + 1).astype(int)
    picks = [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    chosen = {p: i for i, p in enumerate(picks)}
    records, paths = [], []
    with atomic_dir(images, replace=overwrite) as tmp:
        for idx, (t, rgb) in enumerate(_decode(video, False)):
            if idx in chosen:
                name = f"frame_{chosen[idx]:04d}.jpg"
                Image.fromarray(rgb).save(Path(tmp) / name, quality=95)
                records.append({"file": name, "frame": idx, "time_s": round(t, 4), "sharpness": scores[idx]})
                paths.append(images / name)
        if len(records) != n:
            raise PhotoCaptureError(f"{video}: the video changed while it was read; run again")
    doc = {"video": video.name, "frames_in_video": len(times), "frames": records}
    atomic_write_bytes(state_dir / FRAMES_FILE, (json.dumps(doc, indent=1) + "\n").encode())
    if log:
        log(f"{state_dir.name}: {n} of {len(times)} frames from {video.name} -> {images}")
    return paths


def extract_capture_frames(photos: str | Path, n: int, **kw) -> dict[str, list[Path]]:
    """:func:`extract_frames` for every state of the photo capture ``photos`` that holds a video."""
    photos = Path(photos)
    out = {}
    for s in PHOTO_STATES:
        sdir = photos / s
        if sdir.is_dir() and find_video(sdir) is not None:
            out[s] = extract_frames(sdir, n, **kw)
    if not out:
        raise PhotoCaptureError(
            f"{photos}: no state folder holds a video; put one walk-around video in {PHOTO_STATES[0]}/ and "
            f"{PHOTO_STATES[1]}/"
        )
    return out
