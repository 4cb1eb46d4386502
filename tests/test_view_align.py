"""Test-time alignment of evaluation cameras (train_world.eval.view_align)."""

from __future__ import annotations

import numpy as np
import pytest

from dsg_gym.gaussians import GaussianSet
from dsg_gym.splat.sh import rgb_to_sh0
from train_world.capture.alignment import rotation_angle_deg
from train_world.eval.evaluate import render_gaussians
from train_world.eval.view_align import ViewAlignment, align_view, correction_matrix

W = H = 48
K = np.array([[46.0, 0, 24.0], [0, 46.0, 24.0], [0, 0, 1]])


def _checker_plane() -> GaussianSet:
    """A 0.5 m checkerboard of small Gaussians in the plane z = 0 with a few blobs above it."""
    n = 56
    xs = (np.arange(n) + 0.5) / n - 0.5
    x, y = np.meshgrid(xs * 0.5, xs * 0.5)
    means = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1)
    cell = ((np.floor(x.ravel() / 0.0625) + np.floor(y.ravel() / 0.0625)) % 2).astype(np.float32)
    rgb = np.stack([0.15 + 0.7 * cell, 0.2 + 0.5 * cell, 0.8 - 0.6 * cell], 1)
    m = len(means)
    import torch

    sh = rgb_to_sh0(torch.from_numpy(rgb.astype(np.float32))).numpy()[:, None, :]
    return GaussianSet(
        means=means.astype(np.float32),
        quats=np.tile([1.0, 0, 0, 0], (m, 1)).astype(np.float32),
        scales=np.full((m, 3), 0.004, np.float32) * [1, 1, 0.2],
        opacities=np.full(m, 0.95, np.float32),
        sh=sh,
    )


def _look_at(eye) -> np.ndarray:
    """OpenCV world-to-camera looking at the origin with +z world up."""
    eye = np.asarray(eye, dtype=np.float64)
    f = -eye / np.linalg.norm(eye)
    r = np.cross(f, [0, 0, 1.0])
    r /= np.linalg.norm(r)
    d = np.cross(f, r)
    R = np.stack([r, d, f])
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = R, -R @ eye
    return vm


def _render(g, vm):
    return render_gaussians(g, vm[None], K[None], W, H)[0][0]


def test_a_perturbed_camera_is_brought_back():
    g = _checker_plane()
    true = _look_at([0.25, -0.3, 0.45])
    target = _render(g, true)
    off = correction_matrix([0.004, -0.003, 0.002], [0.002, -0.001, 0.0]) @ true  # ~0.3 deg, 2 mm
    r = align_view(g, off, K, W, H, target, lambda v: _render(g, v))
    assert r.kept and r.mse_after < 0.25 * r.mse_before
    err_before = rotation_angle_deg(off[:3, :3] @ true[:3, :3].T)
    err_after = rotation_angle_deg(r.viewmat[:3, :3] @ true[:3, :3].T)
    assert err_after < 0.4 * err_before
    assert np.all(np.isfinite(r.viewmat)) and r.rotation_deg > 0
    np.testing.assert_allclose(r.viewmat[:3, :3] @ r.viewmat[:3, :3].T, np.eye(3), atol=1e-9)  # rigid
    again = align_view(g, off, K, W, H, target, lambda v: _render(g, v))
    np.testing.assert_array_equal(again.viewmat, r.viewmat)  # deterministic


def test_the_given_pose_stays_when_aligning_does_not_help():
    g = _checker_plane()
    true = _look_at([0.25, -0.3, 0.45])
    target = _render(g, true)
    # a learning rate that can only overshoot: the exact pose stays, the figures say so
    r = align_view(
        g, true, K, W, H, target, lambda v: _render(g, v), config=ViewAlignment(steps=2, lr_rotation=0.2)
    )
    assert not r.kept and r.mse_after == r.mse_before
    np.testing.assert_array_equal(r.viewmat, true)
    assert r.rotation_deg == 0.0 and r.translation == 0.0


@pytest.mark.parametrize(
    "bad", [{"steps": 0}, {"steps": 2.5}, {"lr_rotation": float("nan")}, {"blur_px": -1.0}]
)
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError, match="view alignment"):
        ViewAlignment(**bad)
