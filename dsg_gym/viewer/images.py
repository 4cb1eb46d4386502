"""The viewer panel's pictures of an observation: object ids and depth as RGB images."""

from __future__ import annotations

import numpy as np

__all__ = ["MASK_PALETTE", "depth_image", "mask_image", "panel_image"]

#: RGB of id 0 (background) and of objects 1, 2, ... (repeating past the end)
MASK_PALETTE = np.array(
    [
        [40, 40, 40],
        [230, 80, 60],
        [70, 110, 230],
        [70, 170, 90],
        [230, 190, 60],
        [170, 90, 200],
        [60, 190, 200],
    ],
    dtype=np.uint8,
)


def mask_image(mask: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W, 3]`` of an id mask ``[H, W]``: background dark grey, object k in ``MASK_PALETTE[k]``."""
    ids = np.asarray(mask).astype(np.int64)
    colours = np.concatenate([MASK_PALETTE[:1], MASK_PALETTE[1:][np.arange(max(int(ids.max()), 1)) % 6]])
    return colours[ids]


def depth_image(depth: np.ndarray) -> np.ndarray:
    """uint8 ``[H, W, 3]`` grey image of a depth map ``[H, W]`` (metres): inverse depth, scaled between the
    farthest and the nearest hit of this image, so near is bright and far dark (never black); black where
    nothing was hit (depth 0)."""
    d = np.asarray(depth, np.float64)
    hit = np.isfinite(d) & (d > 0)
    out = np.zeros(d.shape, np.float64)
    if hit.any():
        inv = 1.0 / d[hit]
        lo, hi = float(inv.min()), float(inv.max())
        out[hit] = 0.2 + 0.8 * (inv - lo) / max(hi - lo, 1e-12)
    grey = np.rint(out * 255).astype(np.uint8)
    return np.repeat(grey[..., None], 3, axis=-1)


def panel_image(obs) -> np.ndarray:
    """The panel's picture of an observation: its RGB, object ids and depth side by side (uint8 ``[H, 3W, 3]``,
    separated by 2-pixel white lines)."""
    parts = [obs["rgb"], mask_image(obs["mask"]), depth_image(obs["depth"])]
    gap = np.full((parts[0].shape[0], 2, 3), 255, np.uint8)
    return np.concatenate([parts[0], gap, parts[1], gap, parts[2]], axis=1)
