"""Shrink a world file for shipping: drop nearly transparent Gaussians and higher SH bands, keeping the
``max_gaussians`` most opaque-and-large ones per part (background, each object).

    python -m train_world.dual.compact worlds/two_blocks.dsgw assets/worlds/two_blocks_dsg.dsgworld \\
        --sh-degree 1 --min-opacity 0.02 --max-gaussians 50000

Raw encodings (``opacity_logits``, ``log_scales``) are dropped (the activated values remain); everything else
(poses, cameras, classifier, metadata) is kept, and ``metadata.compacted`` records the options.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from types import MappingProxyType

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import World, WorldObject, load_world

__all__ = ["compact_world", "main"]


def _compact_set(g: GaussianSet, sh_degree: int, min_opacity: float, cap: int | None) -> GaussianSet:
    keep = np.nonzero(g.opacities >= min_opacity)[0]
    if cap is not None and len(keep) > cap:
        weight = g.opacities[keep] * g.scales[keep].prod(-1) ** (1.0 / 3.0)
        keep = np.sort(keep[np.argsort(-weight, kind="stable")[:cap]])
    s = g.subset(keep).without_encodings()
    k = (sh_degree + 1) ** 2
    return dataclasses.replace(s, sh=np.ascontiguousarray(s.sh[:, : min(k, s.sh.shape[1])]))


def compact_world(
    world: World, *, sh_degree: int = 1, min_opacity: float = 0.02, max_gaussians: int | None = None
) -> World:
    """``world`` with each part compacted (module docstring); ``max_gaussians`` caps the total, shared
    among the parts in proportion to their sizes after the opacity cut."""
    parts = [world.background] + [world.objects[i].gaussians for i in world.object_ids]
    sizes = [int((p.opacities >= min_opacity).sum()) for p in parts]
    total = max(sum(sizes), 1)
    caps = [None if max_gaussians is None else max(1, int(max_gaussians * s / total)) for s in sizes]
    new = [_compact_set(p, sh_degree, min_opacity, c) for p, c in zip(parts, caps)]
    objects = {oid: WorldObject(world.objects[oid].name, g) for oid, g in zip(world.object_ids, new[1:])}
    meta = {
        **dict(world.metadata),
        "compacted": {"sh_degree": sh_degree, "min_opacity": min_opacity, "max_gaussians": max_gaussians},
        "num_gaussians": sum(g.num for g in new),
    }
    return dataclasses.replace(
        world, background=new[0], objects=MappingProxyType(objects), metadata=MappingProxyType(meta)
    )


def main(argv: list[str] | None = None) -> int:
    from train_world.world_writer import write_world

    p = argparse.ArgumentParser(prog="python -m train_world.dual.compact", description=__doc__.split("\n")[0])
    p.add_argument("world", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--sh-degree", type=int, default=1)
    p.add_argument("--min-opacity", type=float, default=0.02)
    p.add_argument("--max-gaussians", type=int)
    a = p.parse_args(argv)
    try:
        w = compact_world(
            load_world(a.world),
            sh_degree=a.sh_degree,
            min_opacity=a.min_opacity,
            max_gaussians=a.max_gaussians,
        )
        write_world(a.out, w)
    except (ValueError, OSError) as e:
        print(f"compact: error: {e}", file=sys.stderr)
        return 2
    print(
        json.dumps(
            {"out": str(a.out), "gaussians": w.metadata["num_gaussians"], "bytes": a.out.stat().st_size}
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
