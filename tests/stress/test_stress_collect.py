"""Two ``dsg-collect`` processes on one output folder, SIGKILLed at random points, over and over: every requested
episode ends up in the dataset exactly once and the dataset equals an uninterrupted run's.

Three phases: collect 4 episodes, then extend the dataset to 7 and to 10 with ``--resume``. Each round starts
two ``--resume`` runs (at the same instant, or the second after a short random delay, so that it meets the first
at start-up or while it runs) and then up to two kill points, each picked at random: a time, the moment a run
holds the dataset's lock (its holder details appear), the moment a given number of shards exists, the moment
the dataset is being combined (its temporary folder appears), or none. Every process alive at a kill point is
killed with probability 0.8. All choices come from one seeded generator; the rounds per phase, the kills and
the whole time are bounded, after which one run without kills finishes the phase. Small: 16x16 images, 4-step
episodes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

pytest.importorskip("minari")
pytest.importorskip("h5py")

from dsg_gym.collect import collect, episode_seed, load
from dsg_gym.collect.run import WORK_DIR
from dsg_gym.collect.writer import ShardStore

KW = {"width": 16, "height": 16, "obs": ["rgb", "poses"]}
PHASES, STEPS, SEED = (4, 7, 10), 4, 11
MAX_ROUNDS = 4  # per phase
MAX_KILLS = 16
DEADLINE_S = 75  # no more rounds after this
KILL_P = 0.8
#: kill points and their odds
MODES = {"time": 0.2, "lock": 0.2, "shards": 0.3, "combine": 0.2, "none": 0.1}
LOCK_INFO = "dsgworld/.random-v0.dsg-collect.lock.json"


def _start(out, episodes: int, num_envs: int) -> subprocess.Popen:
    args = [sys.executable, "-m", "dsg_gym.cli.collect", "--episodes", str(episodes), "--max-episode-steps",
            str(STEPS), "--seed", str(SEED), "--out", str(out), "--env-kwargs", json.dumps(KW), "--no-progress",
            "--shard-episodes", "1", "--num-envs", str(num_envs), "--resume"]  # fmt: skip
    env = {**os.environ, "MUJOCO_GL": "egl", "NUMBA_NUM_THREADS": "1"}
    return subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)


def _shards(out) -> int:
    try:
        return len(ShardStore(out / WORK_DIR / "dsgworld__random-v0" / "shards").shards())
    except Exception:  # a shard being renamed into place while listed
        return 0


def _combining(out) -> bool:
    ns = out / "dsgworld"
    return ns.is_dir() and any(p.name.startswith(".random-v0.tmp-") for p in ns.iterdir())


def _locked_by(out, procs) -> bool:
    """Whether one of ``procs`` holds the dataset's lock (details left by a killed holder do not count)."""
    try:
        pid = json.loads((out / LOCK_INFO).read_text())["pid"]
    except (OSError, ValueError, KeyError):
        return False
    return any(p.pid == pid and p.poll() is None for p in procs)


def _episodes(target) -> int:
    try:
        return load(target).total_episodes
    except Exception:  # not there yet
        return 0


def _wait_for(cond, procs, limit_s: float) -> None:
    """Poll ``cond`` until it holds, every process has ended, or ``limit_s`` passed."""
    t_end = time.monotonic() + limit_s
    while not cond() and any(p.poll() is None for p in procs) and time.monotonic() < t_end:
        time.sleep(0.002)


def test_two_runs_killed_at_random_end_with_every_episode_once(tmp_path):
    ref = load(
        collect(tmp_path / "ref", env_kwargs=KW, episodes=PHASES[-1], seed=SEED, max_episode_steps=STEPS).path
    )
    out = tmp_path / "out"
    target = out / "dsgworld" / "random-v0"
    rng = np.random.default_rng(0)
    t_end = time.monotonic() + DEADLINE_S
    kills, refused, modes = 0, 0, []
    for episodes in PHASES:
        for _ in range(MAX_ROUNDS):
            if _episodes(target) == episodes or time.monotonic() > t_end or kills >= MAX_KILLS:
                break
            procs = [_start(out, episodes, int(rng.integers(1, 3)))]
            if modes and rng.random() < 0.5:  # else both start at the same instant
                time.sleep(float(rng.uniform(0.0, 3.0)))
            procs.append(_start(out, episodes, int(rng.integers(1, 3))))
            for _point in range(2):
                # the very first kill point is fixed, so that every seed kills a run holding shards
                mode = "shards" if not modes else str(rng.choice(list(MODES), p=list(MODES.values())))
                modes.append(mode)
                if mode == "time":
                    time.sleep(float(rng.uniform(0.0, 4.0)))
                elif mode == "lock":
                    _wait_for(lambda: _locked_by(out, procs), procs, 120)
                elif mode == "shards":
                    n = _shards(out) + int(rng.integers(1, 4))
                    _wait_for(lambda n=n: _shards(out) >= n, procs, 120)
                elif mode == "combine":
                    _wait_for(lambda: _combining(out), procs, 120)
                for p in procs:
                    if mode != "none" and p.poll() is None and kills < MAX_KILLS and rng.random() < KILL_P:
                        p.send_signal(signal.SIGKILL)
                        kills += 1
                if all(p.poll() is not None for p in procs):
                    break
            for p in procs:
                rc, err = p.wait(timeout=300), p.stderr.read()
                if rc == 2:  # refused: only ever because the other run holds the dataset
                    refused += 1
                    assert "is being collected by another dsg-collect run" in err, err
                    assert len(err.strip().splitlines()) == 1, err
                else:
                    assert rc in (0, -signal.SIGKILL), (rc, err)
        p = _start(out, episodes, 1)  # finish the phase without kills (a no-op when it is done)
        assert p.wait(timeout=300) == 0, p.stderr.read()
        assert _episodes(target) == episodes
    print(f"kill points {modes}, kills {kills}, refused {refused}")
    assert kills >= 1  # the first kill point comes at the first shards

    ds = load(target)
    meta = ds.storage.metadata["dsg_collect"]
    assert meta["episode_seeds"] == [episode_seed(SEED, e) for e in range(PHASES[-1])]  # each episode once
    assert meta == ref.storage.metadata["dsg_collect"]
    assert ds.total_episodes == ref.total_episodes and ds.total_steps == ref.total_steps
    for a, b in zip(ds.iterate_episodes(), ref.iterate_episodes(), strict=True):
        for k in ref.observation_space.spaces:
            np.testing.assert_array_equal(a.observations[k], b.observations[k])
        for f in ("actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        for k in b.infos:
            np.testing.assert_array_equal(a.infos[k], b.infos[k])
    assert not (out / WORK_DIR).exists()  # no shards, no run state left
    assert not [p for p in out.rglob("*") if ".tmp-" in p.name]  # no temporaries
    assert not (out / LOCK_INFO).exists()  # the last run released the lock and took its details along
