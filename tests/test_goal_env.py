"""``DSGWorldGoal-v0``: the goal-conditioned observation, ``compute_reward`` against the env's own reward,
Stable-Baselines3 HER + SAC on it, and the goal ghost of ``render(render_goal=True)``."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest

import dsg_gym  # noqa: F401  (registers the envs)
from dsg_gym.envs.goal_env import FlattenGoalObservation

SMALL = {"width": 16, "height": 16}


@pytest.fixture(scope="module")
def transitions():
    """Random transitions of ``DSGWorldGoal-v0`` (collision='ignore': some steps collide and are penalised)."""
    env = gym.make("DSGWorldGoal-v0", **SMALL, obs=("poses",), collision="ignore", max_episode_steps=25)
    env.action_space.seed(1)
    obs, _ = env.reset(seed=0)
    rows = []
    for _ in range(60):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample() * 3.0)
        rows.append((obs["achieved_goal"], obs["desired_goal"], info, reward, terminated))
        if terminated or truncated:
            obs, _ = env.reset()
    yield env, rows
    env.close()


def test_observation_holds_the_env_observation_and_flat_goals():
    env = gym.make("DSGWorldGoal-v0", **SMALL, obs=("rgb", "mask", "poses"))
    obs, _ = env.reset(seed=3)
    base = env.unwrapped
    assert set(obs) == {"observation", "achieved_goal", "desired_goal"}
    assert set(obs["observation"]) == {"rgb", "mask", "poses"}  # pixels stay available
    assert obs["observation"]["rgb"].shape == (16, 16, 3)
    assert np.array_equal(obs["achieved_goal"], base.poses.reshape(-1))
    assert np.array_equal(obs["desired_goal"], base.goal.reshape(-1))
    assert obs in env.observation_space
    obs2, *_ = env.step(env.action_space.sample())
    assert obs2 in env.observation_space
    assert np.array_equal(obs2["desired_goal"], obs["desired_goal"])
    env.close()


def test_compute_reward_equals_the_env_reward_single_and_batched(transitions):
    env, rows = transitions
    compute = env.unwrapped.compute_reward
    assert any(r[2]["collision"] for r in rows) and not all(r[2]["collision"] for r in rows)
    for achieved, desired, info, reward, terminated in rows:
        assert compute(achieved, desired, info) == reward
        assert env.unwrapped.compute_terminated(achieved, desired, info) == terminated
    a = np.stack([r[0] for r in rows])
    d = np.stack([r[1] for r in rows])
    infos = np.array([r[2] for r in rows])
    batched = compute(a, d, infos)
    assert batched.shape == (len(rows),)
    assert np.array_equal(batched, np.array([r[3] for r in rows]))
    # a [2, n/2] batch gives the same numbers in that shape
    half = len(rows) // 2
    shaped = compute(
        a[: 2 * half].reshape(2, half, -1), d[: 2 * half].reshape(2, half, -1), infos[: 2 * half]
    )
    assert np.array_equal(shaped.reshape(-1), batched[: 2 * half])


def test_relabelled_goal_is_a_success_without_penalty(transitions):
    env, rows = transitions
    params = env.unwrapped.task.params
    achieved, _, info, _, _ = rows[0]
    r = env.unwrapped.compute_reward(achieved, achieved, {"collision": False})
    assert r == params.success_bonus  # zero error, success bonus
    assert (
        env.unwrapped.compute_reward(achieved, achieved, {"collision": True}) == r - params.collision_penalty
    )
    assert env.unwrapped.compute_reward(achieved, achieved, None) == r  # no info: no penalty
    assert env.unwrapped.compute_terminated(achieved, achieved, None)
    assert not env.unwrapped.compute_truncated(achieved, achieved, None)


def test_compute_reward_rejects_bad_goals(transitions):
    env, rows = transitions
    a, d = rows[0][0], rows[0][1]
    with pytest.raises(ValueError, match="goals must both be"):
        env.unwrapped.compute_reward(a[:-1], d[:-1], None)
    with pytest.raises(ValueError, match="NaN or Inf"):
        env.unwrapped.compute_reward(np.full_like(a, np.nan), d, None)
    with pytest.raises(ValueError, match="infos for"):
        env.unwrapped.compute_reward(np.stack([a, a]), np.stack([d, d]), [{}])


def test_flatten_goal_observation_keeps_non_pixel_entries():
    env = FlattenGoalObservation(gym.make("DSGWorldGoal-v0", **SMALL, obs=("rgb", "poses")))
    obs, _ = env.reset(seed=0)
    assert env.keys == ("poses",)
    assert obs["observation"].shape == (env.unwrapped.K * 7,)
    assert np.array_equal(obs["observation"], env.unwrapped.poses.reshape(-1))
    assert obs in env.observation_space
    assert callable(env.get_wrapper_attr("compute_reward"))
    with pytest.raises(ValueError, match="must be entries"):
        FlattenGoalObservation(gym.make("DSGWorldGoal-v0", **SMALL, obs=("rgb",)))
    with pytest.raises(ValueError, match="no Dict entry 'observation'"):
        FlattenGoalObservation(gym.make("DSGWorld-v0", **SMALL))
    env.close()


def test_her_sac_trains_on_the_goal_env(request):
    pytest.importorskip("stable_baselines3", reason="the rl extra (Stable-Baselines3) is not installed")
    import torch
    from stable_baselines3 import SAC, HerReplayBuffer

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny networks: more threads only wait on each other (restored below)
    request.addfinalizer(lambda: torch.set_num_threads(threads))
    env = FlattenGoalObservation(
        gym.make("DSGWorldGoal-v0", **SMALL, obs=("rgb", "poses"), max_episode_steps=20)
    )
    model = SAC(
        "MultiInputPolicy",
        env,
        replay_buffer_class=HerReplayBuffer,
        replay_buffer_kwargs={
            "n_sampled_goal": 4,
            "goal_selection_strategy": "future",
            "copy_info_dict": True,
        },
        learning_starts=64,
        batch_size=32,
        policy_kwargs={"net_arch": [32, 32]},
        seed=0,
        device="cpu",
    )
    model.learn(256)
    assert model.num_timesteps == 256
    assert model.replay_buffer.size() > 0
    obs, _ = env.reset(seed=1)
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == env.action_space.shape and np.all(np.abs(action) <= 1)
    env.close()


def test_render_goal_draws_a_ghost_in_render_only():
    from scipy.ndimage import binary_dilation

    kw = dict(width=64, height=64, render_mode="rgb_array", render_width=64, render_height=64)
    plain = gym.make("DSGWorld-v0", **kw)
    ghost = gym.make("DSGWorld-v0", **kw, render_goal=True)
    o1, _ = plain.reset(seed=5)
    o2, _ = ghost.reset(seed=5)
    assert all(np.array_equal(o1[k], o2[k]) for k in o1)  # observations never show the goal
    f1, f2 = plain.render(), ghost.render()
    assert f1.shape == f2.shape == (64, 64, 3)
    changed = np.any(f1 != f2, axis=-1)
    # where the objects stand at the goal: the object mask of the goal configuration from the same camera
    at_goal = gym.make("DSGWorld-v0", width=64, height=64, obs=("mask",))
    goal = ghost.unwrapped.goal
    seen, _ = at_goal.reset(options={"start": goal, "goal": goal})
    objects = seen["mask"] > 0
    assert objects.any() and changed.mean() < 0.5
    assert changed[objects].mean() > 0.95  # the ghost covers the goal poses' objects
    assert changed[binary_dilation(objects, iterations=2)].sum() >= 0.8 * changed.sum()  # and little else
    with pytest.raises(ValueError, match="render_goal must be True or False"):
        gym.make("DSGWorld-v0", **SMALL, render_goal="yes")
    for e in (plain, ghost, at_goal):
        e.close()
