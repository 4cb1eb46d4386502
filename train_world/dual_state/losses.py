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
* ``L_support`` (not in the paper, off by default): objects stand on the table, so no object Gaussian should
  reach below the table top. Fitted freely, the Gaussians at an object's base grow below the table (hidden
  there by the table at the captured poses) and show as the table's colour around the base once the object
  moves. See :func:`support_loss`.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from dsg_gym.geometry import quat_to_rotmat
from train_world.single_state.losses import identity_loss, l1_loss

__all__ = ["align_loss", "pseudo_loss", "semantic_divergence", "support_loss"]


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


def support_loss(
    means: torch.Tensor,
    quats: torch.Tensor,
    log_scales: torch.Tensor,
    opacity_logits: torch.Tensor,
    poses: torch.Tensor | None = None,
    *,
    reach: float = 2.0,
    unit: float = 0.01,
) -> torch.Tensor:
    """``L_support``: how far object Gaussians reach below the table top ``z = 0``, weighted by opacity.

    ``mean_i(sigmoid(opacity_logit_i) * relu(reach * s_i - z_i)) / unit``, with ``z_i`` the height of the
    Gaussian's centre and ``s_i`` its standard deviation along z (from its rotation and scales). A Gaussian
    whose ``reach``-sigma extent stays above the table costs nothing; 0 for no Gaussians.

    means ``[N, 3]``, quats ``[N, 4]`` (wxyz, any norm), log_scales ``[N, 3]``, opacity_logits ``[N]``; poses
    ``[N, 4, 4]``: each Gaussian's object pose (object frame to the table frame), or None when the Gaussians
    already are in the table frame. ``unit``: the length one unit of the loss stands for (scene units).
    """
    if means.shape[0] == 0:
        return means.sum() * 0.0
    rot = quat_to_rotmat(quats)  # [N, 3, 3]
    if poses is None:
        z, rz = means[:, 2], rot[:, 2, :]  # rz: the z row of the Gaussian's rotation
    else:
        z = (poses[:, 2, :3] * means).sum(-1) + poses[:, 2, 3]
        rz = torch.einsum("nj,nji->ni", poses[:, 2, :3], rot)
    s_z = ((rz * log_scales.exp()) ** 2).sum(-1).clamp_min(1e-20).sqrt()
    below = torch.relu(reach * s_z - z)
    return (torch.sigmoid(opacity_logits.reshape(-1)) * below).mean() / unit
