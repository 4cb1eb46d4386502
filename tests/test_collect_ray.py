"""dsg_gym.collect on Ray: a local 2-CPU instance, shards on two workers, combined; equal to a local run."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

ray = pytest.importorskip("ray")
pytest.importorskip("minari")
pytest.importorskip("h5py")

from dsg_gym.collect import collect, load
from dsg_gym.collect.ray_backend import _blocks

KW = {"width": 32, "height": 32}


def test_blocks_split_contiguously():
    assert _blocks([0, 1, 2, 3, 4], 2) == [[0, 1, 2], [3, 4]]
    assert _blocks([5], 4) == [[5]]


def test_ray_two_workers_equals_local(tmp_path):
    common = {"env_kwargs": KW, "policy": "expert", "episodes": 4, "seed": 3, "max_episode_steps": 60}
    # flush_seconds: shards by episode count only (a slow machine must not split them by time)
    res = collect(
        tmp_path / "ray", backend="ray", ray_workers=2, keep_shards=True, flush_seconds=1e9, **common
    )
    assert not ray.is_initialized()  # the instance collect() started is shut down again
    shard_dirs = list((tmp_path / "ray" / ".dsg-collect" / "dsgworld__expert-v0" / "shards").iterdir())
    assert len(shard_dirs) == 2  # one dataset per worker, combined at the end
    local = collect(tmp_path / "local", **common)
    a, b = load(res.path), load(local.path)
    assert a.total_episodes == b.total_episodes == 4 and res.success_rate == local.success_rate
    for i in range(4):
        x, y = a[i], b[i]
        for k in x.observations:
            np.testing.assert_array_equal(x.observations[k], y.observations[k])
        np.testing.assert_array_equal(x.actions, y.actions)
        np.testing.assert_array_equal(x.rewards, y.rewards)
