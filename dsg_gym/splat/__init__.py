"""Differentiable 3D Gaussian splat rendering on the CPU (numba) with a PyTorch reference.

``rasterize`` follows gsplat's ``rasterization()`` argument conventions; see its docstring.

Threads: numba picks its threading layer (TBB when it loads, else OpenMP, else its workqueue;
``NUMBA_THREADING_LAYER`` overrides). OpenMP is the fast one on this CPU, but GNU OpenMP does not
survive ``fork``; the runtime renderer (``dsg_gym.scene_renderer``) therefore runs its kernels
single-threaded in processes started by ``multiprocessing`` (vector-env workers) and in processes
forked after OpenMP started (:mod:`dsg_gym.splat.threads`), with the same results. Under
oversubscription, spin-waiting OpenMP threads are slow: set ``OMP_WAIT_POLICY=PASSIVE`` early.
"""

from .rasterize import BACKENDS, RASTERIZE_MODES, RENDER_MODES, rasterize
from .sh import C0, num_sh_bases, rgb_to_sh0, sh0_to_rgb, spherical_harmonics

__all__ = ["rasterize", "spherical_harmonics", "num_sh_bases", "rgb_to_sh0", "sh0_to_rgb", "C0",
           "BACKENDS", "RASTERIZE_MODES", "RENDER_MODES"]
