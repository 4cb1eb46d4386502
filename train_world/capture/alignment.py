"""Rigid and similarity fits between corresponding 3D point sets, and the errors between poses (float64).

``umeyama(src, dst)`` finds ``s, R, t`` minimising ``sum |s R src_i + t - dst_i|^2`` (Umeyama 1991; with
``with_scale=False`` it is the Kabsch fit, ``s = 1``). Rotations come out orthonormal with determinant +1.
"""

from __future__ import annotations

import numpy as np

__all__ = ["apply", "rotation_angle_deg", "similarity_matrix", "umeyama"]


def umeyama(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R [3,3], t [3])`` with ``dst ~ s R src + t`` for ``src, dst: [N,3]`` (N >= 3, optional
    non-negative ``weights [N]``)."""
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape or len(src) < 3:
        raise ValueError(f"umeyama: need two [N,3] arrays with N >= 3, got {src.shape} and {dst.shape}")
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)
    w = w / max(float(w.sum()), 1e-300)
    mu_s, mu_d = w @ src, w @ dst
    a, b = src - mu_s, dst - mu_d
    cov = (b * w[:, None]).T @ a
    u, sig, vt = np.linalg.svd(cov)
    d = np.diag([1.0, 1.0, 1.0 if np.linalg.det(u) * np.linalg.det(vt) > 0 else -1.0])
    rot = u @ d @ vt
    var = float(w @ np.sum(a * a, axis=1))
    s = float(np.sum(sig * np.diag(d)) / var) if with_scale and var > 0 else 1.0
    return s, rot, mu_d - s * rot @ mu_s


def similarity_matrix(s: float, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The 4x4 matrix ``[[s R, t], [0, 1]]``."""
    m = np.eye(4)
    m[:3, :3] = float(s) * np.asarray(rot, dtype=np.float64)
    m[:3, 3] = np.asarray(t, dtype=np.float64)
    return m


def apply(mat: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points [N,3]`` mapped by the 4x4 ``mat`` (rigid or similarity)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    return p @ np.asarray(mat, dtype=np.float64)[:3, :3].T + np.asarray(mat, dtype=np.float64)[:3, 3]


def rotation_angle_deg(rot: np.ndarray) -> np.ndarray:
    """Rotation angle in degrees of ``rot [...,3,3]`` (e.g. ``R_a^T R_b`` for the angle between two): ``atan2`` of
    its sine (from the antisymmetric part) and cosine (from the trace), accurate near 0 and 180 degrees, where an
    arccos of the trace alone loses half the digits."""
    r = np.asarray(rot, dtype=np.float64)
    c = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    w = np.stack(
        [r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0], r[..., 1, 0] - r[..., 0, 1]], axis=-1
    )
    return np.degrees(np.arctan2(0.5 * np.linalg.norm(w, axis=-1), c))
