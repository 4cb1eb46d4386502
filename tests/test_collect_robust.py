"""dsg-collect against a hostile user: bad settings change nothing and fail in one line, ``--resume`` extends a
finished dataset exactly as an uninterrupted run would have written it, and the rates say what they measure."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

pytest.importorskip("minari")
pytest.importorskip("h5py")

from dsg_gym.cli.collect import main
from dsg_gym.collect import CollectError, CollectSettingsError, collect, load
from dsg_gym.collect.run import WORK_DIR

KW = {"width": 16, "height": 16, "obs": ["rgb", "mask", "poses"]}
STEPS = 4


def _cli(out, episodes=2, kw=KW, *extra):
    return ["--episodes", str(episodes), "--max-episode-steps", str(STEPS), "--seed", "1", "--out", str(out),
            "--no-progress", "--env-kwargs", json.dumps(kw), *extra]  # fmt: skip


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("dsg-collect: error: "), err
    return err[0]


def assert_same_dataset(a, b):
    """Two datasets hold the same episodes, bit for bit, and the same dsg-collect metadata."""
    assert a.total_episodes == b.total_episodes and a.total_steps == b.total_steps
    ma, mb = a.storage.metadata, b.storage.metadata
    assert ma["dsg_collect"] == mb["dsg_collect"]
    assert {k: v for k, v in ma.items() if k != "dsg_collect"} == {
        k: v for k, v in mb.items() if k != "dsg_collect"
    }
    for x, y in zip(a.iterate_episodes(), b.iterate_episodes(), strict=True):
        assert set(x.observations) == set(y.observations) and set(x.infos) == set(y.infos)
        for k in x.observations:
            np.testing.assert_array_equal(x.observations[k], y.observations[k])
            assert x.observations[k].dtype == y.observations[k].dtype
        for k in x.infos:
            np.testing.assert_array_equal(x.infos[k], y.infos[k])
        for f in ("actions", "rewards", "terminations", "truncations"):
            np.testing.assert_array_equal(getattr(x, f), getattr(y, f))


@pytest.fixture(scope="module")
def fresh8(tmp_path_factory):
    """An uninterrupted 8-episode run: the reference for extended and interrupted ones."""
    out = tmp_path_factory.mktemp("fresh8")
    return load(collect(out, env_kwargs=KW, episodes=8, seed=1, max_episode_steps=STEPS).path)


@pytest.fixture
def corrupt_world(tmp_path):
    p = tmp_path / "corrupt.dsgworld"
    p.write_bytes(b"not a world file")
    return str(p)


@pytest.mark.parametrize(
    "bad, needle",
    [
        ({"width": -3}, "width must be a positive integer"),
        ({"world": "CORRUPT"}, "cannot load world file"),
        ({"world": "/nonexistent/x.dsgworld"}, "does not exist"),
        ({"no_such_option": 1}, "no_such_option"),
    ],
    ids=["negative-width", "corrupt-world", "missing-world", "unknown-kwarg"],
)
def test_bad_env_settings_write_nothing_and_the_fixed_command_runs(
    tmp_path, capsys, corrupt_world, bad, needle
):
    out = tmp_path / "out"
    bad = {**KW, **bad, **({"world": corrupt_world} if bad.get("world") == "CORRUPT" else {})}
    for extra in ([], ["--resume"]):
        assert main(_cli(out, 2, bad, *extra)) == 2
        line = _one_error_line(capsys)
        assert line.startswith("dsg-collect: error: cannot make DSGWorld-v0") and needle in line
        assert "fix --env / --env-kwargs" in line
        assert not out.exists()  # no run state: nothing blocks the corrected command
    assert main(_cli(out, 2)) == 0
    assert load(out / "dsgworld" / "random-v0").total_episodes == 2


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["--policy", "no_such_module:f"], "cannot import module 'no_such_module'"),
        (["--policy", "expert", "--env-kwargs", json.dumps({**KW, "obs": ["rgb"]})], "needs 'poses'"),
        (["--dataset-id", "Not An Id"], "dataset id"),
        (["--shard-episodes", "0"], "shard_episodes must be a positive integer"),
        (["--env-kwargs", "{bad"], "--env-kwargs is not valid JSON"),
        (["--env-kwargs", "[1, 2]"], "--env-kwargs must be a JSON object"),
    ],
    ids=["policy-import", "policy-env", "dataset-id", "shard-episodes", "json", "json-list"],
)
def test_bad_settings_are_one_line_with_exit_2(tmp_path, capsys, extra, needle):
    assert main(_cli(tmp_path / "out", 2, KW, *extra)) == 2
    assert needle in _one_error_line(capsys)
    assert not (tmp_path / "out").exists()


def test_out_that_is_a_file_is_refused(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    assert main(_cli(f)) == 2
    assert "is a file" in _one_error_line(capsys) and f.read_text() == "x"


def fail_at_once(obs):
    raise RuntimeError("broken policy")


def test_a_run_that_finished_nothing_does_not_block_other_settings(tmp_path, capsys):
    """A run stopped before its first episode leaves no finished episode: any command may start afresh."""
    assert (
        main(_cli(tmp_path, 2, KW, "--policy", "test_collect_robust:fail_at_once", "--dataset-id", "tt/x-v0"))
        == 1
    )
    line = _one_error_line(capsys)
    assert "raised RuntimeError: broken policy" in line and "--resume" in line
    assert (tmp_path / WORK_DIR / "tt__x-v0" / "run.json").exists()
    assert main(_cli(tmp_path, 3, KW, "--dataset-id", "tt/x-v0")) == 0  # other policy, no --overwrite needed
    assert load(tmp_path / "tt" / "x-v0").total_episodes == 3
    assert not (tmp_path / WORK_DIR).exists()


def test_resume_extends_a_finished_dataset_like_an_uninterrupted_run(tmp_path, capsys, fresh8):
    assert main(_cli(tmp_path, 5)) == 0
    capsys.readouterr()
    args = _cli(tmp_path, 8, KW, "--resume")
    args[args.index("--seed") : args.index("--seed") + 2] = []  # the seed is taken from the dataset
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "8 episodes" in out and "this run: 3 episodes" in out
    ext = load(tmp_path / "dsgworld" / "random-v0")
    assert_same_dataset(ext, fresh8)
    assert not (tmp_path / WORK_DIR).exists()  # the shards (the adopted dataset too) are gone
    assert main(args) == 0  # all 8 there: nothing to do
    assert "nothing to collect" in capsys.readouterr().out


def test_extension_refusals_change_nothing(tmp_path, capsys):
    assert main(_cli(tmp_path, 3)) == 0
    path = tmp_path / "dsgworld" / "random-v0"
    before = load(path)[2].actions.copy()
    capsys.readouterr()
    assert main(_cli(tmp_path, 2, KW, "--resume")) == 2  # never removes episodes
    assert "already holds 3 episodes, more than --episodes 2" in _one_error_line(capsys)
    args = _cli(tmp_path, 5, KW, "--resume")
    args[args.index("--max-episode-steps") + 1] = str(STEPS + 1)
    assert main(args) == 2
    assert "settings differ (max_episode_steps: 4 -> 5)" in _one_error_line(capsys)
    assert main(_cli(tmp_path, 5)) == 2  # without --resume
    assert "already exists" in _one_error_line(capsys)
    ds = load(path)
    assert ds.total_episodes == 3 and np.array_equal(ds[2].actions, before)
    assert not (tmp_path / WORK_DIR).exists()


def test_a_run_left_between_combining_and_clean_up_is_not_shrunk(tmp_path):
    """keep_shards leaves the run's state as a run killed after combining and before its clean-up does."""
    common = {"env_kwargs": KW, "seed": 2, "max_episode_steps": STEPS}
    first = collect(tmp_path, episodes=3, keep_shards=True, **common)
    with pytest.raises(CollectSettingsError, match="already holds 3 episodes, more than --episodes 2"):
        collect(tmp_path, episodes=2, resume=True, **common)
    again = collect(tmp_path, episodes=3, resume=True, **common)  # finishes: the same dataset, state removed
    assert again.new_episodes == 0 and again.episodes == 3 and not (tmp_path / WORK_DIR).exists()
    assert_same_dataset(load(again.path), load(collect(tmp_path / "b", episodes=3, **common).path))
    assert first.path == again.path


def test_a_run_killed_while_removing_its_shards_leaves_a_consistent_state(tmp_path, monkeypatch):
    """The work folder is renamed away before it is deleted: a run stopped part-way through that deletion
    leaves no half-deleted shard that a later run would read."""
    import dsg_gym.collect.state as state

    common = {"env_kwargs": KW, "seed": 2, "max_episode_steps": STEPS, "shard_episodes": 1}
    real_rmtree = state.shutil.rmtree

    def stop_half_way(path, *a, **k):  # deletes one shard's data file, then the process "dies"
        next(Path(path).rglob("main_data.hdf5")).unlink()
        raise KeyboardInterrupt

    monkeypatch.setattr(state.shutil, "rmtree", stop_half_way)
    with pytest.raises(KeyboardInterrupt):
        collect(tmp_path, episodes=3, **common)
    monkeypatch.setattr(state.shutil, "rmtree", real_rmtree)
    assert not (tmp_path / WORK_DIR / "dsgworld__random-v0").exists()  # no run state with a broken shard
    res = collect(tmp_path, episodes=3, resume=True, **common)  # the dataset is complete: nothing to do
    assert res.new_episodes == 0 and res.episodes == 3
    assert not (tmp_path / WORK_DIR).exists()  # the half-deleted temporary is removed
    assert_same_dataset(load(res.path), load(collect(tmp_path / "b", episodes=3, **common).path))


def test_jpeg_dataset_is_not_extended(tmp_path):
    kw = {"width": 32, "height": 32, "obs": ["rgb"]}  # 32x32: an image space, JPEG-encoded
    common = {"env_kwargs": kw, "seed": 0, "max_episode_steps": 2, "image_encoding": "jpeg"}
    collect(tmp_path, episodes=1, **common)
    with pytest.raises(CollectSettingsError, match="JPEG-encoded and would be encoded a second time"):
        collect(tmp_path, episodes=2, resume=True, **common)
    assert load(tmp_path / "dsgworld" / "random-v0").total_episodes == 1


class StopAt:
    """The random policy's actions, but raises ``KeyboardInterrupt`` at call ``at`` (counted over the run)."""

    def __init__(self, at=None):
        self.at, self.calls, self.rng = at, 0, None

    def reset(self, seed):
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs):
        self.calls += 1
        if self.calls == self.at:
            raise KeyboardInterrupt
        return self.rng.uniform(-1, 1, 8).astype(np.float32)


def test_interrupted_extension_keeps_the_dataset_and_resumes_exactly(tmp_path):
    common = {
        "env_kwargs": KW,
        "seed": 1,
        "max_episode_steps": STEPS,
        "shard_episodes": 1,
        "dataset_id": "tt/s-v0",
    }
    collect(tmp_path / "ref", policy=StopAt(), episodes=6, **common)
    collect(tmp_path, policy=StopAt(), episodes=3, **common)
    with pytest.raises(KeyboardInterrupt):  # stopped in episode 4: episode 3 is in a shard
        collect(tmp_path, policy=StopAt(at=STEPS + 2), episodes=6, resume=True, **common)
    assert load(tmp_path / "tt" / "s-v0").total_episodes == 3  # the finished dataset is still there, whole
    with pytest.raises(CollectError, match="unfinished run"):
        collect(tmp_path, policy=StopAt(), episodes=6, **common)
    res = collect(tmp_path, policy=StopAt(), episodes=6, resume=True, **common)
    assert res.new_episodes == 2  # episode 3 came from the interrupted run
    assert_same_dataset(load(res.path), load(tmp_path / "ref" / "tt" / "s-v0"))


def test_rates_say_what_they_measure(tmp_path, capsys):
    args = _cli(tmp_path, 2, KW)
    args.remove("--no-progress")
    assert main(args) == 0
    cap = capsys.readouterr()
    line = [ln for ln in cap.out.splitlines() if ln.startswith("this run:")]
    assert len(line) == 1
    assert "rollout" in line[0] and "env steps/s (resets, policy and env steps only)" in line[0]
    assert "episodes/s (env start-up and dataset writes included)" in line[0]
    bar = [ln for ln in re.split(r"[\r\n]", cap.err) if "episodes [" in ln][
        -1
    ]  # the progress bar's last state
    assert "2/2 episodes" in bar and " env steps/s" in bar and " episodes/s" in bar and "rollout" in bar
    res = collect(tmp_path / "api", env_kwargs=KW, episodes=2, seed=1, max_episode_steps=STEPS)
    # the rollout is a part of the whole call, so its rate is the higher one
    assert 0 < res.rollout_seconds < res.seconds
    assert res.rollout_steps_per_second > res.transitions_per_second > 0
    assert res.episodes_per_second == pytest.approx(2 / res.seconds)
