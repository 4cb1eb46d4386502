"""Differentiable 3D Gaussian splat rendering on the CPU (numba) with a PyTorch reference.

``rasterize`` follows gsplat's ``rasterization()`` argument conventions; see its docstring.

Threads: the runtime (``dsg_gym``) runs the numba kernels on numba's ``workqueue`` layer unless
``NUMBA_THREADING_LAYER`` (or ``numba.config.THREADING_LAYER``) says otherwise: it is fork-safe, so
``AsyncVectorEnv`` workers can be forked after the parent has rendered (GNU OpenMP aborts on that
fork). ``train_world`` selects the faster ``omp`` layer for training (measured on 20k Gaussians at
128x128 with 19 channels: forward 14 ms with OpenMP against 21 ms with workqueue). Under
oversubscription, spin-waiting OpenMP threads are slow: set ``OMP_WAIT_POLICY=PASSIVE`` early.
"""

import os as _os

import numba as _numba

if "NUMBA_THREADING_LAYER" not in _os.environ and _numba.config.THREADING_LAYER == "default":
    _numba.config.THREADING_LAYER = "workqueue"

from .rasterize import BACKENDS, RASTERIZE_MODES, RENDER_MODES, rasterize
from .sh import C0, num_sh_bases, rgb_to_sh0, sh0_to_rgb, spherical_harmonics

__all__ = ["rasterize", "spherical_harmonics", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb", "C0",
           "BACKENDS", "RASTERIZE_MODES", "RENDER_MODES"]
