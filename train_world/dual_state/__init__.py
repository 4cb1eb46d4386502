"""DSG-World's two-state method: two segmented fields, one shared classifier, one merged world.

Modules: :mod:`.transfer` (object-aware state transfer T), :mod:`.losses` (L_align, L_pseudo),
:mod:`.pseudo` (collision-free pseudo-state sampler), :mod:`.merge` (co-pruning, co-pasting, the merged
world), :mod:`.world` (``MergeInputs``, the merged world), :mod:`.views` (which views train),
:mod:`.refine` (refinement of the merged world), :mod:`.motions` (the objects' motions as parameters),
:mod:`.config` (``DualConfig``), :mod:`.trainer` (``DualTrainer``). The
``dsg-train`` command is :mod:`train_world.cli.train`.
"""

from train_world.dual_state.losses import align_loss, pseudo_loss, semantic_divergence
from train_world.dual_state.merge import (
    co_paste_background,
    co_prune_masks,
    footprint_contains,
    object_footprints_xy,
)
from train_world.dual_state.pseudo import footprint_radii, pseudo_state_valid, sample_pseudo_state
from train_world.dual_state.transfer import gaussian_transforms, object_labels, relative_transforms

__all__ = [
    "align_loss",
    "co_paste_background",
    "co_prune_masks",
    "footprint_contains",
    "footprint_radii",
    "gaussian_transforms",
    "object_footprints_xy",
    "object_labels",
    "pseudo_loss",
    "pseudo_state_valid",
    "relative_transforms",
    "sample_pseudo_state",
    "semantic_divergence",
]
