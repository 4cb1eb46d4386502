"""Joint step time under each OpenMP waiting choice, alone and with two trainings competing for the cores.

    python -m benchmarks.omp_waiting --capture CAP --checkpoint CKPT [--steps 60] [--rounds 2] [--out FILE]
    python -m benchmarks.omp_waiting --quick [--out FILE]        # the quick preset on a 24x24 scene

Each OpenMP runtime reads its waiting policy once, when it loads, so every measurement is a fresh process:
``python -m benchmarks.train_step`` with the environment of the mode. Modes: ``auto`` (``OMP_WAIT_POLICY``
unset: what :mod:`train_world._openmp` chooses, normally torch's pool spinning and numba's sleeping) and
``passive`` (both pools sleep, the choice before). ``alone`` runs one process at a time, modes alternating for
``--rounds`` rounds; ``pair`` starts two processes of the same mode, the second ``--stagger`` seconds after
the first (so the first chooses on an idle machine and the second beside it, as when a second training starts
during a first). A stagger longer than one process's load and timed steps lets the two run one after the
other and the pair measures nothing: check that the pair's times exceed the alone ones.
Writes ``{config, runs: [{mode, setting, joint_ms, recon_ms, waiting}], summary: {setting: {mode: best joint
ms}}, auto_over_passive: {setting: ratio}}``: the ratios come from one machine and session; the absolute times
do not carry over.
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

MODES = ("auto", "passive")


def _env(mode: str) -> dict[str, str]:
    env = dict(os.environ)
    env.pop("OMP_WAIT_POLICY", None)
    if mode == "passive":
        env["OMP_WAIT_POLICY"] = "PASSIVE"
    return env


def _launch(mode: str, out: Path, bench_args: list[str]) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "benchmarks.train_step", "--out", str(out), *bench_args]
    return subprocess.Popen(cmd, env=_env(mode), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _collect(proc: subprocess.Popen, out: Path, mode: str, setting: str) -> dict[str, Any]:
    _, err = proc.communicate()
    if proc.returncode != 0:
        raise RuntimeError(f"benchmarks.train_step ({mode}, {setting}) failed:\n{err[-2000:]}")
    r = json.loads(out.read_text())
    return {
        "mode": mode,
        "setting": setting,
        "joint_ms": r["joint"]["ms_median"],
        "recon_ms": r["recon"]["ms_median"],
        "waiting": r["config"].get("openmp_waiting"),
    }


def run(
    out: Path, bench_args: list[str], rounds: int, settings: tuple[str, ...], stagger: float = 5.0
) -> dict[str, Any]:
    runs: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(rounds):
            for mode in MODES if k % 2 == 0 else MODES[::-1]:
                if "alone" in settings:
                    f = Path(tmp) / f"{mode}-{k}.json"
                    runs.append(_collect(_launch(mode, f, bench_args), f, mode, "alone"))
                if "pair" in settings:
                    fs = [Path(tmp) / f"{mode}-{k}-pair{j}.json" for j in range(2)]
                    procs = [_launch(mode, fs[0], bench_args)]
                    time.sleep(stagger)  # the first one chooses on an idle machine, the second beside it
                    procs.append(_launch(mode, fs[1], bench_args))
                    runs += [_collect(p, f, mode, "pair") for p, f in zip(procs, fs)]
    summary = {
        s: {m: min(r["joint_ms"] for r in runs if r["mode"] == m and r["setting"] == s) for m in MODES}
        for s in settings
    }
    result = {
        "config": {
            "train_step_args": bench_args,
            "rounds": rounds,
            "stagger_s": stagger,
            "cpus": os.cpu_count(),
        },
        "runs": runs,
        "summary": summary,
        "auto_over_passive": {s: round(v["auto"] / v["passive"], 3) for s, v in summary.items()},
    }
    write_result(out, result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.omp_waiting",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/omp_waiting/<date>-<commit>.json)",
    )
    p.add_argument("--capture", type=Path, help="two-state capture (benchmarks.train_step --capture)")
    p.add_argument(
        "--checkpoint", type=Path, help="its joint-start checkpoint (benchmarks.train_step --checkpoint)"
    )
    p.add_argument("--steps", type=int, default=60, help="timed joint steps per process (default 60)")
    p.add_argument("--rounds", type=int, default=2, help="rounds of every mode and setting (default 2)")
    p.add_argument("--settings", default="alone,pair", help="comma list of alone, pair (default both)")
    p.add_argument(
        "--stagger",
        type=float,
        default=5.0,
        help="seconds between a pair's starts (default 5: the first chooses alone, yet the timed "
        "steps overlap)",
    )
    p.add_argument("--quick", action="store_true", help="the quick preset on a generated 24x24 scene")
    args = p.parse_args(argv)
    args.out = args.out or default_out("omp_waiting")
    settings = tuple(s for s in args.settings.split(",") if s)
    if not settings or any(s not in ("alone", "pair") for s in settings):
        p.error(f"--settings must list alone and/or pair, got {args.settings!r}")
    if args.steps < 1 or args.rounds < 1:
        p.error("--steps and --rounds must be >= 1")
    if args.quick:
        bench = ["--quick", "--steps", str(args.steps), "--warmup", "2"]
    else:
        if args.capture is None or args.checkpoint is None:
            p.error("give --capture and --checkpoint (a joint-start checkpoint), or --quick")
        bench = [
            "--capture",
            str(args.capture),
            "--checkpoint",
            str(args.checkpoint),
            "--steps",
            str(args.steps),
        ]
    r = run(args.out, bench, args.rounds, settings, args.stagger)
    print(json.dumps({"summary": r["summary"], "auto_over_passive": r["auto_over_passive"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
