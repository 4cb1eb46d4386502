"""Two-state training step time: reconstruction steps against joint (DSG-World) steps, in one process.

    python -m benchmarks.train_step [--scene two_blocks] [--steps 40] [--checkpoint CKPT] [--out FILE]
    python -m benchmarks.train_step --quick [--out FILE]          # a 24x24 scene, quick preset

Builds ``dsg-train``'s two-state trainer (``default`` preset) on a synthetic capture (generated into a
temporary folder, 128x128) and times ``--steps`` reconstruction steps (each field renders its own view: 2
renders), then as many joint steps (2 reconstruction renders, the 2 transfers of B and, every second step, the
2 pseudo-state renders of P). Without ``--checkpoint`` the fields are the initial ones (the preset's initial
points) and the joint steps start by moving the step counter to the joint phase; with a two-state checkpoint
taken at the joint phase's start (``dsg-suite``'s ``worlds/<scene>/recon.ckpt``, made on the same capture and
options) both phases run on its trained fields, which is what a real joint phase costs. ``--profile`` adds the
functions that took most of the joint steps (cProfile, own time).

Writes ``{config, recon: {ms_median, ms_mean, renders_per_step, ms_per_render}, joint: {...},
joint_over_recon, ms_per_render_ratio, profile?}``: the ratios come from the same process and fields, so they
compare across machines and changes where absolute times do not. Absolute times depend on the load: run it on
an idle machine.
"""

from __future__ import annotations

import argparse
import cProfile
import dataclasses
import json
import os
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import train_world  # (OpenMP waiting and numba's threading layer, before torch loads)
from train_world.capture.format import atomic_write_json

from ._results import default_out


def _sync(folder: Path | None, timeout: float = 600.0) -> None:
    """Write ``folder/ready`` and wait until ``folder/go`` exists (``benchmarks.train_shared`` starts the
    competing job in between, once this process has chosen its OpenMP waiting and loaded its fields)."""
    if folder is None:
        return
    (folder / "ready").touch()
    t0 = time.monotonic()
    while not (folder / "go").exists():
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"{folder / 'go'} did not appear within {timeout:.0f} s")
        time.sleep(0.05)


def _time_steps(trainer, n: int, warmup: int) -> list[float]:
    for _ in range(warmup):
        trainer.train_step()
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        trainer.train_step()
        times.append(time.perf_counter() - t0)
    return times


def _summary(times: list[float], renders: float) -> dict[str, float]:
    med = statistics.median(times) * 1e3
    return {
        "steps": len(times),
        "ms_median": round(med, 2),
        "ms_mean": round(statistics.fmean(times) * 1e3, 2),
        "renders_per_step": renders,
        "ms_per_render": round(med / renders, 2),
    }


def _joint_renders(cfg) -> float:
    return 2.0 + 2.0 * cfg.use_align + (2.0 / cfg.pseudo_every) * cfg.use_pseudo


def _profile_top(trainer, n: int, top: int = 12) -> list[dict[str, Any]]:
    pr = cProfile.Profile()
    pr.enable()
    for _ in range(n):
        trainer.train_step()
    pr.disable()
    st = pstats.Stats(pr)
    total = sum(v[2] for v in st.stats.values())  # own time of every function
    rows = sorted(st.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    return [
        {
            "function": f"{Path(f).name}:{line}({name})",
            "calls": v[1],
            "own_ms_per_step": round(v[2] / n * 1e3, 2),
            "share": round(v[2] / total, 4),
        }
        for (f, line, name), v in rows
    ]


def run(
    out: Path,
    *,
    scene: str,
    steps: int,
    warmup: int,
    checkpoint: Path | None,
    quick: bool,
    profile: bool,
    capture: Path | None = None,
    iterations: int | None = None,
    seed: int = 0,
    sync: Path | None = None,
) -> dict[str, Any]:
    import numba
    import torch

    from train_world.cli.synth import main as synth_main
    from train_world.cli.train import two_state_config as config_from_args
    from train_world.cli.train import two_state_parser as dual_parser
    from train_world.dual_state.trainer import DualTrainer

    given = capture
    with tempfile.TemporaryDirectory() as tmp:
        if capture is None:
            capture = Path(tmp) / scene
            size = ["--width", "24", "--height", "24", "--views", "8", "--test-views", "1"] if quick else []
            if synth_main(["--scene", scene, "--out", str(capture), "--quiet", *size]) != 0:
                raise RuntimeError(f"dsg-synth failed for scene {scene!r}")
        args = [
            str(capture),
            "--out",
            str(Path(tmp) / "unused.dsgworld"),
            "--preset",
            "quick" if quick else "default",
            *([] if iterations is None else ["--iterations", str(iterations)]),
            "--seed",
            str(seed),
        ]
        cfg = config_from_args(dual_parser().parse_args(args))
        trainer = DualTrainer(capture, cfg)
        if checkpoint is not None:
            trainer.load_checkpoint(checkpoint, branch=True)
            if trainer.step != trainer.joint_start:
                raise ValueError(
                    f"{checkpoint}: taken at step {trainer.step}, not at the joint phase's start "
                    f"({trainer.joint_start})"
                )
            _sync(sync)
            # reconstruction steps on the trained fields: the joint terms switched off, then the fields restored
            trainer.config = dataclasses.replace(cfg, use_align=False, use_prune=False, use_pseudo=False)
            recon = _time_steps(trainer, steps, warmup)
            trainer.config = cfg
            trainer.load_checkpoint(checkpoint, branch=True)
        else:
            if warmup + steps > trainer.joint_start:
                raise ValueError(
                    f"--warmup + --steps must stay within the reconstruction phase "
                    f"({trainer.joint_start} steps)"
                )
            _sync(sync)
            recon = _time_steps(trainer, steps, warmup)
            trainer.step = trainer.t1.step = trainer.t2.step = trainer.joint_start
        joint = _time_steps(trainer, steps, warmup)
        top = _profile_top(trainer, steps) if profile else None
        n_gauss = trainer.t1.field.num + trainer.t2.field.num
    result: dict[str, Any] = {
        "config": {
            "scene": None if given is not None else scene,
            "capture": None if given is None else str(given),
            "checkpoint": None if checkpoint is None else str(checkpoint),
            "preset": cfg.base.preset.name,
            "gaussians_both_fields": n_gauss,
            "torch_threads": torch.get_num_threads(),
            "numba_threads": numba.get_num_threads(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "openmp_waiting": train_world._openmp.waiting(),
            "cpus": os.cpu_count(),
        },
        "recon": _summary(recon, 2.0),
        "joint": _summary(joint, _joint_renders(cfg)),
    }
    result["joint_over_recon"] = round(result["joint"]["ms_median"] / result["recon"]["ms_median"], 3)
    result["ms_per_render_ratio"] = round(
        result["joint"]["ms_per_render"] / result["recon"]["ms_per_render"], 3
    )
    if top is not None:
        result["profile"] = top
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.train_step",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/train_step/<date>-<commit>.json)",
    )
    p.add_argument("--scene", default="two_blocks", help="dsg-synth scene (default two_blocks)")
    p.add_argument("--capture", type=Path, help="an existing two-state capture instead of generating --scene")
    p.add_argument(
        "--checkpoint",
        type=Path,
        help="two-state checkpoint at the joint phase's start (e.g. dsg-suite's recon.ckpt; needs "
        "--capture, the capture it was trained on)",
    )
    p.add_argument(
        "--iterations",
        type=int,
        help="the training's step count, as dsg-train's (must match the checkpoint's; default: the preset's)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="the training's seed, as dsg-train's (must match the checkpoint's)",
    )
    p.add_argument("--steps", type=int, default=40, help="timed steps per phase (default 40)")
    p.add_argument("--warmup", type=int, default=5, help="untimed steps before each phase (default 5)")
    p.add_argument("--profile", action="store_true", help="also profile the joint steps (cProfile)")
    p.add_argument("--quick", action="store_true", help="a 24x24 scene and the quick preset (for tests)")
    p.add_argument(
        "--sync",
        type=Path,
        help="a folder: once the fields are loaded, write FOLDER/ready and wait for FOLDER/go before the "
        "first step (lets another job start in between)",
    )
    args = p.parse_args(argv)
    args.out = args.out or default_out("train_step")
    if args.steps < 1 or args.warmup < 0:
        p.error("--steps must be >= 1 and --warmup >= 0")
    if args.checkpoint is not None and args.capture is None:
        p.error("--checkpoint needs --capture (the capture the checkpoint was trained on)")
    r = run(
        args.out,
        scene=args.scene,
        steps=args.steps,
        warmup=args.warmup,
        checkpoint=args.checkpoint,
        quick=args.quick,
        profile=args.profile,
        capture=args.capture,
        iterations=args.iterations,
        seed=args.seed,
        sync=args.sync,
    )
    print(json.dumps({k: r[k] for k in ("recon", "joint", "joint_over_recon")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
