"""How a training process's two OpenMP thread pools wait between parallel regions.

torch and numba each load their own GNU OpenMP runtime (``torch/lib/libgomp.so.1`` and the system's), and
each reads ``OMP_WAIT_POLICY`` once, when it loads. The two pools see different work:

* torch runs hundreds of small parallel operations per training step (every op on more than 32k elements:
  the render's activations and transforms, the losses, their backward, Adam). With sleeping workers each one
  pays a futex wake-up, several times the cost of the operation itself.
* numba runs a few dozen long kernels per step (projection, compositing), where a wake-up is noise.

So by default (``OMP_WAIT_POLICY`` unset) torch's pool keeps libgomp's default policy (spin a while, then
sleep) and numba's pool sleeps (``PASSIVE``): joint steps are faster than with both pools passive
(``python -m benchmarks.omp_waiting``; figures in docs/benchmarks.md). Spinning costs dearly when another
process competes for the cores, so when other processes already keep the CPUs busy as this process starts
(over half a core, sampled from ``/proc/stat`` for 0.15 s) both pools sleep: of two trainings started a few
seconds apart, the first spins and the second, seeing it, sleeps. A policy in the environment always wins,
for both pools.

Waiting changes timing only: results are the same bits either way. The environment is left as it was found
(numba's pool is loaded here, while the variable says ``PASSIVE``), so child processes decide for themselves.
"""

from __future__ import annotations

import os
import sys
import time

__all__ = ["busy_cores_of_others", "configure", "waiting"]

_SAMPLE_SECONDS = 0.15
_BUSY_CORES = 0.5
_waiting = "not configured"


def _read_cpu_jiffies() -> tuple[int, int, int]:
    """(busy jiffies of all CPUs, total jiffies of all CPUs, jiffies of this process) from ``/proc``."""
    with open("/proc/stat") as f:
        fields = [int(x) for x in f.readline().split()[1:]]
    total = sum(fields[:8])  # user nice system idle iowait irq softirq steal (guest time is inside user)
    idle = fields[3] + fields[4]
    with open("/proc/self/stat") as f:
        own = f.read().rsplit(")", 1)[1].split()
    return total - idle, total, int(own[11]) + int(own[12])  # utime + stime


def busy_cores_of_others(before: tuple[int, int, int], after: tuple[int, int, int], cpus: int) -> float:
    """Cores kept busy by other processes between two :func:`_read_cpu_jiffies` samples (``>= 0``)."""
    busy = after[0] - before[0]
    total = after[1] - before[1]
    own = after[2] - before[2]
    if total <= 0:
        return 0.0
    return max(0.0, (busy - own) / total * cpus)


def _others_busy() -> bool:
    try:
        a = _read_cpu_jiffies()
        time.sleep(_SAMPLE_SECONDS)
        b = _read_cpu_jiffies()
    except (OSError, ValueError, IndexError):  # no /proc (not Linux): assume an idle machine
        return False
    return busy_cores_of_others(a, b, os.cpu_count() or 1) > _BUSY_CORES


def _numba_pool_loaded() -> bool:
    from numba.np.ufunc import parallel

    return bool(getattr(parallel, "_is_initialized", False))


def configure() -> str:
    """Choose the two pools' waiting (module docstring) before torch and numba load OpenMP; returns and
    remembers what was done (:func:`waiting`). Call once, before torch is imported; later calls return the
    first answer."""
    global _waiting
    if _waiting != "not configured":
        return _waiting
    if "OMP_WAIT_POLICY" in os.environ:
        _waiting = f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']} from the environment (both pools)"
        return _waiting
    torch_loaded, numba_loaded = "torch" in sys.modules, _numba_pool_loaded()
    if torch_loaded:
        torch_waits = "as loaded before train_world"
    elif _others_busy():
        torch_waits = "sleeps (other processes were using the CPUs at start)"
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    else:
        torch_waits = "spins, then sleeps"
    try:
        import torch  # noqa: F401  (its OpenMP runtime reads the policy now)

        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        import numba

        numba.get_num_threads()  # loads numba's threading layer, and its OpenMP runtime reads PASSIVE
    finally:
        os.environ.pop("OMP_WAIT_POLICY", None)
    import numba

    if numba.threading_layer() != "omp":
        numba_waits = f"layer is {numba.threading_layer()} (not OpenMP)"
    else:
        numba_waits = "as loaded before train_world" if numba_loaded else "sleeps"
    _waiting = f"torch's OpenMP pool {torch_waits}; numba's {numba_waits}"
    return _waiting


def waiting() -> str:
    """What :func:`configure` did, in words."""
    return _waiting
