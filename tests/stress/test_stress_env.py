"""Long random episodes of ``DSGWorld-v0``: nothing non-finite anywhere and no memory growth.

CI-sized: a few thousand steps on the small two-box world (``tests/_worlds.py``) at 48x48 with every
observation key rendered. ``benchmarks/stress.py`` runs 1e5 steps and reports the resident memory before and
after.
"""

from __future__ import annotations

import gc
from collections.abc import Mapping

import numpy as np
import pytest
from _stress_ref import non_finite_entries, random_action, rss_bytes
from _worlds import two_box_world

from dsg_gym.envs.dsg_world import DSGWorldEnv

SIZE = 48
MIB = 1 << 20


@pytest.fixture(scope="module")
def world():
    return two_box_world()


def assert_all_finite(obs: Mapping, reward, info: Mapping) -> None:
    """Every number in the observation, the reward and the info dict is finite; poses are unit; depth >= 0."""
    bad = non_finite_entries(obs, reward, info)
    assert not bad, f"not finite or invalid: {bad}"


def run_episodes(env: DSGWorldEnv, steps: int, seed: int, reset_every: int = 250) -> dict:
    """``steps`` random steps with a reset every ``reset_every`` steps (or on success); every result is
    checked with :func:`assert_all_finite`, and the observation against the space every 100 steps."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    assert_all_finite(obs, 0.0, info)
    counts = {"resets": 1, "rejected": 0, "successes": 0}
    for i in range(steps):
        obs, reward, terminated, truncated, info = env.step(random_action(env, rng))
        assert_all_finite(obs, reward, info)
        counts["rejected"] += int(info["rejected"].any())
        counts["successes"] += int(terminated)
        if i % 100 == 0:
            assert obs in env.observation_space
        if terminated or truncated or (i + 1) % reset_every == 0:
            obs, info = env.reset(seed=int(rng.integers(1 << 31)))
            assert_all_finite(obs, 0.0, info)
            counts["resets"] += 1
    return counts


def test_thousands_of_rendered_steps_stay_finite_without_memory_growth(world):
    """2000 steps (se3 actions, ``collision="reject"``, rgb + mask + depth + poses): everything finite, and
    the resident memory after the run is within 24 MiB of the value after a 150-step warm-up (numba
    compilation, caches). A leak of one 48x48 RGB image per step would already add ~13 MiB."""
    env = DSGWorldEnv(world=world, width=SIZE, height=SIZE, obs=("rgb", "mask", "depth", "poses"),
                      collision="reject", action_mode="se3")  # fmt: skip
    run_episodes(env, 150, seed=0)
    gc.collect()
    before = rss_bytes()
    counts = run_episodes(env, 2000, seed=1, reset_every=200)
    gc.collect()
    after = rss_bytes()
    env.close()
    assert counts["resets"] >= 10 and counts["rejected"] > 0  # resets and rejections were exercised
    assert after - before < 24 * MIB, f"RSS grew by {(after - before) / MIB:.1f} MiB"


@pytest.mark.parametrize("mode,collision", [("absolute", "settle"), ("delta", "ignore")])
def test_other_modes_stay_finite(world, mode, collision):
    """The other action modes and collision handling (MuJoCo settling; no checks at all, where objects wander
    off the table and out of view) give finite observations, rewards and infos."""
    env = DSGWorldEnv(world=world, width=32, height=32, obs=("rgb", "mask", "depth", "poses"),
                      collision=collision, action_mode=mode)  # fmt: skip
    counts = run_episodes(env, 150 if collision == "settle" else 600, seed=2, reset_every=1000)
    env.close()
    assert counts["resets"] >= 1


def test_the_finiteness_check_catches_bad_values():
    """The checker used above flags NaN/Inf in observations, rewards and infos, non-unit poses, negative depth."""
    good = {"rgb": np.zeros((2, 2, 3), np.uint8), "depth": np.ones((2, 2), np.float32),
            "poses": np.array([[0.0, 0, 0, 1, 0, 0, 0]])}  # fmt: skip
    info = {"success": False, "position_errors": np.zeros(1), "rejected": np.zeros(1, bool)}
    assert non_finite_entries(good, -0.5, info) == []
    depth = good["depth"].copy()
    depth[0, 0] = np.nan
    assert non_finite_entries({**good, "depth": depth}, 0.0, info) == ["obs['depth']"]
    assert non_finite_entries(good, float("inf"), info) == ["reward"]
    assert non_finite_entries(good, 0.0, {**info, "position_errors": np.array([np.nan])}) == [
        "info['position_errors']"
    ]
    poses = good["poses"].copy()
    poses[0, 3] = 1.001
    assert non_finite_entries({**good, "poses": poses}, 0.0, info) == ["obs['poses'] quaternion norm"]
    assert non_finite_entries({**good, "depth": -(depth.copy() ** 0)}, 0.0, info) == ["obs['depth'] < 0"]
