"""``dsg-capture``: two photo sets of a real tabletop (before/after moving objects) -> a dsg-gym capture.

Examples::

    dsg-capture photos/ --out data/my_table                       # units arbitrary (recorded as "unknown")
    dsg-capture photos/ --out data/my_table --metres-per-unit 0.62 --overwrite
    dsg-capture photos/ --out data/my_table --marker-size 0.06  # metric, from an ArUco marker in the photos
    dsg-capture photos/ --out data/my_table --depth none        # no depth maps: seconds, not minutes
    dsg-capture photos/ --out data/my_table --max-size 128      # phone photos: a capture of 128 px, as worlds train at
    dsg-capture photos/ --extract-frames 40     # state1/walk.mp4 -> state1/images/frame_0000.jpg ... (then masks)

``photos/`` holds ``state1/`` and ``state2/``, each with ``images/`` (JPEG or PNG) and ``masks/`` (one PNG of
object ids per photo, same file stem; 0 = background, 1..K the same object in every photo of both states),
plus an optional ``objects.json`` naming the ids. See ``data/my_table/report.json`` for how well it went.
A state may instead hold one video: ``--extract-frames N`` samples it to N sharp frames in ``images/``; make the
masks for those frames, then run ``dsg-capture`` as for photos.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

# numpy and Pillow before pycolmap: the other order aborts when a PNG is written
import numpy as np  # noqa: F401
from PIL import Image  # noqa: F401

from train_world.capture.fitted_depth import DepthFit

__all__ = ["DEPTH_SOURCES", "main"]

#: ``--depth``: where the capture's depth maps come from
DEPTH_SOURCES = ("fit", "stereo", "none")


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-capture",
        description="Estimate camera poses (joint structure from motion of both states, objects masked out), "
        "the table frame and every object's rigid motion between the states from photos and object masks, "
        "and write a standard capture plus report.json.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("Examples::", 1)[1],
    )
    p.add_argument(
        "photos", type=Path, help="photo capture folder (state1/ and state2/ with images/ and masks/)"
    )
    p.add_argument("--out", type=Path, help="output capture folder")
    p.add_argument(
        "--extract-frames",
        type=int,
        metavar="N",
        help="instead of building a capture: sample the video in each state folder to N sharp frames in "
        "images/ (then make masks/ for them)",
    )
    p.add_argument(
        "--metres-per-unit",
        type=float,
        default=None,
        metavar="X",
        help="metric scale: metres per unit of the estimated frame (unit = median camera distance from the "
        "table origin); without it the capture's units are recorded as arbitrary ('unknown')",
    )
    p.add_argument(
        "--marker-size",
        type=float,
        default=None,
        metavar="METRES",
        help="metric scale from an ArUco marker (OpenCV DICT_4X4_50) lying in the scene: the edge of its black "
        "square in metres; it must be seen whole in at least two photos",
    )
    p.add_argument(
        "--marker-id", type=int, default=None, help="the marker's id (default: the lowest id seen)"
    )
    p.add_argument(
        "--depth",
        choices=DEPTH_SOURCES,
        default="fit",
        help="the depth maps every view gets, which training starts from: 'fit' (default) renders them from "
        "a first reconstruction of each state (--fit-steps training steps per state; minutes on a CPU), "
        "'stereo' from multi-view stereo (0 where none, e.g. bare walls), 'none' writes none (training "
        "then starts from the sparse points, the table top, the objects' hulls, points out to the room and "
        "random points)",
    )
    p.add_argument(
        "--fit-steps",
        type=int,
        default=None,
        metavar="STEPS",
        help=f"training steps of each state's first reconstruction with --depth fit (default {DepthFit.steps})",
    )
    p.add_argument(
        "--fit-downscale",
        type=int,
        default=None,
        metavar="N",
        help="with --depth fit: train each first reconstruction on the capture's views downscaled by the "
        f"integer N (its depth is still rendered at their size; default {DepthFit.downscale})",
    )
    p.add_argument(
        "--floor-tolerance",
        type=float,
        default=None,
        metavar="F",
        help="with --depth fit: background depth within the fraction F of the floor that the structure-from-"
        "motion points show below the table is put on that floor (0: never; default "
        f"{DepthFit.floor_tolerance})",
    )
    p.add_argument(
        "--edge-angle",
        type=float,
        default=None,
        metavar="DEG",
        help="with --depth fit: drop the fitted depth where it changes from a neighbouring pixel's faster than on "
        "a surface seen DEG degrees from edge-on, the depths a fit blends across an object's outline, e.g. 5 "
        f"(default {DepthFit.edge_angle_deg:g}: keep them)",
    )
    p.add_argument(
        "--max-size",
        type=int,
        default=None,
        metavar="PX",
        help="shrink the capture's views to at most PX pixels on the long side (images area-averaged, "
        "intrinsics scaled), the size the world will train at: a phone's photos are far larger than a CPU "
        "trains at; poses, the table frame, the marker and the object motions still use the whole photos "
        "(default: the photos' size)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def _depth_fit(args: argparse.Namespace) -> DepthFit:
    """The :class:`DepthFit` of ``--fit-steps``, ``--fit-downscale``, ``--floor-tolerance`` and
    ``--edge-angle`` (its defaults where not given)."""
    given = {
        "steps": args.fit_steps,
        "downscale": args.fit_downscale,
        "floor_tolerance": args.floor_tolerance,
        "edge_angle_deg": args.edge_angle,
    }
    return DepthFit(**{k: v for k, v in given.items() if v is not None})


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.extract_frames is not None:
        return _extract(args)
    if args.out is None:
        parser.error("--out is required (or --extract-frames N to sample videos to frames)")
    if args.marker_size is not None and args.metres_per_unit is not None:
        parser.error("give the scale once: --marker-size or --metres-per-unit")
    for flag, value in (
        ("--fit-steps", args.fit_steps),
        ("--fit-downscale", args.fit_downscale),
        ("--floor-tolerance", args.floor_tolerance),
        ("--edge-angle", args.edge_angle),
    ):
        if value is not None and args.depth != "fit":
            parser.error(f"{flag} is for --depth fit, not --depth {args.depth}")
    if args.fit_downscale is not None and args.fit_downscale < 1:
        parser.error(f"--fit-downscale must be an integer >= 1, got {args.fit_downscale}")
    if args.floor_tolerance is not None and not 0.0 <= args.floor_tolerance < 1.0:
        parser.error(f"--floor-tolerance must lie in [0, 1) (0: never), got {args.floor_tolerance}")
    if args.edge_angle is not None and not 0.0 <= args.edge_angle < 90.0:
        parser.error(f"--edge-angle must lie in [0, 90) degrees (0: never), got {args.edge_angle}")
    if args.max_size is not None and args.max_size < 16:
        parser.error(f"--max-size must be at least 16 pixels, got {args.max_size}")
    if args.fit_steps is not None and args.fit_steps < 100:
        parser.error(f"--fit-steps needs at least 100 steps, got {args.fit_steps}")
    if args.marker_size is not None and not args.marker_size > 0:
        parser.error(f"--marker-size must be a positive number of metres, got {args.marker_size}")
    if args.metres_per_unit is not None and not args.metres_per_unit > 0:
        print(
            f"dsg-capture: error: --metres-per-unit must be a positive number, got {args.metres_per_unit}",
            file=sys.stderr,
        )
        return 2
    from train_world.capture.photo_capture import build_capture

    def say(msg: str) -> None:
        print(f"dsg-capture: {msg}", file=sys.stderr, flush=True)

    try:
        report = build_capture(
            args.photos,
            args.out,
            metres_per_unit=args.metres_per_unit,
            marker_size=args.marker_size,
            marker_id=args.marker_id,
            overwrite=args.overwrite,
            stereo=args.depth == "stereo",
            depth_fit=_depth_fit(args) if args.depth == "fit" else None,
            progress=not args.quiet,
            log=None if args.quiet else say,
            max_size=args.max_size,
        )
    except (ValueError, FileExistsError) as e:
        print(f"dsg-capture: error: {e}", file=sys.stderr)
        return 2
    reg = ", ".join(f"{s} {r['views']}/{r['of']}" for s, r in report["registered"].items())
    objs = ", ".join(f"{o['name']} ({o['method']})" for o in report["objects"])
    print(
        f"dsg-capture: wrote {args.out} (registered {reg}; reprojection error "
        f"{report['mean_reprojection_error_px']:.2f} px; units {report['units']}; objects: {objs}) in "
        f"{report['timings_s']['total_s']:.1f} s"
    )
    return 0


def _extract(args) -> int:
    from train_world.capture.photos import PhotoCaptureError
    from train_world.capture.video import extract_capture_frames

    try:
        done = extract_capture_frames(
            args.photos,
            args.extract_frames,
            overwrite=args.overwrite,
            progress=not args.quiet,
            log=None if args.quiet else (lambda m: print(f"dsg-capture: {m}", file=sys.stderr, flush=True)),
        )
    except PhotoCaptureError as e:
        print(f"dsg-capture: error: {e}", file=sys.stderr)
        return 2
    for state, paths in done.items():
        print(f"dsg-capture: {state}: {len(paths)} frames in {paths[0].parent}")
    print(f"dsg-capture: next: one object-id mask PNG per frame in <state>/masks/ (same stems), then "
          f"dsg-capture {args.photos} --out CAPTURE")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
