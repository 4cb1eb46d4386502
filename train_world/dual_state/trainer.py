"""``DualTrainer``: DSG-World's joint optimisation of two segmented fields with one shared classifier.

Per step both fields take one view of their own state (Gaussian Grouping's ``L_r`` each, as in
:mod:`train_world.single_state`). The first ``joint_from`` fraction of the steps is reconstruction only; then

``L = L_r(G1) + L_r(G2) + lambda_a L_align + lambda_p L_pseudo``

with ``L_align`` = ``T_1->2(G1)`` rendered at this step's state-2 view against its image and mask plus
``T_2->1(G2)`` at the state-1 view against state 1 (B), and ``L_pseudo`` = both fields moved to a sampled
collision-free configuration and rendered from one training camera (P; every ``pseudo_every``-th joint
step: 2 by default, 1 = every step as in the paper; both reach the same accuracy at the test states and 2
saves a tenth of the training time). Co-pruning (C) runs every
``prune_every`` joint steps and once at the end. Each field keeps its own Adam optimisers and 3DGS
densification (:class:`~train_world.single_state.strategy.DensifyStrategy`, driven by its reconstruction render);
the classifier has one Adam. Object labels (for the transfer) are the classifier's argmax on each Gaussian's
identity feature, recomputed every step. The merged world is built by :mod:`.world`.

With ``refine_motions`` the objects' motions between the two states are parameters too (:mod:`.motions`):
``L_align`` moves each field's object Gaussians by the corrected motions, and a separate Adam steps the
corrections in the joint phase (and only when B is on: ``L_align`` is where their gradients come from).
Co-pruning, the pseudo-states, the footprints and the merged world use the current motions and state-2 poses.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from train_world.dual_state.checkpoint import load_dual_checkpoint, save_dual_checkpoint
from train_world.dual_state.coarse import coarse_views
from train_world.dual_state.config import DualConfig, joint_start_step
from train_world.dual_state.losses import align_loss, pseudo_loss, support_loss
from train_world.dual_state.merge import co_prune_masks, object_footprints_xy, robust_object_points
from train_world.dual_state.motions import ObjectMotions, motions_record
from train_world.dual_state.pseudo import footprint_radii, sample_pseudo_state
from train_world.dual_state.transfer import (
    ObjectTransfer,
    gaussian_transforms,
    object_labels,
    relative_transforms,
)
from train_world.dual_state.views import view_names
from train_world.dual_state.world import MergeInputs, merged_world
from train_world.single_state.camera_refine import correction_lrs
from train_world.single_state.data import TrainData, load_training_data
from train_world.single_state.field import SegmentedField
from train_world.single_state.trainer import (
    Trainer,
    TrainingDiverged,
    check_gradients,
    means_lr,
)

__all__ = ["DualConfig", "DualTrainer", "joint_start_step"]


class DualTrainer:
    """Trains G1 (``states[0]``) and G2 (``states[1]``) of ``capture`` jointly; see the module docstring."""

    def __init__(self, capture: str | Path, config: DualConfig, checkpoint: str | Path | None = None):
        self.capture = Path(capture)
        self.config = config
        self.preset = config.base.preset
        self.checkpoint_path = None if checkpoint is None else Path(checkpoint)
        s1, s2 = config.states
        self.data1 = load_training_data(capture, dataclasses.replace(config.base, state=s1))
        self.data2 = load_training_data(capture, dataclasses.replace(config.base, state=s2))
        if self.data1.object_ids != self.data2.object_ids:
            raise ValueError(f"{capture}: states {s1} and {s2} list different objects")
        if s2 not in self.data1.poses or s1 not in self.data1.poses:
            raise ValueError(f"{capture}: no object poses for {s1} and {s2}")
        # the per-state Trainers hold each field with its optimisers and densification strategy; both draw
        # the same class codes from the same seed, so they start with the same classifier, which is shared
        self.t1 = Trainer(self.data1, dataclasses.replace(config.base, state=s1))
        self.t2 = Trainer(self.data2, dataclasses.replace(config.base, state=s2))
        if not torch.equal(self.t1.classifier.weight, self.t2.classifier.weight):
            raise RuntimeError("the two fields' initial classifiers differ (class codes not shared)")
        self.classifier = self.t1.classifier
        self.t2.classifier = self.classifier
        self.cls_optimizer = torch.optim.Adam(self.classifier.parameters(), lr=self.preset.lrs.classifier)
        self.has_masks = self.t1.has_masks and self.t2.has_masks
        self.poses = {s: np.asarray(P, dtype=np.float64) for s, P in self.data1.poses.items()}
        self.P1, self.P2 = self.poses[s1], self.poses[s2]
        self.T12 = relative_transforms(self.P1, self.P2)
        self.T21 = relative_transforms(self.P2, self.P1)
        self.P2_initial = self.P2
        self.T12_initial = self.P2 @ np.linalg.inv(self.P1)  # float64, as the capture gives it
        self.motions = ObjectMotions(self.P1, self.P2) if config.refine_motions and len(self.P1) else None
        s = config.align_downscale  # the cross-state renders' views: the training views, or coarser ones
        self.cross = {id(d): coarse_views(d.images, d.classes, d.Ks, s, d.num_classes) if s > 1 else d
                      for d in (self.data1, self.data2)}  # fmt: skip
        self.table_bounds = self.data1.table_bounds
        self.rng = np.random.default_rng(config.base.seed + 7919)
        self.generator = torch.Generator().manual_seed(config.base.seed + 7919)
        self.step = 0
        self.motion_optimizer = None
        if self.motions is not None:
            self.motion_optimizer = self.motions.make_optimizer(*self._motion_lrs())
        self.elapsed = 0.0
        self.history: list[dict[str, float]] = []
        self.prune_log: list[dict[str, int]] = []
        self.last_checkpoint_step: int | None = None

    # ------------------------------------------------------------------ helpers
    @property
    def joint_start(self) -> int:
        return joint_start_step(self.config.joint_from, self.preset.iterations)

    @property
    def fields(self) -> tuple[SegmentedField, SegmentedField]:
        return self.t1.field, self.t2.field

    def _motion_lrs(self) -> tuple[float, float]:
        """``(translation, rotation)`` learning rates of the motion corrections at this step."""
        cfg = self.config
        return correction_lrs(
            self.step,
            self.joint_start,
            self.preset.iterations,
            cfg.motion_lr_translation * self.t1.extent,
            cfg.motion_lr_rotation,
        )

    def _sync_motions(self) -> None:
        """The float32 motions and the state-2 poses from the motion parameters (after a step or a load)."""
        if self.motions is None:
            return
        self.T12 = torch.from_numpy(self.motions.T12()).float()
        self.T21 = torch.from_numpy(self.motions.T21()).float()
        self.P2 = self.motions.P2()
        self.poses[self.config.states[1]] = self.P2

    def camera_names(self) -> dict[str, list[str]] | None:
        """Per training state, the names of its views in the order the world stores their cameras."""
        out = {}
        for d in (self.data1, self.data2):
            names = view_names(self.capture, d.state)
            if len(names) != len(d.all_viewmats):
                return None
            out[d.state] = names
        return out

    def camera_summary(self) -> dict[str, Any] | None:
        """Per training state, how far camera refinement moved its cameras
        (:meth:`~train_world.single_state.trainer.Trainer.camera_summary`), or None when not refined."""
        if self.t1.cameras is None:
            return None
        return {t.data.state: t.camera_summary() for t in (self.t1, self.t2)}

    def motion_summary(self) -> dict:
        """The motions as given and as trained (``metadata["motions"]`` of the world, :func:`.motions_record`)."""
        final = self.T12_initial if self.motions is None else self.motions.T12()
        return motions_record(
            self.T12_initial,
            final,
            self.P1,
            self.data1.object_ids,
            self.data1.object_names,
            self.data1.units,
            self.motions is not None,
            tuple(self.config.states),
        )

    def labels(self) -> tuple[torch.Tensor, torch.Tensor]:
        return object_labels(self.t1.field.features, self.classifier), object_labels(
            self.t2.field.features, self.classifier
        )

    def _recon_loss(self, t: Trainer, i: int, deg: int) -> tuple[torch.Tensor, Any, float]:
        loss, out, stats = t.view_loss(i, deg, self.classifier, self.step)  # the shared classifier
        t.strategy.before_backward(out.meta)
        return loss, out.meta, stats["psnr"]

    def _render_moved(self, t: Trainer, transform, d: TrainData, i: int, deg: int):
        """Field ``t`` moved by ``transform``, seen from view ``i`` of ``d`` (at the cross-state resolution)."""
        v = self.cross[id(d)]
        owner = self.t1 if d is self.data1 else self.t2  # its camera as refined so far, when refined
        return t.field.render(
            owner.viewmat(i),
            v.Ks[i : i + 1],
            v.width,
            v.height,
            transform=transform,
            sh_degree=deg,
            background=t.background,
            with_features=self.has_masks,
        )

    def object_points(
        self, field: SegmentedField, labels: torch.Tensor, poses: np.ndarray
    ) -> list[np.ndarray]:
        """Each object's Gaussian centres (opacity > 0.1, outliers dropped) in the object's own frame."""
        means = field.means.detach().double().numpy()
        opaque = (field.opacities().detach() > 0.1).numpy()
        lab = labels.numpy()
        out = []
        for k in range(len(poses)):
            pts = robust_object_points(means[(lab == k + 1) & opaque])
            inv = np.linalg.inv(poses[k])
            out.append(pts @ inv[:3, :3].T + inv[:3, 3])
        return out

    def footprints(self, poses: np.ndarray) -> list[np.ndarray | None]:
        """Object footprints at ``poses`` from both fields' object Gaussians (object frame, then placed)."""
        l1, l2 = self.labels()
        a = self.object_points(self.t1.field, l1, self.P1)
        b = self.object_points(self.t2.field, l2, self.P2)
        placed = []
        for k in range(len(poses)):
            pts = np.concatenate([a[k], b[k]])
            placed.append(pts @ poses[k][:3, :3].T + poses[k][:3, 3])
        return object_footprints_xy(placed)

    # ------------------------------------------------------------------ co-pruning
    @torch.no_grad()
    def co_prune(self) -> dict[str, int]:
        """Collaborative co-pruning of both fields (:func:`.merge.co_prune_masks`); returns the counts."""
        f1, f2 = self.fields
        l1, l2 = self.labels()
        m1 = f1.means.detach()
        m2 = f2.means.detach()
        m1_in_2 = (
            torch.einsum("nij,nj->ni", gaussian_transforms(l1, self.T12)[:, :3, :3], m1)
            + gaussian_transforms(l1, self.T12)[:, :3, 3]
        )
        m2_in_1 = (
            torch.einsum("nij,nj->ni", gaussian_transforms(l2, self.T21)[:, :3, :3], m2)
            + gaussian_transforms(l2, self.T21)[:, :3, 3]
        )
        fp1, fp2 = self.footprints(self.P1), self.footprints(self.P2)
        p1, p2 = co_prune_masks(
            m1_in_2.numpy(),
            m2.numpy(),
            m2_in_1.numpy(),
            m1.numpy(),
            self.config.tau,
            background_1=(l1 == 0).numpy(),
            background_2=(l2 == 0).numpy(),
            footprints_1=fp1,
            footprints_2=fp2,
            table_bounds=self.table_bounds,
            footprint_margin=self.config.footprint_margin,
        )
        info = {"step": self.step, "pruned_1": int(p1.sum()), "pruned_2": int(p2.sum())}
        for t, p in ((self.t1, p1), (self.t2, p2)):
            if p.any() and p.sum() < len(p):
                t.strategy.prune(t.field, t.optimizers, torch.from_numpy(p))
        self.prune_log.append(info)
        return info

    @staticmethod
    def _support(t: Trainer, labels: torch.Tensor) -> torch.Tensor:
        """``L_support`` of the field's object Gaussians (class > 0), which stand in the table frame."""
        f, obj = t.field, labels > 0
        return support_loss(f.means[obj], f.quats[obj], f.log_scales[obj], f.opacity_logits[obj])

    # ------------------------------------------------------------------ one step
    def train_step(self) -> dict[str, float]:
        cfg, p = self.config, self.preset
        t1, t2 = self.t1, self.t2
        i1, i2 = t1._next_view(), t2._next_view()
        deg = min(self.step // p.sh_degree_every, t1.field.max_sh_degree)
        l_r1, meta1, psnr1 = self._recon_loss(t1, i1, deg)
        l_r2, meta2, psnr2 = self._recon_loss(t2, i2, deg)
        loss = l_r1 + l_r2
        stats = {"psnr": 0.5 * (psnr1 + psnr2)}
        joint = self.step >= self.joint_start
        support = joint and cfg.support_weight > 0 and self.table_bounds is not None and self.has_masks
        if joint and (cfg.use_align or cfg.use_pseudo or support):
            lab1, lab2 = self.labels()
        if joint and cfg.use_align:
            if self.motions is not None:  # the motions take gradients through the transferred Gaussians
                tr12, tr21 = self.motions.transfers(lab1, lab2)
            else:
                tr12, tr21 = ObjectTransfer(lab1, self.T12), ObjectTransfer(lab2, self.T21)
            o12 = self._render_moved(t1, tr12, self.data2, i2, deg)
            o21 = self._render_moved(t2, tr21, self.data1, i1, deg)
            v1, v2 = self.cross[id(self.data1)], self.cross[id(self.data2)]
            c2 = v2.classes[i2] if self.has_masks else None
            c1 = v1.classes[i1] if self.has_masks else None
            f12 = o12.features[0] if self.has_masks else None
            f21 = o21.features[0] if self.has_masks else None
            l_a = align_loss(o12.rgb[0], f12, v2.images[i2], c2, self.classifier) + align_loss(
                o21.rgb[0], f21, v1.images[i1], c1, self.classifier
            )
            loss = loss + cfg.lambda_align * l_a
            stats["align"] = float(l_a.detach())
        do_pseudo = (self.step - self.joint_start) % cfg.pseudo_every == 0
        if joint and cfg.use_pseudo and do_pseudo and self.table_bounds is not None and len(self.P1):
            radii = footprint_radii(self.object_points(t1.field, lab1, self.P1), pad=0.005)
            Pp = sample_pseudo_state(self.P1, radii, self.table_bounds, self.rng, margin=cfg.pseudo_margin)
            d = self.data1 if self.rng.random() < 0.5 else self.data2
            v = int(self.rng.integers(len(d)))
            oa = self._render_moved(t1, ObjectTransfer(lab1, relative_transforms(self.P1, Pp)), d, v, deg)
            ob = self._render_moved(t2, ObjectTransfer(lab2, relative_transforms(self.P2, Pp)), d, v, deg)
            fa = oa.features[0] if self.has_masks else None
            fb = ob.features[0] if self.has_masks else None
            l_p = pseudo_loss(oa.rgb[0], fa, ob.rgb[0], fb, self.classifier)
            loss = loss + cfg.lambda_pseudo * l_p
            stats["pseudo"] = float(l_p.detach())
        if support:
            l_s = self._support(t1, lab1) + self._support(t2, lab2)
            loss = loss + cfg.support_weight * l_s
            stats["support"] = float(l_s.detach())
        stats["loss"] = float(loss.detach())
        if not math.isfinite(stats["loss"]):
            raise TrainingDiverged(f"loss became {stats['loss']} at step {self.step + 1}")
        opts = [*t1.optimizers.values(), *t2.optimizers.values(), self.cls_optimizer]
        extra = [
            o for o in (self.motion_optimizer, t1.camera_optimizer, t2.camera_optimizer) if o is not None
        ]
        for opt in opts + extra:
            opt.zero_grad(set_to_none=True)
        loss.backward()
        # a finite loss can still give a non-finite gradient: refuse the step before Adam spreads it
        named = [
            (f"{tag}.{k}", v) for tag, t in (("g1", t1), ("g2", t2)) for k, v in t.field.params().items()
        ]
        named += list(self.classifier.named_parameters(prefix="classifier"))
        named += self.motions.named_parameters() if self.motions is not None else []
        named += [(f"{tag}.{k}", v) for tag, t in (("g1", t1), ("g2", t2)) if t.cameras is not None
                  for k, v in t.cameras.named_parameters()]  # fmt: skip
        check_gradients(named, self.step + 1, self.last_checkpoint_step)
        for t in (t1, t2):
            t.optimizers["means"].param_groups[0]["lr"] = means_lr(self.step, p.iterations, p.lrs, t.extent)
        for opt in opts[:-1]:
            opt.step()
        if self.has_masks:
            self.cls_optimizer.step()
        t1.step_cameras(self.step)
        t2.step_cameras(self.step)
        if self.motion_optimizer is not None and joint and cfg.use_align:
            for group, lr in zip(self.motion_optimizer.param_groups, self._motion_lrs()[::-1]):
                group["lr"] = lr  # groups: rotation, translation
            self.motion_optimizer.step()
            self._sync_motions()
        self.step += 1
        t1.strategy.after_backward(self.step, t1.field, t1.optimizers, meta1, t1.generator)
        t2.strategy.after_backward(self.step, t2.field, t2.optimizers, meta2, t2.generator)
        t1.refresh_filter3d(self.step)
        t2.refresh_filter3d(self.step)
        if cfg.use_prune and joint and (self.step - self.joint_start) % cfg.prune_every == 0:
            self.co_prune()
        t1.step = t2.step = self.step
        stats["n"] = t1.field.num + t2.field.num
        return stats

    # ------------------------------------------------------------------ loop
    def train(self, *, progress: bool = True, stop_after: int | None = None) -> None:
        p = self.preset
        end = p.iterations if stop_after is None else min(p.iterations, stop_after)
        bar = tqdm(
            total=p.iterations,
            initial=self.step,
            disable=not progress,
            desc="dsg-train dual",
            dynamic_ncols=True,
        )
        t0 = time.perf_counter()
        try:
            while self.step < end:
                s = self.train_step()
                if self.step % 10 == 0 or self.step == end:
                    bar.set_postfix(loss=f"{s['loss']:.4f}", psnr=f"{s['psnr']:.2f}", n=s["n"], refresh=False)
                    self.history.append({"step": self.step, **{k: float(v) for k, v in s.items()}})
                bar.update(1)
                if self.step == p.iterations and self.config.use_prune and self.step > self.joint_start:
                    self.co_prune()  # the final co-pruning before merging
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
        save_dual_checkpoint(self, path)

    def load_checkpoint(self, path: str | Path | None = None, *, branch: bool = False) -> None:
        """Continue from a checkpoint (:func:`.checkpoint.load_dual_checkpoint`; ``branch``: ``--branch-from``)."""
        load_dual_checkpoint(self, path, branch=branch)

    # ------------------------------------------------------------------ result
    def merge_inputs(self) -> MergeInputs:
        """What merging needs of this run (:class:`.world.MergeInputs`)."""
        return MergeInputs(
            fields=tuple(self.fields),
            labels=self.labels(),
            P1=self.P1,
            P2=self.P2,
            T21=self.T21,
            footprints=(self.footprints(self.P1), self.footprints(self.P2)),
            data1=self.t1.refined_data(),
            data2=self.t2.refined_data(),
            background=self.t1.background,
            poses=self.poses,
            classifier_weight=self.classifier.weight.detach().numpy(),
            classifier_bias=self.classifier.bias.detach().numpy(),
            config=self.config.to_dict(),
            ablation=self.config.ablation,
            states=tuple(self.config.states),
            footprint_margin=self.config.footprint_margin,
            base_config=self.config.base.to_dict(),
            extent=self.t1.extent,
            step=self.step,
            field_sizes=(self.t1.field.num, self.t2.field.num),
            prune_log=list(self.prune_log[-50:]),
            elapsed=self.elapsed,
            motions=self.motion_summary(),
            camera_names=self.camera_names(),
            cameras=self.camera_summary(),
        )

    def world(self, extra_metadata: dict[str, Any] | None = None):
        """The merged world (:func:`.world.merged_world`)."""
        return merged_world(self.merge_inputs(), extra_metadata)

    def write_world(self, path: str | Path, extra_metadata: dict[str, Any] | None = None) -> Path:
        from dsg_gym.world import write_world

        return write_world(path, self.world(extra_metadata))
