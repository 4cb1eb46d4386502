"""One collection run per dataset at a time: an exclusive, non-blocking file lock held for the whole run.

The lock of ``OUT/<namespace>/<name>-vN`` is the file ``OUT/<namespace>/.<name>-vN.dsg-collect.lock``, beside
the dataset folder (which is replaced as a whole, so the lock cannot live inside it). It is a
:class:`filelock.FileLock` (``flock`` on POSIX): the operating system releases it when the holder exits in any
way, ``SIGKILL`` included, so a lock is never left stale. The lock file itself stays (deleting a lock file that
another process has open would let two runs each lock their own file). The holder writes its process id, host
and start time to ``<lock>.json`` right after taking the lock; a refused run names that holder.
"""

from __future__ import annotations

import json
import os
import socket
import time
from pathlib import Path

from ..io.atomic import atomic_write_bytes
from .rollout import CollectSettingsError

__all__ = ["RunLock", "lock_path"]

#: how long a refused run waits for the holder to write its details (it does so right after locking)
_HOLDER_WAIT_S = 2.0


def lock_path(target: Path) -> Path:
    """The lock file of the dataset folder ``target``."""
    target = Path(target)
    return target.parent / f".{target.name}.dsg-collect.lock"


def _alive_here(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # exists, owned by someone else
        return True
    return True


class RunLock:
    """``with RunLock(target):`` holds the lock of the dataset folder ``target`` or raises
    :class:`~dsg_gym.collect.rollout.CollectSettingsError` naming the run that holds it. Released when the block
    ends, however it ends (exception, ``KeyboardInterrupt``); by the operating system when the process dies."""

    def __init__(self, target: Path):
        self.target = Path(target)
        self.path = lock_path(self.target)
        self.info = Path(f"{self.path}.json")
        self._lock = None

    def holder(self) -> str:
        """Who holds the lock, as far as ``<lock>.json`` tells (waits briefly for a holder that has just taken
        it and not written its details yet)."""
        deadline = time.monotonic() + _HOLDER_WAIT_S
        while True:
            try:
                h = json.loads(self.info.read_text())
                pid, host, started = int(h["pid"]), str(h["host"]), str(h["started"])
            except (OSError, ValueError, KeyError, TypeError):
                h = None
            if h is not None and (host != socket.gethostname() or _alive_here(pid)):
                return f"process {pid} on host {host}, started {started}"
            if time.monotonic() >= deadline:  # details missing or left by a dead process
                return "a process that has not written its details"
            time.sleep(0.1)

    def __enter__(self) -> RunLock:
        from filelock import FileLock, Timeout

        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            lock = FileLock(str(self.path))
            lock.acquire(blocking=False)
        except Timeout:
            raise CollectSettingsError(
                f"dataset {self.target} is being collected by another dsg-collect run ({self.holder()}); wait "
                f"for it to end or stop it (lock file {self.path})"
            ) from None
        except OSError as e:
            raise CollectSettingsError(f"cannot create the lock file {self.path}: {e}") from None
        self._lock = lock
        try:
            holder = {
                "pid": os.getpid(),
                "host": socket.gethostname(),
                "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            }
            atomic_write_bytes(self.info, json.dumps(holder).encode())
        except BaseException:
            self._release()
            raise
        return self

    def _release(self) -> None:
        if self._lock is not None:
            try:
                self.info.unlink(missing_ok=True)  # before unlocking: the next holder's details stay
            finally:
                self._lock.release()
                self._lock = None

    def __exit__(self, *exc) -> None:
        self._release()
