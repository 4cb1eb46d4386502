"""``dsg-demo``: solve a rearrangement episode in ``DSGWorld-v0`` on the bundled world and write a PNG.

    dsg-demo [--out out/demo.png] [--size 128] [--seed 0] [--procedural [--views 4]]

Runs the scripted expert policy from a seeded reset to its goal, keeps every few frames, and
writes a strip of RGB observations (top) and object masks (bottom); prints the steps/s, whether
the goal was reached and where the PNG went. ``--procedural`` instead renders a small procedural
splat scene (a checkered table and three objects from four cameras, RGB plus one-hot object ids
in one ``rasterize`` pass) without any world file. The work is done by :mod:`dsg_gym.demo`.
"""

from __future__ import annotations

import argparse

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="dsg-demo", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out/demo.png", help="PNG path (default out/demo.png)")
    ap.add_argument("--size", type=int, default=128, help="image width = height in pixels")
    ap.add_argument("--seed", type=int, default=0, help="reset seed of the episode")
    ap.add_argument("--procedural", action="store_true", help="render the procedural scene instead")
    ap.add_argument("--views", type=int, default=4, help="cameras on the orbit (--procedural)")
    args = ap.parse_args(argv)
    from dsg_gym.demo import run_env_demo, run_procedural_demo

    if args.procedural:
        run_procedural_demo(args.out, args.size, args.views)
    else:
        run_env_demo(args.out, args.size, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
