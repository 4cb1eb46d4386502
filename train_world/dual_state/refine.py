"""Refinement of a merged two-state world on both states' training views (not part of DSG-World).

The merged world (:mod:`.world`) is assembled after training: the background from ``G1`` with ``G2``'s
co-pasted patches, each object from one of the two fields. Nothing has yet fitted that assembly to the images.
:func:`refine_world` does: every step renders the merged world with its objects at one training state's poses,
from one of that state's training views (the states alternate, the view is drawn with a seeded generator), and
takes an Adam step on the reconstruction loss (L1 + D-SSIM, the preset's weight) for the centres, rotations,
scales, opacities and SH colours of every Gaussian. Learning rates are 3DGS's late-training rates and decay
linearly to zero. Identity features, the classifier, the Gaussian count and the poses do not change.

Object Gaussians are optimised in their own frames (where the world stores them) and placed by each state's
poses while rendering, so one copy of each object learns from the views of both states: that, and not the
longer training, is the gain: refining on ``state1``'s views alone gains almost nothing at the test states
(docs/training.md). A step takes one 3-channel render.

Deterministic for a given world, views, configuration and thread count. ``dsg-train`` runs it after merging
(the preset's ``dual_refine_steps``, ``--refine-steps``); ``python -m train_world.cli.refine`` refines a world
file that was written without it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from dsg_gym.gaussians import GaussianSet, activate_opacity, activate_scale
from dsg_gym.world import World, WorldObject
from train_world.dual_state.losses import support_loss
from train_world.dual_state.transfer import ObjectTransfer, gaussian_transforms
from train_world.single_state.field import SegmentedField
from train_world.single_state.losses import photometric_loss

__all__ = ["RefineConfig", "StateViews", "refine_world", "training_views_of"]


@dataclass(frozen=True)
class RefineConfig:
    """``steps``: Adam steps (0: off); learning rates at step 0 (``means`` in scene units, i.e. not scaled by the
    extent), decaying linearly to 0; ``lambda_dssim``: the D-SSIM weight of the loss; ``seed``: view order;
    ``support_weight``: weight of ``L_support`` (:func:`.losses.support_loss`) on the objects' Gaussians at the
    pose of the state each step renders (0: off; only for worlds whose table top is z = 0); ``layers``: render
    the background and the objects as two layers merged per pixel by expected depth
    (:mod:`dsg_gym.splat.layers`); the refined world then records ``metadata["compositing"] = "layers"``."""

    steps: int = 3000
    lr_means: float = 1.6e-5
    lr_quats: float = 1e-3
    lr_scales: float = 5e-3
    lr_opacities: float = 2.5e-2
    lr_sh0: float = 2.5e-3
    lr_shN: float = 2.5e-3 / 20
    lambda_dssim: float = 0.2
    seed: int = 0
    support_weight: float = 0.0
    layers: bool = False

    def __post_init__(self) -> None:
        if int(self.steps) != self.steps or self.steps < 0:
            raise ValueError(f"refine steps must be an integer >= 0, got {self.steps}")
        for f in dataclasses.fields(self):
            if f.name.startswith("lr_") or f.name in ("lambda_dssim", "support_weight"):
                v = getattr(self, f.name)
                if not (math.isfinite(v) and v >= 0):
                    raise ValueError(f"refine {f.name} must be a finite number >= 0, got {v}")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class StateViews(NamedTuple):
    """Training views of one state: ``images [V,H,W,3]`` float32 in [0,1] (over the world's background colour),
    ``viewmats [V,4,4]`` OpenCV world-to-camera, ``Ks [V,3,3]``."""

    images: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


def _field(parts: list[GaussianSet], world: World) -> SegmentedField:
    g = GaussianSet.concat(parts)
    sh = _t(g.sh)
    f = SegmentedField(
        _t(g.means),
        _t(g.quats),
        _t(g.encoded_log_scales()),
        _t(g.encoded_opacity_logits()),
        sh[:, :1],
        sh[:, 1:],
        _t(g.features),
    )
    f.configure_filters(**world.splat_options)
    return f


def _split(f: SegmentedField, parts: list[GaussianSet]) -> list[GaussianSet]:
    """``parts`` with the field's rows written back (features and labels kept)."""
    with torch.no_grad():
        q = f.quats.detach()
        q = (q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)).numpy()
        logits = f.opacity_logits.detach().numpy().astype(np.float32)
        log_s = f.log_scales.detach().numpy().astype(np.float32)
        means = f.means.detach().numpy()
        sh = f.sh().detach().numpy()
    out, a = [], 0
    for p in parts:
        b = a + p.num
        k = p.sh.shape[1]
        out.append(
            dataclasses.replace(
                p,
                means=means[a:b].copy(),
                quats=q[a:b].copy(),
                sh=sh[a:b, :k].copy(),
                opacities=activate_opacity(logits[a:b]),
                scales=activate_scale(log_s[a:b]),
                opacity_logits=logits[a:b].copy(),
                log_scales=log_s[a:b].copy(),
            )
        )
        a = b
    return out


def _check_views(world: World, views: Mapping[str, StateViews]) -> None:
    if not views:
        raise ValueError("refine_world: no training views given")
    for s, v in views.items():
        if s not in world.poses:
            raise ValueError(
                f"refine_world: the world has no poses for state {s!r} (states: {list(world.poses)})"
            )
        n = v.images.shape[0]
        if n == 0 or v.images.dim() != 4 or v.images.shape[-1] != 3:
            raise ValueError(
                f"refine_world: state {s!r}: images must be [V,H,W,3] with V > 0, got {tuple(v.images.shape)}"
            )
        if v.viewmats.shape != (n, 4, 4) or v.Ks.shape != (n, 3, 3):
            raise ValueError(
                f"refine_world: state {s!r}: {n} images but viewmats {tuple(v.viewmats.shape)}, "
                f"Ks {tuple(v.Ks.shape)}"
            )
        if not bool(torch.isfinite(v.images).all()):
            raise ValueError(f"refine_world: state {s!r}: images have NaN or Inf")


def refine_world(
    world: World,
    views: Mapping[str, StateViews],
    config: RefineConfig = RefineConfig(),
    *,
    progress: bool = False,
) -> tuple[World, dict[str, Any]]:
    """``world`` refined on ``views`` (training views per state, :class:`StateViews`); returns the new world
    (``metadata["refine"]`` records the configuration and the loss) and that record plus ``seconds``.
    ``config.steps == 0`` returns ``world`` unchanged. The input world is not modified."""
    _check_views(world, views)
    if config.steps == 0 or not world.background.num + sum(o.gaussians.num for o in world.objects.values()):
        return world, {"steps": 0}
    t0 = time.perf_counter()
    ids = world.object_ids
    parts = [world.background] + [world.objects[i].gaussians for i in ids]
    labels = torch.cat([torch.full((p.num,), r, dtype=torch.int64) for r, p in enumerate(parts)])
    f = _field(parts, world)
    # object frame -> world at each state: the object's pose there (ObjectTransfer moves class r by table[r-1])
    transfers = {
        s: ObjectTransfer(labels, torch.from_numpy(np.asarray(world.poses[s], np.float32).reshape(-1, 4, 4)))
        for s in views
    }
    c = config
    n_bg = world.background.num
    front = labels > 0 if c.layers or world.metadata.get("compositing") == "layers" else None
    object_poses = {  # each object Gaussian's pose at each state (object frame -> table frame)
        s: gaussian_transforms(labels[n_bg:], np.asarray(world.poses[s], np.float32).reshape(-1, 4, 4))
        for s in views
        if c.support_weight > 0
    }
    lrs = {
        "means": c.lr_means,
        "quats": c.lr_quats,
        "log_scales": c.lr_scales,
        "opacity_logits": c.lr_opacities,
        "sh0": c.lr_sh0,
        "shN": c.lr_shN,
    }
    opt = torch.optim.Adam([{"params": [getattr(f, k)], "lr": v} for k, v in lrs.items()], eps=1e-15)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1.0 - i / c.steps)
    bg = torch.tensor(tuple(world.metadata.get("background", (0.0, 0.0, 0.0))), dtype=torch.float32)
    width, height = (
        int(x) for x in (views[next(iter(views))].images.shape[2], views[next(iter(views))].images.shape[1])
    )
    gen = torch.Generator().manual_seed(int(c.seed))
    states = list(views)
    losses: list[float] = []
    bar = tqdm(range(c.steps), desc="refine", disable=not progress, leave=False)
    for i in bar:
        s = states[i % len(states)]
        v = views[s]
        j = int(torch.randint(v.images.shape[0], (1,), generator=gen))
        out = f.render(
            v.viewmats[j : j + 1],
            v.Ks[j : j + 1],
            width,
            height,
            transform=transfers[s],
            background=bg,
            with_features=False,
            layers=front,
        )
        loss = photometric_loss(out.rgb, v.images[j : j + 1], c.lambda_dssim)
        if c.support_weight > 0:
            o = slice(n_bg, None)
            loss = loss + c.support_weight * support_loss(
                f.means[o], f.quats[o], f.log_scales[o], f.opacity_logits[o], object_poses[s]
            )
        if not torch.isfinite(loss):
            raise FloatingPointError(f"refine_world: loss is {float(loss)} at step {i}")
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
    refined = _split(f, parts)
    window = max(1, min(100, c.steps // 10))
    info = {
        **c.to_dict(),
        "states": states,
        "views": [int(views[s].images.shape[0]) for s in states],
        "loss_first": float(np.mean(losses[:window])),
        "loss_last": float(np.mean(losses[-window:])),
    }
    meta = {**world.metadata, "refine": dict(info)}  # no time in the file: a rerun writes the same bytes
    if front is not None:
        meta["compositing"] = "layers"
    info["seconds"] = round(time.perf_counter() - t0, 1)
    objects = {i: WorldObject(world.objects[i].name, g) for i, g in zip(ids, refined[1:])}
    return dataclasses.replace(world, background=refined[0], objects=objects, metadata=meta), info


def training_views_of(world: World, capture: str | Path) -> dict[str, StateViews]:
    """The training views of a two-state world's training states, loaded from ``capture`` as ``dsg-train``
    used them (its held-out views left out, its downscale and background colour); with the world's own
    cameras when training refined them (``metadata["camera_refinement"]``)."""
    from train_world.capture.loader import load_capture

    meta = world.metadata
    states = meta.get("training_states")
    if not states or len(states) != 2:
        raise ValueError("the world is not a two-state world (no 'training_states' in its metadata)")
    held = meta.get("heldout_views_by_state", {})
    downscale = int(meta.get("source", {}).get("downscale", 1))
    cap = load_capture(
        capture,
        states=list(states),
        downscale=downscale,
        load_depth=False,
        load_masks=False,
        background=tuple(meta.get("background", (0.0, 0.0, 0.0))),
    )
    out = {}
    for s in states:
        v = cap.states[s]
        keep = torch.tensor([i for i in range(len(v)) if i not in set(held.get(s, ()))], dtype=torch.int64)
        vm = v.viewmats
        if meta.get("camera_refinement") and s in world.cameras:
            stored = torch.from_numpy(np.asarray(world.cameras[s].viewmats, dtype=np.float32))
            if stored.shape != vm.shape:
                raise ValueError(
                    f"{capture}: state {s!r} has {len(vm)} views, the world {len(stored)} cameras"
                )
            vm = stored
        out[s] = StateViews(v.images[keep].contiguous(), vm[keep].contiguous(), v.Ks[keep].contiguous())
    return out
