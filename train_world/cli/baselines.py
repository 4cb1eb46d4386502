"""``python -m train_world.cli.baselines``: train the comparison baselines (a) and (b) of the suite; the work
is :mod:`train_world.suite.baselines`.
"""

from __future__ import annotations

from pathlib import Path

from train_world.suite import baselines as _lib
from train_world.suite.baselines import knn_complete, train_single_state


def main(argv: list[str] | None = None) -> int:
    """``python -m train_world.cli.baselines single CAPTURE --out W`` (a) / ``knn WORLD --out W`` (b)."""
    import argparse
    import json
    import resource
    import sys
    import time

    from dsg_gym.world import write_world

    p = argparse.ArgumentParser(
        prog="python -m train_world.cli.baselines", description=_lib.__doc__.split("\n")[0]
    )
    sub = p.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("single", help="baseline (a): train one field on state1")
    a.add_argument("capture", type=Path)
    a.add_argument("--out", type=Path, required=True)
    a.add_argument("--preset", default="default")
    a.add_argument("--iterations", type=int)
    a.add_argument("--seed", type=int, default=0)
    a.add_argument("--max-gaussians", type=int, help="cap on the field's Gaussian count (default: preset's)")
    a.add_argument("--checkpoint", type=Path, help="checkpoint file (default: none)")
    a.add_argument("--resume", action="store_true", help="continue from --checkpoint if it exists")
    a.add_argument(
        "--holdout-every",
        type=int,
        help="hold out every n-th view (default: as dsg-train, none when the capture has test states)",
    )
    a.add_argument(
        "--mip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="Mip-Splatting filters, as dsg-train --mip (default: the preset's)",
    )
    b = sub.add_parser("knn", help="baseline (b): kNN background completion of a single-state world")
    b.add_argument("world", type=Path)
    b.add_argument("--out", type=Path, required=True)
    b.add_argument("--k", type=int, default=8)
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    try:
        if args.cmd == "single":
            info = train_single_state(
                args.capture,
                args.out,
                preset=args.preset,
                iterations=args.iterations,
                seed=args.seed,
                max_gaussians=args.max_gaussians,
                mip=args.mip,
                checkpoint=args.checkpoint,
                resume=args.resume,
                holdout_every=args.holdout_every,
            )
        else:
            from dsg_gym.world import load_world

            w = knn_complete(load_world(args.world), k=args.k)
            write_world(args.out, w)
            info = {"world": str(args.out), **w.metadata.get("knn_completion", {})}
            held = (w.metadata.get("train_config") or {}).get("holdout_every")
            if held is not None:  # the single-state world's: what the suite's table checks
                info["holdout_every"] = held
    except (ValueError, FileNotFoundError) as e:
        print(f"baselines: error: {e}", file=sys.stderr)
        return 2
    info["wall_seconds"] = round(time.perf_counter() - t0, 1)
    info["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    print(json.dumps(info))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
