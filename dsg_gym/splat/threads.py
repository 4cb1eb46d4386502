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

__all__ = ["min_parallel_work", "parallel_allowed", "ThreadChooser"]

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


class ThreadChooser:
    """Chooses, call by call, between a kernel sequence's threaded and single-threaded twins (same bits) by
    their measured time per unit of work, so that rendering stays fast when other work shares the cores.

    A parallel region waits for its slowest thread: when another thread or process holds one of the cores, a
    two-thread region stalls for the scheduler's time slices and the threaded path becomes many times slower
    than the single-threaded one. The chooser times each path (``record``: seconds per unit of work, the
    median of the last three calls; each path's first call is a warm-up and not counted), takes the faster one
    (``choose``) and now and then tries the other again for ``probe_calls`` calls: after ``probe`` calls at
    first, then after twice as many each time the other path stays slower (at most ``max_probe``), so a slow
    path costs little once it is known. On an idle machine it settles on the threaded path and then costs
    ``probe_calls`` single-threaded calls every ``max_probe`` calls.

    The single-threaded path takes over only when it is faster by more than ``margin`` (threads stay while their
    cost is at most ``margin`` times the single thread's): the time per unit of work varies by about 40 % from
    call to call (how many Gaussians the recomposited tiles list), so without a margin a lucky probe on an idle
    machine hands over to the slower path until the next probes undo it. Beside a busy process the threaded
    path steps 2.5-3.5x slower than one thread (``benchmarks.env_scaling``), well past the margin; beside a
    learner thread 1.1-1.6x, where the two paths differ less.

    Only where threads are allowed at all (:func:`parallel_allowed`); otherwise it always answers ``False``.
    """

    def __init__(self, probe: int = 16, max_probe: int = 128, probe_calls: int = 2, margin: float = 1.25):
        if not margin >= 1.0:
            raise ValueError(
                f"margin must be >= 1 (the single thread's lead that hands over to it), got {margin!r}"
            )
        self.probe, self.max_probe, self.probe_calls = int(probe), int(max_probe), int(probe_calls)
        self.margin = float(margin)
        self.samples: dict[bool, list[float]] = {True: [], False: []}
        self._warm = {True: False, False: False}
        self._interval = self.probe
        self._since = 0
        self._probing = 0  # calls left in the current probe

    def cost(self, parallel: bool) -> float | None:
        """Seconds per unit of work of a path (median of its last three calls), ``None`` before any."""
        s = sorted(self.samples[parallel][-3:])
        return s[len(s) // 2] if s else None

    def best(self) -> bool:
        t, s = self.cost(True), self.cost(False)
        return True if t is None or s is None else t <= s * self.margin

    def choose(self, allowed: bool = True) -> bool:
        if not allowed:
            return False
        for path in (True, False):  # measure both paths first
            if len(self.samples[path]) < 2:
                return path
        best = self.best()
        if self._probing:
            return not best
        if self._since >= self._interval:
            self._since = 0
            self._probing = self.probe_calls
            self.samples[not best].clear()
            return not best
        return best

    def record(self, parallel: bool, seconds: float, work: float) -> None:
        """Time one call took on the path ``choose`` returned, for ``work`` units (> 0)."""
        if not self._warm[parallel]:
            self._warm[parallel] = True
            return
        before = self.best()
        self.samples[parallel] = self.samples[parallel][-2:] + [float(seconds) / max(float(work), 1e-9)]
        if not self._probing:
            self._since += 1
            return
        if parallel == before:  # a probe's call
            return
        self._probing -= 1
        if self._probing:
            return
        if self.best() == before:  # the probe lost again: wait longer before the next one
            self._interval = min(2 * self._interval, self.max_probe)
        else:  # the probe won: the paths swap, probe the old one soon
            self._interval = self.probe
