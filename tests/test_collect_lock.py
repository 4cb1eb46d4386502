"""One dsg-collect run per dataset: the lock is held for the whole run, a second run is refused naming the
holder, and the lock is freed however the holder ends (normal end, error, Ctrl-C, SIGKILL)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

pytest.importorskip("minari")
pytest.importorskip("h5py")

from dsg_gym.cli.collect import main
from dsg_gym.collect import CollectError, CollectSettingsError, collect, load
from dsg_gym.collect.lock import RunLock, lock_path
from dsg_gym.collect.run import WORK_DIR

KW = {"width": 16, "height": 16, "obs": ["poses"]}
COMMON = {"env_kwargs": KW, "seed": 0, "max_episode_steps": 3, "dataset_id": "tt/lock-v0"}


def _target(out):
    return out / "tt" / "lock-v0"


def _can_lock(out) -> bool:
    try:
        with RunLock(_target(out)):
            return True
    except CollectSettingsError:
        return False


class Probe:
    """A policy that, at its first call (the run under way), tries a second run on the same dataset and
    keeps what happened; then it acts randomly."""

    def __init__(self, out, raise_at=None, exc=RuntimeError):
        self.out, self.raise_at, self.exc, self.calls, self.seen = out, raise_at, exc, 0, None
        self.rng = np.random.default_rng(0)

    def __call__(self, obs):
        self.calls += 1
        if self.calls == 1:
            try:
                collect(self.out, policy="random", episodes=1, resume=True, **COMMON)
                self.seen = "not refused"
            except CollectSettingsError as e:
                self.seen = str(e)
        if self.calls == self.raise_at:
            raise self.exc("stop")
        return self.rng.uniform(-1, 1, 8).astype(np.float32)


def test_the_lock_is_held_for_the_whole_run_and_names_the_holder(tmp_path):
    probe = Probe(tmp_path)
    collect(tmp_path, policy=probe, episodes=2, **COMMON)
    assert probe.seen is not None and "is being collected by another dsg-collect run" in probe.seen
    assert f"process {os.getpid()} on host {socket.gethostname()}" in probe.seen
    assert load(_target(tmp_path)).total_episodes == 2
    assert _can_lock(tmp_path)  # released at the end
    assert not Path(f"{lock_path(_target(tmp_path))}.json").exists()  # the holder's details go with it


@pytest.mark.parametrize("exc", [RuntimeError, KeyboardInterrupt], ids=["error", "ctrl-c"])
def test_the_lock_is_released_on_errors_and_ctrl_c(tmp_path, exc):
    probe = Probe(tmp_path, raise_at=5, exc=exc)  # after episode 0 (3 steps), in episode 1
    with pytest.raises(CollectError if exc is RuntimeError else KeyboardInterrupt):
        collect(tmp_path, policy=probe, episodes=3, shard_episodes=1, **COMMON)
    assert "is being collected by another" in probe.seen  # it was held during the run
    assert _can_lock(tmp_path)
    res = collect(tmp_path, policy=Probe(tmp_path), episodes=3, resume=True, **COMMON)
    assert res.new_episodes == 2 and res.episodes == 3


HOLD = (
    "import sys, time\n"
    "from pathlib import Path\n"
    "from dsg_gym.collect.lock import RunLock\n"
    "with RunLock(Path(sys.argv[1])):\n"
    "    print('held', flush=True)\n"
    "    time.sleep(120)\n"
)


def test_a_second_process_is_refused_and_a_killed_holder_frees_the_lock(tmp_path, capsys):
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(_target(tmp_path))], stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        args = ["--episodes", "1", "--max-episode-steps", "3", "--seed", "0", "--out", str(tmp_path),
                "--dataset-id", "tt/lock-v0", "--env-kwargs", json.dumps(KW), "--no-progress"]  # fmt: skip
        for extra in ([], ["--resume"], ["--overwrite"]):
            assert main(args + extra) == 2
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and err[0].startswith("dsg-collect: error: dataset ")
            assert f"another dsg-collect run (process {holder.pid} on host {socket.gethostname()}" in err[0]
        assert not (tmp_path / WORK_DIR).exists() and not _target(tmp_path).exists()  # nothing written
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    assert holder.returncode == -signal.SIGKILL
    assert main(args) == 0  # the dead holder's lock is gone; its stale details do not matter
    assert load(_target(tmp_path)).total_episodes == 1


def test_two_runs_started_together_one_runs_one_is_refused(tmp_path):
    args = [sys.executable, "-m", "dsg_gym.cli.collect", "--episodes", "3", "--max-episode-steps", "3", "--seed",
            "0", "--out", str(tmp_path), "--env-kwargs", json.dumps(KW), "--no-progress"]  # fmt: skip
    procs = [
        subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)
    ]
    results = [(p.wait(timeout=300), p.stdout.read(), p.stderr.read()) for p in procs]
    codes = sorted(r[0] for r in results)
    assert codes == [0, 2], results
    refused = next(r for r in results if r[0] == 2)[2]
    # refused by the lock while the other runs, or by the finished dataset if the other was already done
    assert "being collected by another dsg-collect run" in refused or "already exists" in refused, refused
    assert len(refused.strip().splitlines()) == 1
    ds = load(tmp_path / "dsgworld" / "random-v0")
    assert ds.total_episodes == 3 and not (tmp_path / WORK_DIR).exists()
