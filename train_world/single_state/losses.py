"""Reconstruction losses (pure functions): Gaussian Grouping's L_r.

``L_r = (1 - lambda) * L1 + lambda * (1 - SSIM) + lambda_id * CE(classifier(S), mask) / log(K + 1)``
plus, every few steps, the 3D neighbour term: the KL divergence between the class distribution of sampled
Gaussians and that of their k nearest neighbours (by position), weighted ~2. Optional (not DSG-World's, off
by default): :func:`depth_loss` where the capture has depth.

Images are ``[..., H, W, C]`` (channels last, like the renderer's output).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "depth_loss",
    "identity_loss",
    "knn_indices",
    "l1_loss",
    "neighbour_kl_loss",
    "photometric_loss",
    "psnr",
    "ssim",
]


def l1_loss(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return (pred - gt).abs().mean()


def depth_loss(
    depth_sum: torch.Tensor, alpha: torch.Tensor, gt: torch.Tensor, min_alpha: float = 0.5
) -> torch.Tensor:
    """Mean relative error ``|D - D_gt| / D_gt`` of the rendered expected depth ``D = depth_sum / alpha``.

    ``depth_sum [..., H, W]``: the alpha-blended camera-space z (``sum_i w_i z_i``), ``alpha [..., H, W]`` the
    accumulated opacity, ``gt [..., H, W]`` z-depth in the same units (``<= 0``: no depth there). Only pixels
    with depth and ``alpha > min_alpha`` count (which pixels count carries no gradient), so the term shapes
    geometry, not opacity: it neither fights opacity resets nor fills holes. Zero (with gradient) where no
    pixel counts. Relative, so the weight does not depend on the scene's units or size.
    """
    valid = (gt > 0) & (alpha.detach() > min_alpha)
    if not bool(valid.any()):
        return depth_sum.sum() * 0.0
    d = depth_sum[valid] / alpha[valid]
    g = gt[valid]
    return ((d - g).abs() / g).mean()


def _gaussian_window(size: int, sigma: float, channels: int, dtype, device) -> torch.Tensor:
    x = torch.arange(size, dtype=torch.float64) - (size - 1) / 2.0
    g = torch.exp(-(x**2) / (2.0 * sigma**2))
    g = g / g.sum()
    w2 = torch.outer(g, g).to(dtype=dtype, device=device)
    return w2.expand(channels, 1, size, size).contiguous()


def ssim(
    pred: torch.Tensor, gt: torch.Tensor, window: int = 11, sigma: float = 1.5, data_range: float = 1.0
) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) with an ``window``x``window`` Gaussian window (sigma 1.5), zero padded
    to keep the image size as in 3DGS. ``pred``, ``gt``: ``[H,W,C]`` or ``[B,H,W,C]``."""
    if pred.shape != gt.shape:
        raise ValueError(f"ssim: shapes differ: {tuple(pred.shape)} vs {tuple(gt.shape)}")
    if pred.dim() == 3:
        pred, gt = pred[None], gt[None]
    if pred.dim() != 4:
        raise ValueError(f"ssim: expected [H,W,C] or [B,H,W,C], got {tuple(pred.shape)}")
    x = pred.permute(0, 3, 1, 2)
    y = gt.permute(0, 3, 1, 2)
    c = x.shape[1]
    w = _gaussian_window(window, sigma, c, x.dtype, x.device)
    pad = window // 2

    def filt(t):
        return F.conv2d(t, w, padding=pad, groups=c)

    mu_x, mu_y = filt(x), filt(y)
    sxx = filt(x * x) - mu_x * mu_x
    syy = filt(y * y) - mu_y * mu_y
    sxy = filt(x * y) - mu_x * mu_y
    c1 = (0.01 * data_range) ** 2
    c2 = (0.03 * data_range) ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2)
    return (num / den).mean()


def photometric_loss(pred: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """``(1 - lambda) * L1 + lambda * (1 - SSIM)``; exactly 0 for identical images."""
    return (1.0 - lambda_dssim) * l1_loss(pred, gt) + lambda_dssim * (1.0 - ssim(pred, gt))


def identity_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of per-pixel class logits ``[..., K+1]`` against integer class ids ``[...]``,
    divided by ``log(K + 1)`` (Gaussian Grouping's normalisation). 0 when K = 0."""
    n = logits.shape[-1]
    if n < 2:
        return logits.sum() * 0.0
    ce = F.cross_entropy(logits.reshape(-1, n), target.reshape(-1).long())
    return ce / math.log(n)


def knn_indices(points: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    """Indices ``[Q, k]`` of the k nearest ``points`` to each query, the query itself excluded when it is
    one of the points (exact, via a k-d tree)."""
    from scipy.spatial import cKDTree

    k_eff = min(k + 1, len(points))
    # an unbalanced tree without node compaction builds in about half the time, same neighbours
    _, idx = cKDTree(points, balanced_tree=False, compact_nodes=False).query(queries, k=k_eff)
    idx = np.asarray(idx).reshape(len(queries), k_eff)
    return idx[:, 1:] if k_eff > 1 else idx


def neighbour_kl_loss(
    means: torch.Tensor,
    logits: torch.Tensor,
    k: int = 5,
    samples: int = 1000,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Gaussian Grouping's 3D regulariser: sample ``samples`` Gaussians, find their ``k`` nearest neighbours
    by position (no gradient through positions) and average ``KL(p_i || p_j)`` over the pairs, where ``p`` is
    the softmax of each Gaussian's classifier logits ``[N, K+1]``."""
    n = means.shape[0]
    if n < 2 or logits.shape[-1] < 2:
        return logits.sum() * 0.0
    s = min(samples, n)
    sel = torch.randperm(n, generator=generator)[:s]
    pts = means.detach().double().numpy()
    nbr = torch.from_numpy(knn_indices(pts, pts[sel.numpy()], k).astype(np.int64))
    logp = F.log_softmax(logits, dim=-1)
    lp_i = logp[sel][:, None, :]
    lp_j = logp[nbr]
    kl = (lp_i.exp() * (lp_i - lp_j)).sum(-1)
    return kl.mean()


def psnr(pred: torch.Tensor, gt: torch.Tensor) -> float:
    mse = float(((pred.detach().double() - gt.double()) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)
