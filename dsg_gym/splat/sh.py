"""Real spherical harmonics (degree 0..3) as used by 3D Gaussian Splatting.

Coefficient layout: ``coeffs [..., K, D]`` with ``K >= (degree + 1)^2`` basis functions in the
order of 3DGS (index 0 is the constant term, then the 3 linear, 5 quadratic and 7 cubic ones)
and D channels (3 for RGB). A DC-only colour is ``rgb = 0.5 + C0 * coeffs[..., 0, :]``.
"""

from __future__ import annotations

import torch

from ..sh_basis import C0, C1, C2, C3, basis_columns, num_sh_bases, rotate_sh, sh_rotation  # noqa: F401  (re-exported)


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
    if degree == 0:
        return C0 * coeffs[..., 0, :]
    fast = _numba_shapes(dirs, coeffs)
    if fast is not None:  # CPU, RGB, coefficients shared by the leading views: one numba pass each way
        from ._numba_backend import sh_colors

        C, N = fast
        out = sh_colors(degree, dirs.reshape(C, N, 3), coeffs.reshape(N, coeffs.shape[-2], 3))
        return out.reshape(dirs.shape)
    return _spherical_harmonics_torch(degree, dirs, coeffs)


def _numba_shapes(dirs: torch.Tensor, coeffs: torch.Tensor) -> tuple[int, int] | None:
    """(C, N) when ``dirs [..., N, 3]`` and ``coeffs [(1,)* N, K, 3]`` suit the numba kernels, else None."""
    if dirs.device.type != "cpu" or coeffs.device.type != "cpu" or coeffs.shape[-1] != 3:
        return None
    if dirs.dtype not in (torch.float32, torch.float64) or coeffs.dtype != dirs.dtype or dirs.dim() < 2:
        return None
    N = dirs.shape[-2]
    lead = coeffs.shape[:-2]
    if len(lead) == 0 or lead[-1] != N or any(s != 1 for s in lead[:-1]) or len(lead) > dirs.dim() - 1:
        return None
    C = dirs.numel() // (3 * N) if N else 0
    return (C, N) if C > 0 else None


def _spherical_harmonics_torch(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """The torch reference of :func:`spherical_harmonics` (any device, dtype and broadcasting)."""
    k = num_sh_bases(degree)
    if degree == 0:
        return C0 * coeffs[..., 0, :]
    basis = _basis(degree, dirs)  # [..., k]
    # one batched [1, k] x [k, D] product: its backward is two more, where indexing each coefficient
    # (coeffs[..., i, :]) would allocate and fill a full-size zero gradient per coefficient
    used = coeffs if coeffs.shape[-2] == k else coeffs[..., :k, :]  # a slice's backward fills a zero tensor
    return torch.matmul(basis.unsqueeze(-2), used).squeeze(-2)


def _basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """``[..., (degree + 1)^2]`` basis functions at ``dirs [..., 3]`` (normalised here; zero -> constant)."""
    norm = dirs.norm(dim=-1, keepdim=True)
    d = dirs / torch.where(norm > 0, norm, torch.ones_like(norm))
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    return torch.stack(basis_columns(degree, x, y, z, torch.ones_like(x)), dim=-1)
