"""Training time against error: novel-state PSNR of DSG-World (``dsg-train``'s two-state trainer) against its
training wall-clock, for the three presets, each capped at ``--train-minutes``.

``python -m benchmarks.pareto_training --capture data/two_blocks [--out FILE]`` (``benchmarks.pareto
--training`` runs this in a subprocess, so training gets ``train_world``'s OpenMP threading layer while the
env timings use the runtime's default).

No hook in the trainer is needed: :meth:`DualTrainer.train` takes ``stop_after``, so the run is driven in
chunks of ``--chunk`` steps; at wall-clock checkpoints (doubling from ``--first-eval`` seconds, and at the
end) the merged world (:meth:`DualTrainer.world`, what ``dsg-train`` would write at that step) is rendered
at every test state by the env's renderer and compared with the MuJoCo ground truth
(:func:`benchmarks.pareto_core.render_error`). The clock counts training steps only (``trainer.elapsed``),
not the evaluations nor a throwaway 3-step warm-up run first (numba compiles the training kernels there).
Chunking changes nothing in the training itself (same steps, same random streams).
"""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import argparse
import sys
import time
from pathlib import Path

import train_world  # noqa: F401  (how torch's and numba's OpenMP pools wait, chosen before torch loads)

from ._results import default_out, write_result

PRESET_NAMES = ("quick", "default", "paper")


def eval_times(first: float, cap: float) -> list[float]:
    """Wall-clock checkpoints (seconds): ``first, 2 first, 4 first, ...`` below ``cap``, then ``cap``."""
    if first <= 0 or cap <= 0:
        raise ValueError("first and cap must be > 0")
    out, t = [], float(first)
    while t < cap:
        out.append(t)
        t *= 2
    return out + [float(cap)]


def training_curve(
    capture: str | Path,
    preset: str,
    minutes: float,
    *,
    downscale: int = 2,
    seed: int = 0,
    first_eval: float = 15.0,
    chunk: int = 10,
    max_gaussians: int | None = None,
    iterations: int | None = None,
    log=None,
) -> dict:
    """Train ``preset`` on ``capture`` for at most ``minutes`` of training time; returns the curve
    ``{"preset", "iterations", "points": [{"step", "train_seconds", "psnr", "ssim", "mask_iou", ...}]}``."""
    from dsg_gym.world_model import WorldModel
    from train_world.dual_state.trainer import DualConfig, DualTrainer
    from train_world.single_state.presets import TrainConfig, scaled_preset

    from .pareto_core import Point, load_test_states, render_error

    p = scaled_preset(preset, iterations, max_gaussians)
    cfg = DualConfig(base=TrainConfig(preset=p, seed=seed, downscale=downscale))
    t_setup = time.perf_counter()
    tr = DualTrainer(capture, cfg)
    setup_s = time.perf_counter() - t_setup
    test = load_test_states(capture, tuple(tr.data1.object_ids))
    size = tr.data1.width
    if tr.data1.height != size:
        raise ValueError("the training views must be square")
    cap_s = 60.0 * minutes
    marks = eval_times(first_eval, cap_s)
    points: list[dict] = []
    eval_s = 0.0
    while True:
        due = tr.step >= p.iterations or tr.elapsed >= cap_s or tr.elapsed >= marks[0]
        if due:
            t0 = time.perf_counter()
            row = {
                "step": tr.step,
                "train_seconds": round(tr.elapsed, 2),
                "train_psnr": tr.history[-1]["psnr"] if tr.history else None,
            }
            try:
                world = WorldModel.from_world(tr.world()).without_features()
            except ValueError as e:  # e.g. early on, the classifier gives an object no Gaussians yet
                row.update(psnr=None, ssim=None, mask_iou=None, gaussians=None, error=str(e))
            else:
                row.update(render_error(world, test, Point("training", "training", size=size)))
            eval_s += time.perf_counter() - t0
            points.append(row)
            if log:
                got = (
                    "no world"
                    if row["psnr"] is None
                    else f"PSNR {row['psnr']:.2f} dB, {row['gaussians']} Gaussians"
                )
                log(f"{preset}: step {tr.step} at {tr.elapsed:.0f} s: {got}")
            while marks and tr.elapsed >= marks[0]:
                marks.pop(0)
        if tr.step >= p.iterations or tr.elapsed >= cap_s or not marks:
            break
        tr.train(progress=False, stop_after=min(p.iterations, tr.step + chunk))
    return {
        "preset": preset,
        "iterations": p.iterations,
        "reached_step": tr.step,
        "finished": tr.step >= p.iterations,
        "cap_minutes": minutes,
        "setup_seconds": round(setup_s, 2),
        "eval_seconds": round(eval_s, 2),
        "image_size": [size, size],
        "points": points,
    }


def warm_up(capture: str | Path, downscale: int, seed: int = 0) -> float:
    """A throwaway 3-step run, so that numba's compilation (or cache loading) of the training kernels is not
    counted in the first preset's clock. Returns its seconds."""
    from train_world.dual_state.trainer import DualConfig, DualTrainer
    from train_world.single_state.presets import TrainConfig, scaled_preset

    t0 = time.perf_counter()
    cfg = DualConfig(base=TrainConfig(preset=scaled_preset("quick", 6), seed=seed, downscale=downscale))
    DualTrainer(capture, cfg).train(progress=False, stop_after=3)
    return time.perf_counter() - t0


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.pareto_training",
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n", 2)[2],
    )
    ap.add_argument(
        "--capture", type=Path, required=True, help="a dsg-synth capture (state1, state2, test_*)"
    )
    ap.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/pareto_training/<date>-<commit>.json)",
    )
    ap.add_argument("--presets", default=",".join(PRESET_NAMES), help="comma-separated (default: all three)")
    ap.add_argument(
        "--train-minutes", type=float, default=5.0, help="training time cap per preset (default 5)"
    )
    ap.add_argument("--downscale", type=int, default=2, help="image downscale for training and evaluation")
    ap.add_argument("--first-eval", type=float, default=15.0, help="first evaluation after this many seconds")
    ap.add_argument("--chunk", type=int, default=10, help="steps between clock checks")
    ap.add_argument("--iterations", type=int, help="scale every preset's schedule to this many steps (tests)")
    ap.add_argument("--max-gaussians", type=int, help="cap each field (default: the preset's)")
    ap.add_argument("--seed", type=int, default=0)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    args.out = args.out or default_out("pareto_training")

    presets = [s for s in args.presets.split(",") if s]
    bad = [s for s in presets if s not in PRESET_NAMES]
    if bad or not presets:
        print(f"error: unknown presets {bad}; choose from {PRESET_NAMES}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    warm = warm_up(args.capture, args.downscale, args.seed)
    curves = []
    for name in presets:
        curves.append(
            training_curve(
                args.capture,
                name,
                args.train_minutes,
                downscale=args.downscale,
                seed=args.seed,
                first_eval=args.first_eval,
                chunk=args.chunk,
                max_gaussians=args.max_gaussians,
                iterations=args.iterations,
                log=lambda m: print(m, file=sys.stderr, flush=True),
            )
        )
    result = {
        "benchmark": "pareto_training",
        "capture": str(args.capture),
        "downscale": args.downscale,
        "train_minutes": args.train_minutes,
        "seed": args.seed,
        "curves": curves,
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "warm_up_seconds": round(warm, 1),
        "note": "novel-state PSNR on every test state's views (MuJoCo ground truth, area-downsampled), "
        "rendered by the env's renderer with default settings; time = training steps only",
    }
    write_result(Path(args.out), result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
