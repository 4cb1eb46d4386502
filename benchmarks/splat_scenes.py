"""Procedural Gaussian scenes (``rasterize`` keyword arguments) for the render benchmark and splat tests."""

from __future__ import annotations

import math

import torch


def intrinsics(width: int, height: int, fov_deg: float = 60.0, dtype=torch.float32) -> torch.Tensor:
    """K [3,3] with square pixels, horizontal field of view ``fov_deg``, centred principal point."""
    f = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=dtype)


def random_scene(
    n: int,
    width: int = 64,
    height: int = 48,
    channels: int = 19,
    seed: int = 0,
    dtype=torch.float32,
    cameras: int = 1,
    scale_range=(0.02, 0.1),
):
    """N Gaussians filling a 60-degree view at depths 2..6 in front of camera 0.

    Returns a dict of rasterize() keyword arguments. With ``cameras > 1`` the extra cameras
    are small rotations/translations of the first one.
    """
    g = torch.Generator().manual_seed(seed)
    K = intrinsics(width, height, dtype=dtype)
    f = float(K[0, 0])
    z = torch.rand(n, generator=g, dtype=dtype) * 4 + 2
    x = (torch.rand(n, generator=g, dtype=dtype) * 2 - 1) * z * width / (2 * f)
    y = (torch.rand(n, generator=g, dtype=dtype) * 2 - 1) * z * height / (2 * f)
    lo, hi = scale_range
    scales = torch.exp(torch.rand(n, 3, generator=g, dtype=dtype) * math.log(hi / lo)) * lo
    viewmats = [torch.eye(4, dtype=dtype)]
    for c in range(1, cameras):
        a = 0.05 * c
        R = torch.tensor(
            [[math.cos(a), 0.0, math.sin(a)], [0.0, 1.0, 0.0], [-math.sin(a), 0.0, math.cos(a)]], dtype=dtype
        )
        V = torch.eye(4, dtype=dtype)
        V[:3, :3] = R
        V[:3, 3] = torch.tensor([0.05 * c, -0.02 * c, 0.1 * c], dtype=dtype)
        viewmats.append(V)
    return dict(
        means=torch.stack([x, y, z], -1),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=scales,
        opacities=torch.rand(n, generator=g, dtype=dtype) * 0.9 + 0.05,
        colors=torch.rand(n, channels, generator=g, dtype=dtype),
        viewmats=torch.stack(viewmats),
        Ks=K[None].expand(cameras, 3, 3).contiguous(),
        width=width,
        height=height,
    )
