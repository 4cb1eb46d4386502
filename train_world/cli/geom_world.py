"""``python -m train_world.cli.geom_world``: write the geometry world of a synthetic scene; the work is
:mod:`train_world.synth.geom_world`.
"""

from __future__ import annotations

from train_world.synth.geom_world import GeomWorldConfig, build_geom_world, to_world


def main(argv: list[str] | None = None) -> int:
    """``python -m train_world.cli.geom_world --scene two_blocks --out assets/worlds/default_geom.dsgworld``"""
    import argparse

    from dsg_gym.world import write_world

    ap = argparse.ArgumentParser(description="Write the geometry world of a synthetic scene as a world file.")
    ap.add_argument("--scene", default="two_blocks")
    ap.add_argument("--out", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--detail", type=float, default=1.0)
    args = ap.parse_args(argv)
    wm = build_geom_world(args.scene, GeomWorldConfig(seed=args.seed, detail=args.detail))
    print(write_world(args.out, to_world(wm)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
