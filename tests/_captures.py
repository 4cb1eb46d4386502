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
