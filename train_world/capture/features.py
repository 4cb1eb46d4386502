"""Object features of the undistorted views, and matching them between two views with known cameras.

:func:`extract_view_features` keeps the SIFT features (pycolmap, CPU) that lie well inside an object's mask;
the helpers match two views' features as mutual nearest neighbours passing a ratio test, optionally only
where the known epipolar geometry allows (Sampson distance). Pixel coordinates have pixel ``(u, v)`` centred at
``(u + 0.5, v + 0.5)``; float64 unless stated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RATIO", "ViewFeatures", "extract_view_features", "fundamental", "mutual_ratio_matches", "sampson"]

#: Lowe ratio for descriptor matches (within a state and between states)
RATIO = 0.85


@dataclass(frozen=True)
class ViewFeatures:
    """Object features of one undistorted view: ``K [3,3]``, OpenCV world-to-camera ``w2c [4,4]``, keypoints
    ``xy [N,2]`` (pixel centres at +0.5), unit descriptors ``desc [N,128]`` float32 and the object id under
    each keypoint ``label [N]`` (0 never appears: background features are dropped)."""

    K: np.ndarray
    w2c: np.ndarray
    xy: np.ndarray
    desc: np.ndarray
    label: np.ndarray


def extract_view_features(
    gray: np.ndarray, ids: np.ndarray, K: np.ndarray, w2c: np.ndarray, extractor, max_size: int = 1600
) -> ViewFeatures:
    """SIFT features of ``gray`` (uint8 ``[H,W]``) that lie well inside an object of ``ids`` (uint8 ``[H,W]``).

    A keypoint is kept when the pixels at its scale around it all carry the same object id. Views larger than
    ``max_size`` are detected at a reduced size (keypoints are returned in full-size pixels).
    """
    import pycolmap
    from PIL import Image

    h, w = gray.shape
    s = min(1.0, max_size / max(h, w))
    img = (
        gray
        if s == 1.0
        else np.asarray(Image.fromarray(gray).resize((round(w * s), round(h * s)), Image.BILINEAR))
    )
    kp, desc = extractor.extract_from_float32_array(np.ascontiguousarray(img, dtype=np.float32) / 255.0)
    kp = pycolmap.keypoints_to_matrix(kp).astype(np.float64).reshape(-1, 4)  # x, y, scale, orientation
    d = np.asarray(getattr(desc, "data", desc), dtype=np.float32).reshape(len(kp), -1)
    xy = kp[:, :2] / s
    scale = kp[:, 2] / s
    r = np.clip(scale, 1.0, 0.05 * max(h, w))
    label = ids[np.clip(xy[:, 1].astype(np.int64), 0, h - 1), np.clip(xy[:, 0].astype(np.int64), 0, w - 1)]
    keep = label > 0
    for ang in np.linspace(0.0, 2 * np.pi, 8, endpoint=False):
        px = np.clip((xy[:, 0] + r * np.cos(ang)).astype(np.int64), 0, w - 1)
        py = np.clip((xy[:, 1] + r * np.sin(ang)).astype(np.int64), 0, h - 1)
        keep &= ids[py, px] == label
    d = d[keep]
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return ViewFeatures(
        np.asarray(K, np.float64), np.asarray(w2c, np.float64), xy[keep], d, label[keep].astype(np.uint8)
    )


def fundamental(a: ViewFeatures, b: ViewFeatures) -> np.ndarray:
    """Fundamental matrix ``[3,3]`` with ``x_b^T F x_a = 0`` for the two views' known cameras."""
    rel = b.w2c @ np.linalg.inv(a.w2c)
    t = rel[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(b.K).T @ tx @ rel[:3, :3] @ np.linalg.inv(a.K)


def sampson(F: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distances (pixels) between all ``xa [A,2]`` and ``xb [B,2]`` -> ``[A,B]``."""
    ha = np.c_[xa, np.ones(len(xa))]
    hb = np.c_[xb, np.ones(len(xb))]
    fa = ha @ F.T  # [A,3] epipolar lines in b
    fb = hb @ F  # [B,3] epipolar lines in a
    num = (hb @ fa.T).T ** 2
    den = fa[:, 0:1] ** 2 + fa[:, 1:2] ** 2 + (fb[:, 0] ** 2 + fb[:, 1] ** 2)[None, :]
    return np.sqrt(num / np.maximum(den, 1e-300))


def mutual_ratio_matches(sim: np.ndarray, ratio: float) -> np.ndarray:
    """Pairs ``[M,2]`` (row, column) that are mutual best matches passing the ratio test on both sides;
    ``sim`` holds cosine similarities, ``-inf`` where a pair is not allowed."""
    if sim.size == 0:
        return np.zeros((0, 2), np.int64)
    dist = np.sqrt(np.maximum(2.0 - 2.0 * sim, 0.0))
    out = []
    best_r = np.argmin(dist, axis=1)
    best_c = np.argmin(dist, axis=0)
    for i, j in enumerate(best_r):
        if not np.isfinite(sim[i, j]) or best_c[j] != i:
            continue
        row = np.partition(dist[i], 1)[1] if dist.shape[1] > 1 else np.inf
        col = np.partition(dist[:, j], 1)[1] if dist.shape[0] > 1 else np.inf
        if dist[i, j] < ratio * row and dist[i, j] < ratio * col:
            out.append((i, j))
    return np.asarray(out, np.int64).reshape(-1, 2)
