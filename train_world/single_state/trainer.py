"""Single-state reconstruction: train a :class:`SegmentedField` and its identity classifier on one state.

One view per iteration (the queue is a seeded permutation, refilled when empty). Per step: render RGB +
identity features in one pass, Gaussian Grouping's loss (:mod:`.losses`), Adam steps (one optimiser per
parameter, 3DGS learning rates, exponentially decaying position rate), then the densification strategy
(:mod:`.strategy`). Checkpoints (:mod:`.checkpoint`) hold everything needed to continue bit for bit.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from dsg_gym.cameras import Cameras
from dsg_gym.splat.finite import all_finite
from dsg_gym.world import World, build_world, write_world
from train_world.single_state.camera_refine import CameraCorrections, correction_lrs
from train_world.single_state.checkpoint import (
    load_checkpoint,
    optimizer_from_tensors,
    optimizer_to_tensors,
    save_checkpoint,
)
from train_world.single_state.data import TrainData
from train_world.single_state.field import PARAM_NAMES, Classifier, SegmentedField
from train_world.single_state.init import (
    carve_silhouettes,
    initial_field,
    points_from_depth,
    points_in_bounds,
    scene_bounds_from_cameras,
    scene_extent,
    tabletop_points,
)
from train_world.single_state.losses import (
    depth_loss,
    identity_loss,
    neighbour_kl_loss,
    photometric_loss,
    psnr,
)
from train_world.single_state.presets import TrainConfig
from train_world.single_state.strategy import DensifyStrategy, StrategyConfig

__all__ = ["Trainer", "TrainingDiverged", "check_gradients", "make_optimizers", "means_lr"]

_LR_KEY = {
    "means": "means",
    "quats": "quats",
    "log_scales": "scales",
    "opacity_logits": "opacities",
    "sh0": "sh0",
    "shN": "shN",
    "features": "features",
}


class TrainingDiverged(RuntimeError):
    """The loss or a gradient became NaN or infinite; the last good checkpoint is kept."""


def check_gradients(named, step: int, last_checkpoint: int | None) -> None:
    """Raise :class:`TrainingDiverged` naming every parameter in ``named`` ``[(name, tensor)]`` whose
    gradient has a NaN or Inf (called between ``backward`` and the optimiser steps: nothing has changed)."""
    bad = [k for k, t in named if t.grad is not None and not all_finite(t.grad)]
    if bad:
        raise TrainingDiverged(
            f"gradient of {', '.join(bad)} became non-finite at step {step} (parameters unchanged); "
            f"the last good checkpoint (step {last_checkpoint}) is kept"
        )


def make_optimizers(field: SegmentedField, lrs, extent: float) -> dict[str, torch.optim.Optimizer]:
    """One Adam (eps 1e-15) per field parameter at the 3DGS rates (positions times the scene extent).

    PyTorch's fused CPU Adam: same update as the per-tensor loop up to float rounding, about 10x faster on
    fields of 1e5 Gaussians (the loop was a tenth of a training step)."""
    out = {}
    for name in PARAM_NAMES:
        lr = getattr(lrs, _LR_KEY[name]) * (extent if name == "means" else 1.0)
        out[name] = torch.optim.Adam([getattr(field, name)], lr=lr, eps=1e-15, fused=True)
    return out


def means_lr(step: int, total: int, lrs, extent: float) -> float:
    t = min(max(step / max(total, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(lrs.means) + t * math.log(lrs.means_final))


class Trainer:
    """Trains one field on ``data``. ``checkpoint``: where checkpoints go (None: none)."""

    def __init__(self, data: TrainData, config: TrainConfig, checkpoint: str | Path | None = None):
        self.data = data
        self.config = config
        self.preset = config.preset
        self.checkpoint_path = None if checkpoint is None else Path(checkpoint)
        self.extent = scene_extent(data.viewmats)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.rng = np.random.default_rng(config.seed)
        self.step = 0
        self.queue = torch.zeros(0, dtype=torch.int64)
        self.background = torch.tensor(data.background, dtype=torch.float32)
        self.has_masks = data.classes is not None and data.num_classes > 1
        # optional depth term (preset.lambda_depth, not DSG-World's): only where the capture has depth
        self.uses_depth = config.preset.lambda_depth > 0 and data.depths is not None
        self.field, self.classifier = self._initial_field()
        self._configure_filters()
        self.optimizers = make_optimizers(self.field, self.preset.lrs, self.extent)
        self.cls_optimizer = torch.optim.Adam(self.classifier.parameters(), lr=self.preset.lrs.classifier)
        self.strategy = DensifyStrategy(StrategyConfig.from_preset(self.preset, self.extent), self.field.num)
        self.cameras, self.camera_optimizer = self._camera_corrections()
        self.history: list[dict[str, float]] = []
        self.elapsed = 0.0
        self.last_checkpoint_step: int | None = None

    # ------------------------------------------------------------------ camera refinement
    def _camera_corrections(self) -> tuple[CameraCorrections | None, torch.optim.Adam | None]:
        """Zero corrections of the training cameras and their Adam (``refine_cameras``), else ``(None, None)``."""
        if not self.config.refine_cameras:
            return None, None
        cams = CameraCorrections(self.data.viewmats)
        return cams, cams.make_optimizer(*self._camera_lrs())

    def _camera_lrs(self, step: int | None = None) -> tuple[float, float]:
        c = self.config
        return correction_lrs(
            self.step if step is None else step, self.preset.densify_from, self.preset.iterations,
            c.camera_lr_translation * self.extent, c.camera_lr_rotation,
        )  # fmt: skip

    def cameras_refined_at(self, step: int) -> bool:
        """Whether step ``step`` renders through (and steps) the camera corrections."""
        return self.cameras is not None and step >= self.preset.densify_from

    def step_cameras(self, step: int) -> None:
        """The corrections' Adam step after a backward pass of step ``step`` (no-op when not refining)."""
        if not self.cameras_refined_at(step):
            return
        for group, lr in zip(self.camera_optimizer.param_groups, self._camera_lrs(step)[::-1]):
            group["lr"] = lr  # groups: rotation, translation
        self.camera_optimizer.step()

    def viewmat(self, i: int) -> torch.Tensor:
        """``[1,4,4]`` float32: training view ``i``'s camera as refined so far (no gradient), else as given."""
        if self.cameras is None or not self.cameras_refined_at(self.step):
            return self.data.viewmats[i : i + 1]
        return self.cameras.viewmat(i)

    def refined_data(self) -> TrainData:
        """:attr:`data` with the refined training cameras (in ``viewmats`` and among ``all_viewmats``); the
        data itself when the cameras are not refined."""
        d = self.data
        if self.cameras is None:
            return d
        vm = self.cameras.viewmats().float()
        held = set(d.heldout)
        train = [i for i in range(len(d.all_viewmats)) if i not in held]
        all_vm = np.array(d.all_viewmats, dtype=np.float32, copy=True)
        all_vm[train] = vm.numpy()
        return dataclasses.replace(d, viewmats=vm, all_viewmats=all_vm)

    def camera_summary(self) -> dict[str, Any] | None:
        """The world's ``metadata["camera_refinement"]`` (:meth:`CameraCorrections.summary`), or None."""
        return None if self.cameras is None else self.cameras.summary(self.data.units)

    # ------------------------------------------------------------------ initialisation
    def _initial_field(self) -> tuple[SegmentedField, Classifier]:
        d, p = self.data, self.preset
        if d.depths is not None and bool((d.depths > 0).any()):  # measured depth, or stereo's (with holes)
            # as many points per pixel with depth as a complete depth map gets: depth with holes starts with
            # fewer, which leaves the field's Gaussian cap room to grow where it has none (walls, floor)
            cover = float((d.depths > 0).double().mean())
            n = max(1, int(round(cover * p.num_init_points)))
            pts, cols, ids = points_from_depth(d.images, d.depths, d.viewmats, d.Ks, d.classes, n, self.rng)
        else:
            bounds = scene_bounds_from_cameras(d.viewmats, d.Ks, d.width)
            if d.table_bounds is not None:  # tabletop: the table box up to its half-width in height
                lo, hi = d.table_bounds.copy()
                hi[2] = lo[2] + 0.5 * max(hi[0] - lo[0], hi[1] - lo[1])
                bounds = np.stack([lo, hi])
            if d.silhouettes is not None:  # RGBA data: random points inside the visual hull
                pts, cols, ids = points_in_bounds(bounds, 8 * p.num_init_points, self.rng)
                keep = carve_silhouettes(pts, d.silhouettes, d.viewmats, d.Ks)
                if keep.sum() >= 100:
                    pts, cols, ids = (
                        pts[keep][: p.num_init_points],
                        cols[keep][: p.num_init_points],
                        ids[keep][: p.num_init_points],
                    )
                else:
                    pts, cols, ids = (
                        pts[: p.num_init_points],
                        cols[: p.num_init_points],
                        ids[: p.num_init_points],
                    )
            elif d.table_bounds is not None and self.has_masks:  # tabletop from photos: table, hulls, random
                pts, cols, ids = tabletop_points(
                    bounds, p.num_init_points, d.images, d.classes, d.viewmats, d.Ks, self.rng
                )
            else:
                pts, cols, ids = points_in_bounds(bounds, p.num_init_points, self.rng)
        if d.points is not None and len(d.points[0]):  # the capture's sparse points lead, as in 3DGS
            sp, sc = d.points
            sp, sc = sp[: p.num_init_points], sc[: p.num_init_points]
            rest = p.num_init_points - len(sp)
            pts = np.concatenate([sp, pts[:rest]])
            cols = np.concatenate([sc.astype(np.float64), cols[:rest]])
            ids = np.concatenate([np.zeros(len(sp), np.int64), ids[:rest]])
        field, codes = initial_field(
            pts,
            cols,
            ids,
            num_classes=d.num_classes,
            sh_degree=p.sh_degree,
            num_features=self.config.num_features,
            opacity=p.init_opacity,
            generator=self.generator,
        )
        classifier = Classifier(self.config.num_features, d.num_classes)
        with torch.no_grad():
            classifier.weight.copy_(5.0 * codes)
            classifier.bias.zero_()
        return field, classifier

    def _configure_filters(self) -> None:
        d, p = self.data, self.preset
        self.field.configure_filters(
            p.rasterize_mode, p.filter3d_scale, (d.viewmats, d.Ks, d.width, d.height), p.eps2d
        )

    def refresh_filter3d(self, step: int) -> None:
        """Mip-Splatting's schedule: the 3D filter follows the means every ``densify_every`` steps."""
        if self.preset.filter3d_scale > 0 and step % self.preset.densify_every == 0:
            self.field.update_filter3d()

    # ------------------------------------------------------------------ one step
    def _next_view(self) -> int:
        if self.queue.numel() == 0:
            self.queue = torch.from_numpy(self.rng.permutation(len(self.data)).astype(np.int64))
        i, self.queue = int(self.queue[0]), self.queue[1:]
        return i

    def view_loss(self, i: int, deg: int, classifier: torch.nn.Module | None = None, step: int | None = None):
        """Reconstruction loss of training view ``i`` at SH degree ``deg``: the photometric term, with masks
        the identity cross-entropy (``classifier``, default this trainer's) and every ``reg3d_every`` steps the
        3D neighbour term. Returns ``(loss, render output, stats)`` (stats: psnr, and id with masks);
        ``step``: the step counter (default this trainer's)."""
        d, p = self.data, self.preset
        classifier = self.classifier if classifier is None else classifier
        step = self.step if step is None else step
        out = self.field.render(
            d.viewmats[i : i + 1],
            d.Ks[i : i + 1],
            d.width,
            d.height,
            transform=self.cameras.transform(i) if self.cameras_refined_at(step) else None,
            sh_degree=deg,
            background=self.background,
            with_features=self.has_masks,
            with_depth=self.uses_depth,
            absgrad=self.strategy.wants_absgrad(step),
        )
        gt = d.images[i]
        loss = photometric_loss(out.rgb[0], gt, p.lambda_dssim)
        stats = {"psnr": psnr(out.rgb[0].clamp(0, 1), gt)}
        if self.uses_depth:
            dl = depth_loss(out.depth[0], out.alpha[0, ..., 0], d.depths[i])
            loss = loss + p.lambda_depth * dl
            stats["depth"] = float(dl.detach())
        if self.has_masks:
            id_loss = identity_loss(classifier(out.features[0]), d.classes[i])
            loss = loss + p.lambda_identity * id_loss
            stats["id"] = float(id_loss.detach())
            if p.reg3d_weight > 0 and (step + 1) % p.reg3d_every == 0:
                reg = neighbour_kl_loss(
                    self.field.means,
                    classifier(self.field.features),
                    p.reg3d_k,
                    p.reg3d_samples,
                    self.generator,
                )
                loss = loss + p.reg3d_weight * reg
        return loss, out, stats

    def train_step(self) -> dict[str, float]:
        p = self.preset
        i = self._next_view()
        deg = min(self.step // p.sh_degree_every, self.field.max_sh_degree)
        loss, out, stats = self.view_loss(i, deg)
        self.strategy.before_backward(out.meta)
        stats["loss"] = float(loss.detach())
        if not math.isfinite(stats["loss"]):
            where = (
                f"the last good checkpoint (step {self.last_checkpoint_step}) is kept at "
                f"{self.checkpoint_path}"
                if self.last_checkpoint_step is not None
                else "no checkpoint yet"
            )
            raise TrainingDiverged(f"loss became {stats['loss']} at step {self.step + 1}; {where}")
        for opt in self.optimizers.values():
            opt.zero_grad(set_to_none=True)
        self.cls_optimizer.zero_grad(set_to_none=True)
        if self.camera_optimizer is not None:
            self.camera_optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # a finite loss can still give a NaN/Inf gradient: stop before Adam spreads it into the field
        check_gradients(
            [
                *self.field.params().items(),
                *self.classifier.named_parameters(prefix="classifier"),
                *(self.cameras.named_parameters() if self.cameras is not None else []),
            ],
            self.step + 1,
            self.last_checkpoint_step,
        )
        self.optimizers["means"].param_groups[0]["lr"] = means_lr(self.step, p.iterations, p.lrs, self.extent)
        for opt in self.optimizers.values():
            opt.step()
        if self.has_masks:
            self.cls_optimizer.step()
        self.step_cameras(self.step)
        self.step += 1
        self.strategy.after_backward(self.step, self.field, self.optimizers, out.meta, self.generator)
        self.refresh_filter3d(self.step)
        stats["n"] = self.field.num
        return stats

    # ------------------------------------------------------------------ loop
    def train(
        self, *, progress: bool = True, stop_after: int | None = None, label: str = "dsg-train"
    ) -> None:
        """Run until the preset's iteration count, checkpointing every ``checkpoint_every`` steps and at the
        end. ``stop_after``: stop after that many steps as if killed (no extra checkpoint; for tests);
        ``label``: the progress bar's."""
        p = self.preset
        end = p.iterations if stop_after is None else min(p.iterations, stop_after)
        bar = tqdm(
            total=p.iterations, initial=self.step, disable=not progress, desc=label, dynamic_ncols=True
        )
        t0 = time.perf_counter()
        ema = None
        try:
            while self.step < end:
                s = self.train_step()
                ema = s["psnr"] if ema is None or not math.isfinite(ema) else 0.9 * ema + 0.1 * s["psnr"]
                if self.step % 10 == 0 or self.step == end:
                    bar.set_postfix(loss=f"{s['loss']:.4f}", psnr=f"{ema:.2f}", n=s["n"], refresh=False)
                    self.history.append(
                        {"step": self.step, "loss": s["loss"], "psnr": s["psnr"], "n": s["n"]}
                    )
                bar.update(1)
                if self.checkpoint_path is not None and (
                    self.step % p.checkpoint_every == 0 or self.step == p.iterations
                ):
                    self.elapsed += time.perf_counter() - t0
                    self.save_checkpoint()  # its write is not training time
                    t0 = time.perf_counter()
        finally:
            bar.close()
            if self.step != self.last_checkpoint_step:  # ending on a checkpoint: its time is the run's
                self.elapsed += time.perf_counter() - t0

    # ------------------------------------------------------------------ checkpoints
    def save_checkpoint(self, path: str | Path | None = None) -> None:
        path = Path(path or self.checkpoint_path)
        for name, t in self.field.params().items():
            if not bool(torch.isfinite(t).all()):
                raise TrainingDiverged(
                    f"parameter {name} became non-finite at step {self.step}; "
                    f"the last good checkpoint (step {self.last_checkpoint_step}) is kept"
                )
        tensors = {f"field/{k}": v.data for k, v in self.field.params().items()}
        if self.field.filter3d is not None:
            tensors["filter3d"] = self.field.filter3d
        for name, opt in self.optimizers.items():
            tensors.update(optimizer_to_tensors(f"adam/{name}", opt))
        tensors.update({f"classifier/{k}": v.data for k, v in self.classifier.named_parameters()})
        tensors.update(optimizer_to_tensors("adam/classifier", self.cls_optimizer))
        tensors.update({f"strategy/{k}": v for k, v in self.strategy.state_tensors().items()})
        if self.cameras is not None:
            tensors.update(self.cameras.state_tensors())
            tensors.update(optimizer_to_tensors("adam/cameras", self.camera_optimizer))
        tensors["rng/torch"] = self.generator.get_state()
        tensors["queue"] = self.queue
        meta = {
            "step": self.step,
            "config": self.config.to_dict(),
            "elapsed": self.elapsed,
            "numpy_rng": self.rng.bit_generator.state,
            "history": self.history[-200:],
        }
        save_checkpoint(path, tensors, meta)
        self.last_checkpoint_step = self.step

    def load_checkpoint(self, path: str | Path | None = None) -> None:
        path = Path(path or self.checkpoint_path)
        tensors, meta = load_checkpoint(path)
        stored = TrainConfig.from_dict(meta["config"])
        if stored != self.config:
            diff = {
                k: (v, self.config.to_dict()[k])
                for k, v in stored.to_dict().items()
                if self.config.to_dict()[k] != v
            }
            raise ValueError(
                f"{path}: checkpoint was made with a different configuration "
                f"(checkpoint vs now: {json.dumps(diff)[:400]}); use the same options to resume"
            )
        self.field = SegmentedField(*(tensors[f"field/{k}"] for k in PARAM_NAMES))
        self._configure_filters()
        if "filter3d" in tensors:
            self.field.filter3d = tensors["filter3d"].clone()
        self.optimizers = make_optimizers(self.field, self.preset.lrs, self.extent)
        for name, opt in self.optimizers.items():
            optimizer_from_tensors(f"adam/{name}", opt, tensors)
        with torch.no_grad():
            for k, v in self.classifier.named_parameters():
                v.copy_(tensors[f"classifier/{k}"])
        self.cls_optimizer = torch.optim.Adam(self.classifier.parameters(), lr=self.preset.lrs.classifier)
        optimizer_from_tensors("adam/classifier", self.cls_optimizer, tensors)
        self.strategy = DensifyStrategy(self.strategy.config, self.field.num)
        self.strategy.load_state_tensors(
            {"grad2d": tensors["strategy/grad2d"], "count": tensors["strategy/count"]}
        )
        self.cameras, self.camera_optimizer = self._camera_corrections()
        if self.cameras is not None:
            self.cameras.load_state_tensors(tensors)
            optimizer_from_tensors("adam/cameras", self.camera_optimizer, tensors)
        self.generator.set_state(tensors["rng/torch"].clone())
        self.rng.bit_generator.state = meta["numpy_rng"]
        self.queue = tensors["queue"].clone()
        self.step = int(meta["step"])
        self.elapsed = float(meta.get("elapsed", 0.0))
        self.history = list(meta.get("history", []))
        self.last_checkpoint_step = self.step

    # ------------------------------------------------------------------ result
    def world(self, extra_metadata: dict[str, Any] | None = None) -> World:
        d = self.refined_data()
        classes = self.field.labels(self.classifier).numpy()
        meta = {
            "format_note": "see dsg_gym.world",
            "num_classes": d.num_classes,
            "object_ids": list(d.object_ids),
            "object_names": list(d.object_names),
            "train_config": self.config.to_dict(),
            "source": d.source,
            "state": d.state,
            "heldout_views": list(d.heldout),
            "background": list(d.background),
            "image_size": [d.width, d.height],
            "iterations": self.step,
            "scene_extent": self.extent,
            "num_gaussians": self.field.num,
            "rasterize_mode": self.preset.rasterize_mode,
            "eps2d": self.preset.eps2d,
            **({"camera_refinement": self.camera_summary()} if self.cameras is not None else {}),
            **(extra_metadata or {}),
        }
        if "name" in d.source:
            meta["name"] = d.source["name"]
        if d.table_bounds is not None:  # as in scene.json; the world runtime reads it
            meta["table"] = {"bounds": np.asarray(d.table_bounds, dtype=np.float64).tolist()}
        return build_world(
            self.field.to_gaussian_set(),
            classes,
            d.object_ids,
            d.object_names,
            d.poses,
            d.state,
            {
                d.state: Cameras(
                    np.asarray(d.all_viewmats, np.float32),
                    np.asarray(d.all_Ks, np.float32),
                    d.width,
                    d.height,
                )
            },
            self.classifier.weight.detach().numpy(),
            self.classifier.bias.detach().numpy(),
            d.units,
            meta,
        )

    def write_world(self, path: str | Path, extra_metadata: dict[str, Any] | None = None) -> Path:
        return write_world(path, self.world(extra_metadata))
