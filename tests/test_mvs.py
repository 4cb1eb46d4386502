"""Multi-view stereo depth (train_world.capture.mvs) on a textured plane rendered exactly."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("cv2")

from dsg_gym.cameras import look_at  # noqa: E402
from train_world.capture.mvs import (  # noqa: E402
    MvsConfig,
    select_neighbours,
    stereo_depths,
)

SIZE = 64
F = 60.0


def _texture(x: np.ndarray, y: np.ndarray, flat: bool) -> np.ndarray:
    if flat:
        return np.full(x.shape + (3,), 120, np.uint8)
    rng = np.random.default_rng(3)
    grid = rng.uniform(0, 255, (80, 80))
    gx = np.clip((x + 0.4) / 0.8 * 79, 0, 78.999)
    gy = np.clip((y + 0.4) / 0.8 * 79, 0, 78.999)
    i, j = np.floor(gx).astype(int), np.floor(gy).astype(int)
    a, b = gx - i, gy - j
    v = (grid[j, i] * (1 - a) * (1 - b) + grid[j, i + 1] * a * (1 - b) + grid[j + 1, i] * (1 - a) * b
         + grid[j + 1, i + 1] * a * b)  # fmt: skip
    return np.repeat(np.clip(v, 0, 255).astype(np.uint8)[..., None], 3, axis=-1)


def _scene(n: int = 6, flat: bool = False, size: int = SIZE):
    """``n`` views of the plane z = 0 from about 1 m: images, Ks, OpenCV w2c, true depths."""
    f = F * size / SIZE
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    rays = np.linalg.inv(K) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    images, w2cs, depths = [], [], []
    for k in range(n):
        az = np.radians(10.0 * k)
        eye = np.array([np.cos(az), np.sin(az), 1.2]) * 0.8
        w2c = look_at(eye, np.zeros(3))
        R, t = w2c[:3, :3], w2c[:3, 3]
        d_world = R.T @ rays  # ray directions with camera z = 1
        c = -R.T @ t
        z = -c[2] / d_world[2]  # camera depth where the ray meets z = 0
        p = c[:, None] + d_world * z
        images.append(_texture(p[0], p[1], flat).reshape(size, size, 3))
        w2cs.append(w2c)
        depths.append(z.reshape(size, size))
    pts = np.random.default_rng(0).uniform(-0.3, 0.3, (200, 3)) * [1, 1, 0]
    return np.stack(images), np.repeat(K[None], n, 0), np.stack(w2cs), np.stack(depths), pts


def test_textured_plane_depth_is_recovered():
    images, Ks, w2c, truth, pts = _scene()
    cfg = MvsConfig(neighbours=4, best_of=2, min_consistent=2, rel_depth=0.02)
    d = stereo_depths(images, Ks, w2c, pts, cfg)
    assert d.shape == truth.shape and d.dtype == np.float32
    valid = d > 0
    assert valid.mean() > 0.4
    rel = np.abs(d[valid] - truth[valid]) / truth[valid]
    assert np.median(rel) < 0.01
    assert np.mean(rel > 0.05) < 0.05
    assert np.array_equal(d, stereo_depths(images, Ks, w2c, pts, cfg))  # deterministic


def test_flat_colour_gets_no_depth():
    images, Ks, w2c, _, pts = _scene(flat=True)
    d = stereo_depths(
        images, Ks, w2c, pts, MvsConfig(neighbours=4, best_of=2, min_consistent=2, rel_depth=0.02)
    )
    assert not (d > 0).any()


def test_large_photos_are_reduced_and_depth_comes_back_full_size():
    images, Ks, w2c, truth, pts = _scene(size=96)
    d = stereo_depths(
        images,
        Ks,
        w2c,
        pts,
        MvsConfig(neighbours=4, best_of=2, min_consistent=2, rel_depth=0.02, max_size=48),
    )
    assert d.shape == truth.shape
    valid = d > 0
    assert valid.mean() > 0.3
    assert np.median(np.abs(d[valid] - truth[valid]) / truth[valid]) < 0.02


def test_neighbours_within_the_angle_range():
    _, _, w2c, _, _ = _scene(n=6)
    cfg = MvsConfig(neighbours=3, best_of=1, min_angle_deg=5.0, max_angle_deg=20.0, preferred_angle_deg=8.0)
    nb = select_neighbours(w2c, np.zeros(3), cfg)
    c = np.array([-w[:3, :3].T @ w[:3, 3] for w in w2c])
    d = -c / np.linalg.norm(c, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1, 1)))
    for i, n in enumerate(nb):
        assert i not in n and len(n) <= 3
        ok = [j for j in range(6) if 5.0 <= ang[i, j] <= 20.0]
        assert set(n) <= set(ok)
        assert len(n) == min(3, len(ok))
        assert list(n) == sorted(n, key=lambda j: abs(ang[i, j] - cfg.preferred_angle_deg))


def test_too_few_points_give_no_depth():
    images, Ks, w2c, _, pts = _scene(n=3)
    calls = []
    d = stereo_depths(
        images, Ks, w2c, pts[:5], MvsConfig(neighbours=2, best_of=1), progress=lambda: calls.append(1)
    )
    assert d.shape == images.shape[:3] and not (d > 0).any() and len(calls) == 3
    with pytest.raises(ValueError, match="two views"):
        stereo_depths(images[:1], Ks[:1], w2c[:1], pts)


def test_averaging_keeps_the_same_pixels_and_cuts_the_noise():
    images, Ks, w2c, truth, pts = _scene()
    cfg = MvsConfig(neighbours=4, best_of=2, min_consistent=2, rel_depth=0.02)
    plain = stereo_depths(images, Ks, w2c, pts, cfg)
    avg = stereo_depths(images, Ks, w2c, pts, MvsConfig(**{**cfg.__dict__, "average": True}))
    assert np.array_equal(plain > 0, avg > 0)  # the same depths kept, only their values change
    valid = plain > 0
    err = lambda d: np.abs(d[valid] - truth[valid]) / truth[valid]  # noqa: E731
    assert np.mean(err(avg)) < np.mean(err(plain))
    assert not np.array_equal(avg, plain)
