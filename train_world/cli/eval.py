"""``dsg-eval``: score a world against a capture (PSNR, SSIM, mask IoU) and write error grids; the work is
:mod:`train_world.eval.evaluate`. A world trained in a frame estimated from photos is scored against a ground
truth in its own frame through the similarity fitted from their cameras (:mod:`train_world.eval.frames`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dsg_gym.world import WorldFormatError, load_world
from train_world.capture import CaptureError
from train_world.eval import evaluate as _lib
from train_world.eval.evaluate import default_state, evaluate, evaluate_test_states
from train_world.eval.frames import fit_frame_alignment, needs_alignment
from train_world.eval.view_align import ViewAlignment


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-eval",
        description=_lib.__doc__.split("\n")[0].split(": ", 1)[1],
        epilog=_lib.__doc__.split("Example::", 1)[1],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("world", type=Path, help="world file written by dsg-train")
    p.add_argument(
        "capture",
        type=Path,
        help="the capture (or NeRF-Blender folder) it was trained on, or the ground truth of that capture "
        "(e.g. the ground_truth/ folder of dsg-synth --as-photos) for a world trained on a dsg-capture capture",
    )
    p.add_argument("--out", type=Path, required=True, help="output folder for report.json/report.md/grid.png")
    p.add_argument(
        "--state",
        help="evaluate this state at its object poses: all its views, or at a training state of the world the "
        "views it held out; 'test': every test state of the capture (default: 'test' for a two-state world, "
        "or one trained without held-out views, on a capture with test states; else the held-out views of the "
        "training state)",
    )
    p.add_argument(
        "--training-views",
        action="store_true",
        help="with --state naming a training state of the world: score all of that state's views, the ones it "
        "was trained on included (the fit, to set beside the test states); the report says training_views",
    )
    frame = p.add_mutually_exclusive_group()
    frame.add_argument(
        "--align-frames",
        dest="align",
        action="store_true",
        default=None,
        help="fit the similarity between the capture's frame and the world's from the world's training cameras "
        "and evaluate through it (default when the world was trained on a dsg-capture capture and CAPTURE is "
        "another folder: its ground truth)",
    )
    frame.add_argument(
        "--same-frame",
        dest="align",
        action="store_false",
        help="take the capture to be in the world's frame (the default for any other world)",
    )
    p.add_argument(
        "--align-views",
        type=int,
        nargs="?",
        const=ViewAlignment.steps,
        metavar="STEPS",
        help="before scoring, align each camera's pose to the world against its image (STEPS Adam steps, "
        f"default {ViewAlignment.steps}), as pose-free evaluations do; the unaligned PSNR is reported beside it",
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
        views = None if args.align_views is None else ViewAlignment(steps=args.align_views)
        world = load_world(args.world)
        align = needs_alignment(world, args.capture) if args.align is None else args.align
        alignment = fit_frame_alignment(world, args.capture) if align else None
        if alignment is not None:
            a = alignment.to_dict()
            print(
                f"dsg-eval: ground-truth frame -> world frame: scale {a['scale']:.6f}, rotation "
                f"{a['rotation_deg']:.4f} deg, translation {[round(x, 6) for x in a['translation']]}; "
                f"{a['cameras']} cameras, centre error rms {a['camera_centre_rms']:.3g} max "
                f"{a['camera_centre_max']:.3g} (ground-truth units), rotation rms "
                f"{a['camera_rotation_rms_deg']:.3g} deg",
                file=sys.stderr,
            )
        if args.training_views and args.state in (None, "test"):
            raise ValueError(
                "--training-views scores a training state's views: name it with --state (e.g. state1)"
            )
        state = args.state if args.state is not None else default_state(args.world, args.capture)
        if state == "test":
            r = evaluate_test_states(
                args.world, args.capture, args.out, alignment=alignment, view_alignment=views
            )
        elif alignment is not None and state is None:
            raise ValueError(
                f"{args.capture}: a ground truth in another frame is scored at its test states or a named "
                "--state; it has no test states"
            )
        else:
            r = evaluate(
                args.world,
                args.capture,
                args.out,
                state=state,
                alignment=alignment,
                view_alignment=views,
                training_views=args.training_views,
            )
    except (WorldFormatError, CaptureError, ValueError, KeyError) as e:
        print(f"dsg-eval: error: {e}", file=sys.stderr)
        return 2
    summary = {"out": str(args.out), "views": r["views"], "mean": r["mean"]}
    if "mean_unaligned" in r:
        summary["mean_unaligned"] = r["mean_unaligned"]
    if alignment is not None:
        summary["frame_alignment"] = {
            k: v for k, v in alignment.to_dict().items() if k not in ("rotation", "identity")
        }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
