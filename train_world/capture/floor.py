"""The floor around a tabletop capture: a horizontal plane below the table from the structure-from-motion
points, and depth maps put on it where they roughly agree.

A depth fit (:mod:`.fitted_depth`) leaves the room around the table far off (a tenth of its depth and more),
the floor included, although a textured floor gives the structure-from-motion points that pin it down.
:func:`fit_floor` finds the floor in a capture's table frame (+z up, table top at z = 0): the height below the
table with the most points within a band, among the points beyond the table's bounds; None when too few points
or too small a share of them agree. :func:`floor_depth` moves a depth map's background pixels onto it: those
whose point lies nearer the floor than the table top (so never the table nor its edge), whose ray meets the
floor inside the extent of the floor's points, and whose depth is within a tolerance of that meeting's.
Lengths scale with ``ref``, a typical camera distance to the table (the frame's units may be arbitrary).
Float64; deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dsg_gym.cameras import camera_centres

__all__ = ["FLOOR_BAND", "MIN_FLOOR_POINTS", "Floor", "fit_floor", "floor_depth"]

#: half-width of the floor's inlier band, and the margin around the table's bounds, times ``ref``
FLOOR_BAND, TABLE_MARGIN = 0.008, 0.04
#: a floor needs this many points in its band, and this share of the points beyond the table
MIN_FLOOR_POINTS, MIN_FLOOR_SHARE = 30, 0.3
#: the floor's extent: these percentiles of its points' x and y
EXTENT_PERCENTILES = (2.0, 98.0)


@dataclass(frozen=True)
class Floor:
    """The floor plane ``z`` (table frame, below the table top), the extent ``lo [2]``, ``hi [2]`` (x, y) of
    the ``points`` structure-from-motion points in its band, of ``candidates`` beyond the table."""

    z: float
    lo: np.ndarray
    hi: np.ndarray
    points: int
    candidates: int

    def to_dict(self) -> dict:
        return {"z": round(self.z, 6), "extent": [np.round(self.lo, 6).tolist(), np.round(self.hi, 6).tolist()],
                "points": self.points, "candidates": self.candidates}  # fmt: skip


def _beyond_table(xy: np.ndarray, bounds: np.ndarray, margin: float) -> np.ndarray:
    lo, hi = bounds[0, :2] - margin, bounds[1, :2] + margin
    return ((xy < lo) | (xy > hi)).any(axis=-1)


def fit_floor(points: np.ndarray, bounds: np.ndarray, ref: float) -> Floor | None:
    """The floor (module docstring) of structure-from-motion ``points [N,3]`` in the table frame around the
    table of ``bounds [2,3]`` (min and max corner); None when there is none to find."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    bounds = np.asarray(bounds, np.float64)
    if ref <= 0 or not np.isfinite(ref):
        raise ValueError(f"the reference length must be positive and finite, got {ref}")
    band, margin = FLOOR_BAND * ref, TABLE_MARGIN * ref
    cand = p[np.isfinite(p).all(axis=1)]
    cand = cand[_beyond_table(cand[:, :2], bounds, margin) & (cand[:, 2] < -margin)]
    if len(cand) < MIN_FLOOR_POINTS:
        return None
    z = np.sort(cand[:, 2])
    counts = np.searchsorted(z, z + band, side="right") - np.searchsorted(z, z - band, side="left")
    best = int(np.argmax(counts))  # the lowest of equally supported heights: np.argmax takes the first
    inliers = cand[np.abs(cand[:, 2] - z[best]) <= band]
    if len(inliers) < max(MIN_FLOOR_POINTS, MIN_FLOOR_SHARE * len(cand)):
        return None
    lo, hi = np.percentile(inliers[:, :2], EXTENT_PERCENTILES, axis=0)
    return Floor(float(np.median(inliers[:, 2])), lo, hi, len(inliers), len(cand))


def floor_depth(depth: np.ndarray, background: np.ndarray, viewmat: np.ndarray, K: np.ndarray, floor: Floor,
                tolerance: float) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``depth [H,W]`` (camera z, 0 = none) of the camera ``viewmat [4,4]`` (world-to-camera, OpenCV), ``K
    [3,3]`` with its ``background [H,W]`` pixels put on ``floor`` where their points lie nearer the floor than
    the table top, their rays meet the floor inside its extent, and their depth is within ``tolerance`` (a
    fraction) of that meeting's; returns the new map (float64) and the pixels moved."""
    d = np.asarray(depth, np.float64)
    H, W = d.shape
    vm, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    R, centre = vm[:3, :3], camera_centres(vm)
    v, u = np.mgrid[0:H, 0:W] + 0.5
    ray = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1) @ R  # R^T x
    point = centre + ray * d[..., None]  # world points at depth d (camera z)
    with np.errstate(divide="ignore", invalid="ignore"):
        z_floor = np.where(ray[..., 2] < -1e-12, (floor.z - centre[2]) / ray[..., 2], np.inf)
    hit = centre[:2] + ray[..., :2] * np.where(np.isfinite(z_floor), z_floor, 0.0)[..., None]
    on_floor = np.isfinite(z_floor) & (z_floor > 0) & ((hit >= floor.lo) & (hit <= floor.hi)).all(axis=-1)
    low = point[..., 2] < floor.z / 2  # nearer the floor than the table top: not the table, nor its edge
    move = np.asarray(background, bool) & (d > 0) & low & on_floor
    move &= np.abs(np.where(move, z_floor, 0.0) - d) <= tolerance * np.where(move, z_floor, 1.0)
    return np.where(move, z_floor, d), move
