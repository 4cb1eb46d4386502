"""Atomic writes: a file or folder appears complete at its path, or not at all.

Every writer of dsg-gym and train_world (world files, PLY, USD stages, episodes, datasets, captures, reports)
goes through this module. A file is written under a hidden temporary name in the target's folder,
``.<name>.tmp-<pid>-<host>-<random><suffix>`` (the writing process's id and a hash of the machine's name),
flushed to disk (``fsync``) and renamed over the target with ``os.replace`` (atomic within one file system); on
any exception, ``KeyboardInterrupt`` included, the temporary is removed and the target is left as it was. Files
get the mode a plain ``open`` gives (``0o666`` less the umask). A folder is built as a hidden sibling with the
same kind of name and renamed into place. :func:`remove_partial` deletes the temporaries a killed process left
behind (with ``stale_only``, only those whose writer no longer runs: what a writer calls before writing its
target). Missing parent folders are created.
"""

from __future__ import annotations

import contextlib
import os
import re
import secrets
import shutil
import socket
import zlib
from collections.abc import Iterator
from pathlib import Path

__all__ = ["TMP_TAG", "atomic_dir", "atomic_path", "atomic_write_bytes", "remove_partial"]

#: marks a temporary: ``.<target name><TMP_TAG><pid>-<host>-<random>``
TMP_TAG = ".tmp-"
_HOST = f"{zlib.crc32(socket.gethostname().encode()):08x}"
_OWNER = re.compile(re.escape(TMP_TAG) + r"(\d+)-([0-9a-f]{8})-[0-9a-f]{12}")


def _temp_sibling(target: Path, suffix: str = "") -> Path:
    return target.parent / f".{target.name}{TMP_TAG}{os.getpid()}-{_HOST}-{secrets.token_hex(6)}{suffix}"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # it exists but belongs to someone else, or this system cannot tell
        return True
    return True


def _stale(name: str) -> bool:
    """Whether the temporary ``name`` was left by a process of this machine that no longer runs (a name without
    the writer's id is never judged stale)."""
    found = list(_OWNER.finditer(name))
    if not found:
        return False
    pid, host = int(found[-1].group(1)), found[-1].group(2)
    return host == _HOST and pid != os.getpid() and not _running(pid)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    """Make a rename in ``folder`` durable (best effort: not every file system allows it)."""
    with contextlib.suppress(OSError):
        _fsync(folder)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, suffix: str = "") -> Iterator[Path]:
    """Yield a fresh temporary path next to ``path`` for the caller to write a file at (for writers that
    take a path: USD, PIL). When the block ends normally the file is fsync'ed and moved onto ``path``; on
    any exception it is removed. ``suffix`` ends the temporary name (e.g. ``".usdc"`` where the writer picks
    the format by extension)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(path, suffix)
    try:
        yield tmp
        _fsync(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see the module docstring); returns the path."""
    with atomic_path(path) as tmp, open(tmp, "xb") as fh:
        fh.write(data)
    return Path(path)


@contextlib.contextmanager
def atomic_dir(target: str | os.PathLike, *, replace: bool = False) -> Iterator[Path]:
    """Yield a fresh, empty hidden sibling folder of ``target`` to fill; when the block ends normally it is
    renamed to ``target``, on any exception it is deleted.

    ``target`` must not exist (or be an empty folder) unless ``replace``: then an existing ``target`` (file or
    folder) is moved aside only after the new folder is complete, the new one takes its place and the old one
    is deleted."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_sibling(target)
    tmp.mkdir()
    try:
        yield tmp
        old = None
        if replace and (target.is_symlink() or target.exists()):
            old = _temp_sibling(target)
            os.rename(target, old)
        try:
            os.rename(tmp, target)
        except BaseException:
            if old is not None:
                os.rename(old, target)
            raise
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        _remove(old)
    _fsync_dir(target.parent)


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def remove_partial(folder: str | os.PathLike, name: str = "", *, stale_only: bool = False) -> None:
    """Delete the temporaries interrupted writes left in ``folder``: those of the target ``name``, or all of
    them when ``name`` is empty. ``stale_only``: only those whose writer, a process of this machine, no longer
    runs (safe while other processes write the same target)."""
    folder = Path(folder)
    if not folder.is_dir():
        return
    for p in folder.iterdir():
        if p.name.startswith(f".{name}{TMP_TAG}") if name else (p.name.startswith(".") and TMP_TAG in p.name):
            if not stale_only or _stale(p.name):
                _remove(p)
