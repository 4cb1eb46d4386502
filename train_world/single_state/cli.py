"""``dsg-train``: train a segmented Gaussian field from one capture and write the world file.

Examples::

    dsg-train data/four_mixed --out worlds/four_mixed.dsgw --single-state           # state1, default preset
    dsg-train data/tiny --out /tmp/tiny.dsgw --preset quick --single-state
    dsg-train ../shared/external/nerf_synthetic_lego --out worlds/lego.dsgw --downscale 4
    dsg-train data/four_mixed --out worlds/four_mixed.dsgw --single-state --resume  # continue a killed run

Checkpoints go to ``WORLD.ckpt`` (override with ``--checkpoint``), written atomically every
``checkpoint_every`` steps of the preset; ``--resume`` continues from it with the same options.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path

from train_world.single_state.presets import PRESETS, TrainConfig, get_preset, mip_overrides

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-train",
        description="Train a segmented Gaussian field (Gaussian Grouping loss, 3DGS densification) on one "
        "state of a capture (or NeRF-Blender data) and write a world file (see README 'Training a world').",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("Examples::", 1)[1],
    )
    p.add_argument(
        "capture", type=Path, help="capture folder (scene.json) or NeRF-Blender folder/transforms json"
    )
    p.add_argument("--out", type=Path, required=True, help="world file to write (e.g. worlds/scene.dsgw)")
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
    return p


def add_mip_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--mip: all of Mip-Splatting (antialiased rasterizer, 2D Mip filter, 3D smoothing filter 0.2); "
        "--no-mip: 3DGS's classic rasterizer (default: the preset's; default/paper: antialiased, no 3D filter)",
    )


def add_depth_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--depth-weight",
        type=float,
        default=None,
        metavar="W",
        help="weight of an expected-depth term against the capture's depth, where it has depth (relative L1; "
        "not part of DSG-World; default: the preset's, 0 = off)",
    )


def depth_overrides(weight: float | None) -> dict[str, float]:
    """Preset fields for ``--depth-weight`` (none when not given)."""
    return {} if weight is None else {"lambda_depth": float(weight)}


def main(argv: list[str] | None = None) -> int:
    from train_world.dual_state.cli import wants_two_state

    argv = sys.argv[1:] if argv is None else list(argv)
    if wants_two_state(argv):  # two training states: DSG-World's two-state training (train_world.dual_state)
        from train_world.dual_state.cli import main as dual_main

        return dual_main(argv)
    args = _parser().parse_args(argv)
    from train_world.single_state.checkpoint import CheckpointError
    from train_world.single_state.data import load_training_data
    from train_world.single_state.trainer import Trainer, TrainingDiverged

    ckpt = args.checkpoint or args.out.with_name(args.out.name + ".ckpt")
    try:
        preset = get_preset(args.preset, **({"iterations": args.iterations} if args.iterations else {}),
                            **mip_overrides(args.mip), **depth_overrides(args.depth_weight))
        config = TrainConfig(
            preset=preset,
            seed=args.seed,
            downscale=args.downscale,
            state=args.state,
            single_state=args.single_state,
            holdout_every=args.holdout_every,
            background=None if args.background is None else tuple(args.background),
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
        trainer.write_world(args.out)
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
        "gaussians": trainer.field.num,
        "train_seconds": round(trainer.elapsed, 1),
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "peak_rss_mb": round(rss_mb, 1),
        "last_train_psnr": trainer.history[-1]["psnr"] if trainer.history else None,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
