"""Threads of a training process: one OpenMP pool that sleeps, torch's operations on one thread.

torch ships its own GNU OpenMP runtime (``torch/lib/libgomp.so.1``) and loads it into the global symbol
scope; numba's OpenMP layer, loaded later, links the system's ``libgomp.so.1``, but its parallel regions bind
to the runtime loaded first. So a training process has **one** OpenMP pool, serving torch's operations and
numba's kernels, and its waiting is what ``OMP_WAIT_POLICY`` (or ``GOMP_SPINCOUNT``) said when torch loaded.

What :func:`configure` chooses, before torch loads (``import train_world`` calls it):

* **Waiting: the pool sleeps** (``PASSIVE``), unless ``OMP_WAIT_POLICY`` or ``GOMP_SPINCOUNT`` is set, which
  then applies as set. A spinning pool is a little faster alone, but collapses when another job starts
  beside the training: the competitor's threads wait for cores the spinning threads hold, and every parallel
  region of both processes pays for it (``python -m benchmarks.train_shared``; figures in docs/benchmarks.md).
* **torch runs its operations on one thread**, unless ``OMP_NUM_THREADS`` is set (then torch takes that
  count). A training step runs hundreds of small torch operations, and the heavy work (projection,
  compositing and its gradients) runs in numba's kernels on all of numba's threads (``NUMBA_NUM_THREADS``).
  Two-thread torch operations gain little alone and stall whenever another process holds a core. One thread
  also makes a training repeat bit for bit at any numba thread count: numba's kernels sum in a fixed order,
  and torch splits its reductions by its own thread count.

The environment is left as it was found, so child processes decide for themselves. :func:`waiting` reports
what was chosen. A process that imported torch before ``train_world`` keeps the waiting it loaded with; the
thread count is set either way.
"""

from __future__ import annotations

import os
import sys

__all__ = ["configure", "waiting"]

_waiting = "not configured"


def _numba_pool_loaded() -> bool:
    from numba.np.ufunc import parallel

    return bool(getattr(parallel, "_is_initialized", False))


def _torch_threads() -> int:
    raw = os.environ.get("OMP_NUM_THREADS", "").split(",")[0].strip()
    try:
        n = int(raw)
    except ValueError:
        return 1
    return max(1, n)


def configure() -> str:
    """Choose the pool's waiting and torch's thread count (module docstring) before torch loads OpenMP;
    returns and remembers what was done (:func:`waiting`). Call once, before torch is imported; later calls
    return the first answer."""
    global _waiting
    if _waiting != "not configured":
        return _waiting
    preset = [k for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if k in os.environ]
    torch_loaded, numba_loaded = "torch" in sys.modules, _numba_pool_loaded()
    if preset:
        waits = "as set: " + ", ".join(f"{k}={os.environ[k]}" for k in preset)
    elif torch_loaded or numba_loaded:
        waits = "as loaded before train_world"
    else:
        waits = "sleeps"
    set_here = not preset and not torch_loaded and not numba_loaded
    try:
        if set_here:
            os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        import numba
        import torch  # its OpenMP runtime reads the policy now

        numba.get_num_threads()  # numba's layer starts and sets the pool's thread count to its own
    finally:
        if set_here:
            os.environ.pop("OMP_WAIT_POLICY", None)
    n = _torch_threads()
    torch.set_num_threads(n)  # after numba's start, which reset it
    layer = numba.threading_layer()
    pool = "the OpenMP pool" if layer == "omp" else f"torch's OpenMP pool (numba's layer is {layer})"
    _waiting = (
        f"{pool} {waits}; torch on {n} thread{'s' if n != 1 else ''}, numba on {numba.get_num_threads()}"
    )
    return _waiting


def waiting() -> str:
    """What :func:`configure` did, in words."""
    return _waiting
