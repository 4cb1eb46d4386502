"""dsg_gym.collect: rollouts to Minari datasets (exact data, resume, errors, CLI)."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest

minari = pytest.importorskip("minari")
pytest.importorskip("h5py")

import dsg_gym  # noqa: F401
from dsg_gym.cli.collect import main
from dsg_gym.collect import CollectError, collect, episode_seed, load
from dsg_gym.collect.run import WORK_DIR
from dsg_gym.collect.writer import ShardStore

KW = {"width": 32, "height": 32}
SEED = 7


def zero_policy(obs):
    """A ``module:callable`` policy for the CLI test: never moves anything."""
    return np.zeros(8, np.float32)


class Interrupting:
    """Acts randomly (deterministic per observation) and raises ``exc`` on call number ``at`` (if set)."""

    def __init__(self, at=None, exc=KeyboardInterrupt, bad=None):
        self.calls, self.at, self.exc, self.bad = 0, at, exc, bad

    def __call__(self, obs):
        self.calls += 1
        if self.at is not None and self.calls == self.at:
            if self.bad is not None:
                return self.bad
            raise self.exc("boom")
        rng = np.random.default_rng(int(obs["poses"].sum() * 1e6) % 2**32)
        return rng.uniform(-1, 1, 8).astype(np.float32)


def _episodes(ds):
    return [ds[i] for i in range(ds.total_episodes)]


def _assert_same(a, b):
    """Two lists of minari EpisodeData hold identical data."""
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert set(x.observations) == set(y.observations)
        for k in x.observations:
            np.testing.assert_array_equal(x.observations[k], y.observations[k])
        for f in ("actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(x, f), getattr(y, f))


def _replay_check(ds, seeds, max_steps, env_kwargs=KW):
    """Re-run every stored episode from its seed with the stored actions: all data must match bit for bit."""
    env = gym.make("DSGWorld-v0", max_episode_steps=max_steps, **env_kwargs)
    space = env.observation_space
    for ep, seed in zip(_episodes(ds), seeds):
        t = len(ep)
        for k, sub in space.spaces.items():
            assert ep.observations[k].shape == (t + 1, *sub.shape)
            assert ep.observations[k].dtype == sub.dtype
        assert ep.actions.shape == (t, *env.action_space.shape) and ep.actions.dtype == np.float32
        assert ep.rewards.dtype == np.float64 and ep.terminations.dtype == bool
        obs, info = env.reset(seed=int(seed))
        for k in obs:
            np.testing.assert_array_equal(ep.observations[k][0], obs[k])
        for s in range(t):
            obs, r, term, trunc, info = env.step(ep.actions[s])
            for k in obs:
                np.testing.assert_array_equal(ep.observations[k][s + 1], obs[k])
            assert ep.rewards[s] == r and ep.terminations[s] == term and ep.truncations[s] == trunc
            np.testing.assert_array_equal(ep.infos["position_errors"][s + 1], info["position_errors"])
            np.testing.assert_array_equal(ep.infos["rejected"][s + 1], info["rejected"])
            assert ep.infos["success"][s + 1] == info["success"]
        assert term or trunc
    env.close()


@pytest.fixture(scope="module")
def random_ref(tmp_path_factory):
    """3 random episodes, one env, 6 steps each (the reference for resume and Ray)."""
    out = tmp_path_factory.mktemp("ref")
    res = collect(out, env_kwargs=KW, policy="random", episodes=3, seed=SEED, max_episode_steps=6)
    return out, res


def test_random_roundtrip_exact(random_ref, monkeypatch):
    out, res = random_ref
    assert res.dataset_id == "dsgworld/random-v0" and res.episodes == 3 and res.transitions == 18
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(out))
    ds = minari.load_dataset("dsgworld/random-v0")
    assert ds.total_episodes == 3 and ds.total_steps == 18
    meta = ds.storage.metadata
    assert meta["jpeg_encoding"] is False  # RGB stored raw (lossless)
    seeds = meta["dsg_collect"]["episode_seeds"]
    assert seeds == [episode_seed(SEED, e) for e in range(3)]
    assert not (out / WORK_DIR).exists()  # shards are removed once combined
    _replay_check(ds, seeds, 6)
    env = ds.recover_environment()  # the env spec (with kwargs and time limit) is recorded
    assert env.observation_space == ds.observation_space and env.spec.max_episode_steps == 6


@pytest.mark.parametrize("vectorization", ["auto", "async"])
def test_expert_two_envs(tmp_path, vectorization):
    """Two envs in DSGWorld-v0's own vector env (auto) or in worker processes (async): the same episodes."""
    res = collect(tmp_path, env_kwargs=KW, policy="expert", episodes=3, num_envs=2, seed=1, max_episode_steps=60,
                  vectorization=vectorization)  # fmt: skip
    ds = load(res.path)
    eps = _episodes(ds)
    assert res.success_rate == 1.0 and all(e.terminations[-1] for e in eps)
    assert all(not e.infos["collision"].any() for e in eps)  # never a rejected move
    _replay_check(ds, ds.storage.metadata["dsg_collect"]["episode_seeds"], 60)
    # the data does not depend on the number of envs
    one = collect(tmp_path / "one", env_kwargs=KW, policy="expert", episodes=3, num_envs=1, seed=1,
                  max_episode_steps=60)  # fmt: skip
    _assert_same(eps, _episodes(load(one.path)))


def test_interrupt_then_resume(tmp_path):
    pol = Interrupting(at=15)  # episode 0 done (6 calls), 1 done (12), KeyboardInterrupt in episode 2
    kw = {
        "env_kwargs": KW,
        "episodes": 3,
        "seed": SEED,
        "max_episode_steps": 6,
        "shard_episodes": 1,
        "dataset_id": "tt/x-v0",
    }
    with pytest.raises(KeyboardInterrupt):
        collect(tmp_path, policy=pol, **kw)
    assert not (tmp_path / "tt" / "x-v0").exists()  # no half-written dataset
    shards = ShardStore(tmp_path / WORK_DIR / "tt__x-v0" / "shards").shards()
    assert sorted(i for s in shards for i in s.indices) == [0, 1]
    for s in shards:  # each finished episode is a readable Minari dataset already
        assert minari.MinariDataset(s.path).total_episodes == 1
    with pytest.raises(CollectError, match="resume"):
        collect(tmp_path, policy=Interrupting(), **kw)
    with pytest.raises(CollectError, match="settings differ"):
        collect(tmp_path, policy=Interrupting(), resume=True, **{**kw, "max_episode_steps": 7})
    res = collect(tmp_path, policy=Interrupting(), resume=True, **kw)
    assert res.new_episodes == 1 and res.episodes == 3
    got = _episodes(load(res.path))
    # same seeds as the random reference; episodes 0/1 came from the first run, 2 from the resumed one
    _replay_check(load(res.path), [episode_seed(SEED, e) for e in range(3)], 6)
    full = collect(tmp_path / "full", policy=Interrupting(), **kw)  # the same run without interruption
    _assert_same(got, _episodes(load(full.path)))
    again = collect(tmp_path, policy=Interrupting(), resume=True, **kw)  # already complete: nothing to do
    assert again.new_episodes == 0 and again.episodes == 3


@pytest.mark.parametrize(
    "policy, match",
    [
        (Interrupting(at=8, exc=ValueError), "raised ValueError: boom"),
        (Interrupting(at=8, bad=np.full(8, np.nan, np.float32)), "NaN"),
        (Interrupting(at=8, bad=np.zeros(3, np.float32)), "shape"),
        (Interrupting(at=8, bad=np.full(8, 3.0, np.float32)), "outside the action space"),
        (Interrupting(at=8, bad="left"), "bad action"),
    ],
)
def test_bad_policy_stops_and_keeps_finished(tmp_path, policy, match):
    with pytest.raises(CollectError, match=match) as ei:
        collect(
            tmp_path, env_kwargs=KW, policy=policy, episodes=3, seed=0, max_episode_steps=5, shard_episodes=4
        )
    assert "episode 1 step 2" in str(ei.value)
    shards = ShardStore(tmp_path / WORK_DIR / "dsgworld__interrupting-v0" / "shards").shards()
    assert [s.indices for s in shards] == [(0,)]  # the finished episode was flushed on the error


def test_jpeg_is_opt_in_and_lossy(tmp_path, random_ref):
    res = collect(tmp_path, env_kwargs=KW, policy="random", episodes=1, seed=SEED, max_episode_steps=6,
                  image_encoding="jpeg")  # fmt: skip
    ds = load(res.path)
    assert ds.storage.metadata["jpeg_encoding"] is True
    ref = _episodes(load(random_ref[1].path))[0]
    ep = ds[0]
    np.testing.assert_array_equal(ep.observations["mask"], ref.observations["mask"])  # never JPEG
    np.testing.assert_array_equal(ep.actions, ref.actions)
    assert ep.observations["rgb"].shape == ref.observations["rgb"].shape
    diff = np.abs(ep.observations["rgb"].astype(int) - ref.observations["rgb"].astype(int))
    assert diff.max() > 0 and diff.mean() < 20  # lossy but close


def test_cli_module_callable_and_existing_output(tmp_path, capsys):
    args = [
        "--env-kwargs",
        json.dumps({**KW, "obs": ["mask", "poses"]}),
        "--policy",
        "test_collect:zero_policy",
        "--episodes",
        "2",
        "--out",
        str(tmp_path),
        "--seed",
        "3",
        "--max-episode-steps",
        "4",
        "--no-progress",
    ]
    assert main(args) == 0
    assert "dsgworld/zero_policy-v0" in capsys.readouterr().out
    ds = load(tmp_path / "dsgworld" / "zero_policy-v0")
    assert ds.total_steps == 8 and set(ds[0].observations) == {"mask", "poses", "goal"}
    assert not ds[0].actions.any() and ds[1].truncations[-1]
    assert ds.storage.metadata["algorithm_name"] == "test_collect:zero_policy"
    assert main(args) == 2  # the dataset exists: refused without --overwrite
    assert "already exists" in capsys.readouterr().err
    assert main(args + ["--overwrite"]) == 0
    assert (
        main(
            ["--policy", "no_such_module:f", "--episodes", "1", "--out", str(tmp_path / "b"), "--no-progress"]
        )
        == 2
    )
    assert "cannot import module 'no_such_module'" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()  # a bad setting writes nothing
    assert main(["--env-kwargs", "{bad", "--episodes", "1", "--out", str(tmp_path)]) == 2


def test_expert_refuses_unsuitable_env(tmp_path):
    with pytest.raises(CollectError, match="needs 'poses'"):
        collect(tmp_path, env_kwargs={**KW, "obs": ["rgb"]}, policy="expert", episodes=1, seed=0)
    with pytest.raises(CollectError, match="action_mode='delta'"):
        collect(tmp_path, env_kwargs={**KW, "action_mode": "se3"}, policy="expert", episodes=1, seed=0,
                overwrite=True)  # fmt: skip
