"""DSG-World's cross-state losses (pure functions; images channels-last ``[..., H, W, C]``).

* ``L_align`` (bidirectional alignment): a field transferred into the other state, rendered from one of that
  state's views, against the view's image (L1) and mask (cross-entropy of the shared classifier on the
  rendered identity features, divided by ``log(K+1)`` as in the reconstruction loss). The trainer sums both
  directions, ``T_1->2(G1)`` vs state 2 and ``T_2->1(G2)`` vs state 1.
* ``L_pseudo`` (pseudo-state alignment): both fields moved to the same sampled configuration and rendered
  from the same view; L1 between the two renders plus the semantic term between the two class distributions.
  The paper writes the semantic term as a cross-entropy between the two classifier outputs; a cross-entropy
  between soft distributions is not zero for identical inputs (it equals their entropy), so this uses the
  symmetric KL divergence (cross-entropy minus the target's entropy, both ways), which is zero exactly when
  the two renders agree and has the same gradient with respect to the prediction as the cross-entropy.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from train_world.single_state.losses import identity_loss, l1_loss

__all__ = ["align_loss", "pseudo_loss", "semantic_divergence"]


def align_loss(
    rgb: torch.Tensor,
    features: torch.Tensor | None,
    image: torch.Tensor,
    classes: torch.Tensor | None,
    classifier: torch.nn.Module,
) -> torch.Tensor:
    """One direction of ``L_align``: ``L1(rgb, image) + CE(classifier(features), classes) / log(K+1)``.

    ``rgb`` ``[H,W,3]`` (or batched), ``features`` ``[H,W,F]`` or None (no masks: photometric term only).
    """
    loss = l1_loss(rgb, image)
    if features is not None and classes is not None:
        loss = loss + identity_loss(classifier(features), classes)
    return loss


def semantic_divergence(logits_a: torch.Tensor, logits_b: torch.Tensor) -> torch.Tensor:
    """Mean symmetric KL between the per-pixel class distributions ``softmax(logits)`` ``[..., K+1]``,
    divided by ``log(K+1)``; 0 for identical logits, 0 when K = 0."""
    n = logits_a.shape[-1]
    if n < 2:
        return logits_a.sum() * 0.0
    la = F.log_softmax(logits_a.reshape(-1, n), dim=-1)
    lb = F.log_softmax(logits_b.reshape(-1, n), dim=-1)
    kl = (la.exp() * (la - lb)).sum(-1) + (lb.exp() * (lb - la)).sum(-1)
    return 0.5 * kl.mean() / math.log(n)


def pseudo_loss(
    rgb_a: torch.Tensor,
    features_a: torch.Tensor | None,
    rgb_b: torch.Tensor,
    features_b: torch.Tensor | None,
    classifier: torch.nn.Module,
) -> torch.Tensor:
    """``L_pseudo`` for one view: ``L1(R(T_1->p G1), R(T_2->p G2))`` + :func:`semantic_divergence` of the
    classifier on the two rendered feature maps (both fields receive gradients)."""
    loss = l1_loss(rgb_a, rgb_b)
    if features_a is not None and features_b is not None:
        loss = loss + semantic_divergence(classifier(features_a), classifier(features_b))
    return loss
