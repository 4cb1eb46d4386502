"""Pseudo-states for ``L_pseudo``: object configurations that are collision-free and on the table.

Each object gets a planar pose: its reference orientation turned by a yaw about the table normal (+z), its
reference height kept, its centre ``(x, y)`` uniform in the table bounds shrunk by the object's footprint
radius. Footprints are discs: the radius of the object's Gaussians around its own origin in the table plane
(:func:`footprint_radii`), so any yaw keeps the disc. Two objects are compatible when their discs are at least
``margin`` apart. Objects are placed one at a time in a random order by rejection sampling; after
``max_tries`` failures the whole configuration is redrawn, and after ``max_restarts`` the reference poses are
returned (state 1 itself is a valid configuration), so the sampler always terminates.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["footprint_radii", "pseudo_state_valid", "sample_pseudo_state"]


def footprint_radii(
    object_points: list[np.ndarray], quantile: float = 0.98, default: float = 0.05, pad: float = 0.0
) -> np.ndarray:
    """Disc radius ``[K]`` per object from its Gaussian centres ``[M_k,3]`` in the object's own frame: the
    ``quantile`` of their distance from the object's origin in the xy plane (robust to a few floaters), plus
    ``pad``; ``default`` for an object with no Gaussians."""
    out = []
    for pts in object_points:
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
        r = default if len(pts) == 0 else float(np.quantile(np.linalg.norm(pts[:, :2], axis=1), quantile))
        out.append(r + pad)
    return np.asarray(out, dtype=np.float64)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pseudo_state_valid(
    poses: np.ndarray, radii: np.ndarray, table_bounds: np.ndarray, margin: float = 0.0, tol: float = 1e-9
) -> bool:
    """True when every footprint disc lies inside the table's xy bounds and no two discs come closer than
    ``margin``."""
    poses = np.asarray(poses, dtype=np.float64)
    lo, hi = np.asarray(table_bounds, dtype=np.float64)[:, :2]
    xy = poses[:, :2, 3]
    r = np.asarray(radii, dtype=np.float64)
    if np.any(xy - r[:, None] < lo - tol) or np.any(xy + r[:, None] > hi + tol):
        return False
    for i in range(len(xy)):
        for j in range(i + 1, len(xy)):
            if np.linalg.norm(xy[i] - xy[j]) < r[i] + r[j] + margin - tol:
                return False
    return True


def sample_pseudo_state(
    reference_poses: np.ndarray,
    radii: np.ndarray,
    table_bounds: np.ndarray,
    rng: np.random.Generator,
    *,
    margin: float = 0.005,
    max_tries: int = 100,
    max_restarts: int = 20,
) -> np.ndarray:
    """A random collision-free configuration ``[K,4,4]`` (see the module docstring)."""
    ref = np.asarray(reference_poses, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    lo, hi = np.asarray(table_bounds, dtype=np.float64)[:, :2]
    k = len(ref)
    for _ in range(max_restarts):
        out = ref.copy()
        placed: list[int] = []
        ok = True
        for i in rng.permutation(k):
            a, b = lo + radii[i], hi - radii[i]
            if np.any(a > b):
                ok = False
                break
            for _ in range(max_tries):
                xy = rng.uniform(a, b)
                if all(np.linalg.norm(xy - out[j, :2, 3]) >= radii[i] + radii[j] + margin for j in placed):
                    break
            else:
                ok = False
                break
            out[i, :3, :3] = _rot_z(float(rng.uniform(-math.pi, math.pi))) @ ref[i, :3, :3]
            out[i, :2, 3] = xy
            placed.append(int(i))
        if ok:
            return out
    return ref.copy()
