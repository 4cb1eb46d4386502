"""``dsg-suite``: the paper comparison suite (baselines (a), (b) and the DSG-World ablations over the
synthetic scenes); the work is :mod:`train_world.suite.runner`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from train_world.suite import runner as _lib
from train_world.suite.runner import METHODS, _scene_list, _write_tables, merge_tables, run_suite
from train_world.suite.seeds import (
    merge_by_seed,
    run_seeds,
    seed_folder,
    summarise_seeds,
    write_seed_tables,
)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-suite",
        description=_lib.__doc__.split("\n")[0].split(": ", 1)[1],
        epilog=_lib.__doc__.split("Examples::", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--out", type=Path, required=True, help="output folder (captures, worlds, eval, tables)")
    p.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        metavar="TABLE_JSON",
        help="train nothing: join these runs' table.json files into OUT/table.md and OUT/table.json; runs of "
        "several seeds into OUT/seed-<s>/ per seed and the summary over seeds (as --seeds writes)",
    )
    p.add_argument("--scenes", default="all", help="comma-separated scene names or 'all' (default)")
    p.add_argument("--methods", default="a,b,B,BC,BCP", help="subset of a,b,B,BC,BCP (default: all)")
    p.add_argument("--preset", default="default")
    p.add_argument("--iterations", type=int, help="steps per training (schedules scaled)")
    p.add_argument(
        "--pseudo-every", type=int, help="pseudo-state loss every n-th joint step (default: dsg-train's)"
    )
    p.add_argument(
        "--align-downscale",
        type=int,
        metavar="S",
        help="cross-state renders at 1/S resolution (dsg-train --align-downscale; default: dsg-train's)",
    )
    p.add_argument(
        "--support-weight",
        type=float,
        metavar="W",
        help="weight of the support term of ours (dsg-train --support-weight; default: the preset's)",
    )
    p.add_argument(
        "--layers",
        action=argparse.BooleanOptionalAction,
        help="ours refined and rendered in two layers, background and objects (dsg-train --layers; "
        "default: the preset's)",
    )
    p.add_argument(
        "--max-gaussians",
        type=int,
        help="cap on each field's Gaussian count, baseline (a) too (default: the preset's two-state cap)",
    )
    p.add_argument(
        "--refine-steps",
        type=int,
        help="refinement steps after ours' joint phase (default: the preset's; 0: none, the paper's method)",
    )
    p.add_argument("--seed", type=int, default=0, help="capture (dsg-synth) and training seed (default 0)")
    p.add_argument(
        "--seeds",
        help="comma-separated seeds, e.g. 0,1,2: the whole suite once per seed into OUT/seed-<s>/, then per scene "
        "the mean, spread and worst case over the seeds in OUT/seeds.md and OUT/seeds.json",
    )
    p.add_argument(
        "--mip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="train every world with (or without) the Mip-Splatting filters (default: the preset's)",
    )
    p.add_argument("--width", type=int)
    p.add_argument("--height", type=int)
    p.add_argument("--views", type=int)
    p.add_argument("--test-views", type=int)
    p.add_argument("--test-states", type=int)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        print(f"dsg-suite: error: unknown methods {bad}; choose from {list(METHODS)}", file=sys.stderr)
        return 2
    if args.merge:  # joining tables trains nothing: a training option here is a mistake, not a no-op
        defaults = vars(parser.parse_args(["--out", str(args.out)]))
        given = [
            "--" + k.replace("_", "-")
            for k, v in vars(args).items()
            if k not in ("merge", "methods") and v != defaults[k]
        ]
        if given:
            print(
                f"dsg-suite: error: --merge trains nothing and takes no training options (got {', '.join(given)})",
                file=sys.stderr,
            )
            return 2
        try:
            tables = [json.loads(Path(f).read_text()) for f in args.merge]
            by_seed = merge_by_seed(tables, methods) if len({t.get("seed") for t in tables}) > 1 else None
            r = merge_tables(tables, methods) if by_seed is None else None
        except (OSError, ValueError, KeyError, AttributeError) as e:
            print(f"dsg-suite: error: {e}", file=sys.stderr)
            return 2
        args.out.mkdir(parents=True, exist_ok=True)
        if by_seed is not None:  # runs of several seeds: one table per seed, then the summary over seeds
            for seed, t in by_seed.items():
                seed_folder(args.out, seed).mkdir(exist_ok=True)
                _write_tables(seed_folder(args.out, seed), t)
            summary = summarise_seeds(by_seed)
            write_seed_tables(args.out, summary, {m: METHODS[m][0] for m in METHODS})
            print(json.dumps({"out": str(args.out), "over_scene_seeds": {
                m: {k: v["mean"] for k, v in x["all"].items()} for m, x in summary["methods"].items()}}))  # fmt: skip
            return 0
        _write_tables(args.out, r)
        print(json.dumps({"out": str(args.out), "mean_over_scenes": r["mean_over_scenes"]}))
        return 0
    synth = []
    for name in ("width", "height", "views", "test_views", "test_states"):
        v = getattr(args, name)
        if v is not None:
            synth += [f"--{name.replace('_', '-')}", str(v)]
    seeds = None
    if args.seeds is not None:
        try:
            seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
        except ValueError:
            parser.error(f"--seeds must be comma-separated integers, got {args.seeds!r}")
        if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
            parser.error(f"--seeds must be distinct integers >= 0, got {args.seeds!r}")
        if args.seed != 0:
            parser.error("give --seed or --seeds, not both")

    def one(out: Path, seed: int) -> dict:
        return run_suite(out, _scene_list(args.scenes), methods, preset=args.preset, iterations=args.iterations,
                         synth_args=synth, seed=seed, pseudo_every=args.pseudo_every,
                         align_downscale=args.align_downscale, max_gaussians=args.max_gaussians, mip=args.mip,
                         refine_steps=args.refine_steps, support_weight=args.support_weight,
                         layers=args.layers)  # fmt: skip

    try:
        if seeds is not None:
            summary = run_seeds(args.out, seeds, one, {m: METHODS[m][0] for m in methods})
            print(json.dumps({"out": str(args.out), "over_scene_seeds": {
                m: {k: v["mean"] for k, v in r["all"].items()} for m, r in summary["methods"].items()}}))  # fmt: skip
            return 0
        r = one(args.out, args.seed)
    except (RuntimeError, ValueError) as e:
        print(f"dsg-suite: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"out": str(args.out), "mean_over_scenes": r["mean_over_scenes"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
