"""Shrinking a capture folder's views to at most a given size, in place: a phone's photos are far larger than the
size a world trains at on a CPU.

Images are area-averaged (each pixel the mean of the photo's pixels it covers, as a smaller sensor would see
them), object-id masks take the id most of those pixels show (:func:`~train_world.capture.files.label_resize`),
depth maps the nearest pixel (ids and depths are never blended), and the
pinhole intrinsics scale with the size along each axis. Pixel ``(u, v)`` is centred at ``(u + 0.5, v + 0.5)``,
so a point seen at ``(x, y)`` in the photo is seen at ``(x * W' / W, y * H' / H)`` in the shrunk view.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image

from train_world.capture.files import area_resize, label_resize
from train_world.capture.format import atomic_write_bytes, atomic_write_json, encode_png

__all__ = ["shrunk_size", "shrink_capture"]


def shrunk_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    """``(width, height)`` scaled so that the long side is at most ``max_size`` (unchanged when it already is),
    each side at least one pixel."""
    if max_size < 1:
        raise ValueError(f"the largest side must be at least one pixel, got {max_size}")
    s = min(1.0, max_size / max(width, height))
    return max(1, round(width * s)), max(1, round(height * s))


def _shrink_image(path: Path, size: tuple[int, int]) -> None:
    with Image.open(path) as im:
        a = np.asarray(im.convert("RGB"))
    small = np.clip(np.rint(area_resize(a, size)), 0, 255).astype(np.uint8)
    atomic_write_bytes(path, encode_png(small))


def _shrink_mask(path: Path, size: tuple[int, int]) -> None:
    with Image.open(path) as im:
        a = np.asarray(im)
    atomic_write_bytes(path, encode_png(label_resize(a, size)))


def _shrink_depth(path: Path, size: tuple[int, int]) -> None:
    """The nearest pixel's depth, never a blend."""
    with Image.open(path) as im:
        a = np.asarray(im)
    small = np.asarray(Image.fromarray(a.astype(np.int32)).resize(size, Image.Resampling.NEAREST))
    atomic_write_bytes(path, encode_png(small.astype(a.dtype)))


def shrink_capture(folder: str | os.PathLike, states: Iterable[str], max_size: int) -> tuple[int, int] | None:
    """Shrink every view of ``states`` in the capture ``folder`` (images, masks, depth maps and each
    ``transforms.json``'s intrinsics) so that its long side is at most ``max_size`` pixels; returns the new
    ``(width, height)``, or None when the views were already that small (nothing is rewritten then). All
    states must have one size. ``transforms.json`` is rewritten last, so its intrinsics always describe
    the files it lists once the rewrite is complete; a capture being built is staged, and a crash in between
    leaves no capture at all."""
    folder = Path(folder)
    docs = {s: json.loads((folder / s / "transforms.json").read_text(encoding="utf-8")) for s in states}
    sizes = {(int(d["w"]), int(d["h"])) for d in docs.values()}
    if len(sizes) != 1:
        raise ValueError(
            f"{folder}: the states' views differ in size ({sorted(sizes)}); shrink them one by one"
        )
    (w, h) = sizes.pop()
    size = shrunk_size(w, h, max_size)
    if size == (w, h):
        return None
    sx, sy = size[0] / w, size[1] / h
    for s, doc in docs.items():
        for fr in doc["frames"]:
            _shrink_image(folder / s / fr["file_path"], size)
            if fr.get("mask_path"):
                _shrink_mask(folder / s / fr["mask_path"], size)
            if fr.get("depth_path"):
                _shrink_depth(folder / s / fr["depth_path"], size)
        doc["w"], doc["h"] = size
        doc["fl_x"], doc["cx"] = float(doc["fl_x"]) * sx, float(doc["cx"]) * sx
        doc["fl_y"], doc["cy"] = float(doc["fl_y"]) * sy, float(doc["cy"]) * sy
        doc["camera_angle_x"] = float(2.0 * np.arctan(0.5 * size[0] / doc["fl_x"]))
        doc["camera_angle_y"] = float(2.0 * np.arctan(0.5 * size[1] / doc["fl_y"]))
        atomic_write_json(folder / s / "transforms.json", doc)
    return size
