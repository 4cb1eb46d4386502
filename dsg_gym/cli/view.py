"""``dsg-view``: serve a world in the browser, with the ``DSGWorldEnv`` behind the page.

    dsg-view [WORLD] [--host 127.0.0.1] [--port 8080] [--camera 0] [--size 256] [--seed 0]
             [--out out/viewer] [--episode FILE|DATASET [--episode-index 0]]

Without WORLD it serves the bundled world. Open the printed address: drag an object's handle to move it;
the panel shows the env's observation from the chosen capture camera and the physics verdict; buttons
reset, save the configuration (JSON) or export it as a USD stage, and play an episode file or a Minari
dataset episode. Needs the ``viewer`` extra (``pip install 'dsg-gym[viewer]'``). Ctrl-C stops it.
The work is done by :mod:`dsg_gym.viewer`.
"""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="dsg-view", description=__doc__.split("\n\n")[0])
    ap.add_argument("world", nargs="?", default=None, help="world file (default: the bundled world)")
    ap.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    ap.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    ap.add_argument("--camera", type=int, default=0, help="capture camera of the observation panel")
    ap.add_argument("--size", type=int, default=256, help="observation width = height in pixels")
    ap.add_argument("--seed", type=int, default=0, help="seed of the first random configuration")
    ap.add_argument("--out", default="out/viewer", help="folder the save and export buttons write to")
    ap.add_argument("--episode", default=None, help="episode file (.npz) or Minari dataset to play")
    ap.add_argument("--episode-index", type=int, default=0, help="episode of the dataset (--episode)")
    args = ap.parse_args(argv)
    if not 0 < args.port < 65536:
        ap.error(f"--port {args.port}: give a port in 1..65535")
    os.environ.setdefault("MUJOCO_GL", "egl")
    from dsg_gym.viewer.server import Viewer

    try:
        viewer = Viewer(
            args.world, host=args.host, port=args.port, camera=args.camera, size=args.size, seed=args.seed,
            out_dir=args.out, episode=args.episode, episode_index=args.episode_index,
        )  # fmt: skip
    except (ValueError, ModuleNotFoundError, OSError) as e:
        print(f"dsg-view: {e}", file=sys.stderr)
        return 1
    print(f"dsg-view: serving {viewer.session.world.name} at {viewer.url} (Ctrl-C stops)", flush=True)
    viewer.serve_forever()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
