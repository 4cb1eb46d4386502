"""Two dsg-collect runs against one output folder, killed at random points, then resumed until one finishes:
every requested episode ends up in the dataset exactly once, equal to an uninterrupted run's."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np

from dsg_gym.collect import collect, load

KW = {"width": 48, "height": 48, "obs": ["rgb", "poses"]}
EPISODES, STEPS, SEED = 12, 30, 11
DEADLINE_S = 150  # the whole test stops launching runs after this


def _run(out) -> subprocess.Popen:
    args = [sys.executable, "-m", "dsg_gym.cli.collect", "--episodes", str(EPISODES), "--max-episode-steps",
            str(STEPS), "--seed", str(SEED), "--out", str(out), "--env-kwargs", json.dumps(KW), "--no-progress",
            "--shard-episodes", "1", "--resume"]  # fmt: skip
    env = {**os.environ, "MUJOCO_GL": "egl", "NUMBA_NUM_THREADS": "1"}
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)


def _finished(out) -> int:
    """Episodes in complete shards of the unfinished run (``shard-*`` folders of one episode each)."""
    return len(list(out.glob(".dsg-collect/*/shards/shard-*")))


def test_two_runs_killed_at_random_end_with_every_episode_once(tmp_path):
    ref = load(
        collect(tmp_path / "ref", env_kwargs=KW, episodes=EPISODES, seed=SEED, max_episode_steps=STEPS).path
    )
    out = tmp_path / "out"
    rng = np.random.default_rng(0)
    target = out / "dsgworld" / "random-v0" / "data" / "metadata.json"
    t_end, rounds, kills, refused = time.monotonic() + DEADLINE_S, 0, 0, 0
    while not target.exists() and time.monotonic() < t_end:
        rounds += 1
        procs = [_run(out), _run(out)]  # started together: at most one may hold the dataset
        # kill once a random number of further episodes are in shards (0: during start-up), or after a while
        goal, t_kill = (
            _finished(out) + int(rng.integers(0, 3)),
            time.monotonic() + float(rng.uniform(1.0, 8.0)),
        )
        while any(p.poll() is None for p in procs) and _finished(out) < goal and time.monotonic() < t_kill:
            time.sleep(0.005)
        for p in procs:
            if p.poll() is None and rng.random() < 0.9:
                p.send_signal(signal.SIGKILL)
                kills += 1
        for p in procs:
            p.wait(timeout=120)
            err = p.stderr.read()
            if p.returncode == 2:
                refused += 1
                assert "in use by another dsg-collect run" in err, err
            else:
                assert p.returncode in (0, -signal.SIGKILL), (p.returncode, err)
    if not target.exists():  # the deadline passed: one last run without kills
        p = _run(out)
        assert p.wait(timeout=300) == 0, p.stderr.read()
    print(f"rounds {rounds}, kills {kills}, refused {refused}")
    assert kills >= 1 and refused >= 1
    ds = load(out / "dsgworld" / "random-v0")
    assert ds.total_episodes == EPISODES
    seeds = ds.storage.metadata["dsg_collect"]["episode_seeds"]
    assert len(set(seeds)) == EPISODES and seeds == ref.storage.metadata["dsg_collect"]["episode_seeds"]
    for a, b in zip(ds.iterate_episodes(), ref.iterate_episodes(), strict=True):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.rewards, b.rewards)
        np.testing.assert_array_equal(a.observations["poses"], b.observations["poses"])
    assert not [p.name for p in out.rglob("*") if p.name.startswith(".tmp") or ".partial" in p.name]
