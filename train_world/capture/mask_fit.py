"""Choosing an object's motion between the states by the masks themselves (known cameras).

The voxel hulls of :mod:`.silhouettes` tell turns apart only to about a voxel (a tenth of the object's radius):
on a small, irregular object two turns tens of degrees apart can fit the hulls equally well. The masks hold
more. Moved by the true motion, the first state's hull must cover the object's silhouette in every photo of the
second state and stay inside it, and the second state's hull, moved back, likewise in the first state's photos.
:func:`mask_cost` scores a motion by both, in pixels: how far the hulls' surface points land outside the
objects (from each photo's distance map to the nearest object pixel: a pixel of another object may hide this
one, so it costs nothing) and how far each pixel of the object's outline is from the nearest projected point.
:func:`choose_on_masks` takes the candidate with the lowest score, and among candidates within
:data:`MASK_TIE` of it the one whose rotation is closest to a preferred one (symmetric shapes score alike at
their equivalent turns; a score such as the colours', texture or the smallest turn decides there). Float64;
deterministic.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.ndimage import binary_erosion, map_coordinates
from scipy.spatial import cKDTree

from train_world.capture.alignment import rotation_angle_deg
from train_world.capture.silhouettes import SilhouetteView, surface_voxels

__all__ = ["MASK_TIE", "MAX_POINTS", "choose_on_masks", "mask_cost"]

#: surface points of each hull that are scored (every n-th, in voxel order)
MAX_POINTS = 800
#: candidates whose mask cost is within this fraction of the lowest count as equally good
MASK_TIE = 0.05


class _Views:
    """One state's photos of one object: projection matrices, distance maps (px) to the objects and the
    object's outline pixels."""

    def __init__(self, views: list[SilhouetteView], obj: int):
        self.P = [v.K @ v.w2c[:3, :4] for v in views]
        self.dist = [v.object_distance for v in views]
        self.outline = []
        for v in views:
            m = v.ids == obj
            # outline: the object's pixels with a 4-neighbour off it; the photo's edge is not an outline
            ys, xs = np.nonzero(m & ~binary_erosion(m, border_value=1))
            self.outline.append(np.stack([xs, ys], axis=1).astype(np.float64))

    def residuals(self, X: np.ndarray) -> np.ndarray:
        """Pixels outside the objects for each projected point of ``X [N,3]`` (points behind a camera or outside
        the photo are not scored), then for each outline pixel its distance beyond half a pixel to the nearest
        projection."""
        Xh = np.concatenate([X, np.ones((len(X), 1))], axis=1)
        out = []
        for P, dist, px in zip(self.P, self.dist, self.outline, strict=True):
            p = Xh @ P.T
            z = p[:, 2]
            front = z > 1e-12
            uv = p[front, :2] / z[front, None] - 0.5  # pixel centres at integers
            h, w = dist.shape
            ok = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
            out.append(map_coordinates(dist, [uv[ok, 1], uv[ok, 0]], order=1, mode="nearest"))
            if len(px):
                d = cKDTree(uv).query(px)[0] if len(uv) else np.full(len(px), float(max(h, w)))
                out.append(np.maximum(d - 0.5, 0.0))
        return np.concatenate(out) if out else np.zeros(0)


def _points(hull: tuple[np.ndarray, float]) -> np.ndarray:
    s = surface_voxels(*hull)
    return s if len(s) <= MAX_POINTS else s[:: int(np.ceil(len(s) / MAX_POINTS))]


def _cost(a: np.ndarray, b: np.ndarray, v1: _Views, v2: _Views, T: np.ndarray) -> float:
    R, t = T[:3, :3], T[:3, 3]
    r = np.concatenate([v2.residuals(a @ R.T + t), v1.residuals((b - t) @ R)])
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def mask_cost(
    hull1: tuple[np.ndarray, float],
    hull2: tuple[np.ndarray, float],
    views1: list[SilhouetteView],
    views2: list[SilhouetteView],
    obj: int,
    T: np.ndarray,
) -> float:
    """RMS pixels by which the motion ``T [4,4]`` (state 1 to state 2) of object ``obj`` disagrees with its
    masks (module docstring). ``hull1 = (points [N,3], voxel size)`` is the object's visual hull in state 1
    (:func:`.silhouettes.visual_hull`), ``views1`` that state's photos; likewise for state 2."""
    return _cost(
        _points(hull1), _points(hull2), _Views(views1, obj), _Views(views2, obj), np.asarray(T, float)
    )


def choose_on_masks(
    candidates: list[np.ndarray],
    hull1: tuple[np.ndarray, float],
    hull2: tuple[np.ndarray, float],
    views1: list[SilhouetteView],
    views2: list[SilhouetteView],
    obj: int,
    prefer: np.ndarray | None = None,
    rank: Callable[[np.ndarray], float] | None = None,
) -> tuple[int, float]:
    """The index of the candidate motion ``[4,4]`` that agrees best with the masks (:func:`mask_cost`;
    arguments as there), and its cost. Among the candidates within :data:`MASK_TIE` of the best: the one
    ``rank`` scores lowest (a score of motions, e.g. :func:`.appearance.colour_score`) when given, and of
    equally ranked ones the one whose rotation is closest to ``prefer [3,3]`` (default: no turn)."""
    a, b = _points(hull1), _points(hull2)
    v1, v2 = _Views(views1, obj), _Views(views2, obj)
    costs = [_cost(a, b, v1, v2, np.asarray(T, np.float64)) for T in candidates]
    costs = [c if np.isfinite(c) else np.inf for c in costs]  # nothing to score: never better than a score
    best = min(costs)
    prefer = np.eye(3) if prefer is None else np.asarray(prefer, np.float64)
    close = [i for i, c in enumerate(costs) if c <= best * (1.0 + MASK_TIE) or not np.isfinite(best)]
    ranks = {k: rank(np.asarray(candidates[k], np.float64)) if rank is not None else 0.0 for k in close}
    i = min(close, key=lambda k: (ranks[k], float(rotation_angle_deg(prefer.T @ candidates[k][:3, :3])), k))
    return i, costs[i]
