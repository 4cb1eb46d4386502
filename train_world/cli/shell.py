"""``python -m train_world.cli.shell``: add the far shell to a world written without it; the work is
:mod:`train_world.complete.shell`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m train_world.cli.shell",
        description="Add the far shell (flat Gaussians behind the background for the directions no capture view "
        "saw; what dsg-train adds by default) to a world written without it. Writes a new world file.",
    )
    p.add_argument("world", type=Path, help="world file (dsg-train)")
    p.add_argument("--out", type=Path, required=True, help="world file to write")
    return p


def main(argv: list[str] | None = None) -> int:
    from dsg_gym.world import WorldFormatError, load_world, write_world
    from train_world.complete.shell import with_background_shell

    args = _parser().parse_args(argv)
    try:
        world = load_world(args.world)
        if "background_shell" in world.metadata:
            raise ValueError(f"{args.world} has a far shell already; nothing to add")
        shelled = with_background_shell(world)
        write_world(args.out, shelled)
    except (ValueError, FileNotFoundError, WorldFormatError) as e:
        print(f"shell: error: {e}", file=sys.stderr)
        return 2
    print(json.dumps({"world": str(args.out), **shelled.metadata["background_shell"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
