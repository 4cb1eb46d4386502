"""Collaborative co-pruning, co-pasting and the merged world (DSG-World sections "Co-Pruning" and
"Co-pasting").

**Co-pruning** (threshold ``tau`` in scene units, metres for synthetic captures): a Gaussian of field ``a``,
transferred into state ``b``, is pruned when its centre is farther than ``tau`` from every centre of field
``b``; the same the other way. Two restrictions keep Gaussians that the other field cannot explain because it
never saw their region: only Gaussians over the table (xy inside the table bounds padded by ``tau``) are
tested, and background Gaussians of ``a`` inside an object footprint of state ``b`` (the table under the
objects there) are never pruned.

**Co-pasting**: the merged background is ``G1``'s background outside the state-1 object footprints plus
``G2``'s background inside them (where state 2 saw the table), excluding any ``G2`` Gaussian that also lies
in a state-2 footprint. Footprints are the convex hulls, in the table plane, of each object's Gaussian
centres placed at that state's pose, dilated by ``margin``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree

__all__ = [
    "co_paste_background",
    "co_prune_masks",
    "footprint_contains",
    "object_footprints_xy",
    "robust_object_points",
]


def robust_object_points(points: np.ndarray, quantile: float = 0.98, slack: float = 1.25) -> np.ndarray:
    """Drop outlying centres ``[M,3]``: keep those within ``slack`` x the ``quantile`` distance from the
    median point."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 8:
        return pts
    d = np.linalg.norm(pts - np.median(pts, axis=0), axis=1)
    return pts[d <= slack * np.quantile(d, quantile) + 1e-12]


def object_footprints_xy(object_points: list[np.ndarray]) -> list[np.ndarray | None]:
    """Per object, the half-plane equations ``[E,3]`` (``n_x x + n_y y + d <= 0`` inside) of the convex hull
    of its points' xy (world frame), or None when it has fewer than 3 non-collinear points."""
    out: list[np.ndarray | None] = []
    for pts in object_points:
        xy = np.asarray(pts, dtype=np.float64).reshape(-1, 3)[:, :2]
        if len(xy) < 3:
            out.append(None)
            continue
        try:
            out.append(ConvexHull(xy).equations.copy())
        except QhullError:
            out.append(None)
    return out


def footprint_contains(
    footprints: list[np.ndarray | None], xy: np.ndarray, margin: float = 0.0
) -> np.ndarray:
    """Bool ``[N]``: the point lies within ``margin`` of (or inside) any footprint."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    inside = np.zeros(len(xy), dtype=bool)
    for eq in footprints:
        if eq is None:
            continue
        sd = xy @ eq[:, :2].T + eq[:, 2]  # [N,E] signed distances to the edge lines (unit normals)
        inside |= sd.max(axis=1) <= margin
    return inside


def _in_table(xy: np.ndarray, table_bounds: np.ndarray | None, pad: float) -> np.ndarray:
    if table_bounds is None:
        return np.ones(len(xy), dtype=bool)
    lo, hi = np.asarray(table_bounds, dtype=np.float64)[:, :2]
    return np.all((xy >= lo - pad) & (xy <= hi + pad), axis=1)


def co_prune_masks(
    means_1_in_2: np.ndarray,
    means_2: np.ndarray,
    means_2_in_1: np.ndarray,
    means_1: np.ndarray,
    tau: float,
    *,
    background_1: np.ndarray | None = None,
    background_2: np.ndarray | None = None,
    footprints_1: list[np.ndarray | None] | None = None,
    footprints_2: list[np.ndarray | None] | None = None,
    table_bounds: np.ndarray | None = None,
    footprint_margin: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Prune masks ``([N1], [N2])`` bool (True: remove) of co-pruning (module docstring).

    ``means_1_in_2``: ``T_1->2(G1)`` centres; ``means_2``: ``G2`` centres; ``means_2_in_1``, ``means_1`` the
    reverse. ``background_*``: bool masks of the background Gaussians; ``footprints_*``: object footprints of
    each state (:func:`object_footprints_xy`); ``table_bounds``: ``[[xmin,ymin,.],[xmax,ymax,.]]`` (None: test
    everything).
    """

    def one_way(src_moved, dst, bg, fp_dst):
        src_moved = np.asarray(src_moved, dtype=np.float64).reshape(-1, 3)
        dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
        if len(src_moved) == 0:
            return np.zeros(0, dtype=bool)
        if len(dst) == 0:
            far = np.ones(len(src_moved), dtype=bool)
        else:
            dist, _ = cKDTree(dst).query(src_moved, k=1)
            far = dist > tau
        test = _in_table(src_moved[:, :2], table_bounds, tau)
        if bg is not None and fp_dst is not None:
            test &= ~(np.asarray(bg, bool) & footprint_contains(fp_dst, src_moved[:, :2], footprint_margin))
        return far & test

    return (
        one_way(means_1_in_2, means_2, background_1, footprints_2),
        one_way(means_2_in_1, means_1, background_2, footprints_1),
    )


def co_paste_background(
    bg_means_1: np.ndarray,
    bg_means_2: np.ndarray,
    footprints_1: list[np.ndarray | None],
    footprints_2: list[np.ndarray | None],
    margin: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Keep masks ``([B1], [B2])`` bool of co-pasting: ``G1`` background outside the state-1 footprints, and
    ``G2`` background inside them but outside the state-2 footprints."""
    xy1 = np.asarray(bg_means_1, dtype=np.float64).reshape(-1, 3)[:, :2]
    xy2 = np.asarray(bg_means_2, dtype=np.float64).reshape(-1, 3)[:, :2]
    keep1 = ~footprint_contains(footprints_1, xy1, margin)
    keep2 = footprint_contains(footprints_1, xy2, margin) & ~footprint_contains(footprints_2, xy2, margin)
    return keep1, keep2
