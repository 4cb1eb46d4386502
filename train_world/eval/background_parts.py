"""Which part of the scene a background pixel shows, from the ground truth's depth and table.

A capture whose scene has a table (``scene.json``'s ``table``: ``bounds [2, 3]`` and ``top_z`` in a +z-up
frame) and depth maps tells, for every pixel, the surface point it shows. The background splits into:

- ``table_top``: points within ``TABLE_TOL`` of the table top's height and inside its bounds (grown by that
  tolerance);
- ``floor``: points on a horizontal surface (normal within ``HORIZONTAL_DEG`` of +z) more than ``BELOW_TOL``
  below the table top: the floor a tabletop stands on, a low shelf;
- ``other``: the rest: walls, the table's sides, and pixels without depth.

Both tolerances are fractions of the median distance from the cameras to the table top's centre, so they hold
in any unit. A surface's normal is that of the points of neighbouring pixels (central differences of the
back-projected depth map), so a one-pixel rim along every depth jump counts as ``other``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from dsg_gym.cameras import camera_centres, depth_points

if TYPE_CHECKING:
    from train_world.capture.loader import Capture

__all__ = [
    "BELOW_TOL",
    "HORIZONTAL_DEG",
    "PARTS",
    "TABLE_TOL",
    "background_parts",
    "capture_background_parts",
]

PARTS = ("table_top", "floor", "other")
#: how far from the table top's height a point still lies on it (fraction of the camera distance)
TABLE_TOL = 0.01
#: how far below the table top a horizontal surface must lie to count as floor (fraction of the camera distance)
BELOW_TOL = 0.05
#: how far from +z a surface's normal may tilt and the surface still count as horizontal (degrees)
HORIZONTAL_DEG = 30.0


def background_parts(
    depth: np.ndarray, viewmat: np.ndarray, K: np.ndarray, bounds: np.ndarray, top_z: float, scale: float
) -> dict[str, np.ndarray]:
    """Boolean masks ``[H, W]`` of :data:`PARTS` (module docstring), which partition the view: ``depth [H, W]``
    along the optical axis (0: none), world-to-camera ``viewmat [4, 4]``, OpenCV ``K [3, 3]``, the table's
    ``bounds [2, 3]`` (min, max corners; x and y are used) and ``top_z`` in the same +z-up frame; ``scale``:
    the length the tolerances are fractions of (the cameras' distance to the table). In float64."""
    d = np.asarray(depth, np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be a map [H, W], got shape {d.shape}")
    if not scale > 0:
        raise ValueError(f"scale must be positive, got {scale}")
    p = depth_points(d, viewmat, K)
    has = d > 0
    b = np.asarray(bounds, np.float64)
    tol = TABLE_TOL * scale
    inside = (
        (p[..., 0] >= b[0, 0] - tol) & (p[..., 0] <= b[1, 0] + tol)
        & (p[..., 1] >= b[0, 1] - tol) & (p[..., 1] <= b[1, 1] + tol)
    )  # fmt: skip
    table = has & inside & (np.abs(p[..., 2] - top_z) <= tol)
    n = np.cross(np.gradient(p, axis=1), np.gradient(p, axis=0))
    norm = np.linalg.norm(n, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        up = np.where(norm > 0, np.abs(n[..., 2]) / norm, 0.0)
    # a normal needs depth at the pixel and at its four neighbours (clamped at the image's edge)
    pad = np.pad(has, 1, mode="edge")
    whole = has & pad[:-2, 1:-1] & pad[2:, 1:-1] & pad[1:-1, :-2] & pad[1:-1, 2:]
    horizontal = whole & (up >= np.cos(np.radians(HORIZONTAL_DEG)))
    floor = horizontal & ~table & (p[..., 2] < top_z - BELOW_TOL * scale)
    return {"table_top": table, "floor": floor, "other": ~(table | floor)}


def capture_background_parts(
    capture: Capture, state: str, indices: Sequence[int]
) -> list[dict[str, np.ndarray]] | None:
    """:func:`background_parts` of views ``indices`` of ``state`` of the loaded ``capture``, or None when it
    has no depth maps there, no table with bounds, or a frame other than +z up."""
    scene = capture.metadata
    table = scene.get("table")
    views = capture.states.get(state)
    if (
        str(scene.get("up_axis", "+z")).lstrip("+") != "z"
        or not isinstance(table, dict)
        or capture.table_bounds is None
        or views is None
        or views.depths is None
    ):
        return None
    bounds = capture.table_bounds
    top = float(table.get("top_z", bounds[1, 2]))
    vm, Ks, depths = views.viewmats.double().numpy(), views.Ks.double().numpy(), views.depths.numpy()
    centre = np.r_[(bounds[0, :2] + bounds[1, :2]) / 2, top]
    scale = float(np.median(np.linalg.norm(camera_centres(vm) - centre, axis=1)))
    return [background_parts(depths[i], vm[i], Ks[i], bounds, top, scale) for i in indices]
