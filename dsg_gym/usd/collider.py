"""Convex-hull collider meshes for rigid objects (and a static box for the table).

``convex_hull_mesh(points)`` returns the hull of the points as an outward-facing triangle mesh.
Degenerate inputs never fail: point sets that are empty, flat, on a line, a single point or
smaller than ``min_thickness`` along some direction are first thickened to ``min_thickness``
along their degenerate principal axes (so a flat sheet becomes a thin prism, a point a small
cube), and the hull is taken of the thickened set. If Qhull still fails, the result is the
axis-aligned box of the points padded to ``min_thickness``.
"""

from __future__ import annotations

import itertools

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdPhysics, Vt

__all__ = ["MIN_THICKNESS_M", "convex_hull_mesh", "box_mesh", "write_collider"]

MIN_THICKNESS_M = 2e-3  # metres; converted to stage units by the caller


def box_mesh(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box ``[lo, hi]`` as ``(points [8, 3] float64, triangles [12, 3] int32)``,
    counter-clockwise seen from outside."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    pts = np.array(
        [[(hi if b else lo)[i] for i, b in enumerate(bits)] for bits in itertools.product((0, 1), repeat=3)]
    )
    return _hull(pts) or (pts, np.zeros((0, 3), np.int32))


def _hull(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Hull of ``pts`` as (vertices, outward triangles) or None if Qhull fails."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(pts)
    except (QhullError, ValueError):
        return None
    used = np.sort(hull.vertices)
    remap = np.full(pts.shape[0], -1, np.int64)
    remap[used] = np.arange(used.size)
    tris = hull.simplices.copy()
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    normal = np.cross(b - a, c - a)
    inward = (normal * hull.equations[:, :3]).sum(axis=1) < 0
    tris[inward] = tris[inward][:, [0, 2, 1]]
    return pts[used], remap[tris].astype(np.int32)


def convex_hull_mesh(points, min_thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """Convex hull of ``points [N, 3]`` as ``(vertices [M, 3] float64, triangles [F, 3] int32)``
    with outward (counter-clockwise) winding; see the module docstring for degenerate sets."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if pts.shape[0] == 0:
        pts = np.zeros((1, 3))
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    local = pts - centre
    # Principal axes; an axis is degenerate if the set is thinner than min_thickness along it.
    _, axes = np.linalg.eigh(local.T @ local)  # columns: an orthonormal basis, always 3 of them
    spans = np.ptp(local @ axes, axis=0)
    thin = [axes[:, i] for i in range(3) if spans[i] < min_thickness]
    if thin:
        offsets = [np.zeros(3)]
        for axis in thin:
            offsets = [o + s * 0.5 * min_thickness * axis for o in offsets for s in (-1.0, 1.0)]
        local = (local[None, :, :] + np.asarray(offsets)[:, None, :]).reshape(-1, 3)
    result = _hull(local)
    if result is None:
        half = np.maximum(0.5 * np.ptp(local, axis=0), 0.5 * min_thickness)
        lo, hi = local.min(axis=0), local.max(axis=0)
        mid = 0.5 * (lo + hi)
        return box_mesh(mid - half + centre, mid + half + centre)
    verts, tris = result
    return verts + centre, tris


def write_collider(
    stage: Usd.Stage, path: str | Sdf.Path, vertices: np.ndarray, triangles: np.ndarray, *, convex_hull: bool
) -> UsdGeom.Mesh:
    """A guide-purpose ``UsdGeom.Mesh`` at ``path`` with ``CollisionAPI`` and ``MeshCollisionAPI``
    (``physics:approximation = convexHull`` when ``convex_hull``, else ``none``)."""
    mesh = UsdGeom.Mesh.Define(stage, Sdf.Path(str(path)))
    pts = np.ascontiguousarray(vertices, dtype=np.float32)
    tris = np.ascontiguousarray(triangles, dtype=np.int32)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(tris.shape[0], 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(tris.reshape(-1)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(UsdGeom.Mesh.ComputeExtent(Vt.Vec3fArray.FromNumpy(pts)))
    mesh.CreatePurposeAttr(UsdGeom.Tokens.guide)  # a proxy for physics, not for rendering
    prim = mesh.GetPrim()
    UsdPhysics.CollisionAPI.Apply(prim).CreateCollisionEnabledAttr(True)
    approx = UsdPhysics.Tokens.convexHull if convex_hull else UsdPhysics.Tokens.none
    UsdPhysics.MeshCollisionAPI.Apply(prim).CreateApproximationAttr(approx)
    return mesh
