"""Training step time when other work shares the cores, per thread and waiting choice.

    python -m benchmarks.train_shared [--capture CAP [--checkpoint CKPT]] [--steps 30] [--rounds 2] [--out FILE]
    python -m benchmarks.train_shared --quick [--out FILE]        # the quick preset on a 24x24 scene

Every measurement is a fresh ``python -m benchmarks.train_step`` process (median reconstruction and joint step
times), for each mode of ``--modes``, each numba thread count of ``--threads`` (``NUMBA_NUM_THREADS``;
default: all cores) and each setting of ``--settings``. Modes (the competing job runs in the same mode):

- ``default``: what ``train_world`` chooses (:mod:`train_world._openmp`: the OpenMP pool sleeps, torch on one
  thread);
- ``torch_threads``: torch on as many threads as numba (``OMP_NUM_THREADS``), the pool still sleeping;
- ``spin``: torch on as many threads as numba and libgomp's own waiting (spin 300 000 rounds, then sleep:
  ``GOMP_SPINCOUNT=300000``), which is what a process gets without any waiting policy.

Settings:

- ``idle``: nothing else runs;
- ``busy``: beside a process that keeps one core busy (a Python loop), started first, as a data-collection or
  simulation job would;
- ``training``: beside a second training of the same kind (all cores), made long enough to outlast the
  measured one; the measured training starts ``--stagger`` seconds after the other's first step;
- ``busy_after`` and ``training_after``: the same competitors, started after the measured training has loaded
  and at work before its first timed step, as when a job is started beside a running training.

Writes ``{config, runs: [{mode, threads, setting, recon_ms, joint_ms, waiting}], summary: {"<mode>@<threads>":
{setting: {recon_ms, joint_ms}}}, speed: {"<mode>@<threads>": {setting: joint speed over the idle run of the
first mode and thread count}}}`` (each summary figure is the best of the rounds); speeds are ratios within
one run on one machine; the absolute times do not carry over.
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

SETTINGS = ("idle", "busy", "training", "busy_after", "training_after")
MODES = ("default", "torch_threads", "spin")
_SPIN = "import time\nwhile True:\n    time.perf_counter()\n"
_CHOICES = ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "OMP_NUM_THREADS")


def _env(mode: str, threads: int) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in _CHOICES}
    env["NUMBA_NUM_THREADS"] = str(threads)
    if mode in ("torch_threads", "spin"):
        env["OMP_NUM_THREADS"] = str(threads)
    if mode == "spin":
        env["GOMP_SPINCOUNT"] = "300000"
    return env


def _bench(out: Path, args: list[str], mode: str, threads: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "benchmarks.train_step", "--out", str(out), *args]
    return subprocess.Popen(
        cmd, env=_env(mode, threads), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )


def _wait_ready(folder: Path, proc: subprocess.Popen, what: str, timeout: float = 600.0) -> None:
    t0 = time.monotonic()
    while not (folder / "ready").exists():
        if proc.poll() is not None:
            raise RuntimeError(f"{what} ended before its first step:\n{proc.communicate()[1][-2000:]}")
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"{what} did not load within {timeout:.0f} s")
        time.sleep(0.05)


def _competitor(tmp: Path, args: list[str], mode: str, setting: str, tag: str) -> subprocess.Popen:
    """Start the competing job of ``setting`` and return once it is at work."""
    if setting.startswith("busy"):
        other = subprocess.Popen([sys.executable, "-c", _SPIN])
        time.sleep(1.0)
        return other
    long_args = [*args]
    i = long_args.index("--steps")
    long_args[i + 1] = str(int(long_args[i + 1]) * 4 + 100)  # outlasts the measured run
    sync = tmp / f"other-{tag}"
    sync.mkdir()
    (sync / "go").touch()
    other = _bench(tmp / f"other-{tag}.json", [*long_args, "--sync", str(sync)], mode, os.cpu_count() or 1)
    _wait_ready(sync, other, "the competing training")
    return other


def _measure(
    tmp: Path, args: list[str], mode: str, threads: int, setting: str, stagger: float, tag: str
) -> dict[str, Any]:
    other = None
    out = tmp / f"{tag}.json"
    sync = tmp / f"sync-{tag}"
    sync.mkdir()
    try:
        if setting in ("busy", "training"):  # the competitor first: this training sees it as it starts
            other = _competitor(tmp, args, mode, setting, tag)
            if setting == "training":
                time.sleep(stagger)
            (sync / "go").touch()
            proc = _bench(out, [*args, "--sync", str(sync)], mode, threads)
        else:  # this training starts on idle cores; the competitor joins before its first timed step
            proc = _bench(out, [*args, "--sync", str(sync)], mode, threads)
            if setting != "idle":
                _wait_ready(sync, proc, "the measured training")
                other = _competitor(tmp, args, mode, setting, tag)
            (sync / "go").touch()
        _, err = proc.communicate()
        still = other is None or other.poll() is None
    finally:
        if other is not None:
            other.kill()
            other.communicate()
    if proc.returncode != 0:
        raise RuntimeError(
            f"benchmarks.train_step ({mode}, {threads} threads, {setting}) failed:\n{err[-2000:]}"
        )
    if not still:
        raise RuntimeError(f"the competing job of setting {setting!r} ended before the measured training")
    r = json.loads(out.read_text())
    return {
        "mode": mode,
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
    modes: tuple[str, ...] = MODES,
) -> dict[str, Any]:
    """Measure every mode x thread count x setting ``rounds`` times (the order reversed every other round)."""
    combos = [(m, n) for m in modes for n in threads]
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            for m, n in combos if k % 2 == 0 else combos[::-1]:
                for s in settings:
                    runs.append(_measure(Path(tmp), bench_args, m, n, s, stagger, f"{m}-{n}-{s}-{k}"))
    summary: dict[str, dict[str, dict[str, float]]] = {}
    for m, n in combos:
        mine = [r for r in runs if r["mode"] == m and r["threads"] == n]
        summary[f"{m}@{n}"] = {
            s: {f: min(r[f] for r in mine if r["setting"] == s) for f in ("recon_ms", "joint_ms")}
            for s in settings
        }
    first = summary[f"{modes[0]}@{threads[0]}"]
    ref = first["idle"]["joint_ms"] if "idle" in settings else None
    speed = (
        {c: {s: round(ref / v["joint_ms"], 3) for s, v in per.items()} for c, per in summary.items()}
        if ref
        else {}
    )
    result = {
        "config": {"train_step_args": bench_args, "modes": list(modes), "threads": list(threads),
                   "rounds": rounds, "stagger_s": stagger, "cpus": os.cpu_count()},
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
        "--rounds", type=int, default=2, help="rounds of every mode, thread count and setting (default 2)"
    )
    p.add_argument("--threads", default=None, help="comma list of numba thread counts (default: all cores)")
    p.add_argument("--modes", default=",".join(MODES), help=f"comma list of {', '.join(MODES)} (default all)")
    p.add_argument(
        "--settings", default=",".join(SETTINGS), help=f"comma list of {', '.join(SETTINGS)} (default all)"
    )
    p.add_argument(
        "--stagger", type=float, default=20.0, help="seconds the competing training runs first (default 20)"
    )
    p.add_argument("--quick", action="store_true", help="the quick preset on a 24x24 scene (for tests)")
    args = p.parse_args(argv)
    settings = tuple(s for s in args.settings.split(",") if s)
    if not settings or any(s not in SETTINGS for s in settings):
        p.error(f"--settings must be a comma list of {', '.join(SETTINGS)}, got {args.settings!r}")
    modes = tuple(m for m in args.modes.split(",") if m)
    if not modes or any(m not in MODES for m in modes):
        p.error(f"--modes must be a comma list of {', '.join(MODES)}, got {args.modes!r}")
    try:
        cores = os.cpu_count() or 1
        threads = tuple(int(t) for t in args.threads.split(",")) if args.threads else (cores,)
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
    r = run(
        args.out or default_out("train_shared"), bench, threads, args.rounds, settings, args.stagger, modes
    )
    print(json.dumps({"summary": r["summary"], "speed": r["speed"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
