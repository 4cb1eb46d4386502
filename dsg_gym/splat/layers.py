"""Two-layer splatting: background and objects rendered apart, merged per pixel by expected depth.

One depth-sorted list per tile orders Gaussians by their centres' depth. Where a flat background Gaussian
(the table top) is centred in front of an object's base, it is blended first even at pixels where the base is
in front of it; at the poses a world was trained at, the fit works around that, at new poses it cannot. Two
layers avoid it: each layer is splatted alone, and at every pixel the nearer layer goes over the other. The
objects' layer (``a``) is nearer unless the background's expected depth is smaller than ``1 / (1 + margin)`` of
the objects' (``margin``: :data:`dsg_gym.splat_options.LAYER_MARGIN`, 1 %). An object's Gaussians are centred
inside it, so where it stands on the table its expected depth lies a few millimetres behind its visible surface,
within the table's; without the margin the table would cover the base there:

    C = C_near + (1 - a_near) C_far + (1 - a_near)(1 - a_far) bg,    alpha = 1 - (1 - a_near)(1 - a_far)

with ``C`` premultiplied layer colours (what the rasterizer accumulates over a zero background), ``a`` their
alphas and the expected depth ``D / a`` (``D``: accumulated depth). A layer with no coverage at a pixel
(``a`` below ``1e-6``) is infinitely far there. The choice of the near layer is not differentiated; gradients
flow through both layers' colours and alphas.

A world records this with ``metadata["compositing"] = "layers"`` (``dsg_gym.world.World.compositing``);
every renderer of such a world composites the same way.
"""

from __future__ import annotations

import torch

from ..splat_options import LAYER_MARGIN
from .rasterization import rasterize

__all__ = ["merge_layers", "rasterize_layers"]

_EMPTY = 1e-6  # a layer whose alpha is below this at a pixel does not cover it


def merge_layers(
    colors_a: torch.Tensor,
    alphas_a: torch.Tensor,
    depths_a: torch.Tensor,
    colors_b: torch.Tensor,
    alphas_b: torch.Tensor,
    depths_b: torch.Tensor,
    backgrounds: torch.Tensor | None = None,
    margin: float = LAYER_MARGIN,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Merge two rendered layers per pixel, the nearer (by expected depth) over the other.

    Args:
        colors_a, colors_b: ``[..., H, W, D]`` premultiplied colours (rendered over a zero background).
        alphas_a, alphas_b: ``[..., H, W, 1]``.
        depths_a, depths_b: ``[..., H, W, 1]`` accumulated depth (``sum w_i z_i``; ``D / alpha`` is the
            expected depth). Layer ``a`` goes in front where its expected depth is less than ``1 + margin`` times
            layer ``b``'s.
        backgrounds: ``[..., D]`` colour behind both layers (default 0).
        margin: how far, relative to its depth, ``b`` must be nearer than ``a`` to go in front (module docstring).

    Returns:
        ``colors [..., H, W, D]``, ``alphas [..., H, W, 1]`` and accumulated ``depths [..., H, W, 1]`` of the
        merged image.
    """
    inf = torch.full_like(depths_a, float("inf"))
    ed_a = torch.where(alphas_a > _EMPTY, depths_a / alphas_a.clamp_min(_EMPTY), inf)
    ed_b = torch.where(alphas_b > _EMPTY, depths_b / alphas_b.clamp_min(_EMPTY), inf)
    a_first = ed_a < ed_b * (1.0 + margin)
    ta, tb = 1.0 - alphas_a, 1.0 - alphas_b
    colors = torch.where(a_first, colors_a + ta * colors_b, colors_b + tb * colors_a)
    depths = torch.where(a_first, depths_a + ta * depths_b, depths_b + tb * depths_a)
    trans = ta * tb
    if backgrounds is not None:
        colors = colors + trans * backgrounds[..., None, None, :]
    return colors, 1.0 - trans, depths


def rasterize_layers(
    front: torch.Tensor,
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    **kwargs,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """:func:`~dsg_gym.splat.rasterize` of two layers, merged by :func:`merge_layers`.

    ``front``: ``[N]`` bool, the Gaussians of layer ``a`` (the objects); the others form layer ``b`` (the
    background). ``render_mode``: "RGB" or "RGB+D". Every other argument as :func:`~dsg_gym.splat.rasterize`
    (colours as final colours, ``[N, D]`` or ``[C, N, D]``; opacities ``[N]`` or ``[C, N]``).

    Returns ``colors [C, H, W, D(+1)]``, ``alphas [C, H, W, 1]`` and ``meta`` with ``layers``: the two
    rasterize calls' meta (front, back) and ``index``: the Gaussians of each, ``[N_a]`` and ``[N_b]`` int64.
    """
    if render_mode not in ("RGB", "RGB+D"):
        raise ValueError(f"rasterize_layers: render_mode must be 'RGB' or 'RGB+D', got {render_mode!r}")
    front = torch.as_tensor(front, dtype=torch.bool)
    if front.shape != (means.shape[0],):
        raise ValueError(f"rasterize_layers: front must be [N] = [{means.shape[0]}], got {list(front.shape)}")
    outs, metas, index = [], [], []
    for sel in (front, ~front):
        idx = torch.nonzero(sel).squeeze(1)
        op = opacities[..., idx]
        col = colors[idx] if colors.dim() == 2 else colors[:, idx]
        out, alpha, meta = rasterize(
            means[idx], quats[idx], scales[idx], op, col, viewmats, Ks, width, height,
            render_mode="RGB+D", **kwargs,
        )  # fmt: skip
        outs.append((out[..., :-1], alpha, out[..., -1:]))
        metas.append(meta)
        index.append(idx)
    bg = None
    if backgrounds is not None:
        bg = backgrounds if backgrounds.dim() == 2 else backgrounds[None].expand(viewmats.shape[0], -1)
    rgb, alpha, depth = merge_layers(*outs[0], *outs[1], backgrounds=bg)
    if render_mode == "RGB+D":
        rgb = torch.cat([rgb, depth], dim=-1)
    return rgb, alpha, {"layers": tuple(metas), "index": tuple(index)}
