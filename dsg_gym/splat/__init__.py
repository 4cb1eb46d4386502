"""Differentiable 3D Gaussian splat rendering on the CPU (numba) with a PyTorch reference.

``rasterize`` follows gsplat's ``rasterization()`` argument conventions; see its docstring.

Modules: the numba kernels (``numba_project``, ``numba_bins``, ``numba_raster``, ``numba_sh``,
``numba_incremental``, ``numba_rigid``, ``numba_batch``, ``numba_intrinsics``, ``numba_tails``, ``numba_layers``)
are torch-free and shared by the runtime renderers (:mod:`dsg_gym.scene_renderer`, :mod:`dsg_gym.batch_renderer`)
and training-side tools; ``rasterize`` (the differentiable training renderer), ``layers`` (its two-layer form) and
the SH helpers need torch, which this package imports only when one of those names is first used.

Threads: numba picks its threading layer (TBB when it loads, else OpenMP, else its workqueue;
``NUMBA_THREADING_LAYER`` overrides). OpenMP is the fast one on this CPU, but GNU OpenMP does not
survive ``fork``; the runtime renderer (``dsg_gym.scene_renderer``) therefore runs its kernels
single-threaded in processes started by ``multiprocessing`` (vector-env workers) and in processes
forked after OpenMP started (:mod:`dsg_gym.splat.threads`), with the same results. Under
oversubscription, spin-waiting OpenMP threads are slow: set ``OMP_WAIT_POLICY=PASSIVE`` early.
"""

import importlib

from ..sh_basis import C0, num_sh_bases
from ..splat_options import RASTERIZE_MODES

__all__ = [
    "rasterize",
    "spherical_harmonics",
    "num_sh_bases",
    "rgb_to_sh0",
    "sh0_to_rgb",
    "C0",
    "BACKENDS",
    "RASTERIZE_MODES",
    "RENDER_MODES",
]

#: names that need torch, and the submodule that defines each (imported on first use)
_LAZY = {
    "rasterize": ".rasterization",
    "BACKENDS": ".rasterization",
    "RENDER_MODES": ".rasterization",
    "spherical_harmonics": ".sh",
    "rgb_to_sh0": ".sh",
    "sh0_to_rgb": ".sh",
}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name], __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
