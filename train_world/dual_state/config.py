"""``DualConfig``: the options of a two-state (DSG-World) training run, and the step its joint phase starts at."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from train_world.single_state.presets import TrainConfig

__all__ = ["BRANCH_OPTIONS", "JOINT_OPTIONS", "DualConfig", "joint_start_step", "training_options"]

#: options that may differ from a checkpoint branched from (they act in the joint phase only)
BRANCH_OPTIONS = (
    "use_align",
    "use_prune",
    "use_pseudo",
    "refine_motions",
    "motion_lr_translation",
    "motion_lr_rotation",
    "align_downscale",
    "support_weight",
)

#: joint-phase options that ``dsg-train`` reports in its summary and ``dsg-suite`` checks before it reuses a world
JOINT_OPTIONS = ("pseudo_every", "align_downscale", "support_weight")


def joint_start_step(joint_from: float, iterations: int) -> int:
    """The first joint step of a two-state run of ``iterations`` steps whose first ``joint_from`` fraction is
    reconstruction only."""
    return round(joint_from * iterations)


def training_options(config: DualConfig) -> DualConfig:
    """``config`` without what only acts after training (the merged world's refinement: its step count and
    layers) or is set elsewhere (the preset's support weight, which ``support_weight`` carries), for comparing
    a checkpoint's options with a run's."""
    preset = dataclasses.replace(
        config.base.preset, dual_refine_steps=0, dual_layers=False, dual_support_weight=0.0
    )
    return dataclasses.replace(config, base=dataclasses.replace(config.base, preset=preset))


@dataclass(frozen=True)
class DualConfig:
    """Two-state training options. ``base``: the reconstruction configuration (preset, seed, ...; its
    ``state`` is ignored). ``joint_from``: fraction of the iterations that is reconstruction only (paper:
    0.5). ``use_align``/``use_prune``/``use_pseudo``: B, C, P of the ablation. ``tau``: co-pruning distance
    in scene units (metres for synthetic captures: 0.02 = 2 cm, about a quarter of the smallest default
    object). ``footprint_margin``: dilation of object footprints for co-pasting/co-pruning (scene units).

    ``refine_motions``: make the objects' motions between the two states parameters of the joint phase
    (:mod:`.motions`; off: the capture's motions are taken as exact, as in the paper). Their Adam starts at
    ``motion_lr_translation`` times the scene extent (scene units per step) and ``motion_lr_rotation`` (radians
    per step), both decaying exponentially to a tenth over the joint phase.

    ``align_downscale``: the cross-state renders (``L_align``, ``L_pseudo``) at ``1/align_downscale`` of the
    training resolution (:mod:`.coarse`; 1: full resolution, as in the paper). The reconstruction renders stay
    at full resolution.

    ``support_weight``: weight of ``L_support`` (:func:`.losses.support_loss`: object Gaussians reaching below
    the table top) in the joint phase, for captures with a table (0: off, as in the paper)."""

    base: TrainConfig
    states: tuple[str, str] = ("state1", "state2")
    joint_from: float = 0.5
    lambda_align: float = 1.0
    lambda_pseudo: float = 1.0
    use_align: bool = True
    use_prune: bool = True
    use_pseudo: bool = True
    tau: float = 0.02
    prune_every: int = 500
    pseudo_every: int = 2
    pseudo_margin: float = 0.005
    footprint_margin: float = 0.01
    refine_motions: bool = False
    motion_lr_translation: float = 1e-4
    motion_lr_rotation: float = 3e-4
    align_downscale: int = 1
    support_weight: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.joint_from <= 1.0:
            raise ValueError(f"joint_from must be in [0, 1], got {self.joint_from}")
        if self.tau <= 0:
            raise ValueError(f"tau must be > 0 (scene units), got {self.tau}")
        if self.prune_every < 1 or self.pseudo_every < 1:
            raise ValueError("prune_every and pseudo_every must be >= 1")
        if len(self.states) != 2 or self.states[0] == self.states[1]:
            raise ValueError(f"states must be two different names, got {self.states}")
        if isinstance(self.align_downscale, bool) or not isinstance(self.align_downscale, int):
            raise ValueError(f"align_downscale must be an integer >= 1, got {self.align_downscale!r}")
        if self.align_downscale < 1:
            raise ValueError(f"align_downscale must be an integer >= 1, got {self.align_downscale}")
        if not (math.isfinite(self.support_weight) and self.support_weight >= 0):
            raise ValueError(f"support_weight must be a finite number >= 0, got {self.support_weight}")
        for name in ("motion_lr_translation", "motion_lr_rotation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")

    @property
    def ablation(self) -> str:
        return (
            "+".join(n for n, on in zip("BCP", (self.use_align, self.use_prune, self.use_pseudo)) if on)
            or "-"
        )

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["base"] = self.base.to_dict()
        d["states"] = list(self.states)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> DualConfig:
        d = dict(d)
        d["base"] = TrainConfig.from_dict(d["base"])
        d["states"] = tuple(d["states"])
        return cls(**d)
