"""The goal ghost that ``DSGWorldEnv.render()`` draws with ``render_goal=True``.

Each object is rendered alone (no background) at its goal pose by a renderer with the view cameras of
``render()``; that render's colour and coverage (alpha) are composited over the frame at :data:`GHOST_OPACITY`,
and the ghost's outline (where its coverage crosses one half) is drawn in :data:`OUTLINE_COLOR`. Observations
never carry the ghost: only ``render()`` frames do.
"""

from __future__ import annotations

import weakref
from typing import Any

import numpy as np

from ..gaussians import GaussianSet

__all__ = ["GHOST_OPACITY", "OUTLINE_COLOR", "check_render_goal", "draw_ghost", "overlay_goal"]

#: how strongly the ghost covers the frame where the goal objects are opaque
GHOST_OPACITY = 0.5
#: RGB of the goal objects' outline
OUTLINE_COLOR = (255, 255, 255)
# one objects-only renderer per view renderer (an env's render() renderer), dropped with it
_GHOST_RENDERERS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def check_render_goal(value: Any) -> bool:
    """``render_goal`` as given: ``True`` or ``False`` (anything else raises ``ValueError``)."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"render_goal must be True or False, got {value!r}")
    return bool(value)


def _empty_set() -> GaussianSet:
    z = np.zeros
    return GaussianSet(z((0, 3)), z((0, 4)), z((0, 3)), z((0,)), z((0, 1, 3)))


def _ghost_renderer(env, view):
    """The objects-only renderer that goes with ``view`` (the env's ``render()`` renderer)."""
    ghost = _GHOST_RENDERERS.get(view)
    if ghost is None:
        from ..scene_renderer import SceneRenderer

        w = env.world
        ghost = SceneRenderer(
            _empty_set(), list(w.objects), view.viewmats, view.Ks, view.width, view.height,
            background_color=(0.0, 0.0, 0.0), **w.splat_options, **env.render_settings.kwargs(),
        )  # fmt: skip
        _GHOST_RENDERERS[view] = ghost
    return ghost


def draw_ghost(frames: np.ndarray, ghost_rgb: np.ndarray, ghost_alpha: np.ndarray) -> np.ndarray:
    """``frames`` ``[..., H, W, 3]`` uint8 with a ghost composited over them: ``ghost_rgb`` (premultiplied:
    rendered over black) and ``ghost_alpha`` ``[..., H, W]`` in [0, 1] at :data:`GHOST_OPACITY`, and the
    ghost's outline in :data:`OUTLINE_COLOR`. Returns a new uint8 array."""
    a = GHOST_OPACITY * np.clip(ghost_alpha, 0.0, 1.0)[..., None]
    out = frames.astype(np.float32) * (1.0 - a) + GHOST_OPACITY * ghost_rgb.astype(np.float32)
    inside = ghost_alpha > 0.5
    edge = np.zeros_like(inside)
    edge[..., 1:, :] |= inside[..., 1:, :] != inside[..., :-1, :]
    edge[..., :, 1:] |= inside[..., :, 1:] != inside[..., :, :-1]
    out[edge & inside] = OUTLINE_COLOR
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def overlay_goal(env, frames: np.ndarray) -> np.ndarray:
    """``frames`` ``[V, H, W, 3]`` (the env's ``render()`` views of its current state) with the ghost of each
    object at its goal pose (``env.goal``) drawn over them."""
    view = env._view_renderer
    out = _ghost_renderer(env, view).render(env.goal, rgb=True, mask=False, depth=False)
    return draw_ghost(frames, out.rgb, out.alpha)
