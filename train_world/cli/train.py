"""``dsg-train``: train a world from a capture and write the world file.

A capture with two training states (``state1`` and ``state2``) trains DSG-World's two-state model
(:class:`train_world.dual_state.trainer.DualTrainer`) unless ``--single-state`` or ``--state`` is given; any
other capture (one state, or NeRF-Blender data) trains one segmented Gaussian field
(:class:`train_world.single_state.trainer.Trainer`).

Examples::

    dsg-train data/two_blocks --out worlds/two_blocks.dsgworld                      # B+C+P, default preset
    dsg-train data/two_blocks --out /tmp/b.dsgworld --no-prune --no-pseudo          # ablation B
    dsg-train data/tiny --out /tmp/tiny.dsgworld --preset quick --iterations 200    # schedule scaled to 200
    dsg-train data/two_blocks --out worlds/two_blocks.dsgworld --resume             # continue a killed run
    dsg-train data/four_mixed --out worlds/four_mixed.dsgworld --single-state       # state1 only
    dsg-train ../shared/external/nerf_synthetic_lego --out worlds/lego.dsgworld --downscale 4

Two states: ``--iterations N`` scales the preset's whole schedule (densification window, opacity resets, SH
degree steps, checkpoint interval) to ``N`` steps. Each step trains both fields; the first ``--joint-from``
fraction is reconstruction only. Every view of both states trains when the capture has test states (their
cameras are what ``dsg-eval`` measures); without test states every 8th view of each state is held out for
evaluation (``--holdout-every``). After merging, the world is refined on both states' training views
(``--refine-steps``, :mod:`train_world.dual_state.refine`; not part of DSG-World: the ``paper`` preset leaves
it off).

Checkpoints go to ``WORLD.ckpt`` (override with ``--checkpoint``), written atomically every
``checkpoint_every`` steps of the preset; ``--resume`` continues from it with the same options.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import resource
import sys
import time
from pathlib import Path

from train_world.cli.train_options import (
    add_absgrad_argument,
    add_camera_argument,
    add_depth_argument,
    add_mip_argument,
    add_shell_argument,
    camera_options,
    refine_config,
)
from train_world.complete.shell import with_background_shell
from train_world.dual_state.config import JOINT_OPTIONS, DualConfig
from train_world.dual_state.views import (
    HOLDOUT_WITHOUT_TEST_STATES,
    default_holdout_every,
    has_two_training_states,
    motions_estimated,
)
from train_world.single_state.presets import (
    PRESETS,
    TrainConfig,
    absgrad_overrides,
    depth_overrides,
    get_preset,
    mip_overrides,
    scaled_preset,
)

__all__ = [
    "main",
    "main_single_state",
    "main_two_state",
    "single_state_parser",
    "two_state_config",
    "two_state_parser",
]

_EXAMPLES = __doc__.split("Examples::", 1)[1]


def single_state_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-train",
        description="Train a world from a capture and write the world file (docs/training.md). A capture with "
        "two training states trains DSG-World's two-state model; `dsg-train CAPTURE --help` on such a capture "
        "lists the two-state options (--joint-from, --no-align, --no-prune, --no-pseudo, --refine-steps, "
        "--branch-from, ...). These options train one segmented Gaussian field (Gaussian Grouping loss, 3DGS "
        "densification) on one state of a capture, or on NeRF-Blender data.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EXAMPLES,
    )
    p.add_argument(
        "capture", type=Path, help="capture folder (scene.json) or NeRF-Blender folder/transforms json"
    )
    p.add_argument("--out", type=Path, required=True, help="world file to write (e.g. worlds/scene.dsgworld)")
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="default",
        help="quick (tests), default (~15 min), paper (20k iterations); default: default",
    )
    p.add_argument("--iterations", type=int, help="override the preset's iteration count")
    p.add_argument("--downscale", type=int, default=1, help="integer image downscale factor (default 1)")
    p.add_argument("--state", help="state to train (default: the first training state)")
    p.add_argument(
        "--single-state",
        action="store_true",
        help="train one field on one state of a capture with two training states",
    )
    p.add_argument(
        "--holdout-every",
        type=int,
        default=8,
        help="hold out every n-th view of the state for evaluation (0: none; default 8)",
    )
    p.add_argument(
        "--background",
        type=float,
        nargs=3,
        metavar=("R", "G", "B"),
        help="background colour (default: white for NeRF-Blender, black otherwise)",
    )
    add_mip_argument(p)
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--checkpoint", type=Path, help="checkpoint file (default: WORLD.ckpt)")
    p.add_argument("--resume", action="store_true", help="continue from the checkpoint if it exists")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_depth_argument(p)
    add_absgrad_argument(p)
    add_shell_argument(p)
    add_camera_argument(p)
    return p


def wants_two_state(argv: list[str]) -> bool:
    """The single-state ``dsg-train`` command line ``argv`` names a capture with two training states and
    neither ``--single-state`` nor ``--state``: hand it to :func:`main_two_state` (``--help`` then shows the
    two-state options)."""
    if any(a == "--single-state" or a == "--state" or a.startswith("--state=") for a in argv):
        return False
    return any(not a.startswith("-") and has_two_training_states(a) for a in argv)


def two_state_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-train",
        description="DSG-World two-state training: two segmented Gaussian fields with a shared classifier, "
        "bidirectional alignment (B), co-pruning (C), pseudo-state alignment (P); writes the merged world.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=_EXAMPLES,
    )
    p.add_argument("capture", type=Path, help="capture folder with state1 and state2 (scene.json)")
    p.add_argument("--out", type=Path, required=True, help="world file to write")
    p.add_argument("--preset", choices=sorted(PRESETS), default="default", help="default: default")
    p.add_argument(
        "--iterations",
        type=int,
        help="steps (both fields per step; default: the preset's two-state count); scales the schedule",
    )
    p.add_argument(
        "--max-gaussians",
        type=int,
        help="cap on each field's Gaussian count (default: the preset's two-state cap)",
    )
    p.add_argument("--downscale", type=int, default=1)
    p.add_argument(
        "--holdout-every",
        type=int,
        help="hold out every n-th view of each state (0: none; default: none "
        f"when the capture has test states, else {HOLDOUT_WITHOUT_TEST_STATES})",
    )
    p.add_argument("--background", type=float, nargs=3, metavar=("R", "G", "B"))
    add_mip_argument(p)
    add_depth_argument(p)
    add_absgrad_argument(p)
    add_shell_argument(p)
    add_camera_argument(p)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--joint-from",
        type=float,
        help="reconstruction-only fraction of the steps (default: the preset's; default 2/3, paper 0.5)",
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
        "--pseudo-every",
        type=int,
        default=2,
        help="pseudo-state loss every n-th joint step (default 2; paper: 1)",
    )
    p.add_argument(
        "--align-downscale",
        type=int,
        default=1,
        metavar="S",
        help="render the cross-state views (alignment and pseudo-state losses) at 1/S of the training "
        "resolution (default 1: full; train_world.dual_state.coarse)",
    )
    motions = p.add_mutually_exclusive_group()
    motions.add_argument(
        "--refine-motions",
        dest="refine_motions",
        action="store_true",
        default=None,
        help="optimise each object's motion between the two states in the joint phase (default when the "
        "capture's motions are estimates, i.e. made by dsg-capture)",
    )
    motions.add_argument(
        "--freeze-motions",
        dest="refine_motions",
        action="store_false",
        help="take the capture's motions as exact, as DSG-World does (default for synthetic captures)",
    )
    p.add_argument(
        "--motion-lr-translation",
        type=float,
        default=DualConfig.motion_lr_translation,
        help="motion refinement: translation learning rate, times the scene extent "
        f"(default {DualConfig.motion_lr_translation:g})",
    )
    p.add_argument(
        "--motion-lr-rotation",
        type=float,
        default=DualConfig.motion_lr_rotation,
        help=f"motion refinement: rotation learning rate in radians (default {DualConfig.motion_lr_rotation:g})",
    )
    p.add_argument(
        "--support-weight",
        type=float,
        metavar="W",
        help="weight of the support term, which keeps object Gaussians above the table top, in the joint "
        "phase and the refinement (default: the preset's, 0.1 for default, 0 (off) for quick and paper; "
        "captures with a table and masks only)",
    )
    p.add_argument(
        "--layers",
        action=argparse.BooleanOptionalAction,
        help="refine and render the world as two layers, background and objects merged per pixel by expected "
        "depth (the world records it; every renderer follows; see docs/training.md; default: the preset's, "
        "on for default, off for quick and paper)",
    )
    p.add_argument(
        "--refine-steps",
        type=int,
        metavar="N",
        help="after merging, refine the world on both states' training "
        "views for N steps (not DSG-World's; 0: off; default: the preset's, 4000 for default, 0 for paper)",
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


def two_state_config(args: argparse.Namespace) -> DualConfig:
    preset = dataclasses.replace(
        scaled_preset(args.preset, args.iterations, args.max_gaussians, two_state=True),
        **mip_overrides(args.mip),
        **depth_overrides(args.depth_weight),
        **absgrad_overrides(args.absgrad, args.absgrad_threshold),
    )
    base = TrainConfig(
        preset=preset,
        seed=args.seed,
        downscale=args.downscale,
        holdout_every=default_holdout_every(args.capture)
        if args.holdout_every is None
        else args.holdout_every,
        background=None if args.background is None else tuple(args.background),
        **camera_options(args),
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
        align_downscale=args.align_downscale,
        refine_motions=motions_estimated(args.capture)
        if args.refine_motions is None
        else args.refine_motions,
        motion_lr_translation=args.motion_lr_translation,
        motion_lr_rotation=args.motion_lr_rotation,
        support_weight=preset.dual_support_weight if args.support_weight is None else args.support_weight,
    )


def motion_lines(record: dict, units: str) -> list[str]:
    """One line per object of a world's ``metadata["motions"]``: how far refinement moved and turned it (mm
    when the units are metres, else scene units)."""
    out = []
    for o in record["objects"]:
        if units == "metres":
            dist = f"{o['correction_translation'] * 1000:.2f} mm"
        else:
            dist = f"{o['correction_translation']:.5f} scene units"
        out.append(f"motion of {o['name']!r} corrected by {dist}, {o['correction_rotation_deg']:.3f} deg")
    return out


def main(argv: list[str] | None = None) -> int:
    """``dsg-train``: two-state training for a capture with two training states (see :func:`wants_two_state`),
    else single-state training."""
    argv = sys.argv[1:] if argv is None else list(argv)
    return main_two_state(argv) if wants_two_state(argv) else main_single_state(argv)


def main_single_state(argv: list[str] | None = None) -> int:
    args = single_state_parser().parse_args(argv)
    from train_world.single_state.checkpoint import CheckpointError
    from train_world.single_state.data import load_training_data
    from train_world.single_state.trainer import Trainer, TrainingDiverged

    ckpt = args.checkpoint or args.out.with_name(args.out.name + ".ckpt")
    try:
        preset = get_preset(
            args.preset,
            **({"iterations": args.iterations} if args.iterations else {}),
            **mip_overrides(args.mip),
            **depth_overrides(args.depth_weight),
            **absgrad_overrides(args.absgrad, args.absgrad_threshold),
        )
        config = TrainConfig(
            preset=preset,
            seed=args.seed,
            downscale=args.downscale,
            state=args.state,
            single_state=args.single_state,
            holdout_every=args.holdout_every,
            background=None if args.background is None else tuple(args.background),
            **camera_options(args),
        )
        t0 = time.perf_counter()
        data = load_training_data(args.capture, config)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        trainer = Trainer(data, config, checkpoint=ckpt)
        if args.resume and ckpt.exists():
            trainer.load_checkpoint()
            print(f"dsg-train: resumed from {ckpt} at step {trainer.step}", file=sys.stderr)
        elif args.resume:
            print(f"dsg-train: no checkpoint at {ckpt}; starting from scratch", file=sys.stderr)
        print(
            f"dsg-train: {len(data)} training views {data.width}x{data.height} of {data.state!r}, "
            f"{data.num_classes - 1} objects, held out {list(data.heldout)}, {trainer.field.num} "
            f"Gaussians at step {trainer.step}, preset {preset.name} ({preset.iterations} iterations)",
            file=sys.stderr,
        )
        trainer.train(progress=not args.quiet)
        world = trainer.world()
        if not args.no_shell and data.source.get("kind") != "blender":
            world = with_background_shell(world)
        from dsg_gym.world import write_world

        write_world(args.out, world)
    except TrainingDiverged as e:
        print(f"dsg-train: error: training diverged: {e}", file=sys.stderr)
        return 3
    except (ValueError, CheckpointError, FileNotFoundError) as e:
        print(f"dsg-train: error: {e}", file=sys.stderr)
        return 2
    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    summary = {
        "world": str(args.out),
        "iterations": trainer.step,
        "gaussians": int(world.metadata["num_gaussians"]),  # the far shell included, as two states count it
        "train_seconds": round(trainer.elapsed, 1),
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "peak_rss_mb": round(rss_mb, 1),
        "last_train_psnr": trainer.history[-1]["psnr"] if trainer.history else None,
    }
    print(json.dumps(summary))
    return 0


def main_two_state(argv: list[str] | None = None) -> int:
    args = two_state_parser().parse_args(argv)
    from train_world.dual_state.refine import StateViews, refine_world
    from train_world.dual_state.trainer import DualTrainer
    from train_world.single_state.checkpoint import CheckpointError
    from train_world.single_state.trainer import TrainingDiverged

    ckpt = args.checkpoint or args.out.with_name(args.out.name + ".ckpt")
    t0 = time.perf_counter()
    try:
        config = two_state_config(args)
        refine = refine_config(args, config.base.preset)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        trainer = DualTrainer(args.capture, config, checkpoint=ckpt)
        if trainer.table_bounds is not None and trainer.has_masks:
            refine = dataclasses.replace(refine, support_weight=config.support_weight)
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
            f"({config.base.preset.iterations} steps, joint from {trainer.joint_start}), motions "
            f"{'refined' if config.refine_motions else 'frozen'}, cameras "
            f"{'refined' if config.base.refine_cameras else 'fixed'}",
            file=sys.stderr,
        )
        if args.stop_at_joint:
            trainer.train(progress=not args.quiet, stop_after=trainer.joint_start)
            trainer.save_checkpoint()
            print(
                json.dumps(
                    {
                        "checkpoint": str(ckpt),
                        "step": trainer.step,
                        "train_seconds": round(trainer.elapsed, 1),
                        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
                    }
                )
            )
            return 0
        trainer.train(progress=not args.quiet)
        world = trainer.world()
        if config.refine_motions:
            for line in motion_lines(world.metadata["motions"], trainer.data1.units):
                print(f"dsg-train: {line}", file=sys.stderr)
        for state, c in (world.metadata.get("camera_refinement") or {}).items():
            print(f"dsg-train: cameras of {state} refined: median {c['rotation_deg_median']:.3f} deg, "
                  f"{c['translation_median']:.4g} {trainer.data1.units} (largest {c['rotation_deg_max']:.3f} "
                  f"deg, {c['translation_max']:.4g})", file=sys.stderr)  # fmt: skip
        refined_data = (trainer.t1.refined_data(), trainer.t2.refined_data())  # refined cameras, if any
        views = {d.state: StateViews(d.images, d.viewmats, d.Ks) for d in refined_data}
        world, refined = refine_world(world, views, refine, progress=not args.quiet)
        if not args.no_shell:
            world = with_background_shell(world)
        from dsg_gym.world import write_world

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
        **{k: getattr(config, k) for k in JOINT_OPTIONS},
        "layers": refine.layers,
        "training_views": [len(trainer.data1), len(trainer.data2)],
        "gaussians": int(world.metadata["num_gaussians"]),
        "field_sizes": dual["field_sizes"],
        "object_sources": dual["object_sources"],
        "background_from_2": dual["background_from_2"],
        "motions_refined": world.metadata["motions"]["refined"],
        "motion_corrections": [
            {k: o[k] for k in ("name", "correction_translation", "correction_rotation_deg")}
            for o in world.metadata["motions"]["objects"]
        ],
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
