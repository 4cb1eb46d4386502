"""Reading a capture's files: JSON, images (RGB composited over a background), object-id masks and depth maps,
each error a :class:`CaptureError` naming the file."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

__all__ = ["CaptureError", "image_size", "read_depth", "read_json", "read_mask", "read_rgb"]


class CaptureError(ValueError):
    """Malformed capture input; the message starts with the offending file."""


def read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as e:
        raise CaptureError(f"{path}: file not found") from e
    except (OSError, UnicodeDecodeError) as e:
        raise CaptureError(f"{path}: cannot read ({e})") from e
    except json.JSONDecodeError as e:
        raise CaptureError(f"{path}: invalid JSON ({e})") from e


def _open_image(path: Path, what: str) -> Image.Image:
    if not path.is_file():
        raise CaptureError(f"{path}: {what} file not found")
    try:
        img = Image.open(path)
        img.load()
    except Exception as e:  # Pillow raises many types for corrupt files
        raise CaptureError(f"{path}: cannot read {what} ({e})") from e
    return img


def image_size(path: Path) -> tuple[int, int]:
    """``(width, height)`` of the image at ``path``, from its header (nothing is decoded)."""
    if not path.is_file():
        raise CaptureError(f"{path}: image file not found")
    try:
        with Image.open(path) as img:
            return img.size
    except Exception as e:  # Pillow raises many types for corrupt files
        raise CaptureError(f"{path}: cannot read image ({e})") from e


def area_resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` ``[H,W,C]`` (any numeric dtype) resized to ``size`` ``(width, height)`` by area averaging, as
    float32 ``[height,width,C]``: each output pixel is the mean of the input pixels it covers (exactly the
    ``k x k`` block means for an integer factor ``k``). Computed in floating point, so nothing is rounded: an
    8-bit resize in Pillow rounds every mean up by about half a level."""
    a = np.asarray(image, dtype=np.float32)
    if (a.shape[1], a.shape[0]) == tuple(size):
        return a.copy()
    planes = [
        Image.fromarray(np.ascontiguousarray(a[..., c])).resize(size, Image.Resampling.BOX)
        for c in range(a.shape[2])
    ]
    return np.stack([np.asarray(q, dtype=np.float32) for q in planes], axis=-1)


def label_resize(ids: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Object ids ``[H,W]`` (uint8) resized to ``size`` ``(width, height)`` without blending them: by an integer
    factor ``k``, each output pixel takes the id most of its ``k x k`` block shows; otherwise the id under the
    output pixel's centre. A tie goes to the lowest of the tied ids where the output pixel's ``x + y`` is even
    and to the highest where it is odd: a block split evenly by an outline gives no side, and a fixed rule
    (the lower id, the background) would move every object's outline inwards.
    (Pillow's nearest pixel, by an even factor, takes a pixel half an input pixel off the block's centre,
    which shifts every outline.)"""
    a = np.asarray(ids)
    (h, w), (ow, oh) = a.shape, size
    if (ow, oh) == (w, h):
        return a.copy()
    if w % ow or h % oh or w // ow != h // oh:
        return np.asarray(Image.fromarray(a.astype(np.uint8)).resize(size, Image.Resampling.NEAREST))
    k = w // ow
    blocks = a.reshape(oh, k, ow, k).transpose(0, 2, 1, 3).reshape(oh, ow, k * k)
    present = np.unique(blocks)
    counts = np.stack([(blocks == i).sum(axis=-1) for i in present], axis=-1)
    low = np.argmax(counts, axis=-1)
    high = len(present) - 1 - np.argmax(counts[..., ::-1], axis=-1)
    yy, xx = np.indices((oh, ow))
    return present[np.where((yy + xx) % 2 == 0, low, high)].astype(a.dtype)


def read_rgb(path: Path, background: Sequence[float], downscale: int) -> tuple[np.ndarray, tuple[int, int]]:
    """RGB float32 [H,W,3] (downscaled) and the original (width, height)."""
    img = _open_image(path, "image")
    orig = img.size
    if img.mode in ("I", "I;16", "F"):
        raise CaptureError(f"{path}: image has mode {img.mode}; expected an 8-bit RGB(A) or grey image")
    has_alpha = img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info)
    img = img.convert("RGBA" if has_alpha else "RGB")
    a = np.asarray(img, dtype=np.float32)
    if downscale > 1:
        a = area_resize(a, (img.width // downscale, img.height // downscale))
    a = a / 255.0
    if has_alpha:
        alpha = a[..., 3:4]
        a = a[..., :3] * alpha + np.asarray(background, dtype=np.float32)[:3] * (1.0 - alpha)
    return np.ascontiguousarray(a[..., :3]), orig


def _check_size(img: Image.Image, path: Path, what: str, image_path: Path, full: tuple[int, int]) -> None:
    if img.size != full:
        raise CaptureError(
            f"{path}: {what} is {img.width}x{img.height} but its image {image_path.name} is "
            f"{full[0]}x{full[1]} (image/{what} size mismatch)"
        )


def read_mask(
    path: Path,
    image_path: Path,
    full: tuple[int, int],
    size: tuple[int, int],
    downscale: int,
    valid_ids: np.ndarray | None,
) -> np.ndarray:
    img = _open_image(path, "mask")
    _check_size(img, path, "mask", image_path, full)
    if img.mode in ("RGB", "RGBA"):
        a = np.asarray(img)
        if not (np.array_equal(a[..., 0], a[..., 1]) and np.array_equal(a[..., 0], a[..., 2])):
            raise CaptureError(f"{path}: mask is a colour image; expected one channel of object ids")
        img = Image.fromarray(np.ascontiguousarray(a[..., 0]))
    elif img.mode == "1":
        img = img.convert("L").point(lambda v: 1 if v else 0)
    elif img.mode in ("I", "I;16"):
        a = np.asarray(img)
        if a.max(initial=0) > 255 or a.min(initial=0) < 0:
            raise CaptureError(f"{path}: mask ids must be in 0..255")
        img = Image.fromarray(a.astype(np.uint8))
    elif img.mode not in ("L", "P"):
        raise CaptureError(f"{path}: unsupported mask mode {img.mode}")
    m = np.asarray(img, dtype=np.uint8)
    if downscale > 1:
        m = label_resize(m, size)
    if valid_ids is not None:
        present = np.unique(m)
        bad = np.setdiff1d(present, np.append(valid_ids, 0))
        if bad.size:
            raise CaptureError(
                f"{path}: mask contains ids {bad.tolist()} that are not objects in scene.json "
                f"(known ids: {sorted(int(i) for i in valid_ids)}; 0 = background)"
            )
    return np.ascontiguousarray(m)


def read_depth(
    path: Path, image_path: Path, full: tuple[int, int], size: tuple[int, int], downscale: int, scale: float
) -> np.ndarray:
    img = _open_image(path, "depth")
    _check_size(img, path, "depth", image_path, full)
    if img.mode not in ("I;16", "I", "L"):
        raise CaptureError(f"{path}: depth must be a 16-bit grey PNG (millimetres), got mode {img.mode}")
    if downscale > 1:
        img = img.resize(size, Image.Resampling.NEAREST)
    return np.asarray(img).astype(np.float32) * np.float32(scale)
