"""``dsg-demo``: solve a rearrangement episode in ``DSGWorld-v0`` on the bundled world and write a PNG.

    dsg-demo [--out out/demo.png] [--size 128] [--seed 0] [--no-video] [--procedural [--views 4]]

Runs the scripted expert policy from a seeded reset to its goal, keeps every few frames, and
writes a strip of RGB observations (top) and object masks (bottom); beside the PNG it writes the
whole episode as an animated GIF (``render()`` frames with the goal drawn as a translucent ghost),
and an MP4 of the same frames when the ``video`` extra is installed (``--no-video``: neither).
Prints the steps/s, whether the goal was reached and where the files went. ``--procedural``
instead renders a small procedural splat scene (a checkered table and three objects from four
cameras, RGB plus one-hot object ids in one ``rasterize`` pass) without any world file. The work
is done by :mod:`dsg_gym.demo`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="dsg-demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/demo.png", help="PNG path (default out/demo.png)")
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels")
    ap.add_argument("--seed", type=int, default=0, help="reset seed of the episode")
    ap.add_argument("--no-video", action="store_true", help="write no GIF/MP4 of the episode beside the PNG")
    ap.add_argument("--procedural", action="store_true", help="render the procedural scene instead")
    ap.add_argument("--views", type=int, default=4, help="cameras on the orbit (--procedural)")
    args = ap.parse_args(argv)
    if Path(args.out).suffix.lower() in (".gif", ".mp4"):
        ap.error(f"--out {args.out}: give the PNG's path (.png); the GIF and MP4 go beside it")
    from dsg_gym.demo import run_env_demo, run_procedural_demo

    if args.procedural:
        run_procedural_demo(args.out, args.size, args.views)
    else:
        run_env_demo(args.out, args.size, args.seed, video=not args.no_video)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
