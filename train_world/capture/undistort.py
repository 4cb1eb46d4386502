"""Undistorting photos to a pinhole camera (the capture format holds pinhole cameras only).

The pinhole camera keeps the photo's size and principal point; its focal length is the lens's, scaled by the
smallest factor for which every output pixel sees the photo (no blank pixels; exactly the lens's focal length
when there is no distortion). :class:`Undistorter` maps
each output pixel centre through the pinhole camera to a ray and through the estimated lens back to the photo;
colours are sampled bilinearly, object ids by nearest neighbour so that ids stay exact. Pixel coordinates are
continuous with pixel ``(u, v)`` centred at ``(u + 0.5, v + 0.5)`` (COLMAP's and the capture format's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from train_world.capture.cameras import intrinsics_matrix

__all__ = ["Undistorter"]


def _to_photo(cam, u: np.ndarray, v: np.ndarray, fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """Photo coordinates ``[N,2]`` seen by pinhole pixels ``(u, v)`` (``[N]`` each)."""
    rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones(u.size)], axis=1)
    return np.asarray(cam.img_from_cam(rays), dtype=np.float64).reshape(-1, 2)


def _zoom(cam, w: int, h: int, fx: float, fy: float, cx: float, cy: float) -> float:
    """Smallest focal-length factor for which every pinhole pixel of the same size and principal point sees
    the photo (no blank pixels; 1 for a lens without distortion). Found by bisection on the border pixels."""
    edge_u = np.concatenate([np.arange(w) + 0.5, np.arange(w) + 0.5, np.full(h, 0.5), np.full(h, w - 0.5)])
    edge_v = np.concatenate([np.full(w, 0.5), np.full(w, h - 0.5), np.arange(h) + 0.5, np.arange(h) + 0.5])

    def inside(s: float) -> bool:
        p = _to_photo(cam, edge_u, edge_v, fx * s, fy * s, cx, cy)
        tol = 1e-9
        return bool(
            np.all(np.isfinite(p))
            and np.all(p[:, 0] >= 0.5 - tol)
            and np.all(p[:, 0] <= w - 0.5 + tol)
            and np.all(p[:, 1] >= 0.5 - tol)
            and np.all(p[:, 1] <= h - 0.5 + tol)
        )

    if inside(1.0) and not inside(1.0 - 1e-9):
        return 1.0
    lo, hi = 0.25, 4.0
    if not inside(hi):
        raise ValueError(f"undistort: lens {cam.model_name} {list(cam.params)} is too distorted to undistort")
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if inside(mid) else (mid, hi)
    return hi


@dataclass(frozen=True)
class Undistorter:
    """The pinhole camera (``width``, ``height``, ``K [3,3]`` float64) and, for every one of its pixels,
    where it samples the photo: ``src_x, src_y [height, width]`` float64 continuous coordinates."""

    width: int
    height: int
    K: np.ndarray
    src_x: np.ndarray
    src_y: np.ndarray
    src_size: tuple[int, int]

    @classmethod
    def for_camera(cls, model: str, params: tuple[float, ...], width: int, height: int) -> Undistorter:
        """Build the maps for a COLMAP camera ``model`` with ``params`` at ``width x height``."""
        import pycolmap

        cam = pycolmap.Camera.create_from_model_name(1, model, 1.0, int(width), int(height))
        cam.params = np.asarray(params, dtype=np.float64)
        w, h = int(width), int(height)
        fx, fy = float(cam.focal_length_x), float(cam.focal_length_y)
        cx, cy = float(cam.principal_point_x), float(cam.principal_point_y)
        scale = _zoom(cam, w, h, fx, fy, cx, cy)
        fx, fy = fx * scale, fy * scale
        u, v = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
        src = _to_photo(cam, u.ravel(), v.ravel(), fx, fy, cx, cy).reshape(h, w, 2)
        return cls(w, h, intrinsics_matrix(fx, fy, cx, cy), src[..., 0].copy(), src[..., 1].copy(), (w, h))

    def _check(self, a: np.ndarray) -> None:
        if (a.shape[1], a.shape[0]) != self.src_size:
            raise ValueError(f"Undistorter: image is {a.shape[1]}x{a.shape[0]}, camera is {self.src_size}")

    def rgb(self, image: np.ndarray) -> np.ndarray:
        """uint8 ``[H,W,3]`` photo -> uint8 ``[height,width,3]`` pinhole image (bilinear)."""
        self._check(image)
        sw, sh = self.src_size
        x = np.clip(self.src_x - 0.5, 0.0, sw - 1.0)
        y = np.clip(self.src_y - 0.5, 0.0, sh - 1.0)
        x0 = np.minimum(np.floor(x).astype(np.int64), sw - 2) if sw > 1 else np.zeros(x.shape, np.int64)
        y0 = np.minimum(np.floor(y).astype(np.int64), sh - 2) if sh > 1 else np.zeros(y.shape, np.int64)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        x1, y1 = np.minimum(x0 + 1, sw - 1), np.minimum(y0 + 1, sh - 1)
        a = image.astype(np.float64)
        top = a[y0, x0] * (1 - fx) + a[y0, x1] * fx
        bottom = a[y1, x0] * (1 - fx) + a[y1, x1] * fx
        return np.clip(np.rint(top * (1 - fy) + bottom * fy), 0, 255).astype(np.uint8)

    def ids(self, ids: np.ndarray) -> np.ndarray:
        """uint8 ``[H,W]`` object ids -> uint8 ``[height,width]`` (nearest pixel, ids unchanged)."""
        self._check(ids)
        sw, sh = self.src_size
        x = np.clip(np.floor(self.src_x).astype(np.int64), 0, sw - 1)
        y = np.clip(np.floor(self.src_y).astype(np.int64), 0, sh - 1)
        return np.ascontiguousarray(ids[y, x])
