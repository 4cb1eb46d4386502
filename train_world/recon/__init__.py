"""Single-state reconstruction of a segmented Gaussian field (Gaussian Grouping's recipe) and the world file.

Modules: :mod:`.presets` (configuration), :mod:`.data` (views to train on), :mod:`.init` (initial Gaussians),
:mod:`.field` (``SegmentedField``, ``Classifier``), :mod:`.losses` (pure loss functions), :mod:`.strategy`
(densification), :mod:`.checkpoint` (pickle-free checkpoints), :mod:`.trainer` (the loop), :mod:`.cli`
(``dsg-train``).

Importing this package sets ``OMP_WAIT_POLICY=PASSIVE`` unless the environment already sets it (and takes
effect only if torch/numba's OpenMP runtime is not loaded yet): on a shared 2-core machine, OpenMP threads
spin-waiting at barriers made each training step up to 25x slower when another process competed for the
cores (measured: 355 ms vs 15 ms per step). On an idle machine it costs nothing measurable: a two-state joint
step at 60k Gaussians took 0.46-0.48 s passive against 0.47-0.49 s with ``ACTIVE`` (an earlier measurement of
0.69-0.82 s against 0.53 s did not reproduce; README, "Time").
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from .field import Classifier, RenderOutput, SegmentedField, rigid_transform_gaussians
from .presets import PRESETS, LearningRates, Preset, TrainConfig, get_preset
from .strategy import DensifyStrategy, StrategyConfig

__all__ = [
    "PRESETS",
    "Classifier",
    "DensifyStrategy",
    "LearningRates",
    "Preset",
    "RenderOutput",
    "SegmentedField",
    "StrategyConfig",
    "TrainConfig",
    "get_preset",
    "rigid_transform_gaussians",
]
