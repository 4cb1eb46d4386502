"""Real spherical harmonics (degree 0..3) as used by 3D Gaussian Splatting.

Coefficient layout: ``coeffs [..., K, D]`` with ``K >= (degree + 1)^2`` basis functions in the
order of 3DGS (index 0 is the constant term, then the 3 linear, 5 quadratic and 7 cubic ones)
and D channels (3 for RGB). A DC-only colour is ``rgb = 0.5 + C0 * coeffs[..., 0, :]``.
"""

from __future__ import annotations

import torch

from ..sh_basis import C0, C1, C2, C3, num_sh_bases, rotate_sh, sh_rotation  # noqa: F401  (re-exported)


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    """Inverse of the DC colour map: ``(rgb - 0.5) / C0``."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: torch.Tensor) -> torch.Tensor:
    """DC colour map: ``0.5 + C0 * sh0``."""
    return 0.5 + C0 * sh0


def spherical_harmonics(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """Evaluate real SH up to ``degree`` in direction ``dirs``.

    Args:
        degree: 0..3; coefficients beyond ``(degree + 1)^2`` are ignored.
        dirs: ``[..., 3]`` view directions (need not be normalised; a zero vector gives the
            constant term only).
        coeffs: ``[..., K, D]`` SH coefficients, K >= (degree + 1)^2.

    Returns:
        ``[..., D]`` the SH value (without the +0.5 offset 3DGS adds to colours).
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"coeffs has {coeffs.shape[-2]} bases, degree {degree} needs {k}")
    if dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have shape [..., 3], got {tuple(dirs.shape)}")
    out = C0 * coeffs[..., 0, :]
    if degree == 0:
        return out
    norm = dirs.norm(dim=-1, keepdim=True)
    d = dirs / torch.where(norm > 0, norm, torch.ones_like(norm))
    x, y, z = d[..., 0:1], d[..., 1:2], d[..., 2:3]
    out = out - C1 * y * coeffs[..., 1, :] + C1 * z * coeffs[..., 2, :] - C1 * x * coeffs[..., 3, :]
    if degree == 1:
        return out
    xx, yy, zz = x * x, y * y, z * z
    xy, yz, xz = x * y, y * z, x * z
    out = (out + C2[0] * xy * coeffs[..., 4, :] + C2[1] * yz * coeffs[..., 5, :]
           + C2[2] * (2.0 * zz - xx - yy) * coeffs[..., 6, :] + C2[3] * xz * coeffs[..., 7, :]
           + C2[4] * (xx - yy) * coeffs[..., 8, :])
    if degree == 2:
        return out
    return (out + C3[0] * y * (3.0 * xx - yy) * coeffs[..., 9, :]
            + C3[1] * xy * z * coeffs[..., 10, :]
            + C3[2] * y * (4.0 * zz - xx - yy) * coeffs[..., 11, :]
            + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[..., 12, :]
            + C3[4] * x * (4.0 * zz - xx - yy) * coeffs[..., 13, :]
            + C3[5] * z * (xx - yy) * coeffs[..., 14, :]
            + C3[6] * x * (xx - 3.0 * yy) * coeffs[..., 15, :])

