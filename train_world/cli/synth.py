"""``dsg-synth``: generate synthetic dual-state captures of the default (or your own) MuJoCo scenes.

Examples::

    dsg-synth --list
    dsg-synth --scene two_blocks --out data/two_blocks      # writes data/two_blocks/scene.json, state1/ ...
    dsg-synth --scene all --out data/synth --seed 1         # one folder per scene: data/synth/<name>/
    dsg-synth --scene my_scene.json --out data/mine --width 256 --height 192 --shadows
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from train_world.synth.spec import SpecError, default_scene_names, resolve_scene

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-synth",
        description="Render synthetic dual-state captures (two training states with every object moved, plus "
        "held-out test states) of tabletop MuJoCo scenes, with RGB, object-id masks, depth and "
        "exact object poses. See docs/captures.md.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("Examples::", 1)[1],
    )
    p.add_argument("--list", action="store_true", help="list the default scenes and exit")
    p.add_argument("--scene", help="default scene name, 'all', or a path to a scene description .json")
    p.add_argument("--out", type=Path, help="output folder (with --scene all: one sub-folder per scene)")
    p.add_argument("--seed", type=int, default=0, help="random seed for states and cameras (default 0)")
    p.add_argument("--width", type=int, default=128, help="image width in pixels (default 128)")
    p.add_argument("--height", type=int, default=128, help="image height in pixels (default 128)")
    p.add_argument("--views", type=int, default=48, help="training views per training state (default 48)")
    p.add_argument("--test-views", type=int, default=12, help="held-out test cameras (default 12)")
    p.add_argument("--test-states", type=int, default=3, help="test states with new object poses (default 3)")
    p.add_argument(
        "--shadows", action="store_true", help="lights cast shadows (harder variant; off by default)"
    )
    p.add_argument(
        "--lighting",
        choices=("soft", "spot", "headlight"),
        default="soft",
        help="soft (default): light mostly from a point light at the camera, weak fixed lights; spot: strong "
        "fixed spot lights that shade moved objects differently (harder variant; generator 1.0's fixed lights); "
        "headlight: generator 1.2's soft (MuJoCo's directional headlight instead of the camera point light)",
    )
    p.add_argument(
        "--supersample",
        type=int,
        default=4,
        help="RGB samples per pixel along each axis, box-averaged like a camera sensor (default 4; 1 = one "
        "point sample per pixel, generator 1.1's aliased look)",
    )
    p.add_argument(
        "--as-photos",
        action="store_true",
        help="write what a phone would give (OUT/state1|state2/images/*.jpg + masks/*.png, objects.json), the "
        "input of dsg-capture, with the full synthetic capture in OUT/ground_truth/",
    )
    p.add_argument(
        "--photo-noise",
        type=float,
        default=0.0,
        metavar="SIGMA",
        help="with --as-photos: Gaussian sensor noise of SIGMA grey levels (0..255 scale) plus a slight blur "
        "(default 0: clean JPEGs)",
    )
    p.add_argument(
        "--photo-exposure",
        type=float,
        default=0.0,
        metavar="E",
        help="with --as-photos: each photo's brightness scaled by a gain drawn from [1 - E, 1 + E], as a phone's "
        "auto-exposure varies (default 0)",
    )
    p.add_argument(
        "--photo-scale",
        type=int,
        default=1,
        metavar="S",
        help="with --as-photos: photos S times as wide and high as the ground truth (the same views, "
        "--supersample // S samples per photo pixel), as a phone's photos are larger than the size a world "
        "trains at; train on them with dsg-train --downscale S (default 1)",
    )
    p.add_argument(
        "--marker",
        type=float,
        default=0.0,
        metavar="METRES",
        help="lay an ArUco marker (OpenCV DICT_4X4_50, id 0) with a black square of this edge on the table "
        "(needs opencv-python-headless; default 0: none)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.list:
        try:
            names = default_scene_names()
        except (SpecError, OSError) as e:  # no scene descriptions installed
            print(f"dsg-synth: error: {e}", file=sys.stderr)
            return 2
        for name in names:
            spec = resolve_scene(name)
            print(f"{name:20s} {len(spec.objects)} objects  {spec.description}")
        return 0
    if not args.scene or args.out is None:
        _parser().error("--scene and --out are required (or use --list)")
    if (args.photo_noise or args.photo_exposure or args.photo_scale != 1) and not args.as_photos:
        _parser().error("--photo-noise, --photo-exposure and --photo-scale need --as-photos")
    if not 1 <= args.photo_scale <= 16:
        _parser().error(f"--photo-scale must be an integer in 1..16, got {args.photo_scale}")
    if not 0 <= args.photo_exposure < 1:
        _parser().error(f"--photo-exposure must be in [0, 1), got {args.photo_exposure}")
    from train_world.synth.generate import GenerateConfig, generate_scene  # imports MuJoCo

    try:
        cfg = GenerateConfig(
            seed=args.seed,
            width=args.width,
            height=args.height,
            views=args.views,
            test_views=args.test_views,
            test_states=args.test_states,
            shadows=args.shadows,
            lighting=args.lighting,
            supersample=args.supersample,
            marker=args.marker,
            progress=not args.quiet,
        )
        if args.scene == "all":
            jobs = [(resolve_scene(n), args.out / n) for n in default_scene_names()]
        else:
            jobs = [(resolve_scene(args.scene), args.out)]
        for spec, out in jobs:
            t0 = time.perf_counter()
            if args.as_photos:
                from train_world.synth.photos import generate_photo_capture

                generate_photo_capture(
                    spec,
                    out,
                    cfg,
                    overwrite=args.overwrite,
                    noise=args.photo_noise,
                    exposure=args.photo_exposure,
                    scale=args.photo_scale,
                )
            else:
                generate_scene(spec, out, cfg, overwrite=args.overwrite)
            print(f"{spec.name}: wrote {out} in {time.perf_counter() - t0:.1f} s")
    except (SpecError, ValueError, FileExistsError) as e:
        print(f"dsg-synth: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
