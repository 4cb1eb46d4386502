"""Adaptive density control (3DGS): clone, split, prune and opacity reset, as a strategy object.

The strategy owns its statistics (accumulated view-space gradient norms and visibility counts) and edits a
:class:`~train_world.single_state.field.SegmentedField` together with its optimisers (one Adam per parameter,
``{name: optimizer}``): rows added by clone/split get zero Adam moments, pruned rows lose theirs, the opacity
reset zeroes the opacity moments. Usage per step::

    strategy.before_backward(out.meta)          # retain the 2D mean gradient
    loss.backward()
    strategy.after_backward(step, field, optimizers, out.meta, generator)

The view-space gradient is measured in NDC units (pixel gradient times ``(W/2, H/2)`` times the number of
cameras), so the 3DGS threshold 2e-4 applies unchanged. With ``absgrad`` (AbsGS) the statistic is the norm of
the sums of absolute per-pixel gradients instead (the renders must be made with ``absgrad=True``:
:meth:`DensifyStrategy.wants_absgrad`), so a large Gaussian over texture, whose pixels pull its mean in
opposite directions, is split rather than left to blur; its threshold is ``absgrad_threshold``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from dsg_gym.geometry import quat_to_rotmat
from train_world.single_state.field import PARAM_NAMES, SegmentedField

__all__ = ["DensifyStrategy", "StrategyConfig", "update_rows"]


@dataclass(frozen=True)
class StrategyConfig:
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    reset_every: int = 3000
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_big_world: float = 0.1
    max_gaussians: int = 1_000_000
    scene_extent: float = 1.0
    absgrad: bool = False
    absgrad_threshold: float = 8e-4

    @classmethod
    def from_preset(cls, preset, scene_extent: float) -> StrategyConfig:
        return cls(
            densify_from=preset.densify_from,
            densify_until=preset.densify_until,
            densify_every=preset.densify_every,
            reset_every=preset.reset_every,
            grad_threshold=preset.grad_threshold,
            percent_dense=preset.percent_dense,
            prune_opacity=preset.prune_opacity,
            prune_big_world=preset.prune_big_world,
            max_gaussians=preset.max_gaussians,
            scene_extent=float(scene_extent),
            absgrad=preset.absgrad,
            absgrad_threshold=preset.absgrad_threshold,
        )


def update_rows(
    field: SegmentedField,
    optimizers: dict[str, torch.optim.Optimizer],
    keep: torch.Tensor | None,
    new_values: dict[str, torch.Tensor] | None,
) -> None:
    """Keep rows ``keep`` (bool ``[N]`` or None for all) of every parameter and append ``new_values``
    (same keys as the parameters); Adam moments follow (zeros for appended rows)."""
    for name in PARAM_NAMES:
        old = getattr(field, name)
        val = old.data if keep is None else old.data[keep]
        extra = None if new_values is None else new_values[name].to(val.dtype)
        if extra is not None:
            val = torch.cat([val, extra], dim=0)
        new = field.set_param(name, val)
        opt = optimizers.get(name)
        if opt is None:
            continue
        opt.param_groups[0]["params"] = [new]
        state = opt.state.pop(old, None)
        if state:
            for key in ("exp_avg", "exp_avg_sq"):
                if key in state:
                    v = state[key] if keep is None else state[key][keep]
                    if extra is not None:
                        v = torch.cat([v, torch.zeros_like(extra)], dim=0)
                    state[key] = v.contiguous()
            opt.state[new] = state


class DensifyStrategy:
    """3DGS densification schedule (see the module docstring). ``state`` tensors are checkpointed."""

    def __init__(self, config: StrategyConfig, num: int = 0):
        self.config = config
        self.grad2d = torch.zeros(num, dtype=torch.float64)
        self.count = torch.zeros(num, dtype=torch.int64)

    # ------------------------------------------------------------------ state
    def state_tensors(self) -> dict[str, torch.Tensor]:
        return {"grad2d": self.grad2d, "count": self.count}

    def load_state_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        self.grad2d = tensors["grad2d"].clone().to(torch.float64)
        self.count = tensors["count"].clone().to(torch.int64)

    def _reset_stats(self, n: int) -> None:
        self.grad2d = torch.zeros(n, dtype=torch.float64)
        self.count = torch.zeros(n, dtype=torch.int64)

    # ------------------------------------------------------------------ per step
    @staticmethod
    def before_backward(meta: dict) -> None:
        if meta["means2d"].requires_grad:
            meta["means2d"].retain_grad()

    def wants_absgrad(self, step: int) -> bool:
        """Whether the render of the step after ``step`` steps must carry absolute 2D mean gradients."""
        return self.config.absgrad and step < self.config.densify_until

    def accumulate(self, meta: dict) -> None:
        """Add this step's NDC-scaled 2D mean gradient norms of the visible Gaussians."""
        g = meta["means2d"].grad
        if g is None:
            return
        if self.config.absgrad:
            g = getattr(meta["means2d"], "absgrad", None)
            if g is None:
                raise ValueError(
                    "absgrad densification needs renders made with absgrad=True (the numba backend)"
                )
        n = g.shape[1]
        if self.grad2d.shape[0] != n:
            raise ValueError(f"strategy statistics cover {self.grad2d.shape[0]} Gaussians, render has {n}")
        c = int(meta.get("n_cameras", g.shape[0]))
        scale = torch.tensor([meta["width"] / 2.0 * c, meta["height"] / 2.0 * c], dtype=torch.float64)
        norms = (g.detach().double() * scale).norm(dim=-1)  # [C,N]
        visible = (meta["radii"] > 0).all(dim=-1)  # [C,N]
        self.grad2d += torch.where(visible, norms, torch.zeros_like(norms)).sum(0)
        self.count += visible.sum(0)

    def after_backward(
        self,
        step: int,
        field: SegmentedField,
        optimizers: dict[str, torch.optim.Optimizer],
        meta: dict,
        generator: torch.Generator | None = None,
    ) -> dict[str, int]:
        """Accumulate statistics and, on schedule, densify/prune and reset opacities. ``step`` counts from 1
        (the number of optimiser steps taken after this one). Returns what changed."""
        cfg = self.config
        info = {"clone": 0, "split": 0, "prune": 0, "reset": 0}
        if step > cfg.densify_until:
            return info
        self.accumulate(meta)
        if step >= cfg.densify_from and step % cfg.densify_every == 0:
            info.update(
                self.densify_and_prune(field, optimizers, generator, after_reset=step > cfg.reset_every)
            )
        if step % cfg.reset_every == 0 and step < cfg.densify_until:
            self.reset_opacity(field, optimizers, 2.0 * cfg.prune_opacity)
            info["reset"] = 1
        return info

    # ------------------------------------------------------------------ operations
    def densify_and_prune(
        self,
        field: SegmentedField,
        optimizers: dict[str, torch.optim.Optimizer],
        generator: torch.Generator | None = None,
        after_reset: bool = False,
    ) -> dict[str, int]:
        cfg = self.config
        avg = self.grad2d / self.count.clamp_min(1)
        high = avg > (cfg.absgrad_threshold if cfg.absgrad else cfg.grad_threshold)
        room = cfg.max_gaussians - field.num
        if int(high.sum()) > max(room, 0):  # keep the strongest candidates under the cap
            keep_n = max(room, 0)
            order = torch.argsort(avg, descending=True, stable=True)
            capped = torch.zeros_like(high)
            capped[order[:keep_n]] = True
            high &= capped
        small = field.scales().detach().max(dim=-1).values <= cfg.percent_dense * cfg.scene_extent
        clone_mask = high & small
        split_mask = high & ~small
        n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())
        if n_clone:
            self.clone(field, optimizers, clone_mask)
            split_mask = torch.cat([split_mask, torch.zeros(n_clone, dtype=torch.bool)])
        if n_split:
            self.split(field, optimizers, split_mask, generator)
        prune_mask = field.opacities().detach() < cfg.prune_opacity
        if after_reset:
            big = field.scales().detach().max(dim=-1).values > cfg.prune_big_world * cfg.scene_extent
            prune_mask |= big
        n_prune = int(prune_mask.sum())
        if n_prune:
            self.prune(field, optimizers, prune_mask)
        self._reset_stats(field.num)
        return {"clone": n_clone, "split": n_split, "prune": n_prune}

    def clone(self, field: SegmentedField, optimizers: dict, mask: torch.Tensor) -> None:
        """Duplicate the Gaussians in ``mask`` (appended at the end)."""
        new = {name: getattr(field, name).data[mask].clone() for name in PARAM_NAMES}
        update_rows(field, optimizers, None, new)
        self._grow_stats(int(mask.sum()))

    def split(
        self,
        field: SegmentedField,
        optimizers: dict,
        mask: torch.Tensor,
        generator: torch.Generator | None = None,
        n_split: int = 2,
    ) -> None:
        """Replace each Gaussian in ``mask`` by ``n_split`` samples from it, scales divided by 1.6."""
        sel = mask.nonzero().squeeze(-1)
        m = sel.numel()
        scales = field.scales().data[sel]
        R = quat_to_rotmat(field.quats.data[sel])
        noise = torch.randn((n_split, m, 3), generator=generator, dtype=scales.dtype)
        offsets = torch.einsum("nij,snj->sni", R, scales[None] * noise)
        new = {}
        for name in PARAM_NAMES:
            v = getattr(field, name).data[sel]
            new[name] = v.repeat((n_split,) + (1,) * (v.dim() - 1))
        new["means"] = (field.means.data[sel][None] + offsets).reshape(-1, 3)
        new["log_scales"] = torch.log(scales / (0.8 * n_split)).repeat(n_split, 1)
        keep = ~mask
        update_rows(field, optimizers, keep, new)
        self.grad2d = torch.cat([self.grad2d[keep], torch.zeros(n_split * m, dtype=torch.float64)])
        self.count = torch.cat([self.count[keep], torch.zeros(n_split * m, dtype=torch.int64)])

    def prune(self, field: SegmentedField, optimizers: dict, mask: torch.Tensor) -> None:
        """Remove the Gaussians in ``mask``."""
        keep = ~mask
        update_rows(field, optimizers, keep, None)
        self.grad2d = self.grad2d[keep]
        self.count = self.count[keep]

    @staticmethod
    def reset_opacity(field: SegmentedField, optimizers: dict, value: float) -> None:
        """Clamp every opacity to at most ``value`` and zero the opacity Adam moments."""
        cap = math.log(value / (1.0 - value))
        with torch.no_grad():
            field.opacity_logits.data.clamp_(max=cap)
        opt = optimizers.get("opacity_logits")
        if opt is not None:
            st = opt.state.get(field.opacity_logits)
            if st:
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in st:
                        st[key].zero_()

    def _grow_stats(self, n: int) -> None:
        self.grad2d = torch.cat([self.grad2d, torch.zeros(n, dtype=torch.float64)])
        self.count = torch.cat([self.count, torch.zeros(n, dtype=torch.int64)])
