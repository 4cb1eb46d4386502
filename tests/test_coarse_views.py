"""Cross-state renders at a lower resolution (train_world.dual_state.coarse, dsg-train --align-downscale): block
averages and block-majority classes, intrinsics that keep a coarse render where the full camera sees it, the
option's checks, and a two-state run with it branching from a full-resolution reconstruction phase."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import load_world
from train_world.cli import train as train_cli
from train_world.dual_state.coarse import coarse_views
from train_world.dual_state.config import DualConfig
from train_world.single_state.field import SegmentedField
from train_world.single_state.presets import TrainConfig, get_preset


def test_blocks_are_averaged_and_take_their_majority_class():
    img = torch.arange(2 * 5 * 4 * 3, dtype=torch.float32).reshape(2, 5, 4, 3)
    rows = [[0, 1, 2, 2], [1, 1, 2, 0], [0, 0, 1, 2], [2, 0, 1, 2], [1, 1, 1, 1]]
    cls = torch.tensor(rows)[None].repeat(2, 1, 1)
    K = torch.tensor([[10.0, 0, 2.0], [0, 12.0, 2.5], [0, 0, 1]])[None].repeat(2, 1, 1)
    v = coarse_views(img, cls, K, 2, 3)
    assert (v.width, v.height) == (2, 2) and v.images.shape == (2, 2, 2, 3)  # the fifth row is dropped
    assert torch.equal(v.images[0, 1, 0], img[0, 2:4, 0:2].reshape(-1, 3).mean(0))
    # blocks: [[0,1],[1,1]] -> 1; [[2,2],[2,0]] -> 2; [[0,0],[2,0]] -> 0; [[1,2],[1,2]] -> tie 1/2 -> 1
    assert v.classes[0].tolist() == [[1, 2], [0, 1]]
    assert torch.equal(v.Ks[0], torch.tensor([[5.0, 0, 1.0], [0, 6.0, 1.25], [0, 0, 1]]))
    assert coarse_views(img, None, K, 1, 3).images.shape == img.shape
    with pytest.raises(ValueError, match="factor"):
        coarse_views(img, cls, K, 0, 3)
    with pytest.raises(ValueError, match="smaller"):
        coarse_views(img, cls, K, 8, 3)


def test_a_coarse_render_sees_what_the_full_camera_sees():
    """One small Gaussian off the optical axis: its blob's centroid in the coarse render, scaled back, is the
    full render's centroid (a half-pixel slip of the principal point would move it by 0.5 px)."""
    f = SegmentedField.from_points(
        torch.tensor([[0.031, -0.017, 0.0]], dtype=torch.float64), torch.ones(1, 3, dtype=torch.float64),
        torch.full((1,), 0.006, dtype=torch.float64), sh_degree=0, num_features=1, opacity=0.9,
    )  # fmt: skip
    V = torch.eye(4)
    V[2, 3] = 1.0
    K = torch.tensor([[64.0, 0, 32.0], [0, 64.0, 32.0], [0, 0, 1]])
    v = coarse_views(torch.zeros(1, 64, 64, 3), None, K[None], 2, 1)

    def centroid(Kc, size):
        with torch.no_grad():
            w = f.render(V[None], Kc[None], size, size, with_features=False).rgb[0, ..., 0].double()
        ys, xs = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
        return np.array([float((w * xs).sum() / w.sum()), float((w * ys).sum() / w.sum())])

    fine, coarse = centroid(K, 64), centroid(v.Ks[0], 32)
    assert np.allclose(fine, [32 + 64 * 0.031, 32 - 64 * 0.017], atol=0.05)
    assert np.allclose(2 * coarse, fine, atol=0.05)


def test_the_option_is_checked():
    base = TrainConfig(preset=get_preset("quick"))
    for bad in (0, -2, 1.5, True):
        with pytest.raises(ValueError, match="align_downscale"):
            DualConfig(base=base, align_downscale=bad)
    assert DualConfig(base=base).align_downscale == 1


def test_two_state_training_with_coarse_cross_state_renders(tmp_path):
    cap = tiny_capture(tmp_path, test_views=2, test_states=1)
    common = ["--preset", "quick", "--iterations", "60", "--prune-every", "10", "--quiet"]
    ck = tmp_path / "recon.ckpt"
    run = train_cli.main_two_state
    recon = ["--stop-at-joint", "--checkpoint", str(ck)]
    assert run([str(cap), "--out", str(tmp_path / "r.dsgworld"), *common, *recon]) == 0
    out = tmp_path / "w.dsgworld"
    coarse = ["--align-downscale", "2", "--branch-from", str(ck)]
    assert run([str(cap), "--out", str(out), *common, *coarse]) == 0
    w = load_world(out)
    assert w.metadata["dual"]["align_downscale"] == 2
    assert np.isfinite(w.gaussians().means).all() and w.gaussians().num > 0
    full = tmp_path / "full.dsgworld"
    assert run([str(cap), "--out", str(full), *common, "--branch-from", str(ck)]) == 0
    assert not np.array_equal(
        load_world(full).gaussians().means, w.gaussians().means
    )  # the joint phase differs
