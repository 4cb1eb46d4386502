"""train_world._openmp: one OpenMP pool in a training process, sleeping by default, torch on one thread; and a
training that repeats bit for bit at any numba thread count (each case in fresh interpreters on numba's OpenMP
layer; libgomp reports its settings with OMP_DISPLAY_ENV=VERBOSE, one block per runtime, torch's first)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import numpy as np
import pytest
from _captures import tiny_capture

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="GNU OpenMP on Linux")

_CHOICES = (
    "OMP_WAIT_POLICY",
    "GOMP_SPINCOUNT",
    "OMP_NUM_THREADS",
    "NUMBA_THREADING_LAYER",
    "NUMBA_NUM_THREADS",
)


def _env(**overrides: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in _CHOICES}  # the test session's workqueue layer too
    env.update(overrides)
    return env


def _run(code: str, **overrides: str) -> tuple[str, list[int]]:
    env = _env(OMP_DISPLAY_ENV="VERBOSE", **overrides)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    spins = [int(x) for x in re.findall(r"GOMP_SPINCOUNT = '(\d+)'", r.stderr)]
    return r.stdout.strip(), spins


_BURN = """
import os, time
os.environ["OMP_WAIT_POLICY"] = "{torch}"
import torch
os.environ["OMP_WAIT_POLICY"] = "{numba}"
import numba, numpy as np
numba.config.THREADING_LAYER = "omp"
numba.get_num_threads()

@numba.njit(parallel=True)
def add_one(a):
    for i in numba.prange(a.shape[0]):
        a[i] += 1.0

add_one(np.zeros(100_000))
c0 = time.process_time()
time.sleep(0.5)
print(numba.threading_layer(), numba.get_num_threads(), round(time.process_time() - c0, 2))
"""


def test_numba_regions_run_on_the_openmp_runtime_torch_loaded():
    # torch loads its runtime spinning forever, numba's own sleeping: after a numba kernel, a worker burns a core
    # through a sleep of the main thread, so numba's region ran on torch's runtime; the other way round, none does
    out, _ = _run(_BURN.format(torch="ACTIVE", numba="PASSIVE"))
    layer, threads, cpu = out.split()
    if int(threads) < 2:
        pytest.skip("one CPU: no worker threads")
    assert layer == "omp" and float(cpu) > 0.3, out
    out, _ = _run(_BURN.format(torch="PASSIVE", numba="ACTIVE"))
    assert float(out.split()[2]) < 0.2, out


def test_by_default_the_pool_sleeps_torch_uses_one_thread_and_the_environment_is_restored():
    code = (
        "import os, train_world, torch\n"
        "print(os.environ.get('OMP_WAIT_POLICY'), '|', torch.get_num_threads(), '|', train_world._openmp.waiting())"
    )
    out, spins = _run(code)
    policy, threads, what = out.split(" | ")
    assert policy == "None"  # child processes decide for themselves
    assert threads == "1"
    assert spins and spins[0] == 0  # torch's runtime, the one both use, sleeps at once
    assert what.startswith("the OpenMP pool sleeps; torch on 1 thread, numba on ")


@pytest.mark.parametrize(
    ("overrides", "spin", "threads", "said"),
    [
        ({"OMP_WAIT_POLICY": "ACTIVE"}, 30_000_000_000, "1", "as set: OMP_WAIT_POLICY=ACTIVE"),
        ({"GOMP_SPINCOUNT": "1000"}, 1000, "1", "as set: GOMP_SPINCOUNT=1000"),
        ({"OMP_NUM_THREADS": "2"}, 0, "2", "sleeps; torch on 2 threads"),
    ],
)
def test_the_environment_wins(overrides, spin, threads, said):
    code = "import train_world, torch; print(torch.get_num_threads(), '|', train_world._openmp.waiting())"
    out, spins = _run(code, **overrides)
    n, what = out.split(" | ")
    assert spins[0] == spin and n == threads and said in what


def test_torch_loaded_first_keeps_its_waiting_and_still_gets_one_thread():
    out, spins = _run(
        "import torch, train_world; print(torch.get_num_threads(), '|', train_world._openmp.waiting())"
    )
    n, what = out.split(" | ")
    assert spins[0] > 0  # loaded with libgomp's default before train_world could choose
    assert n == "1" and "as loaded before train_world" in what


_TRAIN = """
import sys
from train_world.cli import train
assert train.main([sys.argv[1], "--out", sys.argv[2], "--preset", "quick", "--iterations", "120", "--quiet"]) == 0
"""


def test_training_repeats_bit_for_bit_at_any_numba_thread_count(tmp_path):
    cap = tiny_capture(tmp_path, size=24, views=8, test_views=1)
    worlds = []
    for n in (1, 2):
        out = tmp_path / f"w{n}.dsgworld"
        r = subprocess.run(
            [sys.executable, "-c", _TRAIN, str(cap), str(out)],
            capture_output=True,
            text=True,
            env=_env(NUMBA_NUM_THREADS=str(n)),
            timeout=600,
        )
        assert r.returncode == 0, r.stderr[-2000:]
        worlds.append(out)
    from dsg_gym.world import load_world

    a, b = (load_world(w) for w in worlds)
    assert a.background.num == b.background.num and a.background.num > 0
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert np.array_equal(getattr(a.background, name), getattr(b.background, name)), name
    assert set(a.objects) == set(b.objects)
    for k in a.objects:
        assert np.array_equal(a.objects[k].gaussians.means, b.objects[k].gaussians.means), k
