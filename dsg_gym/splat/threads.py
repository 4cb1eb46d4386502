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

__all__ = ["parallel_allowed"]

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
