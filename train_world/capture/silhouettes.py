"""Object shape and motion from masks alone (known cameras): visual hulls and their alignment.

Textureless objects (a plain white ball) give no features to match; their masks still pin them down. For
one object in one state, :func:`object_centre` intersects the rays through its mask centroids and
:func:`visual_hull` carves a voxel grid around that centre with every view's mask (a pixel of another object
does not carve: it may hide this one) and cuts it at the table plane. :func:`hull_fits` fits the first
state's hull to the second's by trimmed ICP from several starting turns about the table normal (the candidates
:mod:`.mask_fit` chooses from); :func:`refine_hull_alignment` refines a given motion locally;
:func:`fit_into_larger` places the smaller of two hulls inside the larger when they disagree;
:func:`symmetric_fits` lists the motions a symmetric shape cannot tell from a given one (what colours then
choose among, :mod:`.appearance`).
Float64 throughout; deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numba as nb
import numpy as np
from scipy.ndimage import distance_transform_edt
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from train_world.capture.alignment import umeyama

__all__ = [
    "SilhouetteView",
    "hull_cost",
    "hull_fits",
    "object_centre",
    "refine_hull_alignment",
    "fit_into_larger",
    "surface_voxels",
    "symmetric_fits",
    "visual_hull",
]

#: voxels along each side of the carving grid
HULL_RESOLUTION = 64
#: fraction of a voxel's informative views that may see background there (mask noise)
CARVE_TOLERANCE = 0.03
#: fraction of the views that see a voxel in the image that must see the object there (the others may see
#: another object in front of it)
MIN_SEEN = 0.5
#: starting turns (degrees) about the table normal tried by :func:`hull_fits`
START_TURNS = tuple(range(0, 360, 30))
#: turns (degrees) about the table normal, each also upside down, tried by :func:`symmetric_fits`
SYMMETRY_TURNS = tuple(range(0, 360, 15))


@dataclass(frozen=True)
class SilhouetteView:
    """One view's object ids ``ids [h,w]`` uint8 with its ``K [3,3]`` (for that size) and OpenCV
    world-to-camera ``w2c [4,4]``."""

    ids: np.ndarray
    K: np.ndarray
    w2c: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """The camera centre ``[3]``."""
        return -self.w2c[:3, :3].T @ self.w2c[:3, 3]

    @cached_property
    def object_distance(self) -> np.ndarray:
        """``[h,w]`` float64: each pixel's distance in pixels to the nearest pixel of any object (0 on the
        objects); computed once per view."""
        return distance_transform_edt(self.ids == 0)


def object_centre(views: list[SilhouetteView], obj: int) -> tuple[np.ndarray, float, int]:
    """``(centre [3], radius, views used)``: least-squares intersection of the rays through the object's
    mask centroids, and its rough radius from the mask areas (views where the mask touches the border are
    skipped)."""
    A, b, radii = np.zeros((3, 3)), np.zeros(3), []
    rows = []
    for v in views:
        ys, xs = np.nonzero(v.ids == obj)
        h, w = v.ids.shape
        if len(xs) < 4 or xs.min() == 0 or ys.min() == 0 or xs.max() == w - 1 or ys.max() == h - 1:
            continue
        d = np.linalg.solve(v.K, np.array([xs.mean() + 0.5, ys.mean() + 0.5, 1.0]))
        rot = v.w2c[:3, :3]
        o = -rot.T @ v.w2c[:3, 3]
        d = rot.T @ d
        d /= np.linalg.norm(d)
        proj = np.eye(3) - np.outer(d, d)
        A += proj
        b += proj @ o
        rows.append((o, d, np.sqrt(len(xs) / np.pi) / v.K[0, 0]))
    if len(rows) < 2:
        return np.full(3, np.nan), float("nan"), len(rows)
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    for o, d, ang in rows:
        radii.append(ang * float(np.dot(centre - o, d)))
    return centre, float(np.median(radii)), len(rows)


def visual_hull(
    views: list[SilhouetteView],
    obj: int,
    centre: np.ndarray,
    radius: float,
    plane: tuple[np.ndarray, float] | None = None,
    resolution: int = HULL_RESOLUTION,
) -> tuple[np.ndarray, float]:
    """Occupied voxel centres ``[N,3]`` of the object's visual hull in a cube of side ``6 * radius`` around
    ``centre`` (cut below ``plane = (normal, offset)``) and the voxel size."""
    half = 3.0 * radius
    step = 2.0 * half / resolution
    g = (np.arange(resolution) + 0.5) * step - half
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3) + np.asarray(centre, np.float64)
    if plane is not None:
        X = X[X @ plane[0] + plane[1] > 0.0]
    inside = np.zeros(len(X), np.int32)
    outside = np.zeros(len(X), np.int32)
    seen = np.zeros(len(X), np.int32)
    X = np.ascontiguousarray(X)
    for v in views:
        K, w2c = np.asarray(v.K, np.float64), np.ascontiguousarray(v.w2c[:3], np.float64)
        ids = np.ascontiguousarray(v.ids, np.uint8)
        _carve_view(X, w2c, K[0, 0], K[1, 1], K[0, 2], K[1, 2], ids, obj, inside, outside, seen)
    keep = (inside >= 2) & (outside <= CARVE_TOLERANCE * (inside + outside)) & (inside >= MIN_SEEN * seen)
    return X[keep], step


@nb.njit(cache=True)
def _carve_view(X, w2c, fx, fy, cx, cy, ids, obj, inside, outside, seen):  # pragma: no cover - compiled
    """Count, for every point of ``X [N,3]``, whether one view (OpenCV ``w2c [3,4]``, pinhole intrinsics, object
    ids ``ids [h,w]``) sees it in the image (``seen``), on object ``obj`` (``inside``) or on background
    (``outside``); the pixel is ``(int(u), int(v))`` of the projection ``(u, v)``, in the image when
    ``0 <= u < w`` and ``0 <= v < h``."""
    h, wd = ids.shape
    for i in range(X.shape[0]):
        x, y, z = X[i, 0], X[i, 1], X[i, 2]
        c2 = w2c[2, 0] * x + w2c[2, 1] * y + w2c[2, 2] * z + w2c[2, 3]
        if not c2 > 0.0:
            continue
        u = fx * (w2c[0, 0] * x + w2c[0, 1] * y + w2c[0, 2] * z + w2c[0, 3]) / c2 + cx
        v = fy * (w2c[1, 0] * x + w2c[1, 1] * y + w2c[1, 2] * z + w2c[1, 3]) / c2 + cy
        if u >= 0.0 and u < wd and v >= 0.0 and v < h:
            seen[i] += 1
            label = ids[int(v), int(u)]
            if label == obj:
                inside[i] += 1
            elif label == 0:
                outside[i] += 1


def surface_voxels(points: np.ndarray, step: float) -> np.ndarray:
    """The voxels of ``points`` with at least one empty 6-neighbour."""
    if len(points) == 0:
        return points
    key = np.round((points - points.min(axis=0)) / step).astype(np.int64)
    occupied = {tuple(k) for k in key}
    out = []
    for i, k in enumerate(key):
        for dk in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)):
            if (k[0] + dk[0], k[1] + dk[1], k[2] + dk[2]) not in occupied:
                out.append(i)
                break
    return points[out]


def _icp(src: np.ndarray, dst_tree: cKDTree, dst: np.ndarray, T: np.ndarray, iters: int, trim: float):
    for _ in range(iters):
        moved = src @ T[:3, :3].T + T[:3, 3]
        d, j = dst_tree.query(moved)
        keep = d <= np.quantile(d, trim)
        _, rot, t = umeyama(src[keep], dst[j[keep]], with_scale=False)
        T_new = np.eye(4)
        T_new[:3, :3], T_new[:3, 3] = rot, t
        if np.abs(T_new - T).max() < 1e-10:
            T = T_new
            break
        T = T_new
    return T


def _cost(
    src: np.ndarray, dst: np.ndarray, T: np.ndarray, src_tree: cKDTree, dst_tree: cKDTree, trim: float
) -> float:
    moved = src @ T[:3, :3].T + T[:3, 3]
    back = (dst - T[:3, 3]) @ T[:3, :3]
    d1, _ = dst_tree.query(moved)
    d2, _ = src_tree.query(back)
    d = np.concatenate([np.sort(d1)[: int(trim * len(d1))], np.sort(d2)[: int(trim * len(d2))]])
    return float(np.sqrt(np.mean(d**2)))


def hull_cost(src: np.ndarray, dst: np.ndarray, step: float, T: np.ndarray, trim: float = 0.9) -> float:
    """Symmetric trimmed RMS distance between the surfaces of hulls ``dst`` and ``T src``."""
    a, b = surface_voxels(src, step), surface_voxels(dst, step)
    return _cost(a, b, np.asarray(T, np.float64), cKDTree(a), cKDTree(b), trim)


def refine_hull_alignment(
    src: np.ndarray, dst: np.ndarray, step: float, T: np.ndarray, trim: float = 0.9
) -> tuple[np.ndarray, float]:
    """Trimmed ICP of the hulls' surfaces from ``T`` (a local refinement) and the resulting
    :func:`hull_cost`."""
    a, b = surface_voxels(src, step), surface_voxels(dst, step)
    ta, tb = cKDTree(a), cKDTree(b)
    T = _icp(a, tb, b, np.asarray(T, np.float64), 40, trim)
    return T, _cost(a, b, T, ta, tb, trim)


def hull_fits(
    src: np.ndarray,
    dst: np.ndarray,
    step: float,
    up: np.ndarray,
    starts: list[np.ndarray] | None = None,
    trim: float = 0.9,
) -> list[tuple[float, np.ndarray]]:
    """``(hull cost, T [4,4])`` of the trimmed ICP fit from every turn of :data:`START_TURNS` about ``up``
    through the centroids, then from each of ``starts`` (in that order)."""
    a, b = surface_voxels(src, step), surface_voxels(dst, step)
    ca, cb = src.mean(axis=0), dst.mean(axis=0)
    ta, tb = cKDTree(a), cKDTree(b)
    inits = []
    for deg in START_TURNS:
        rot = Rotation.from_rotvec(np.radians(deg) * np.asarray(up, np.float64)).as_matrix()
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = rot, cb - rot @ ca
        inits.append(T)
    inits += list(starts or [])
    fits = []
    for T in inits:
        T = _icp(a, tb, b, T, 40, trim)
        fits.append((_cost(a, b, T, ta, tb, trim), T))
    return fits


def symmetric_fits(
    src: np.ndarray,
    dst: np.ndarray,
    step: float,
    T: np.ndarray,
    up: np.ndarray,
    tolerance: float = 0.1,
    trim: float = 0.9,
    max_points: int = 600,
) -> list[np.ndarray]:
    """The motions ``[4,4]`` that align hull ``src`` to ``dst`` about as well as ``T`` does: ``T`` after each
    turn of :data:`SYMMETRY_TURNS` about ``up`` through ``src``'s centroid, and after each of those turned
    upside down (half a turn about an axis across ``up``), each refined by trimmed ICP; kept when its
    :func:`hull_cost` is at most ``tolerance`` voxels above ``T``'s. A shape without symmetry keeps ``T`` and
    its near neighbours; a ball keeps every turn. ICP runs on at most ``max_points`` surface voxels
    (evenly strided); deterministic."""
    T = np.asarray(T, np.float64)
    up = np.asarray(up, np.float64) / np.linalg.norm(up)
    a, b = surface_voxels(src, step), surface_voxels(dst, step)
    ta, tb = cKDTree(a), cKDTree(b)
    sub = a[:: max(1, int(np.ceil(len(a) / max_points)))]
    base = _cost(a, b, T, ta, tb, trim)
    across = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    flip = Rotation.from_rotvec(np.pi * across / np.linalg.norm(across)).as_matrix()
    centre = src.mean(axis=0)
    out = []
    for upside_down in (False, True):
        for deg in SYMMETRY_TURNS:
            rot = Rotation.from_rotvec(np.radians(deg) * up).as_matrix()
            if upside_down:
                rot = rot @ flip
            S = np.eye(4)
            S[:3, :3], S[:3, 3] = rot, centre - rot @ centre
            fit = _icp(sub, tb, b, T @ S, 10, trim)
            if _cost(a, b, fit, ta, tb, trim) <= base + tolerance * step:
                out.append(fit)
    return out


def fit_into_larger(
    src: np.ndarray, dst: np.ndarray, step: float, T: np.ndarray, trim: float = 0.9
) -> np.ndarray:
    """The motion ``[4,4]`` from hull ``src`` to hull ``dst`` (refined from ``T``) that puts the smaller one's
    surface on the larger one's: trimmed ICP one way only, from the smaller to the larger. A visual hull only
    grows where the photos cannot carve (views where another object hides it), so when two hulls of one object
    disagree in volume the smaller is the truer shape, and it belongs inside the larger where that is carved
    well; their centroids would be off by the larger one's excess."""
    T = np.asarray(T, np.float64)
    a, b = surface_voxels(src, step), surface_voxels(dst, step)
    if len(src) <= len(dst):
        return _icp(a, cKDTree(b), b, T, 60, trim)
    return np.linalg.inv(_icp(b, cKDTree(a), a, np.linalg.inv(T), 60, trim))
