"""Refit a pruned Gaussian set to the renders of the set it came from (distillation), for ``dsg-compact``.

Removing Gaussians leaves small gaps and colour changes that the survivors can absorb: their SH colours,
opacities, scales and (optionally) means are optimised with Adam so that their renders match the original
set's renders (RGB over black plus alpha, L1) from the same cameras the importance was measured with. Two
random views per step (a seeded generator: the result is deterministic), the numba rasterizer's backward,
learning rates decaying linearly to zero.
Higher SH bands that the SH cut zeroed stay zero; Gaussians given a ``min_opacity`` never fall below it
(``dsg-compact`` passes 0.2 for an object's collision-hull vertices, so its physics proxy is unchanged).
Scales may shrink but, unless ``grow_scales``, never grow: a larger footprint costs render time in every
pixel it reaches, and speed is what compaction is for: letting them grow ends at fewer Gaussians and better
self-consistency but a slower render.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from dsg_gym.gaussians import GaussianSet, activate_opacity, activate_scale
from dsg_gym.splat import rasterize

__all__ = ["refit"]


def _t(a) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, np.float32))


@torch.no_grad()
def _targets(
    g: GaussianSet, vm: torch.Tensor, K: torch.Tensor, width: int, height: int, splat: dict
) -> torch.Tensor:
    """``[V,H,W,4]`` RGB over black and alpha of ``g``."""
    out = []
    for a in range(0, len(vm), 8):
        rgb, alpha, _ = rasterize(
            _t(g.means),
            _t(g.quats),
            _t(g.scales),
            _t(g.opacities),
            _t(g.sh),
            vm[a : a + 8],
            K[a : a + 8],
            width,
            height,
            sh_degree=g.sh_degree,
            **splat,
        )
        out.append(torch.cat([rgb, alpha], -1))
    return torch.cat(out)


def refit(
    g: GaussianSet,
    original: GaussianSet,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    *,
    steps: int,
    sh_degrees: np.ndarray | None = None,
    fit_means: bool = True,
    fit_scales: bool = True,
    grow_scales: bool = False,
    min_opacity: np.ndarray | None = None,
    views_per_step: int = 2,
    seed: int = 0,
    splat_options: dict | None = None,
) -> GaussianSet:
    """``g`` (``N`` Gaussians) refitted to ``original``'s renders in ``viewmats [V,4,4]``, ``Ks [V,3,3]``.

    ``sh_degrees [N]``: per-Gaussian SH degree (bands above stay zero; default: all of ``g``'s bands);
    ``min_opacity [N]``: lower bounds on the opacities (default none). Returns a new set with consistent raw
    encodings (``opacity_logits``, ``log_scales`` are the fitted values); ``steps == 0`` returns ``g``.
    ``splat_options``: the world's renderer options (``World.splat_options``; default: 3DGS's).
    """
    if steps <= 0 or g.num == 0 or len(viewmats) == 0:
        return g
    vm, K = _t(viewmats), _t(Ks)
    splat = dict(splat_options or {})
    target = _targets(original, vm, K, width, height, splat)
    k = g.sh.shape[1]
    deg = np.full(g.num, g.sh_degree) if sh_degrees is None else np.asarray(sh_degrees)
    band = torch.from_numpy((np.arange(k)[None, :] < (deg[:, None] + 1) ** 2).astype(np.float32))[..., None]
    sh = _t(g.sh).requires_grad_(True)
    logit = torch.logit(_t(g.opacities).clamp(1e-6, 1 - 1e-6)).requires_grad_(True)
    log_s = torch.log(_t(g.scales).clamp_min(1e-12)).requires_grad_(fit_scales)
    means = _t(g.means).requires_grad_(fit_means)
    quats = _t(g.quats)
    lo = None if min_opacity is None else torch.logit(_t(min_opacity).clamp(1e-6, 1 - 1e-6))
    hi_s = None if grow_scales else log_s.detach().clone()
    scene = float(np.median(g.scales.max(1))) if g.num else 1.0
    groups = [{"params": [sh], "lr": 0.005}, {"params": [logit], "lr": 0.02}]
    if fit_scales:
        groups.append({"params": [log_s], "lr": 0.002})
    if fit_means:
        groups.append({"params": [means], "lr": 0.01 * scene})
    opt = torch.optim.Adam(groups)
    n = int(steps)  # learning rates decay linearly to 0: the last steps only settle (no noise floor)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1.0 - i / n)
    gen = torch.Generator().manual_seed(int(seed))
    for _ in range(n):
        idx = torch.randperm(len(vm), generator=gen)[:views_per_step]
        rgb, alpha, _ = rasterize(
            means,
            quats,
            torch.exp(log_s),
            torch.sigmoid(logit),
            sh * band,
            vm[idx],
            K[idx],
            width,
            height,
            sh_degree=g.sh_degree,
            **splat,
        )
        loss = (rgb - target[idx, ..., :3]).abs().mean() + (alpha - target[idx, ..., 3:]).abs().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        with torch.no_grad():
            if lo is not None:
                logit.copy_(torch.maximum(logit, lo))
            if hi_s is not None:
                log_s.copy_(torch.minimum(log_s, hi_s))
    with torch.no_grad():
        logits = logit.numpy().astype(np.float32)
        log_scales = log_s.numpy().astype(np.float32)
        opac, scales = activate_opacity(logits), activate_scale(log_scales)
        return dataclasses.replace(
            g,
            means=means.detach().numpy().copy(),
            sh=(sh * band).detach().numpy().copy(),
            opacities=opac,
            scales=scales,
            opacity_logits=logits,
            log_scales=log_scales,
        )
