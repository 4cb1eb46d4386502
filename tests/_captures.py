"""Tiny synthetic captures shared by the training tests (not a test module)."""

from __future__ import annotations

from pathlib import Path

from train_world.cli.synth import main as synth_main


def tiny_capture(
    folder: Path,
    scene: str = "two_blocks",
    *,
    size: int = 32,
    views: int = 16,
    test_views: int = 2,
    test_states: int = 1,
) -> Path:
    """Generate ``scene`` at ``size`` x ``size`` into ``folder / scene`` with ``dsg-synth``."""
    out = Path(folder) / scene
    rc = synth_main(
        [
            "--scene",
            scene,
            "--out",
            str(out),
            "--width",
            str(size),
            "--height",
            str(size),
            "--views",
            str(views),
            "--test-views",
            str(test_views),
            "--test-states",
            str(test_states),
            "--quiet",
        ]
    )
    assert rc == 0
    return out


def tiny_suite_folder(run: Path, test_views: int = 2):
    """A ``dsg-suite``-shaped folder ``run`` for the benchmarks that read one: a tiny ``two_blocks`` capture in
    ``data/``, its geometry world as ``worlds/two_blocks/BCP.dsgworld`` and a ``table.json`` naming them.
    Returns the world."""
    import json

    from dsg_gym.world import write_world
    from train_world.synth import geom_world as gw

    run = Path(run)
    tiny_capture(run / "data", test_views=test_views, test_states=1)
    world = gw.to_world(gw.build_geom_world("two_blocks", gw.GeomWorldConfig(detail=0.5)))
    write_world(run / "worlds" / "two_blocks" / "BCP.dsgworld", world)
    (run / "table.json").write_text(json.dumps({"seed": 0, "scenes": {"two_blocks": {"BCP": {}}}}))
    return world
