"""dsg-collect against a hostile user: bad settings write nothing, finished datasets are not silently kept,
one run at a time per dataset, and rates that say what they measure."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from dsg_gym.cli.collect import main
from dsg_gym.collect import CollectSettingsError, collect, load
from dsg_gym.collect.run import WORK_DIR

KW = {"width": 16, "height": 16, "obs": ["poses"]}


def _cli(tmp_path, *extra):
    return ["--episodes", "2", "--max-episode-steps", "3", "--seed", "1", "--out", str(tmp_path), "--no-progress",
            "--env-kwargs", json.dumps(KW), *extra]  # fmt: skip


@pytest.mark.parametrize(
    "bad, needle",
    [
        ({**KW, "width": -3}, "width must be a positive integer"),
        ({**KW, "world": "/nonexistent.dsgworld"}, ""),
    ],
    ids=["negative-width", "missing-world"],
)
def test_bad_env_settings_write_nothing_and_the_fixed_command_runs(tmp_path, capsys, bad, needle):
    args = [
        "--episodes",
        "1",
        "--max-episode-steps",
        "2",
        "--seed",
        "0",
        "--out",
        str(tmp_path),
        "--no-progress",
    ]
    assert main(args + ["--env-kwargs", json.dumps(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1
        and err[0].startswith("dsg-collect: error: cannot make DSGWorld-v0")
        and needle in err[0]
    )
    assert list(tmp_path.iterdir()) == []  # no run state: the corrected command is not refused
    assert main(args + ["--env-kwargs", json.dumps(KW)]) == 0


def test_resume_of_a_finished_dataset_with_more_episodes_is_refused(tmp_path, capsys):
    assert main(_cli(tmp_path)) == 0
    capsys.readouterr()
    assert main(_cli(tmp_path, "--resume")) == 0  # the same count: already complete
    args = _cli(tmp_path, "--resume")
    args[1] = "4"
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "finished dataset of 2 episodes" in err and "--episodes 4 --overwrite" in err
    assert load(tmp_path / "dsgworld" / "random-v0").total_episodes == 2  # unchanged


def test_a_second_run_on_the_same_dataset_is_refused_with_the_holder(tmp_path):
    code = (
        "import sys, time; from dsg_gym.collect.run import _RunLock; from pathlib import Path\n"
        f"with _RunLock(Path({str(tmp_path)!r}) / '.dsg-collect-dsgworld__random-v0.lock'):\n"
        "    print('held', flush=True); time.sleep(30)\n"
    )
    holder = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(
            CollectSettingsError, match=rf"in use by another dsg-collect run .*process {holder.pid}"
        ):
            collect(tmp_path, env_kwargs=KW, episodes=1, seed=0, max_episode_steps=2)
        assert not (tmp_path / WORK_DIR).exists() and not (tmp_path / "dsgworld").exists()
    finally:
        holder.kill()
        holder.wait()
    t0 = time.monotonic()
    res = collect(
        tmp_path, env_kwargs=KW, episodes=1, seed=0, max_episode_steps=2
    )  # a killed holder frees it
    assert res.episodes == 1 and time.monotonic() - t0 < 60


def test_rates_say_what_they_measure(tmp_path, capsys):
    assert main(_cli(tmp_path)) == 0
    out = capsys.readouterr().out
    assert "transitions/s overall: env start-up and dataset writing included" in out
