"""Options of ``dsg-compact`` (:mod:`train_world.compact.compaction`), validated on construction."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["CompactConfig"]


@dataclass(frozen=True)
class CompactConfig:
    """Options of :func:`~train_world.compact.compaction.compact_world` (the docstring of
    :mod:`train_world.compact.compaction` explains them)."""

    max_psnr_drop: float = 0.3
    reference_psnr: float = 30.0
    fraction: float | None = None
    min_weight: float = 1.0 / 255.0
    sh_tolerance: float = 0.01
    rings: int = 4
    per_ring: int = 24
    object_views: int = 64
    step: float = 0.15
    min_fraction: float = 0.05
    neighbours: int = 8
    refit_steps: int = 300
    refit_cycles: int = 3
    validation_views: int = 48
    bisect_steps: int = 6

    def __post_init__(self) -> None:
        def bad(name: str, want: str):
            raise ValueError(f"{name} must be {want}, got {getattr(self, name)!r}")

        for name in ("max_psnr_drop", "min_weight", "sh_tolerance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                bad(name, "a finite number >= 0")
        if not (math.isfinite(self.reference_psnr) and self.reference_psnr > 0):
            bad("reference_psnr", "a positive number of dB")
        if self.fraction is not None and not (0.0 < self.fraction <= 1.0):
            bad("fraction", "in (0, 1]")
        if not 0.0 < self.step < 1.0:
            bad("step", "in (0, 1)")
        if not 0.0 < self.min_fraction <= 1.0:
            bad("min_fraction", "in (0, 1]")
        for name in ("rings", "per_ring", "bisect_steps", "neighbours", "refit_steps", "refit_cycles"):
            if getattr(self, name) < 0:
                bad(name, ">= 0")
        for name in ("object_views", "validation_views"):
            if getattr(self, name) < 1:
                bad(name, ">= 1")
