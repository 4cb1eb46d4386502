"""Whether this process may run the renderer's numba kernels on several threads.

numba chooses its threading layer on the first parallel kernel: TBB when it loads, else OpenMP, else its
own workqueue (``NUMBA_THREADING_LAYER`` overrides). OpenMP is the fast one here (``DSGWorld-v0`` steps
about 1.5x faster than on the workqueue layer, ``benchmarks/env_step.py``), but GNU OpenMP does not
survive ``fork``: numba terminates a forked child at its first parallel kernel when the parent had
started OpenMP threads. And processes started by ``multiprocessing`` (``AsyncVectorEnv`` workers, data
collection workers) already run side by side, so threads inside each would only oversubscribe the cores.

So the runtime renders with its parallel kernels in a main process and with their single-threaded
twins (same arithmetic, same bits) in a process started by ``multiprocessing`` or forked after OpenMP
started. :func:`parallel_allowed` is that rule.
"""

from __future__ import annotations

import multiprocessing
import os

__all__ = ["min_parallel_work", "parallel_allowed"]

_forked_after_openmp = False


def _openmp_started() -> bool:
    try:
        from numba.np.ufunc import parallel
    except ImportError:  # pragma: no cover - numba is a dependency
        return False
    if not getattr(parallel, "_is_initialized", True):
        return False
    try:
        import numba

        return numba.threading_layer() == "omp"
    except ValueError:  # no layer launched
        return False


def _after_fork_in_child() -> None:
    global _forked_after_openmp
    if _openmp_started():
        _forked_after_openmp = True


os.register_at_fork(after_in_child=_after_fork_in_child)


def parallel_allowed(parallel: bool | None = None) -> bool:
    """May kernels run multi-threaded in this process?

    ``parallel``: ``None`` (automatic): yes in a main process, no in a process started by
    ``multiprocessing``; ``True``: yes wherever it is safe; ``False``: no. Never in a process forked after
    its parent started OpenMP threads.
    """
    if parallel is False or _forked_after_openmp:
        return False
    return parallel is True or multiprocessing.parent_process() is None


def min_parallel_work() -> int:
    """Items (Gaussians x cameras) from which a light per-item kernel (projection, the Mip filter) is worth
    starting threads: about a thousand once OpenMP or TBB threads run (``DSGWorld-v0`` projects a moved
    object of ~1.5k Gaussians in 40 us on two OpenMP threads against 104 us on one), 20k on the workqueue
    layer or before the first parallel kernel chose a layer."""
    try:
        import numba

        layer = numba.threading_layer()
    except ValueError:
        return 20_000
    return 1_000 if layer in ("omp", "tbb") else 20_000
