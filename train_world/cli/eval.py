"""``dsg-eval``: score a world against a capture (PSNR, SSIM, mask IoU) and write error grids; the work is
:mod:`train_world.eval.evaluate`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dsg_gym.world import WorldFormatError
from train_world.capture import CaptureError
from train_world.eval import evaluate as _lib
from train_world.eval.evaluate import default_state, evaluate, evaluate_test_states


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-eval",
        description=_lib.__doc__.split("\n")[0].split(": ", 1)[1],
        epilog=_lib.__doc__.split("Example::", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("world", type=Path, help="world file written by dsg-train")
    p.add_argument("capture", type=Path, help="the capture (or NeRF-Blender folder) it was trained on")
    p.add_argument("--out", type=Path, required=True, help="output folder for report.json/report.md/grid.png")
    p.add_argument(
        "--state",
        help="evaluate all views of this state at its object poses; 'test': every test state of the capture "
        "(default: 'test' for a two-state world, or one trained without held-out views, on a capture with test "
        "states; else the held-out views of the training state)",
    )
    p.add_argument(
        "--suite",
        action="store_true",
        help="instead: run the DSG-World comparison (dsg-suite); the other options are dsg-suite's",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if "--suite" in argv:  # dsg-eval --suite: the comparison, with dsg-suite's options
        from train_world.cli.suite import main as suite_main

        return suite_main([a for a in argv if a != "--suite"])
    args = _parser().parse_args(argv)
    try:
        state = args.state if args.state is not None else default_state(args.world, args.capture)
        if state == "test":
            r = evaluate_test_states(args.world, args.capture, args.out)
        else:
            r = evaluate(args.world, args.capture, args.out, state=state)
    except (WorldFormatError, CaptureError, ValueError, KeyError) as e:
        print(f"dsg-eval: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"out": str(args.out), "views": r["views"], "mean": r["mean"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
