"""The table frame of a photo capture: +z up from the table top, table top at z = 0, scale set.

:func:`fit_table_plane` fits the support plane robustly (RANSAC then least squares) to the background points
``[N,3]`` near the objects, its normal pointing toward the cameras. :func:`table_frame` builds the similarity
``world_from_sfm`` (reconstruction frame -> table frame): origin at the objects' centre dropped onto the
table, x along the table points' main in-plane direction, and units either metres (``metres_per_unit``:
metres per normalised unit) or arbitrary ("unknown"), normalised so that the median camera is 1 unit from
the origin. Float64; deterministic (seeded RANSAC).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Plane", "TableFrame", "fit_table_plane", "table_frame"]

#: RANSAC inlier distance as a fraction of the median camera distance to the objects
PLANE_THRESHOLD = 0.006
#: table bounds: percentiles of the in-plane coordinates of the plane's inliers
BOUNDS_PERCENTILES = (1.0, 99.0)


class FrameError(ValueError):
    """No table plane could be found (the message says why)."""


@dataclass(frozen=True)
class Plane:
    """``normal [3]`` (unit, toward the cameras) and ``offset`` with ``normal . x + offset = 0`` on the plane;
    ``inliers [N]`` marks the points used; ``rms`` is their distance RMS (reconstruction units)."""

    normal: np.ndarray
    offset: float
    inliers: np.ndarray
    rms: float

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distances ``[N]`` of ``points [N,3]`` above the plane."""
        return np.asarray(points, np.float64).reshape(-1, 3) @ self.normal + self.offset


@dataclass(frozen=True)
class TableFrame:
    """``world_from_sfm [4,4]`` similarity (``scale * R | t``), ``scale`` (output units per reconstruction
    unit), ``units`` ("metres" or "unknown"), table ``bounds [2,3]`` (min and max corner, z = 0) and the
    plane it came from."""

    world_from_sfm: np.ndarray
    scale: float
    units: str
    bounds: np.ndarray
    plane: Plane

    def points(self, p: np.ndarray) -> np.ndarray:
        """``p [N,3]`` (reconstruction frame) in the table frame."""
        m = self.world_from_sfm
        return np.asarray(p, np.float64).reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]

    def rigid(self, T: np.ndarray) -> np.ndarray:
        """A rigid motion ``[4,4]`` of the reconstruction frame expressed in the table frame."""
        return self.world_from_sfm @ np.asarray(T, np.float64) @ np.linalg.inv(self.world_from_sfm)

    def camera_to_world(self, w2c: np.ndarray) -> np.ndarray:
        """OpenCV camera-to-world ``[4,4]`` in the table frame of a world-to-camera ``w2c`` (reconstruction)."""
        c2w = np.linalg.inv(np.asarray(w2c, np.float64))
        out = np.eye(4)
        rot = self.world_from_sfm[:3, :3] / self.scale
        out[:3, :3] = rot @ c2w[:3, :3]
        out[:3, 3] = self.points(c2w[:3, 3])[0]
        u, _, vt = np.linalg.svd(out[:3, :3])
        out[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        return out


def _lsq_plane(p: np.ndarray) -> tuple[np.ndarray, float]:
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[-1]
    return n, -float(n @ c)


def fit_table_plane(
    points: np.ndarray, anchors: np.ndarray, camera_centres: np.ndarray, seed: int = 0, iters: int = 2000
) -> Plane:
    """The support plane under the objects: RANSAC over background ``points [N,3]`` within reach of the
    objects' centres ``anchors [K,3]`` (inlier distance :data:`PLANE_THRESHOLD` of the median camera
    distance), refined by least squares on its inliers; the normal points toward ``camera_centres [V,3]``
    and the inliers are then taken among all points."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    a = np.asarray(anchors, np.float64).reshape(-1, 3)
    cams = np.asarray(camera_centres, np.float64).reshape(-1, 3)
    centre = a.mean(axis=0)
    cam_dist = float(np.median(np.linalg.norm(cams - centre, axis=1)))
    thr = PLANE_THRESHOLD * cam_dist
    reach = max(2.0 * float(np.max(np.linalg.norm(a - centre, axis=1), initial=0.0)), 0.5 * cam_dist)
    near = p[np.linalg.norm(p - centre, axis=1) <= reach]
    if len(near) < 10:
        raise FrameError(
            f"only {len(near)} background points near the objects; the table around them needs texture "
            "(or photos that show more of it)"
        )
    rng = np.random.default_rng(seed)
    best, best_cost = None, np.inf
    for _ in range(iters):
        s = near[rng.choice(len(near), 3, replace=False)]
        n = np.cross(s[1] - s[0], s[2] - s[0])
        if np.linalg.norm(n) < 1e-12:
            continue
        n /= np.linalg.norm(n)
        d = np.abs(near @ n - n @ s[0])
        cost = np.minimum(d, thr).sum()
        if cost < best_cost:
            best, best_cost = (n, -float(n @ s[0])), cost
    if best is None:
        raise FrameError("the background points near the objects are degenerate (all on one line)")
    n, off = best
    for _ in range(3):
        inl = np.abs(near @ n + off) < thr
        n, off = _lsq_plane(near[inl])
    if np.median(cams @ n + off) < 0:
        n, off = -n, -off
    inl_all = np.abs(p @ n + off) < thr
    return Plane(n, off, inl_all, float(np.sqrt(np.mean((p[inl_all] @ n + off) ** 2))))


def table_frame(
    plane: Plane,
    points: np.ndarray,
    object_centres: np.ndarray,
    camera_centres: np.ndarray,
    metres_per_unit: float | None = None,
) -> TableFrame:
    """The table frame (module docstring) from ``plane`` fitted to ``points [N,3]``, the objects' centres
    ``[K,3]`` and the camera centres ``[V,3]`` (all in the reconstruction frame)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    z = plane.normal
    c = np.asarray(object_centres, np.float64).reshape(-1, 3).mean(axis=0)
    origin = c - plane.height(c)[0] * z
    tab = p[plane.inliers] - origin
    inplane = tab - np.outer(tab @ z, z)
    _, _, vt = np.linalg.svd(inplane - inplane.mean(axis=0), full_matrices=False)
    x = vt[0] - (vt[0] @ z) * z
    x /= np.linalg.norm(x)
    cams = np.asarray(camera_centres, np.float64).reshape(-1, 3)
    if (cams[0] - origin) @ x < 0:
        x = -x
    y = np.cross(z, x)
    rot = np.stack([x, y, z])
    unit = 1.0 / float(np.median(np.linalg.norm(cams - origin, axis=1)))
    scale = unit * (float(metres_per_unit) if metres_per_unit else 1.0)
    m = np.eye(4)
    m[:3, :3] = scale * rot
    m[:3, 3] = -scale * rot @ origin
    xy = (tab @ rot.T)[:, :2] * scale
    lo, hi = np.percentile(xy, BOUNDS_PERCENTILES, axis=0)
    bounds = np.array([[lo[0], lo[1], 0.0], [hi[0], hi[1], 0.0]])
    units = "metres" if metres_per_unit else "unknown"
    return TableFrame(m, scale, units, bounds, plane)
