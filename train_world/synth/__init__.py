"""Synthetic dual-state captures rendered with MuJoCo (``dsg-synth``).

Modules: :mod:`.spec` (scene descriptions), :mod:`.shapes` (exact shape geometry), :mod:`.textures`,
:mod:`.build` (MjSpec model), :mod:`.states` (state sampling and checks), :mod:`.cameras` (orbits),
:mod:`.render` (RGB / ids / depth), :mod:`.generate` (writing a capture), :mod:`.photos` (what a phone would
give, for ``dsg-capture``); the ``dsg-synth`` command is :mod:`train_world.cli.synth`.
Importing this package does not import MuJoCo; the submodules that need it set ``MUJOCO_GL=egl`` by default.
"""

from train_world.synth.spec import SceneSpec, default_scene_names, load_scene_spec, resolve_scene

__all__ = ["SceneSpec", "default_scene_names", "load_scene_spec", "resolve_scene"]
