"""The renderer options a world is trained and rendered with (torch-free, so the world reader can use it).

``rasterize_mode``: "classic" (3DGS) or "antialiased" (Mip-Splatting's 2D Mip filter, gsplat's name);
``eps2d``: the low-pass in px^2 added to each projected 2D covariance (3DGS and gsplat: 0.3). See
:func:`dsg_gym.splat.rasterize`. ``compositing``: "sorted" (one depth-sorted list per tile, 3DGS) or "layers"
(background and objects splatted apart and merged per pixel by expected depth: :mod:`dsg_gym.splat.layers`).
"""

from __future__ import annotations

import math

__all__ = [
    "COMPOSITING_MODES",
    "DEFAULT_EPS2D",
    "LAYER_MARGIN",
    "RASTERIZE_MODES",
    "check_compositing",
    "check_splat_options",
]

RASTERIZE_MODES = ("classic", "antialiased")
COMPOSITING_MODES = ("sorted", "layers")
#: two layers: the objects' layer goes in front at a pixel unless the background's expected depth is nearer by more
#: than this fraction of it. An object's Gaussians are centred inside it, so at its base, where it meets the table,
#: its expected depth lies a few millimetres behind its visible surface and within that of the table's.
LAYER_MARGIN = 0.01
DEFAULT_EPS2D = 0.3


def check_splat_options(rasterize_mode, eps2d) -> tuple[str, float]:
    """``(rasterize_mode, float(eps2d))``; ValueError naming the bad one."""
    if rasterize_mode not in RASTERIZE_MODES:
        raise ValueError(f"rasterize_mode must be one of {RASTERIZE_MODES}, got {rasterize_mode!r}")
    if (
        isinstance(eps2d, bool)
        or not isinstance(eps2d, (int, float))
        or not (math.isfinite(eps2d) and 0 < eps2d <= 10)
    ):
        raise ValueError(f"eps2d must be a number in (0, 10] px^2, got {eps2d!r}")
    return str(rasterize_mode), float(eps2d)


def check_compositing(mode) -> str:
    """``mode`` when it is one of :data:`COMPOSITING_MODES`; else ValueError naming it."""
    if mode not in COMPOSITING_MODES:
        raise ValueError(f"compositing must be one of {COMPOSITING_MODES}, got {mode!r}")
    return str(mode)
