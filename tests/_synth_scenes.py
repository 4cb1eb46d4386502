"""The small synthetic capture the dsg-synth tests share: its scene, its generator settings, and making it."""

from __future__ import annotations

from pathlib import Path

from train_world.synth.generate import GenerateConfig, generate_scene

SCENE = "four_mixed"  # box, cylinder, sphere and a mesh; no props on the table
TINY = GenerateConfig(seed=3, width=32, height=32, views=4, test_views=2, test_states=1, progress=False)


def make_tiny_capture(root: Path) -> Path:
    """Generate :data:`SCENE` with :data:`TINY` into ``root/tiny``."""
    out = root / "tiny"
    generate_scene(SCENE, out, TINY)
    return out
