"""Checkpoints of a two-state run (:class:`~train_world.dual_state.trainer.DualTrainer`): both fields with their
Adam states, densification statistics, random generators and view queues, the shared classifier, the motion
and camera corrections when they are refined, and the run's bookkeeping, in the single-state checkpoint format
(:mod:`train_world.single_state.checkpoint`), so that a resumed or branched run continues bit for bit."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch

from train_world.dual_state.config import BRANCH_OPTIONS, DualConfig, training_options
from train_world.dual_state.motions import ObjectMotions
from train_world.single_state.checkpoint import (
    load_checkpoint,
    optimizer_from_tensors,
    optimizer_to_tensors,
    save_checkpoint,
)
from train_world.single_state.field import PARAM_NAMES, SegmentedField
from train_world.single_state.trainer import TrainingDiverged, make_optimizers

__all__ = ["load_dual_checkpoint", "save_dual_checkpoint"]


def save_dual_checkpoint(tr, path: str | Path | None = None) -> None:
    """Write the checkpoint of ``tr`` (a :class:`~train_world.dual_state.trainer.DualTrainer`) to ``path``
    (default: its own checkpoint path)."""
    tensors: dict[str, torch.Tensor] = {}
    for tag, t in (("g1", tr.t1), ("g2", tr.t2)):
        for k, v in t.field.params().items():
            if not bool(torch.isfinite(v).all()):
                raise TrainingDiverged(f"{tag}.{k} became non-finite at step {tr.step}")
            tensors[f"{tag}/field/{k}"] = v.data
        if t.field.filter3d is not None:
            tensors[f"{tag}/filter3d"] = t.field.filter3d
        for name, opt in t.optimizers.items():
            tensors.update(optimizer_to_tensors(f"{tag}/adam/{name}", opt))
        tensors.update({f"{tag}/strategy/{k}": v for k, v in t.strategy.state_tensors().items()})
        tensors[f"{tag}/rng/torch"] = t.generator.get_state()
        tensors[f"{tag}/queue"] = t.queue
        if t.cameras is not None:
            tensors.update({f"{tag}/{k}": v for k, v in t.cameras.state_tensors().items()})
            tensors.update(optimizer_to_tensors(f"{tag}/adam/cameras", t.camera_optimizer))
    tensors.update({f"classifier/{k}": v.data for k, v in tr.classifier.named_parameters()})
    tensors.update(optimizer_to_tensors("adam/classifier", tr.cls_optimizer))
    if tr.motions is not None:
        tensors.update(tr.motions.state_tensors())
        tensors.update(optimizer_to_tensors("adam/motions", tr.motion_optimizer))
    tensors["rng/torch"] = tr.generator.get_state()
    meta = {
        "kind": "dual",
        "step": tr.step,
        "dual_config": tr.config.to_dict(),
        "elapsed": tr.elapsed,
        "numpy_rng": tr.rng.bit_generator.state,
        "numpy_rng_fields": [tr.t1.rng.bit_generator.state, tr.t2.rng.bit_generator.state],
        "history": tr.history[-200:],
        "prune_log": tr.prune_log,
    }
    save_checkpoint(Path(path or tr.checkpoint_path), tensors, meta)
    tr.last_checkpoint_step = tr.step


def load_dual_checkpoint(tr, path: str | Path | None = None, *, branch: bool = False) -> None:
    """Continue from a checkpoint made with the same options. ``branch=True`` also accepts one that
    differs only in the ablation switches (B, C, P), provided it was taken before the joint phase
    starts: up to then the switches change nothing, so all ablations can share one reconstruction
    phase bit for bit (``dsg-train --branch-from``, used by ``dsg-suite``)."""
    path = Path(path or tr.checkpoint_path)
    tensors, meta = load_checkpoint(path)
    if meta.get("kind") != "dual":
        raise ValueError(f"{path}: not a two-state (dual) checkpoint")
    stored = training_options(DualConfig.from_dict(meta["dual_config"]))
    current = training_options(tr.config)
    if branch:  # the switches and the motion options act in the joint phase only
        switches = {k: getattr(tr.config, k) for k in BRANCH_OPTIONS}
        if dataclasses.replace(stored, **switches) != current:
            raise ValueError(
                f"{path}: can only branch from a checkpoint whose options differ in B/C/P and the "
                "motion refinement alone"
            )
        if int(meta["step"]) > tr.joint_start:
            raise ValueError(
                f"{path}: checkpoint is at step {meta['step']}, past the start of the joint phase "
                f"({tr.joint_start}); branching would not reproduce a separate run"
            )
    elif stored != current:
        raise ValueError(
            f"{path}: checkpoint was made with different options; use the same options to resume"
        )
    for tag, t, st in (
        ("g1", tr.t1, meta["numpy_rng_fields"][0]),
        ("g2", tr.t2, meta["numpy_rng_fields"][1]),
    ):
        t.field = SegmentedField(*(tensors[f"{tag}/field/{k}"] for k in PARAM_NAMES))
        t._configure_filters()
        if f"{tag}/filter3d" in tensors:
            t.field.filter3d = tensors[f"{tag}/filter3d"].clone()
        t.optimizers = make_optimizers(t.field, tr.preset.lrs, t.extent)
        for name, opt in t.optimizers.items():
            optimizer_from_tensors(f"{tag}/adam/{name}", opt, tensors)
        t.strategy.load_state_tensors(
            {"grad2d": tensors[f"{tag}/strategy/grad2d"], "count": tensors[f"{tag}/strategy/count"]}
        )
        t.generator.set_state(tensors[f"{tag}/rng/torch"].clone())
        t.queue = tensors[f"{tag}/queue"].clone()
        t.rng.bit_generator.state = st
        t.cameras, t.camera_optimizer = t._camera_corrections()
        if t.cameras is not None:
            t.cameras.load_state_tensors({k: tensors[f"{tag}/{k}"] for k in t.cameras.state_tensors()})
            optimizer_from_tensors(f"{tag}/adam/cameras", t.camera_optimizer, tensors)
    with torch.no_grad():
        for k, v in tr.classifier.named_parameters():
            v.copy_(tensors[f"classifier/{k}"])
    tr.cls_optimizer = torch.optim.Adam(tr.classifier.parameters(), lr=tr.preset.lrs.classifier)
    optimizer_from_tensors("adam/classifier", tr.cls_optimizer, tensors)
    if tr.motions is not None:
        tr.motions = ObjectMotions(tr.P1, tr.P2_initial)
        if "motions/rotvec" in tensors:  # else branched from a run without refinement: zero corrections
            tr.motions.load_state_tensors(tensors)
        tr.motion_optimizer = tr.motions.make_optimizer(*tr._motion_lrs())
        optimizer_from_tensors("adam/motions", tr.motion_optimizer, tensors)
        if tr.motion_optimizer.state:  # stepped: as after that step (else the capture's, bit for bit)
            tr._sync_motions()
    tr.generator.set_state(tensors["rng/torch"].clone())
    tr.rng.bit_generator.state = meta["numpy_rng"]
    tr.step = tr.t1.step = tr.t2.step = int(meta["step"])
    tr.elapsed = float(meta.get("elapsed", 0.0))
    tr.history = list(meta.get("history", []))
    tr.prune_log = list(meta.get("prune_log", []))
    tr.last_checkpoint_step = tr.step
