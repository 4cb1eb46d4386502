"""A world's background seen all around from one point, and continued where no camera saw it.

Pure functions behind the far shell's colours (:mod:`train_world.complete.shell`):

- :func:`render_cube`: the background splatted into the six 90-degree faces of a cube around ``origin``:
  colour over alpha (what the surface shows, whatever its opacity), alpha, and the distance along each ray
  (expected depth).
- :func:`sample_cube`: those values in any unit directions (nearest pixel of the face the direction leaves by).
- :func:`equirect_directions`: unit directions of an elevation x azimuth grid (rows from -90 to +90 degrees);
  :func:`equirect_cell`: the cell a direction falls in.
- :func:`seen_by_cameras`: which 3D points project into some camera's image.
- :func:`continue_columns`: fill the cells of a grid that are not known from the nearest known cell of the
  same column (the same azimuth: up or down a wall), and the cells of columns with none known from the
  nearest known direction.

Conventions: cameras OpenCV world-to-camera (x right, y down, z forward), pixel centres at +0.5; quaternions wxyz;
float64 outside the rasterizer. Deterministic.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from scipy.spatial import cKDTree

from dsg_gym.cameras import Cameras
from dsg_gym.gaussians import GaussianSet

__all__ = [
    "continue_columns",
    "cube_viewmats",
    "equirect_cell",
    "equirect_directions",
    "render_cube",
    "sample_cube",
    "seen_by_cameras",
]

# the cube's faces: (optical axis, image "up" hint) in world coordinates
_FACES = (
    ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, -1.0, 0.0), (0.0, 0.0, 1.0)),
    ((0.0, 0.0, 1.0), (0.0, 1.0, 0.0)),
    ((0.0, 0.0, -1.0), (0.0, 1.0, 0.0)),
)


def cube_viewmats(origin: np.ndarray) -> np.ndarray:
    """World-to-camera matrices ``[6, 4, 4]`` of the cube's faces around ``origin [3]`` (OpenCV)."""
    out = np.zeros((6, 4, 4))
    for k, (axis, up) in enumerate(_FACES):
        z = np.asarray(axis)
        x = np.cross(z, up)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        out[k, :3, :3] = R
        out[k, :3, 3] = -R @ np.asarray(origin, np.float64)
        out[k, 3, 3] = 1.0
    return out


def _face_K(size: int) -> np.ndarray:
    f = size / 2.0
    return np.array([[f, 0.0, size / 2.0], [0.0, f, size / 2.0], [0.0, 0.0, 1.0]])


def render_cube(
    g: GaussianSet, origin: np.ndarray, size: int, splat_options: dict | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``g`` seen from ``origin [3]``: colour over alpha ``[6, size, size, 3]``, alpha ``[6, size, size]`` and the
    distance from ``origin`` along each pixel's ray ``[6, size, size]`` (the expected depth; 0 where nothing
    is). ``splat_options``: the world's (``World.splat_options``). Splats blend in the order of their centres'
    depth, so off a face's axis, where a surface facing ``origin`` is slanted to the image plane, the distance
    comes out short by up to about a Gaussian's extent."""
    import torch

    from dsg_gym.splat import rasterize

    if size < 2:
        raise ValueError(f"render_cube: size must be >= 2, got {size}")
    vms, K = cube_viewmats(origin), _face_K(size)
    t = lambda a: torch.as_tensor(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    opts = dict(splat_options or {})
    img, alpha, _ = rasterize(
        t(g.means), t(g.quats), t(g.scales), t(g.opacities), t(g.sh), t(vms), t(np.repeat(K[None], 6, 0)),
        size, size, sh_degree=g.sh_degree, render_mode="RGB+ED", **opts,
    )  # fmt: skip
    img, a = img.detach().numpy().astype(np.float64), alpha[..., 0].detach().numpy().astype(np.float64)
    colour = img[..., :3] / np.maximum(a, 1e-6)[..., None]
    # expected depth is along the optical axis: the ray through pixel (u, v) is (u - c, v - c, f) / f long
    c = np.arange(size) + 0.5 - size / 2.0
    stretch = np.sqrt(1.0 + (c[None, :] ** 2 + c[:, None] ** 2) / (size / 2.0) ** 2)
    distance = np.where(a > 1e-6, img[..., 3], 0.0) * stretch[None]
    return colour, a, distance


def sample_cube(values: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """``values [6, S, S, ...]`` (a :func:`render_cube` output) at unit directions ``dirs [N, 3]``: the pixel
    of the face each direction leaves the cube by, ``[N, ...]``."""
    d = np.asarray(dirs, np.float64)
    size = values.shape[1]
    R = cube_viewmats(np.zeros(3))[:, :3, :3]
    cam = np.einsum("kij,nj->nki", R, d)  # [N, 6, 3]
    face = np.argmax(cam[..., 2], axis=1)
    p = cam[np.arange(len(d)), face]
    f = size / 2.0
    u = np.clip(np.floor(f * p[:, 0] / p[:, 2] + f), 0, size - 1).astype(int)
    v = np.clip(np.floor(f * p[:, 1] / p[:, 2] + f), 0, size - 1).astype(int)
    return values[face, v, u]


def equirect_directions(rows: int, cols: int) -> np.ndarray:
    """Unit directions ``[rows, cols, 3]`` at the cell centres of an elevation (rows, -90 to +90 degrees) x
    azimuth (columns, 0 to 360 degrees from +x towards +y) grid."""
    el = (np.arange(rows) + 0.5) / rows * np.pi - np.pi / 2
    az = (np.arange(cols) + 0.5) / cols * 2 * np.pi
    E, A = np.meshgrid(el, az, indexing="ij")
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1)


def equirect_cell(dirs: np.ndarray, rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the :func:`equirect_directions` cells holding unit directions ``dirs [N, 3]``."""
    d = np.asarray(dirs, np.float64)
    el = np.arcsin(np.clip(d[:, 2], -1.0, 1.0))
    az = np.mod(np.arctan2(d[:, 1], d[:, 0]), 2 * np.pi)
    r = np.clip(np.floor((el + np.pi / 2) / np.pi * rows), 0, rows - 1).astype(int)
    c = np.clip(np.floor(az / (2 * np.pi) * cols), 0, cols - 1).astype(int)
    return r, c


def seen_by_cameras(points: np.ndarray, cameras: Iterable[Cameras]) -> np.ndarray:
    """Bool ``[N]``: the point lies in front of some camera and projects into its image (occlusion is not
    tested)."""
    p = np.asarray(points, np.float64)
    seen = np.zeros(len(p), bool)
    for cam in cameras:
        for vm, K in zip(np.asarray(cam.viewmats, np.float64), np.asarray(cam.Ks, np.float64)):
            q = p @ vm[:3, :3].T + vm[:3, 3]
            z = q[:, 2]
            front = z > 1e-9
            zs = np.where(front, z, 1.0)
            u = (K[0, 0] * q[:, 0] + K[0, 1] * q[:, 1]) / zs + K[0, 2]
            v = K[1, 1] * q[:, 1] / zs + K[1, 2]
            seen |= front & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return seen


def continue_columns(known: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """For a grid ``known [R, C]`` (bool) with cell directions ``dirs [R, C, 3]``: the flat index of the cell
    each cell takes its values from, ``[R, C]``. A known cell is its own source; another takes the nearest
    known cell of its column (ties: the lower one), or, in a column with none known, the known cell nearest in
    direction. Raises ``ValueError`` when no cell is known."""
    known = np.asarray(known, bool)
    R, C = known.shape
    if not known.any():
        raise ValueError("continue_columns: no cell is known")
    rows = np.arange(R)
    src = np.full((R, C), -1, dtype=np.int64)
    for j in range(C):
        ks = np.flatnonzero(known[:, j])
        if len(ks) == 0:
            continue
        nearest = ks[np.abs(rows[:, None] - ks[None, :]).argmin(axis=1)]
        src[:, j] = nearest * C + j
    empty = src < 0
    if empty.any():
        flat_known = np.flatnonzero(known.reshape(-1))
        _, i = cKDTree(np.asarray(dirs, np.float64).reshape(-1, 3)[flat_known]).query(
            np.asarray(dirs, np.float64).reshape(-1, 3)[empty.reshape(-1)]
        )
        src[empty] = flat_known[i]
    return src
