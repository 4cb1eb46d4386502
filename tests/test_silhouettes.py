"""train_world.capture.silhouettes: placing a hull inside an inflated one."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from train_world.capture.silhouettes import fit_into_larger

STEP = 0.0025
HALF = np.array([0.03, 0.025, 0.02])


def _inside(p: np.ndarray, grown: float) -> np.ndarray:
    """An object (a box with a block on one end of its top, so that its turn is defined) in its own frame;
    ``grown``: how far the hull extends beyond it towards -x (what a visual hull gains where another object
    hides it from the views that would carve it)."""
    box = np.all(np.abs(p) <= HALF, axis=1)
    block = (p[:, 0] > 0.01) & (p[:, 0] <= HALF[0]) & (np.abs(p[:, 1]) <= 0.01) & (p[:, 2] > HALF[2])
    block &= p[:, 2] <= HALF[2] + 0.015
    extra = (
        (p[:, 0] < -HALF[0]) & (p[:, 0] >= -HALF[0] - grown) & np.all(np.abs(p[:, 1:]) <= HALF[1:], axis=1)
    )
    return box | block | extra


def _hull(pose: np.ndarray, grown: float = 0.0) -> np.ndarray:
    """Voxel centres ``[N,3]`` (a world-aligned grid of STEP) of the object at ``pose``."""
    c = pose[:3, 3]
    axes = [np.arange(x - 0.06, x + 0.06, STEP) + STEP / 2 for x in c]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    local = (g - c) @ pose[:3, :3]
    return g[_inside(local, grown)]


def _motion(deg: float, t) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def _turned(T: np.ndarray, deg: float, about: np.ndarray) -> np.ndarray:
    """``T`` followed by a turn of ``deg`` about the vertical through ``about``."""
    S = _motion(deg, 0.0)
    S[:3, 3] = about - S[:3, :3] @ about
    return S @ T


@pytest.mark.parametrize("inflated_state", [1, 2])
def test_the_smaller_hull_goes_inside_the_inflated_one(inflated_state):
    T_true = _motion(30.0, [0.05, -0.02, 0.0])
    h1 = _hull(np.eye(4), 0.02 if inflated_state == 1 else 0.0)
    h2 = _hull(T_true, 0.02 if inflated_state == 2 else 0.0)
    assert max(len(h1), len(h2)) > 1.25 * min(len(h1), len(h2))
    # the centroids are off by the excess, and the turn a few degrees
    start = T_true.copy()
    start[:3, 3] = h2.mean(axis=0) - start[:3, :3] @ h1.mean(axis=0)
    start = _turned(start, 3.0, h2.mean(axis=0))
    assert np.linalg.norm(start[:3, 3] - T_true[:3, 3]) > 0.004
    T = fit_into_larger(h1, h2, STEP, start)
    # the true object's centre (the origin in the first state) lands where it really went
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.5 * STEP, T[:3, 3] - T_true[:3, 3]
    # the turn is nearer than the start's 3 degrees (the colours refine it after, in dsg-capture)
    assert np.degrees(Rotation.from_matrix(T[:3, :3] @ T_true[:3, :3].T).magnitude()) < 2.0
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)


def test_hulls_of_one_size_fit_as_before():
    """Two hulls of the same object: fitting the smaller into the larger is trimmed ICP, and finds the motion."""
    T_true = _motion(-20.0, [0.01, 0.03, 0.0])
    h1, h2 = _hull(np.eye(4)), _hull(T_true)
    T = fit_into_larger(h1, h2, STEP, _turned(T_true, 3.0, T_true[:3, 3]))
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.5 * STEP
    assert np.degrees(Rotation.from_matrix(T[:3, :3] @ T_true[:3, :3].T).magnitude()) < 2.0  # from 3


def test_carving_counts_every_view_as_a_plain_projection_does():
    """The compiled carving kernel against the projection written out in numpy: the same pixel for every
    point, behind-the-camera and off-image points not seen."""
    from train_world.capture.silhouettes import _carve_view

    rng = np.random.default_rng(3)
    X = rng.uniform(-0.3, 0.3, (5000, 3))
    inside, outside, seen = (np.zeros(len(X), np.int32) for _ in range(3))
    ref = [np.zeros(len(X), np.int64) for _ in range(3)]
    for k in range(4):
        w2c = np.eye(4)
        w2c[:3, :3] = Rotation.from_rotvec(rng.normal(0.0, 0.4, 3)).as_matrix()
        w2c[:3, 3] = [0.0, 0.0, 0.25]  # some points behind the camera
        K = np.array([[70.0 + k, 0.0, 31.0], [0.0, 72.0, 29.5], [0.0, 0.0, 1.0]])
        ids = rng.integers(0, 3, (60, 64)).astype(np.uint8)
        _carve_view(X, w2c[:3].copy(), K[0, 0], K[1, 1], K[0, 2], K[1, 2], ids, 2, inside, outside, seen)
        c = X @ w2c[:3, :3].T + w2c[:3, 3]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * c[:, 0] / c[:, 2] + K[0, 2]
            v = K[1, 1] * c[:, 1] / c[:, 2] + K[1, 2]
        ok = (c[:, 2] > 0) & (u >= 0) & (u < 64) & (v >= 0) & (v < 60)
        label = ids[np.where(ok, v, 0).astype(np.int64), np.where(ok, u, 0).astype(np.int64)]
        ref[0] += ok & (label == 2)
        ref[1] += ok & (label == 0)
        ref[2] += ok
    assert 0 < ref[2].mean() < 4  # some points in view, some not
    for got, want in zip((inside, outside, seen), ref, strict=True):
        assert np.array_equal(got, want)
