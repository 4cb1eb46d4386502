"""train_world._openmp: how torch's and numba's OpenMP pools wait (checked in fresh interpreters through
libgomp's own report, OMP_DISPLAY_ENV=VERBOSE: one block per runtime, torch's first)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from train_world._openmp import busy_cores_of_others

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="GNU OpenMP on Linux")


def _run(code: str, **env_overrides: str | None) -> tuple[str, list[int]]:
    env = dict(os.environ)
    env.pop("OMP_WAIT_POLICY", None)
    env.pop("NUMBA_THREADING_LAYER", None)  # the test session's workqueue layer has no OpenMP runtime
    env["OMP_DISPLAY_ENV"] = "VERBOSE"
    for k, v in env_overrides.items():
        if v is None:
            env.pop(k, None)
        else:
            env[k] = v
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    spins = [int(x) for x in re.findall(r"GOMP_SPINCOUNT = '(\d+)'", r.stderr)]
    return r.stdout.strip(), spins


def test_busy_cores_of_others_subtracts_own_time():
    # 200 of 200 jiffies busy on 2 CPUs, 100 of them ours: the others kept one core busy
    assert busy_cores_of_others((100, 1000, 10), (300, 1200, 110), 2) == pytest.approx(1.0)
    assert busy_cores_of_others((100, 1000, 10), (150, 1200, 110), 2) == 0.0  # never negative
    assert busy_cores_of_others((5, 9, 1), (5, 9, 1), 2) == 0.0  # no time passed


def test_default_torch_pool_spins_numba_pool_sleeps_and_environment_is_restored():
    code = (
        "import os, train_world\nprint(os.environ.get('OMP_WAIT_POLICY'), '|', train_world._openmp.waiting())"
    )
    out, spins = _run(code)
    policy, what = out.split(" | ")
    assert policy == "None"  # children decide for themselves
    assert len(spins) == 2, spins  # torch's runtime, then numba's
    assert spins[1] == 0  # numba's pool sleeps
    if "spins" in what:  # the machine was idle at start: torch's pool keeps libgomp's default spinning
        assert spins[0] > 0
    else:
        assert "other processes" in what and spins[0] == 0


def test_policy_from_environment_applies_to_both_pools():
    code = "import train_world, torch, numba; numba.get_num_threads(); print(train_world._openmp.waiting())"
    out, spins = _run(code, OMP_WAIT_POLICY="PASSIVE")
    assert "from the environment" in out
    assert spins == [0, 0]


def test_torch_loaded_first_keeps_its_pool_and_numba_pool_still_sleeps():
    out, spins = _run("import torch, train_world; print(train_world._openmp.waiting())")
    assert "as loaded before train_world" in out
    assert len(spins) == 2 and spins[0] > 0 and spins[1] == 0
