"""Image metrics used by every evaluation: PSNR, SSIM (on RGB in [0, 1]) and per-class mask IoU.

PSNR is ``-10 log10(MSE)`` for images in [0, 1] (``inf`` for identical images). SSIM is scikit-image's
``structural_similarity`` with the standard Gaussian window (sigma 1.5, population covariance), as in the
3DGS and DSG-World evaluations.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["mask_iou", "psnr", "psnr_from_mse", "ssim"]


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB of a mean squared error of [0, 1] images (``inf`` for 0)."""
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB between two images ``[H, W, C]`` in [0, 1], computed in float64."""
    return psnr_from_mse(float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM between two RGB images ``[H, W, 3]`` in [0, 1]."""
    from skimage.metrics import structural_similarity

    return float(
        structural_similarity(
            a,
            b,
            channel_axis=2,
            data_range=1.0,
            gaussian_weights=True,
            sigma=1.5,
            use_sample_covariance=False,
        )
    )


def mask_iou(pred: np.ndarray, gt: np.ndarray, classes: range) -> dict[int, float | None]:
    """IoU per class of two id masks ``[H, W]`` (None where the class is in neither mask)."""
    out = {}
    for c in classes:
        p, g = pred == c, gt == c
        union = int((p | g).sum())
        out[c] = None if union == 0 else int((p & g).sum()) / union
    return out
