"""Exact geometry of the primitive shapes: mesh vertices, support functions, resting height, poses.

Every shape is convex and centred on its own frame. Its *support function* ``h(d) = max_{p in shape} p . d``
gives both the height at which an object rests on the plane ``z = 0`` (its lowest point touches it) and its
footprint on that plane (the projection of a convex body is the 2D convex set with the same support function
restricted to horizontal directions), which is what state sampling rasterises.
"""

from __future__ import annotations

import numpy as np

from train_world.synth.spec import Shape

__all__ = [
    "geom_size",
    "mesh_vertices",
    "pose_matrix",
    "rest_rotation",
    "resting_height",
    "support",
    "yaw_rotation",
]


def rest_rotation(rest: str) -> np.ndarray:
    """3x3 rotation of the rest orientation: ``upright`` = identity, ``side`` = +90 degrees about x."""
    if rest == "upright":
        return np.eye(3)
    if rest == "side":
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    raise ValueError(f"unknown rest orientation {rest!r}")


def yaw_rotation(yaw: float) -> np.ndarray:
    """3x3 rotation by ``yaw`` radians about +z."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def pose_matrix(rot: np.ndarray, pos) -> np.ndarray:
    """4x4 float64 rigid transform from a 3x3 rotation and a translation."""
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = np.asarray(pos, dtype=np.float64)
    return m


def mesh_vertices(shape: Shape) -> np.ndarray:
    """Vertices [N,3] (float64) of a ``mesh`` shape, centred so its bounding box is centred on the origin.

    MuJoCo builds the convex hull of these points for both rendering and collision.
    """
    if shape.type != "mesh":
        raise ValueError(f"mesh_vertices: shape type is {shape.type!r}, not 'mesh'")
    n, r, h = int(shape.sides), float(shape.radius), float(shape.height)
    if shape.mesh in ("prism", "frustum"):
        ang = (np.arange(n) + 0.5) * 2.0 * np.pi / n
        ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        top_r = r if shape.mesh == "prism" else float(shape.top_radius)
        bottom = np.column_stack([r * ring, np.full(n, -h / 2)])
        if top_r > 0:
            top = np.column_stack([top_r * ring, np.full(n, h / 2)])
        else:
            top = np.array([[0.0, 0.0, h / 2]])
        v = np.concatenate([bottom, top])
    elif shape.mesh == "gem":
        rng = np.random.default_rng(np.random.SeedSequence([int(shape.seed), 0x6E4]))
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        caps = np.array(
            [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
        )
        # flatten the bottom so the gem has a face to stand on
        v = np.concatenate([d, caps * 0.9]) * np.array([r, r, h / 2])
        v[:, 2] = np.maximum(v[:, 2], -0.35 * h)
    else:
        raise ValueError(f"unknown mesh kind {shape.mesh!r}")
    lo, hi = v.min(axis=0), v.max(axis=0)
    return v - 0.5 * (lo + hi)


def support(shape: Shape, dirs: np.ndarray, vertices: np.ndarray | None = None) -> np.ndarray:
    """Support function ``max_p p.d`` of ``shape`` (in its own frame) for directions ``dirs`` [N,3] -> [N]."""
    d = np.atleast_2d(np.asarray(dirs, dtype=np.float64))
    if shape.type == "box":
        return np.abs(d) @ (0.5 * np.asarray(shape.extents))
    if shape.type == "sphere":
        return shape.radius * np.linalg.norm(d, axis=1)
    if shape.type == "cylinder":
        return shape.radius * np.hypot(d[:, 0], d[:, 1]) + 0.5 * shape.height * np.abs(d[:, 2])
    if shape.type == "capsule":
        half_seg = 0.5 * shape.height - shape.radius
        return shape.radius * np.linalg.norm(d, axis=1) + half_seg * np.abs(d[:, 2])
    if shape.type == "mesh":
        v = mesh_vertices(shape) if vertices is None else vertices
        return (d @ v.T).max(axis=1)
    raise ValueError(f"unknown shape type {shape.type!r}")


def resting_height(shape: Shape, rot: np.ndarray) -> float:
    """z of the frame origin so the lowest point of ``shape`` rotated by ``rot`` lies on ``z = 0``."""
    down_local = np.asarray(rot).T @ np.array([0.0, 0.0, -1.0])
    return float(support(shape, down_local[None])[0])


def geom_size(shape: Shape) -> list[float]:
    """MuJoCo ``size`` of a primitive geom (half sizes), zeros for meshes."""
    if shape.type == "box":
        return [0.5 * e for e in shape.extents]
    if shape.type == "sphere":
        return [shape.radius, 0.0, 0.0]
    if shape.type == "cylinder":
        return [shape.radius, 0.5 * shape.height, 0.0]
    if shape.type == "capsule":
        return [shape.radius, 0.5 * shape.height - shape.radius, 0.0]
    return [0.0, 0.0, 0.0]
