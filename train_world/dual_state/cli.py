"""``dsg-train`` on a capture with two training states: DSG-World's two-state training (``DualTrainer``).

``train_world.single_state.cli`` hands captures with ``state1`` and ``state2`` to :func:`main` unless
``--single-state`` (or ``--state``) is given; ``python -m train_world.dual_state.cli`` runs it directly.

Examples::

    dsg-train data/two_blocks --out worlds/two_blocks.dsgw                         # B+C+P, default preset
    dsg-train data/two_blocks --out /tmp/b.dsgw --no-prune --no-pseudo             # ablation B
    dsg-train data/tiny --out /tmp/tiny.dsgw --preset quick --iterations 200       # schedule scaled to 200
    dsg-train data/two_blocks --out worlds/two_blocks.dsgw --resume                # continue a killed run

``--iterations N`` scales the preset's whole schedule (densification window, opacity resets, SH degree steps,
checkpoint interval) to ``N`` steps. Each step trains both fields; the first ``--joint-from`` fraction is
reconstruction only. Checkpoints go to ``WORLD.ckpt`` (override with ``--checkpoint``). Every view of both
states trains when the capture has test states (their cameras are what ``dsg-eval`` measures); without test
states every 8th view of each state is held out for evaluation (``--holdout-every``). After merging, the world
is refined on both states' training views (``--refine-steps``, :mod:`train_world.dual_state.refine`; not part of
DSG-World: the ``paper`` preset leaves it off).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

from train_world.single_state.cli import add_depth_argument, add_mip_argument, depth_overrides
from train_world.single_state.presets import PRESETS, Preset, TrainConfig, get_preset, mip_overrides

__all__ = ["default_holdout_every", "has_two_training_states", "main", "scaled_preset", "wants_two_state"]

#: views held out of each training state (every n-th) when the capture has no test states to evaluate on
HOLDOUT_WITHOUT_TEST_STATES = 8

_SCHEDULE = (
    "densify_from",
    "densify_until",
    "densify_every",
    "reset_every",
    "sh_degree_every",
    "checkpoint_every",
)


def scaled_preset(
    name: str, iterations: int | None = None, max_gaussians: int | None = None, *, two_state: bool = False
) -> Preset:
    """Preset ``name``; with ``iterations``, every schedule step count scaled by ``iterations / preset's``
    (so an opacity reset never lands at the end of a shortened run); ``max_gaussians``: the field size cap.
    ``two_state``: the defaults are the preset's two-state step count and cap (``dual_iterations``,
    ``dual_max_gaussians``) where it has them."""
    p = get_preset(name)
    if two_state:
        iterations = p.dual_iterations if iterations is None else iterations
        max_gaussians = p.dual_max_gaussians if max_gaussians is None else max_gaussians
    if max_gaussians is not None:
        if max_gaussians < 1000:
            raise ValueError(f"--max-gaussians must be at least 1000, got {max_gaussians}")
        p = dataclasses.replace(p, max_gaussians=int(max_gaussians))
    if iterations is None or iterations == p.iterations:
        return p
    if iterations < 1:
        raise ValueError(f"--iterations must be at least 1, got {iterations}")
    f = iterations / p.iterations
    return dataclasses.replace(
        p,
        iterations=int(iterations),
        **{k: max(1, round(getattr(p, k) * f)) for k in _SCHEDULE},
    )


def has_two_training_states(path: str | Path) -> bool:
    """True for a capture folder whose ``scene.json`` lists ``state1`` and ``state2`` as training states."""
    p = Path(path)
    if not (p.is_dir() and (p / "scene.json").is_file()):
        return False
    try:
        from train_world.capture import load_capture

        cap = load_capture(p, states=[], load_depth=False)
    except ValueError:  # CaptureError: not a readable capture
        return False
    return all(cap.splits.get(s) == "train" for s in ("state1", "state2"))


def default_holdout_every(path: str | Path) -> int:
    """Views held out of each training state by default: none (0) when the capture has test states, whose
    cameras are the evaluation (``dsg-eval``), so every captured view trains; else every
    :data:`HOLDOUT_WITHOUT_TEST_STATES`-th view, to have held-out views to evaluate on."""
    from train_world.capture import load_capture

    cap = load_capture(Path(path), states=[], load_depth=False)  # metadata only
    return 0 if any(split == "test" for split in cap.splits.values()) else HOLDOUT_WITHOUT_TEST_STATES


def wants_two_state(argv: list[str]) -> bool:
    """The single-state ``dsg-train`` command line ``argv`` names a capture with two training states and
    neither ``--single-state`` nor ``--state`` (nor help): hand it to :func:`main`."""
    if any(
        a in ("--single-state", "-h", "--help") or a == "--state" or a.startswith("--state=") for a in argv
    ):
        return False
    return any(not a.startswith("-") and has_two_training_states(a) for a in argv)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-train",
        description="DSG-World two-state training: two segmented Gaussian fields with a shared classifier, "
        "bidirectional alignment (B), co-pruning (C), pseudo-state alignment (P); writes the merged world.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("Examples::", 1)[1],
    )
    p.add_argument("capture", type=Path, help="capture folder with state1 and state2 (scene.json)")
    p.add_argument("--out", type=Path, required=True, help="world file to write")
    p.add_argument("--preset", choices=sorted(PRESETS), default="default", help="default: default")
    p.add_argument(
        "--iterations", type=int, help="steps (both fields per step; default: the preset's two-state count); "
        "scales the schedule"
    )
    p.add_argument(
        "--max-gaussians", type=int, help="cap on each field's Gaussian count (default: the preset's two-state cap)"
    )
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument(
        "--holdout-every", type=int, help="hold out every n-th view of each state (0: none; default: none "
        f"when the capture has test states, else {HOLDOUT_WITHOUT_TEST_STATES})"
    )
    p.add_argument("--background", type=float, nargs=3, metavar=("R", "G", "B"))
    add_mip_argument(p)
    add_depth_argument(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--joint-from", type=float, help="reconstruction-only fraction of the steps (default: the preset's; "
        "default 2/3, paper 0.5)"
    )
    p.add_argument("--lambda-align", type=float, default=1.0)
    p.add_argument("--lambda-pseudo", type=float, default=1.0)
    p.add_argument("--no-align", action="store_true", help="switch off bidirectional alignment (B)")
    p.add_argument("--no-prune", action="store_true", help="switch off co-pruning (C)")
    p.add_argument("--no-pseudo", action="store_true", help="switch off pseudo-state alignment (P)")
    p.add_argument(
        "--tau", type=float, default=0.02, help="co-pruning distance, scene units (default 0.02 m)"
    )
    p.add_argument("--prune-every", type=int, default=500, help="co-pruning interval in joint steps")
    p.add_argument(
        "--pseudo-every", type=int, default=2, help="pseudo-state loss every n-th joint step (default 2; paper: 1)"
    )
    p.add_argument(
        "--refine-steps", type=int, metavar="N", help="after merging, refine the world on both states' training "
        "views for N steps (not DSG-World's; 0: off; default: the preset's, 4000 for default, 0 for paper)"
    )
    p.add_argument("--checkpoint", type=Path, help="checkpoint file (default: WORLD.ckpt)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint if it exists")
    p.add_argument(
        "--branch-from",
        type=Path,
        metavar="CKPT",
        help="start from a checkpoint taken before the joint phase by a run that differs only in B/C/P",
    )
    p.add_argument(
        "--stop-at-joint",
        action="store_true",
        help="train the reconstruction phase only, write the checkpoint and stop (no world)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def config_from_args(args: argparse.Namespace):
    from train_world.dual_state.trainer import DualConfig

    preset = dataclasses.replace(
        scaled_preset(args.preset, args.iterations, args.max_gaussians, two_state=True), **mip_overrides(args.mip),
        **depth_overrides(args.depth_weight),
    )
    base = TrainConfig(
        preset=preset,
        seed=args.seed,
        downscale=args.downscale,
        holdout_every=default_holdout_every(args.capture) if args.holdout_every is None else args.holdout_every,
        background=None if args.background is None else tuple(args.background),
    )
    return DualConfig(
        base=base,
        joint_from=preset.dual_joint_from if args.joint_from is None else args.joint_from,
        lambda_align=args.lambda_align,
        lambda_pseudo=args.lambda_pseudo,
        use_align=not args.no_align,
        use_prune=not args.no_prune,
        use_pseudo=not args.no_pseudo,
        tau=args.tau,
        prune_every=args.prune_every,
        pseudo_every=args.pseudo_every,
    )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    from train_world.single_state.checkpoint import CheckpointError
    from train_world.single_state.trainer import TrainingDiverged

    from train_world.dual_state.refine import RefineConfig, StateViews, refine_world
    from train_world.dual_state.trainer import DualTrainer

    ckpt = args.checkpoint or args.out.with_name(args.out.name + ".ckpt")
    t0 = time.perf_counter()
    try:
        config = config_from_args(args)
        refine = RefineConfig(
            steps=config.base.preset.dual_refine_steps if args.refine_steps is None else args.refine_steps,
            seed=args.seed,
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        trainer = DualTrainer(args.capture, config, checkpoint=ckpt)
        if args.resume and ckpt.exists():
            trainer.load_checkpoint()
            print(f"dsg-train: resumed from {ckpt} at step {trainer.step}", file=sys.stderr)
        elif args.branch_from is not None:
            trainer.load_checkpoint(args.branch_from, branch=True)
            print(f"dsg-train: branched from {args.branch_from} at step {trainer.step}", file=sys.stderr)
        print(
            f"dsg-train: two states {config.states}, {len(trainer.data1)}+{len(trainer.data2)} training views "
            f"{trainer.data1.width}x{trainer.data1.height}, {trainer.data1.num_classes - 1} objects, ablation "
            f"{config.ablation}, tau {config.tau} {trainer.data1.units}, preset {config.base.preset.name} "
            f"({config.base.preset.iterations} steps, joint from {trainer.joint_start})",
            file=sys.stderr,
        )
        if args.stop_at_joint:
            trainer.train(progress=not args.quiet, stop_after=trainer.joint_start)
            trainer.save_checkpoint()
            print(json.dumps({"checkpoint": str(ckpt), "step": trainer.step,
                              "train_seconds": round(trainer.elapsed, 1),
                              "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)}))
            return 0
        trainer.train(progress=not args.quiet)
        world = trainer.world()
        views = {d.state: StateViews(d.images, d.viewmats, d.Ks) for d in (trainer.data1, trainer.data2)}
        world, refined = refine_world(world, views, refine, progress=not args.quiet)
        from train_world.world_writer import write_world

        write_world(args.out, world)
    except (TrainingDiverged, FloatingPointError) as e:
        print(f"dsg-train: error: training diverged: {e}", file=sys.stderr)
        return 3
    except (ValueError, CheckpointError, FileNotFoundError) as e:
        print(f"dsg-train: error: {e}", file=sys.stderr)
        return 2
    dual = world.metadata["dual"]
    summary = {
        "world": str(args.out),
        "ablation": config.ablation,
        "iterations": trainer.step,
        "joint_from_step": trainer.joint_start,
        "holdout_every": config.base.holdout_every,
        "training_views": [len(trainer.data1), len(trainer.data2)],
        "gaussians": int(world.metadata["num_gaussians"]),
        "field_sizes": dual["field_sizes"],
        "object_sources": dual["object_sources"],
        "background_from_2": dual["background_from_2"],
        "train_seconds": round(trainer.elapsed, 1),
        "refine_steps": refine.steps,
        "refine_seconds": refined.get("seconds", 0.0),
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "last_train_psnr": trainer.history[-1]["psnr"] if trainer.history else None,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
