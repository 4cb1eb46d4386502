"""Where benchmark results go by default: ``benchmarks/results/<benchmark>/<YYYY-MM-DD>-<commit>.json``.

The date is today's (local time), the commit the checkout's short ``HEAD`` hash (``nocommit`` outside a git
checkout or without git). A result is named by what it measured and on which code, so results of one
benchmark sort by date and each can be traced to its commit.
"""

from __future__ import annotations

import datetime
import subprocess
from pathlib import Path

__all__ = ["RESULTS", "default_out", "short_commit", "write_result"]

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
    """Write ``result`` as JSON to ``out`` atomically, creating its folder. The writer is imported here, not at
    module level: it loads torch, which must not be loaded before a benchmark's measurements."""
    from train_world.capture.format import atomic_write_json

    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, result)
