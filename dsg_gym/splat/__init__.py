"""Differentiable 3D Gaussian splat rendering on the CPU (numba) with a PyTorch reference.

``rasterize`` follows gsplat's ``rasterization()`` argument conventions; see its docstring.

Threads: the numba kernels run on numba's own ``workqueue`` thread pool unless
``NUMBA_THREADING_LAYER`` says otherwise. With torch's OpenMP pool in the same process, numba's
OpenMP layer made short kernels up to ~30x slower here (both pools spin on the same 2 cores).
"""

import os as _os

import numba as _numba

if "NUMBA_THREADING_LAYER" not in _os.environ:
    _numba.config.THREADING_LAYER = "workqueue"

from .rasterize import BACKENDS, RENDER_MODES, rasterize
from .sh import C0, num_sh_bases, rgb_to_sh0, sh0_to_rgb, spherical_harmonics

__all__ = ["rasterize", "spherical_harmonics", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb", "C0",
           "BACKENDS", "RENDER_MODES"]
