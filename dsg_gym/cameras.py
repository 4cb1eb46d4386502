"""Pinhole cameras in float64 numpy: the one camera set type, look-at views and orbits.

Convention (the renderer's, used everywhere in dsg-gym): OpenCV camera axes, x right, y down, z forward (the
viewing direction). A ``viewmat`` is the world-to-camera rigid transform ``[4, 4]``; a camera-to-world matrix
is its inverse. Intrinsics ``K`` are ``[3, 3]``; pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``, so the
centre of a ``W x H`` image is at ``(W/2, H/2)``.

* :class:`Cameras`: ``V`` views sharing one image size (world files, world models, the environment).
* :func:`look_at`: the view from an eye towards a target, world ``up`` pointing up in the image (the
  batched torch equivalent for training is :func:`dsg_gym.geometry.look_at_viewmat`; tests hold them equal).
* :func:`orbit_eyes`: camera positions on rings around a point (look at it with :func:`look_at`, or with
  the torch one in batches).
* :func:`intrinsics_from_fov`: ``K`` of a vertical field of view.
* :func:`unproject`: pixels with depth back to world points; :func:`depth_points` a whole depth map.
* :func:`camera_centres`: where cameras are, from their world-to-camera matrices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Cameras",
    "camera_centres",
    "depth_points",
    "intrinsics_from_fov",
    "look_at",
    "orbit_eyes",
    "unproject",
]


@dataclass(frozen=True, eq=False)
class Cameras:
    """``V >= 1`` pinhole cameras of one image size: world-to-camera ``viewmats [V,4,4]`` and ``Ks [V,3,3]``,
    held as float64 (world files store them as float32, which converts both ways exactly). ValueError for
    wrong shapes, non-finite values or an empty image size."""

    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        vm = np.ascontiguousarray(self.viewmats, dtype=np.float64)
        ks = np.ascontiguousarray(self.Ks, dtype=np.float64)
        if vm.ndim != 3 or vm.shape[1:] != (4, 4) or ks.shape != (vm.shape[0], 3, 3) or vm.shape[0] < 1:
            raise ValueError(f"Cameras: bad shapes viewmats {vm.shape}, Ks {ks.shape}")
        if not (np.all(np.isfinite(vm)) and np.all(np.isfinite(ks))):
            raise ValueError("Cameras: non-finite values")
        if int(self.width) < 1 or int(self.height) < 1:
            raise ValueError(f"Cameras: bad image size {self.width}x{self.height}")
        object.__setattr__(self, "viewmats", vm)
        object.__setattr__(self, "Ks", ks)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    def resized(self, width: int, height: int) -> Cameras:
        """The same cameras for another image size (focal lengths and principal point scaled per axis)."""
        ks = self.Ks.copy()
        ks[:, 0] *= width / self.width
        ks[:, 1] *= height / self.height
        return Cameras(self.viewmats, ks, width, height)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``[4, 4]`` float64 viewmat of a camera at ``eye`` looking at ``target`` (``[3]`` each): camera +z
    points at ``target``, camera x is ``z x up`` normalised, so world ``up`` points up in the image (-y).
    ValueError when ``eye`` equals ``target`` or ``up`` is parallel to the viewing direction (callers that
    want a fallback pick another ``up``)."""
    eye = np.asarray(eye, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(z) < 1e-9:
        raise ValueError("look-at camera: eye equals target")
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look-at camera: up is parallel to the viewing direction")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    vm = np.eye(4)
    vm[:3, :3] = np.stack([x, y, z])
    vm[:3, 3] = -vm[:3, :3] @ eye
    return vm


def orbit_eyes(centre, up, distance: float, elevations: Sequence[float], num_views: int,
               azimuth0: float = 0.0) -> np.ndarray:  # fmt: skip
    """``[num_views, 3]`` camera positions at ``distance`` from ``centre``: view ``i`` at elevation
    ``elevations[i % len(elevations)]`` (radians above the plane normal to ``up``) and azimuth
    ``2 pi i / num_views + azimuth0`` about ``up``, counted from the unit axis ``a = up x e`` (``e`` = world
    x, or world y when ``up`` is near x) towards ``up x a``."""
    if num_views < 1:
        raise ValueError(f"orbit: need at least one view, got {num_views}")
    centre = np.asarray(centre, dtype=np.float64)
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)
    eyes = []
    for i in range(num_views):
        elev = elevations[i % len(elevations)]
        az = 2 * math.pi * i / num_views + azimuth0
        d = math.cos(elev) * (math.cos(az) * a + math.sin(az) * b) + math.sin(elev) * up
        eyes.append(centre + distance * d)
    return np.array(eyes).reshape(num_views, 3)


def intrinsics_from_fov(fovy_deg: float, width: int, height: int) -> np.ndarray:
    """``[3, 3]`` float64 K with square pixels: ``fx = fy = (H/2) / tan(fovy/2)``, principal point
    ``(W/2, H/2)`` (the image centre in the pixel convention above)."""
    f = 0.5 * height / np.tan(0.5 * np.deg2rad(fovy_deg))
    return np.array([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]])


def unproject(u, v, depth, viewmats, Ks) -> np.ndarray:
    """World points ``[N, 3]`` float64 of pixel positions ``u, v [N]`` (pixel units in the convention above: a
    pixel's centre is at ``+0.5``) at ``depth [N]`` along each camera's optical axis (z, not the ray length),
    seen by world-to-camera ``viewmats`` and ``Ks``: one camera (``[4, 4]``, ``[3, 3]``) for every point or one
    per point (``[N, 4, 4]``, ``[N, 3, 3]``). The inverse of projecting ``R x + t`` with ``K``."""
    u, v, z = (np.asarray(a, dtype=np.float64).reshape(-1) for a in (u, v, depth))
    vm = np.asarray(viewmats, dtype=np.float64)
    K = np.asarray(Ks, dtype=np.float64)
    fx, fy, cx, cy = K[..., 0, 0], K[..., 1, 1], K[..., 0, 2], K[..., 1, 2]
    cam = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=-1)
    R, t = vm[..., :3, :3], vm[..., :3, 3]
    return np.einsum("...ji,...j->...i", R, cam - t)  # R^T (p - t)


def depth_points(depth, viewmat, K) -> np.ndarray:
    """World points ``[H, W, 3]`` float64 of every pixel centre of ``depth [H, W]`` (along the optical axis; a
    pixel without depth, 0, lands on the camera centre) seen by ``viewmat [4, 4]``, ``K [3, 3]``."""
    d = np.asarray(depth, dtype=np.float64)
    if d.ndim != 2:
        raise ValueError(f"depth must be a map [H, W], got shape {d.shape}")
    H, W = d.shape
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    return unproject(u + 0.5, v + 0.5, d, viewmat, K).reshape(H, W, 3)


def camera_centres(viewmats) -> np.ndarray:
    """World positions ``[..., 3]`` float64 of the cameras of world-to-camera ``viewmats [..., 4, 4]``:
    ``-R^T t``."""
    vm = np.asarray(viewmats, dtype=np.float64)
    return -np.einsum("...ji,...j->...i", vm[..., :3, :3], vm[..., :3, 3])
