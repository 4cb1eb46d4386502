"""``python -m train_world.cli.refine``: refine a merged two-state world on both states; the work is
:mod:`train_world.dual_state.refine`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from train_world.dual_state.refine import RefineConfig, refine_world, training_views_of
from train_world.single_state.presets import get_preset


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m train_world.cli.refine",
        description="Refine a two-state world on both states' training views (what dsg-train does after "
        "merging with the default preset; for worlds written without it). Writes a new world file.",
    )
    p.add_argument("world", type=Path, help="two-state world file (dsg-train on a capture with two states)")
    p.add_argument("capture", type=Path, help="the capture it was trained on")
    p.add_argument("--out", type=Path, required=True, help="world file to write")
    d = get_preset("default")
    p.add_argument(
        "--steps",
        type=int,
        default=d.dual_refine_steps,
        help=f"default {d.dual_refine_steps}, as dsg-train's default preset",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--support-weight",
        type=float,
        metavar="W",
        help=f"weight of the support term (default {d.dual_support_weight:g}, as dsg-train's default preset, for a "
        "world that records its table top; 0 for one that does not; 0: off)",
    )
    p.add_argument(
        "--layers",
        action=argparse.BooleanOptionalAction,
        default=d.dual_layers,
        help="two layers, background and objects merged per pixel by expected depth (the world records it; "
        f"default {'on' if d.dual_layers else 'off'}, as dsg-train's default preset)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    import json

    from dsg_gym.world import load_world, write_world

    args = _parser().parse_args(argv)
    try:
        world = load_world(args.world)
        if "refine" in world.metadata and world.metadata["refine"].get("steps", 0):
            raise ValueError(f"{args.world} is refined already ({world.metadata['refine']['steps']} steps)")
        support = args.support_weight
        if support is None:
            support = get_preset("default").dual_support_weight if "table" in world.metadata else 0.0
        refined, info = refine_world(
            world,
            training_views_of(world, args.capture),
            RefineConfig(steps=args.steps, seed=args.seed, support_weight=support, layers=args.layers),
            progress=not args.quiet,
        )
        write_world(args.out, refined)
    except (ValueError, FileNotFoundError) as e:
        print(f"refine: error: {e}", file=sys.stderr)
        return 2
    print(
        json.dumps(
            {
                "world": str(args.out),
                **{k: info.get(k) for k in ("steps", "loss_first", "loss_last", "seconds")},
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
