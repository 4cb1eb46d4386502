"""Where benchmark results go by default: ``benchmarks/results/<benchmark>/<YYYY-MM-DD>-<commit>.json``.

The date is today's (local time), the commit the checkout's short ``HEAD`` hash (``nocommit`` outside a git
checkout or without git). A result is named by what it measured and on which code, so results of one
benchmark sort by date and each can be traced to its commit. Every result says which machine measured it
(:func:`machine_info`; :func:`write_result` adds it where a benchmark did not): speeds differ between machines
by up to 2x, so only figures of one machine compare.
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

__all__ = ["RESULTS", "default_out", "machine_info", "short_commit", "write_result"]

REPO = Path(__file__).resolve().parents[1]
#: the folder of committed results, one subfolder per benchmark
RESULTS = REPO / "benchmarks" / "results"


def short_commit(cwd: Path = REPO) -> str:
    """``git rev-parse --short HEAD`` in ``cwd``, or ``"nocommit"`` when that fails (not a checkout, no git)."""
    try:
        r = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "nocommit"
    head = r.stdout.strip()
    return head if r.returncode == 0 and head else "nocommit"


def machine_info(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict:
    """The measuring machine: ``cpu`` (the processor's model name from ``cpuinfo`` on Linux, else
    ``platform.processor()``, else ``"unknown"``), ``cpus`` (logical CPUs), ``platform`` and ``python``."""
    model = ""
    try:
        for line in cpuinfo.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                model = value.strip()
                break
    except OSError:
        pass
    return {
        "cpu": model or platform.processor() or "unknown",
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
    }


def default_out(
    benchmark: str,
    suffix: str = ".json",
    *,
    date: datetime.date | None = None,
    root: Path = RESULTS,
    cwd: Path = REPO,
) -> Path:
    """``<root>/<benchmark>/<YYYY-MM-DD>-<short commit><suffix>``; ``suffix=""`` names a folder (for
    benchmarks that write several files). Nothing is created."""
    if not benchmark or "/" in benchmark or benchmark.startswith("."):
        raise ValueError(f"benchmark must be a plain name, got {benchmark!r}")
    day = (date or datetime.date.today()).isoformat()
    return Path(root) / benchmark / f"{day}-{short_commit(cwd)}{suffix}"


def write_result(out: Path, result: dict) -> None:
    """Write ``result`` as JSON to ``out`` atomically, creating its folder, with a ``machine`` entry
    (:func:`machine_info`) unless it has one. The writer is imported here, not at
    module level: it loads torch, which must not be loaded before a benchmark's measurements."""
    from train_world.capture.format import atomic_write_json

    if "machine" not in result:
        result = {**result, "machine": machine_info()}
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, result)
