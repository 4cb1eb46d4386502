"""Differentiable 3D Gaussian splat rendering on the CPU (numba) with a PyTorch reference.

``rasterize`` follows gsplat's ``rasterization()`` argument conventions; see its docstring.
"""

from .rasterize import BACKENDS, RENDER_MODES, rasterize
from .sh import C0, num_sh_bases, rgb_to_sh0, sh0_to_rgb, spherical_harmonics

__all__ = ["rasterize", "spherical_harmonics", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb", "C0",
           "BACKENDS", "RENDER_MODES"]
