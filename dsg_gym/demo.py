"""Demo: render a small procedural tabletop splat scene and write a PNG.

    python -m dsg_gym.demo [--out out/demo.png] [--size 256]

A checkered table made of flat Gaussians and three objects (a box, a ball and a cylinder),
seen from four cameras on an orbit, rendered in one ``rasterize`` call with RGB and a one-hot
object-id feature per Gaussian in the same pass; the PNG shows RGB (top) and the object-id
argmax (bottom). Prints where it wrote the image and how long the render took.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

from dsg_gym.geometry import intrinsics_from_fov, look_at_viewmat
from dsg_gym.splat import rasterize

PALETTE = np.array([[40, 40, 40], [230, 80, 60], [70, 170, 90], [70, 110, 230]], dtype=np.uint8)


def _table(g: torch.Generator, n_side: int = 48):
    xs = torch.linspace(-0.4, 0.4, n_side)
    ys = torch.linspace(-0.3, 0.3, int(n_side * 0.75))
    X, Y = torch.meshgrid(xs, ys, indexing="ij")
    means = torch.stack([X.reshape(-1), Y.reshape(-1), torch.zeros(X.numel())], -1)
    checker = ((X / 0.05).floor() + (Y / 0.05).floor()).remainder(2).reshape(-1)
    noise = torch.rand(means.shape[0], generator=g) * 0.08
    rgb = torch.stack([0.55 + 0.35 * checker, 0.45 + 0.3 * checker, 0.3 + 0.2 * checker], -1) - noise[:, None]
    step = 0.8 / (n_side - 1)
    scales = torch.tensor([step * 0.7, step * 0.7, 0.002]).expand(means.shape[0], 3)
    return means, scales, rgb.clamp(0, 1), torch.zeros(means.shape[0], dtype=torch.long)


def _object(g: torch.Generator, kind: str, centre, size: float, rgb, label: int, n: int = 900):
    u = torch.rand(n, 3, generator=g) * 2 - 1
    if kind == "box":
        face = torch.randint(0, 3, (n,), generator=g)
        u[torch.arange(n), face] = torch.sign(u[torch.arange(n), face])
        pts = u * size
    elif kind == "ball":
        pts = u / u.norm(dim=-1, keepdim=True) * size
    else:  # cylinder along z
        ang = u[:, 0] * math.pi
        pts = torch.stack([torch.cos(ang) * size, torch.sin(ang) * size, u[:, 2] * size], -1)
    means = pts + torch.tensor(centre) + torch.tensor([0.0, 0.0, size])
    shade = 0.75 + 0.25 * torch.rand(n, 1, generator=g)
    colors = (torch.tensor(rgb) * shade).clamp(0, 1)
    scales = torch.full((n, 3), size * 0.12)
    return means, scales, colors, torch.full((n,), label, dtype=torch.long)


def build_scene(seed: int = 0):
    """Means, quats, scales, opacities and colours (RGB + 4 one-hot ids) of the demo scene."""
    g = torch.Generator().manual_seed(seed)
    parts = [_table(g),
             _object(g, "box", (-0.15, -0.05, 0.0), 0.05, (0.9, 0.3, 0.25), 1),
             _object(g, "ball", (0.12, 0.08, 0.0), 0.045, (0.3, 0.75, 0.35), 2),
             _object(g, "cylinder", (0.05, -0.15, 0.0), 0.04, (0.3, 0.45, 0.95), 3)]
    means = torch.cat([p[0] for p in parts])
    scales = torch.cat([p[1] for p in parts])
    rgb = torch.cat([p[2] for p in parts])
    labels = torch.cat([p[3] for p in parts])
    onehot = torch.nn.functional.one_hot(labels, 4).float()
    n = means.shape[0]
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous()
    opacities = torch.full((n,), 0.95)
    return means, quats, scales.contiguous(), opacities, torch.cat([rgb, onehot], -1)


def orbit_cameras(n: int, size: int, radius: float = 0.75, height: float = 0.45):
    eyes = [torch.tensor([radius * math.cos(a), radius * math.sin(a), height])
            for a in np.linspace(0, 2 * math.pi, n, endpoint=False) + 0.3]
    viewmats = look_at_viewmat(torch.stack(eyes), torch.zeros(n, 3), torch.tensor([0.0, 0.0, 1.0]).expand(n, 3))
    Ks = intrinsics_from_fov(math.radians(50.0), size, size).expand(n, 3, 3)
    return viewmats.float().contiguous(), Ks.float().contiguous()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Render a procedural splat scene to a PNG.")
    ap.add_argument("--out", default="out/demo.png", help="PNG path (default out/demo.png)")
    ap.add_argument("--size", type=int, default=256, help="image width = height in pixels")
    ap.add_argument("--views", type=int, default=4, help="number of cameras on the orbit")
    args = ap.parse_args(argv)
    from PIL import Image

    means, quats, scales, opacities, colors = build_scene()
    viewmats, Ks = orbit_cameras(args.views, args.size)
    bg = torch.tensor([0.85, 0.88, 0.92, 1.0, 0.0, 0.0, 0.0])
    rasterize(means, quats, scales, opacities, colors, viewmats, Ks, args.size, args.size, backgrounds=bg)
    t0 = time.perf_counter()
    out, alpha, meta = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, args.size, args.size,
                                 backgrounds=bg)
    ms = (time.perf_counter() - t0) * 1e3
    rgb = (out[..., :3].clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    ids = out[..., 3:].argmax(-1).numpy()
    top = np.concatenate(list(rgb), axis=1)
    bottom = np.concatenate(list(PALETTE[ids]), axis=1)
    path = Path(args.out)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    Image.fromarray(np.concatenate([top, bottom], axis=0)).save(tmp, format="PNG")
    os.replace(tmp, path)
    print(f"rendered {means.shape[0]} Gaussians into {args.views} views of {args.size}x{args.size} "
          f"(RGB + 4 id channels) in {ms:.1f} ms")
    print(f"wrote {path.resolve()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
