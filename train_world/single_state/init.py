"""Initial Gaussians: back-projected depth where a capture has it, else random points in the scene bounds (led by
the capture's sparse structure-from-motion points where it has them, :mod:`train_world.capture.points`).

Also the scene extent (3DGS: 1.1 x the largest camera distance from the cameras' centroid) that scales the
position learning rate and the clone/split threshold.
"""

from __future__ import annotations

import numpy as np
import torch

from train_world.single_state.field import SegmentedField
from train_world.single_state.losses import knn_indices

__all__ = [
    "camera_centres",
    "carve_silhouettes",
    "initial_field",
    "points_from_depth",
    "points_in_bounds",
    "scene_bounds_from_cameras",
    "scene_extent",
]


def camera_centres(viewmats: torch.Tensor) -> np.ndarray:
    """World positions ``[V,3]`` float64 of world-to-camera matrices."""
    vm = viewmats.detach().double().numpy()
    R, t = vm[:, :3, :3], vm[:, :3, 3]
    return -np.einsum("vji,vj->vi", R, t)


def scene_extent(viewmats: torch.Tensor) -> float:
    c = camera_centres(viewmats)
    return float(1.1 * max(np.linalg.norm(c - c.mean(0), axis=1).max(), 1e-6))


def scene_bounds_from_cameras(viewmats: torch.Tensor, Ks: torch.Tensor, width: int) -> np.ndarray:
    """``[[min], [max]]`` of a cube around the point closest to all optical axes, half-size the image
    half-width at that distance (what every camera sees around its look-at point)."""
    vm = viewmats.detach().double().numpy()
    c = camera_centres(viewmats)
    d = vm[:, 2, :3]  # optical axes in world (third row of R)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ci, di in zip(c, d):
        P = np.eye(3) - np.outer(di, di)
        A += P
        b += P @ ci
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    dist = float(np.median(np.linalg.norm(c - centre, axis=1)))
    fx = float(np.median(Ks[:, 0, 0].double().numpy()))
    half = dist * (width / 2.0) / fx
    return np.stack([centre - half, centre + half])


def points_from_depth(
    images: torch.Tensor,
    depths: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    masks: torch.Tensor | None,
    max_points: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project pixels with depth > 0 of all views; returns points ``[P,3]`` float64, colours ``[P,3]``
    and mask ids ``[P]`` (0 without masks), a random subset of at most ``max_points``."""
    V, H, W = depths.shape
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pts, cols, ids = [], [], []
    per_view = max(1, int(np.ceil(4 * max_points / V)))
    for i in range(V):
        z = depths[i].numpy().astype(np.float64)
        valid = np.flatnonzero(z.reshape(-1) > 0)
        if valid.size == 0:
            continue
        if valid.size > per_view:
            valid = np.sort(rng.choice(valid, per_view, replace=False))
        K = Ks[i].double().numpy()
        zz = z.reshape(-1)[valid]
        x = (u.reshape(-1)[valid] - K[0, 2]) / K[0, 0] * zz
        y = (v.reshape(-1)[valid] - K[1, 2]) / K[1, 1] * zz
        cam = np.stack([x, y, zz], 1)
        vm = viewmats[i].double().numpy()
        world = (cam - vm[:3, 3]) @ vm[:3, :3]  # R^T (p - t)
        pts.append(world)
        cols.append(images[i].reshape(-1, 3).numpy()[valid])
        ids.append(masks[i].reshape(-1).numpy()[valid] if masks is not None else np.zeros(valid.size))
    if not pts:
        raise ValueError("points_from_depth: no pixel has depth > 0")
    P, Cc, ids_all = np.concatenate(pts), np.concatenate(cols), np.concatenate(ids).astype(np.int64)
    if len(P) > max_points:
        keep = np.sort(rng.choice(len(P), max_points, replace=False))
        P, Cc, ids_all = P[keep], Cc[keep], ids_all[keep]
    return P, Cc.astype(np.float64), ids_all


def points_in_bounds(
    bounds: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` uniform random points in the box ``bounds`` with random colours (3DGS's synthetic init)."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    P = lo + (hi - lo) * rng.random((n, 3))
    return P, rng.random((n, 3)), np.zeros(n, np.int64)


def carve_silhouettes(
    points: np.ndarray,
    silhouettes: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    min_fraction: float = 0.95,
) -> np.ndarray:
    """Boolean ``[P]``: points inside the visual hull, i.e. seen inside the silhouette (alpha > 0.5) in at
    least ``min_fraction`` of the views whose image they project into."""
    V, H, W = silhouettes.shape
    inside = np.zeros(len(points), np.int64)
    seen = np.zeros(len(points), np.int64)
    for i in range(V):
        vm, K = viewmats[i].double().numpy(), Ks[i].double().numpy()
        cam = points @ vm[:3, :3].T + vm[:3, 3]
        z = cam[:, 2]
        ok = z > 1e-6
        u = np.floor(K[0, 0] * cam[:, 0] / np.where(ok, z, 1) + K[0, 2]).astype(np.int64)
        v = np.floor(K[1, 1] * cam[:, 1] / np.where(ok, z, 1) + K[1, 2]).astype(np.int64)
        ok &= (u >= 0) & (u < W) & (v >= 0) & (v < H)
        sil = silhouettes[i].numpy() > 0.5
        seen += ok
        inside[ok] += sil[v[ok], u[ok]]
    return (seen > 0) & (inside >= np.ceil(min_fraction * seen))


def nn_scales(points: np.ndarray) -> np.ndarray:
    """3DGS initial scale: RMS distance to the 3 nearest other points."""
    if len(points) < 2:
        return np.full(len(points), 0.01)
    idx = knn_indices(points, points, min(3, len(points) - 1))
    d2 = ((points[idx] - points[:, None, :]) ** 2).sum(-1)
    return np.sqrt(np.maximum(d2.mean(1), 1e-14))


def initial_field(
    points: np.ndarray,
    colours: np.ndarray,
    class_ids: np.ndarray,
    *,
    num_classes: int,
    sh_degree: int,
    num_features: int,
    opacity: float,
    generator: torch.Generator,
) -> tuple[SegmentedField, torch.Tensor]:
    """A field at ``points`` and a matching initial classifier weight ``[K+1, F]``.

    Each class gets a random unit code vector; Gaussians whose class is known (from a mask) start with their
    class's code as identity feature (others: class 0 with small noise), and the classifier starts as the code
    matrix, so known classes are predicted from the first step.
    """
    codes = torch.randn((num_classes, num_features), generator=generator, dtype=torch.float64)
    codes = codes / codes.norm(dim=-1, keepdim=True)
    noise = 0.05 * torch.randn((len(points), num_features), generator=generator, dtype=torch.float64)
    feats = codes[torch.from_numpy(class_ids)] + noise
    field = SegmentedField.from_points(
        torch.from_numpy(points),
        torch.from_numpy(np.clip(colours, 0.0, 1.0)),
        torch.from_numpy(nn_scales(points)),
        sh_degree=sh_degree,
        num_features=num_features,
        opacity=opacity,
        features=feats.float(),
    )
    return field, codes.float()
