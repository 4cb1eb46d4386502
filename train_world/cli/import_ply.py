"""``dsg-import-ply``: a 3DGS PLY as a world background or a new object; the work is
:mod:`train_world.capture.ply_import`.
"""

from __future__ import annotations

import argparse
import sys

from train_world.capture.ply_import import ROLES, world_from_ply


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="dsg-import-ply",
        description="Import a standard 3DGS PLY (Inria layout) as a world's background or as a new object "
        "and write a world file. DSGWorld-v0 needs at least one object: a background-only world (no --base) "
        "renders but is not an env; add an object with --as object --base WORLD.",
    )
    ap.add_argument("ply", help="3DGS PLY file")
    ap.add_argument("--out", required=True, help="world file to write (.dsgworld)")
    ap.add_argument(
        "--as",
        dest="role",
        choices=ROLES,
        default="background",
        help="background (default): replace the base's background (or make a world of it); "
        "object: add it as a new object (its frame = the PLY frame, identity pose)",
    )
    ap.add_argument(
        "--object-name", default=None, help="name of the new object (default: the PLY's file stem)"
    )
    ap.add_argument("--base", default=None, help="world file to start from (objects, states, cameras, table)")
    ap.add_argument(
        "--for-env",
        action="store_true",
        help="refuse to write a world without objects (DSGWorld-v0 needs at least one)",
    )
    ap.add_argument("--views", type=int, default=16, help="orbit cameras when there is no base (default 16)")
    ap.add_argument("--width", type=int, default=256, help="orbit camera image width (default 256)")
    ap.add_argument("--height", type=int, default=256, help="orbit camera image height (default 256)")
    args = ap.parse_args(argv)
    if args.object_name is not None and args.role != "object":
        ap.error("--object-name needs --as object")
    if min(args.views, args.width, args.height) < 1:
        ap.error("--views, --width and --height must be positive")
    from dsg_gym.world import write_world

    try:
        world = world_from_ply(
            args.ply,
            args.base,
            args.role,
            object_name=args.object_name,
            num_views=args.views,
            width=args.width,
            height=args.height,
            for_env=args.for_env,
        )
        out = write_world(args.out, world)
    except (ValueError, OSError) as e:
        ap.error(str(e))
    print(out)
    if world.num_objects == 0:
        print(
            "note: this world has no objects, so DSGWorld-v0 cannot use it; add one with "
            f"`dsg-import-ply OBJECT.ply --as object --base {out} --out WORLD`",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
