"""Training step time when other work shares the cores: alone, beside a busy process, beside a second training.

    python -m benchmarks.train_shared [--capture CAP [--checkpoint CKPT]] [--steps 30] [--rounds 2] [--out FILE]
    python -m benchmarks.train_shared --quick [--out FILE]        # the quick preset on a 24x24 scene

Every measurement is a fresh ``python -m benchmarks.train_step`` process (median reconstruction and joint step
times), run with each thread count of ``--threads`` (``NUMBA_NUM_THREADS`` and ``OMP_NUM_THREADS``; default: all
cores, then one) in each setting:

- ``idle``: nothing else runs;
- ``busy``: beside a process that keeps one core busy (a Python loop), started first, as a data-collection or
  simulation job would;
- ``training``: beside a second training of the same kind (all cores), started ``--stagger`` seconds earlier
  and made long enough to outlast the measured one.

Writes ``{config, runs: [{threads, setting, recon_ms, joint_ms, waiting}], summary: {threads: {setting:
{recon_ms, joint_ms}}}, speed: {threads: {setting: joint speed over the idle run with all cores}}}``; speeds
are ratios from one machine and session, the absolute times do not carry over.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ._results import default_out, write_result

SETTINGS = ("idle", "busy", "training")
_SPIN = "import time\nwhile True:\n    time.perf_counter()\n"


def _env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    env["NUMBA_NUM_THREADS"] = env["OMP_NUM_THREADS"] = str(threads)
    return env


def _bench(out: Path, args: list[str], threads: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "benchmarks.train_step", "--out", str(out), *args]
    return subprocess.Popen(
        cmd, env=_env(threads), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _measure(
    tmp: Path, args: list[str], threads: int, setting: str, stagger: float, tag: str
) -> dict[str, Any]:
    other = None
    if setting == "busy":
        other = subprocess.Popen([sys.executable, "-c", _SPIN])
        time.sleep(1.0)
    elif setting == "training":
        long_args = [*args]
        i = long_args.index("--steps")
        long_args[i + 1] = str(int(long_args[i + 1]) * 4 + 100)  # outlasts the measured run
        other = _bench(tmp / f"other-{tag}.json", long_args, os.cpu_count() or 1)
        time.sleep(stagger)
    out = tmp / f"{tag}.json"
    try:
        proc = _bench(out, args, threads)
        _, err = proc.communicate()
        still = other is None or other.poll() is None
    finally:
        if other is not None:
            other.kill()
            other.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"benchmarks.train_step ({threads} threads, {setting}) failed:\n{err[-2000:]}")
    if not still:
        raise RuntimeError(f"the competing job of setting {setting!r} ended before the measured training")
    r = json.loads(out.read_text())
    return {
        "threads": threads,
        "setting": setting,
        "recon_ms": r["recon"]["ms_median"],
        "joint_ms": r["joint"]["ms_median"],
        "waiting": r["config"].get("openmp_waiting"),
    }


def run(
    out: Path,
    bench_args: list[str],
    threads: tuple[int, ...],
    rounds: int,
    settings: tuple[str, ...] = SETTINGS,
    stagger: float = 20.0,
) -> dict[str, Any]:
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            for n in threads if k % 2 == 0 else threads[::-1]:
                for s in settings:
                    runs.append(_measure(Path(tmp), bench_args, n, s, stagger, f"{n}-{s}-{k}"))
    summary: dict[str, dict[str, dict[str, float]]] = {}
    for n in threads:
        summary[str(n)] = {
            s: {
                f: min(r[f] for r in runs if r["threads"] == n and r["setting"] == s)
                for f in ("recon_ms", "joint_ms")
            }
            for s in settings
        }
    ref = summary[str(threads[0])]["idle"]["joint_ms"] if "idle" in settings else None
    speed = (
        {n: {s: round(ref / v["joint_ms"], 3) for s, v in per.items()} for n, per in summary.items()}
        if ref
        else {}
    )
    result = {
        "config": {"train_step_args": bench_args, "threads": list(threads), "rounds": rounds,
                   "stagger_s": stagger, "cpus": os.cpu_count()},
        "runs": runs,
        "summary": summary,
        "speed": speed,
    }  # fmt: skip
    write_result(out, result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.train_shared",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/train_shared/<date>-<commit>.json)",
    )
    p.add_argument("--capture", type=Path, help="two-state capture (benchmarks.train_step --capture)")
    p.add_argument(
        "--checkpoint", type=Path, help="its joint-start checkpoint (benchmarks.train_step --checkpoint)"
    )
    p.add_argument("--seed", type=int, default=0, help="the training's seed (benchmarks.train_step --seed)")
    p.add_argument("--steps", type=int, default=30, help="timed steps per phase and process (default 30)")
    p.add_argument(
        "--rounds", type=int, default=2, help="rounds of every thread count and setting (default 2)"
    )
    p.add_argument("--threads", default=None, help="comma list of thread counts (default: all cores, then 1)")
    p.add_argument(
        "--settings", default=",".join(SETTINGS), help="comma list of idle, busy, training (default all)"
    )
    p.add_argument(
        "--stagger", type=float, default=20.0, help="seconds the competing training runs first (default 20)"
    )
    p.add_argument("--quick", action="store_true", help="the quick preset on a 24x24 scene (for tests)")
    args = p.parse_args(argv)
    settings = tuple(s for s in args.settings.split(",") if s)
    if not settings or any(s not in SETTINGS for s in settings):
        p.error(f"--settings must be a comma list of {', '.join(SETTINGS)}, got {args.settings!r}")
    try:
        cores = os.cpu_count() or 1
        threads = (
            tuple(int(t) for t in args.threads.split(","))
            if args.threads
            else tuple(dict.fromkeys((cores, 1)))
        )
    except ValueError:
        p.error(f"--threads must be a comma list of positive integers, got {args.threads!r}")
    if not threads or min(threads) < 1:
        p.error(f"--threads must be a comma list of positive integers, got {args.threads!r}")
    if args.steps < 1 or args.rounds < 1:
        p.error("--steps and --rounds must be >= 1")
    if args.checkpoint is not None and args.capture is None:
        p.error("--checkpoint needs --capture (the capture the checkpoint was trained on)")
    bench = ["--steps", str(args.steps), "--seed", str(args.seed)]
    bench += ["--quick"] if args.quick else []
    bench += ["--capture", str(args.capture)] if args.capture else []
    bench += ["--checkpoint", str(args.checkpoint)] if args.checkpoint else []
    r = run(args.out or default_out("train_shared"), bench, threads, args.rounds, settings, args.stagger)
    print(json.dumps({"summary": r["summary"], "speed": r["speed"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
