"""dsg_gym.io.atomic: a target appears complete or not at all; failures and crashes leave no temporaries
behind (or ones that ``remove_partial`` clears)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

from dsg_gym.io.atomic import TMP_TAG, atomic_dir, atomic_path, atomic_write_bytes, remove_partial


def _umask() -> int:
    old = os.umask(0o022)
    os.umask(old)
    return old


def test_write_bytes_creates_folders_and_gives_the_usual_mode(tmp_path):
    target = tmp_path / "a" / "b" / "x.bin"
    assert atomic_write_bytes(target, b"hello") == target
    assert target.read_bytes() == b"hello"
    assert os.listdir(target.parent) == ["x.bin"]
    assert target.stat().st_mode & 0o777 == 0o666 & ~_umask()
    atomic_write_bytes(target, b"again")  # replaces
    assert target.read_bytes() == b"again" and os.listdir(target.parent) == ["x.bin"]


def test_failure_mid_write_leaves_no_target_and_no_temporary(tmp_path):
    target = tmp_path / "x.bin"
    with pytest.raises(RuntimeError, match="disk on fire"):
        with atomic_path(target) as tmp, open(tmp, "xb") as fh:
            fh.write(b"half of it")
            raise RuntimeError("disk on fire")
    assert os.listdir(tmp_path) == []
    target.write_bytes(b"previous")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"new")
            raise KeyboardInterrupt
    assert target.read_bytes() == b"previous" and os.listdir(tmp_path) == ["x.bin"]


def test_failed_rename_and_missing_file_leave_the_target(tmp_path, monkeypatch):
    target = tmp_path / "x.usda"
    target.write_bytes(b"previous")
    with pytest.raises(FileNotFoundError):
        with atomic_path(target, suffix=".usda"):
            pass  # the writer produced nothing
    seen = []

    def failing_replace(src, dst):
        seen.append(os.fspath(src))
        raise OSError("rename failed")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        atomic_write_bytes(target, b"new")
    assert seen and TMP_TAG in os.path.basename(seen[0])
    assert target.read_bytes() == b"previous" and os.listdir(tmp_path) == ["x.usda"]


def test_a_killed_writer_leaves_no_target_and_remove_partial_clears_its_temporary(tmp_path):
    target = tmp_path / "x.bin"
    code = f"""
        import os, signal
        from dsg_gym.io.atomic import atomic_path
        with atomic_path({str(target)!r}) as tmp, open(tmp, "xb") as fh:
            fh.write(b"half of it")
            fh.flush()
            os.kill(os.getpid(), signal.SIGKILL)
    """
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True)
    assert res.returncode != 0
    left = os.listdir(tmp_path)
    assert not target.exists() and len(left) == 1 and left[0].startswith(f".x.bin{TMP_TAG}")
    (tmp_path / ".other.tmp-keep").write_bytes(b"")  # another target's temporary
    remove_partial(tmp_path, "x.bin")
    assert os.listdir(tmp_path) == [".other.tmp-keep"]
    remove_partial(tmp_path)
    assert os.listdir(tmp_path) == []


def test_atomic_dir(tmp_path):
    target = tmp_path / "out"
    with atomic_dir(target) as tmp:
        (tmp / "f").write_text("1")
        assert not target.exists()
    assert (target / "f").read_text() == "1" and os.listdir(tmp_path) == ["out"]
    with pytest.raises(RuntimeError):
        with atomic_dir(tmp_path / "other") as tmp:
            (tmp / "f").write_text("2")
            raise RuntimeError
    assert os.listdir(tmp_path) == ["out"]
    with pytest.raises(OSError):  # target exists and replace is off
        with atomic_dir(target) as tmp:
            (tmp / "g").write_text("2")
    assert os.listdir(target) == ["f"] and os.listdir(tmp_path) == ["out"]
    with pytest.raises(RuntimeError):  # replace: the old folder stays until the new one is complete
        with atomic_dir(target, replace=True) as tmp:
            (tmp / "g").write_text("2")
            raise RuntimeError
    assert os.listdir(target) == ["f"] and os.listdir(tmp_path) == ["out"]
    with atomic_dir(target, replace=True) as tmp:
        (tmp / "g").write_text("2")
    assert os.listdir(target) == ["g"] and os.listdir(tmp_path) == ["out"]
