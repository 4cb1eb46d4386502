"""Training views at a lower resolution, for the joint phase's cross-state renders (``DualConfig.align_downscale``).

A joint step renders each field at its own view (the reconstruction loss) and, on top, each field moved into
the other state's view (``L_align``) and both fields moved into a pseudo-state (``L_pseudo``). The cross-state
renders can run at ``1/s`` of the training resolution: :func:`coarse_views` averages each image over ``s x s``
pixel blocks, gives each block its most frequent class (ties: the lowest id) and divides the intrinsics by
``s`` (pixel ``(u, v)`` centred at ``(u + 0.5, v + 0.5)``: a coarse pixel is the block of fine pixels
``[s u, s u + s) x [s v, s v + s)``), so a coarse render sees what the full camera sees, box-filtered. Rows
and columns past the last whole block are dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

__all__ = ["CoarseViews", "coarse_views"]


@dataclass(frozen=True)
class CoarseViews:
    """``images [V,h,w,3]``, ``classes [V,h,w]`` int64 or None, ``Ks [V,3,3]`` and the coarse size."""

    images: torch.Tensor
    classes: torch.Tensor | None
    Ks: torch.Tensor
    width: int
    height: int


def coarse_views(
    images: torch.Tensor, classes: torch.Tensor | None, Ks: torch.Tensor, factor: int, num_classes: int
) -> CoarseViews:
    """The views ``images [V,H,W,3]``, ``classes [V,H,W]`` (ids ``0 .. num_classes - 1``, or None) and
    ``Ks [V,3,3]`` at ``1/factor`` of their size (module docstring)."""
    s = int(factor)
    if s < 1:
        raise ValueError(f"downscale factor must be an integer >= 1, got {factor}")
    V, H, W, _ = images.shape
    h, w = H // s, W // s
    if h < 1 or w < 1:
        raise ValueError(f"images of {W}x{H} are smaller than the downscale factor {s}")
    img = F.avg_pool2d(images[:, : h * s, : w * s].permute(0, 3, 1, 2), s).permute(0, 2, 3, 1).contiguous()
    cls = None
    if classes is not None:
        one_hot = F.one_hot(classes[:, : h * s, : w * s], num_classes).permute(0, 3, 1, 2).float()
        cls = F.avg_pool2d(one_hot, s).argmax(dim=1)  # argmax: the first of equal counts
    K = Ks.clone()
    K[:, :2, :] = K[:, :2, :] / s
    return CoarseViews(img, cls, K, w, h)
