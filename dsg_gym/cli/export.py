"""``dsg-export``: a world file to a USD stage (optionally animated by a recorded episode) or to standard 3DGS
PLY files (see ``dsg-export --help``; the work is done by :mod:`dsg_gym.export`)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="dsg-export",
        description="Export a DSG world file to a USD stage (.usdc binary, default; .usda text), optionally "
        "with a recorded episode as time-sampled object poses, or (--ply) to standard 3DGS PLY files.",
    )
    ap.add_argument("world", help="world file (.dsgworld)")
    ap.add_argument(
        "--out",
        required=True,
        help="stage path (.usdc/.usda; .usdc appended when there is no suffix), or with --ply a folder",
    )
    ap.add_argument(
        "--poses",
        default=None,
        help="object poses: a state name of the world (state1, state2, ...) or a .npy/.npz/.json "
        "file with [K,4,4] or [K,7] poses (default: the reference state, or the episode's "
        "first step)",
    )
    ap.add_argument(
        "--episode", default=None, help=".npz episode file (RecordEpisode.save): writes an animated stage"
    )
    ap.add_argument(
        "--ply",
        action="store_true",
        help="write background.ply + <object>.ply (3DGS Inria layout) into the --out folder; "
        "objects in their own frames unless --poses is given",
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.ply and args.episode is not None:
        ap.error("--episode needs a USD output (drop --ply)")
    if args.ply and Path(args.out).suffix in (".usdc", ".usda"):
        ap.error(f"--ply writes a folder of .ply files; --out {args.out!r} looks like a USD stage")
    from dsg_gym.export import export_world_ply, export_world_usd

    try:
        if args.ply:
            for p in export_world_ply(args.world, args.out, poses=args.poses):
                print(p)
        else:
            print(export_world_usd(args.world, args.out, poses=args.poses, episode=args.episode))
    except (ValueError, OSError) as e:  # bad input or an unwritable place: one line, nothing left behind
        msg = "; ".join(line.strip() for line in str(e).splitlines() if line.strip())
        print(f"dsg-export: error: {msg}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
