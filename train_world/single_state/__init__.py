"""Single-state reconstruction of a segmented Gaussian field (Gaussian Grouping's recipe) and the world file.

Modules: :mod:`.presets` (configuration), :mod:`.data` (views to train on), :mod:`.init` (initial Gaussians),
:mod:`.field` (``SegmentedField``, ``Classifier``), :mod:`.losses` (pure loss functions), :mod:`.strategy`
(densification), :mod:`.checkpoint` (pickle-free checkpoints), :mod:`.trainer` (the loop). The ``dsg-train``
command is :mod:`train_world.cli.train`.

How the OpenMP pool waits and how many threads torch uses are set when ``train_world`` is imported
(:mod:`train_world._openmp`).
"""

from train_world.single_state.field import Classifier, RenderOutput, SegmentedField, rigid_transform_gaussians
from train_world.single_state.presets import PRESETS, LearningRates, Preset, TrainConfig, get_preset
from train_world.single_state.strategy import DensifyStrategy, StrategyConfig

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
