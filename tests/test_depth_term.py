"""The optional depth term (preset ``lambda_depth``, ``dsg-train --depth-weight``; not part of DSG-World)."""

from __future__ import annotations

import math

import pytest
import torch
from _captures import tiny_capture

from train_world.cli.train import two_state_config as config_from_args
from train_world.cli.train import two_state_parser as dual_parser
from train_world.single_state.data import load_training_data
from train_world.single_state.field import SegmentedField
from train_world.single_state.losses import depth_loss
from train_world.single_state.presets import TrainConfig, get_preset
from train_world.single_state.trainer import Trainer


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("cap"), test_views=2)


def test_depth_loss_hand_cases():
    gt = torch.tensor([[1.0, 2.0], [0.0, 4.0]])  # one pixel without depth
    alpha = torch.tensor([[1.0, 0.8], [1.0, 0.2]])  # one pixel too transparent to count
    exact = gt * alpha
    assert float(depth_loss(exact, alpha, gt)) == pytest.approx(0.0, abs=1e-7)
    off = exact.clone()
    off[0, 0] = 1.1  # 10% too far
    off[0, 1] = 0.8 * 1.8  # 10% too near
    off[1, 0] = 123.0  # no depth there: ignored
    off[1, 1] = 0.0  # alpha 0.2: ignored
    assert float(depth_loss(off, alpha, gt)) == pytest.approx(0.1, abs=1e-6)
    # the gradient pulls each counted pixel towards its depth and leaves the others alone
    x = off.clone().requires_grad_(True)
    depth_loss(x, alpha, gt).backward()
    assert x.grad[0, 0] > 0 and x.grad[0, 1] < 0
    assert x.grad[1, 0] == 0 and x.grad[1, 1] == 0
    # nothing counts: zero, still differentiable
    y = torch.ones(2, 2, requires_grad=True)
    z = depth_loss(y, torch.full((2, 2), 0.1), gt)
    z.backward()
    assert float(z.detach()) == 0.0 and torch.equal(y.grad, torch.zeros(2, 2))


def _wall(z: float) -> SegmentedField:
    """A fronto-parallel wall of opaque Gaussians at camera-space depth ``z`` (identity camera)."""
    xs = torch.linspace(-1.0, 1.0, 21)
    gx, gy = torch.meshgrid(xs, xs, indexing="ij")
    means = torch.stack([gx.reshape(-1), gy.reshape(-1), torch.full((441,), z)], -1)
    f = SegmentedField.from_points(
        means, torch.full((441, 3), 0.5), torch.full((441,), 0.08), sh_degree=0, num_features=4
    )
    with torch.no_grad():
        f.opacity_logits.fill_(6.0)
    return f


def test_render_with_depth_gives_camera_space_z_and_leaves_colours_alone():
    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    vm = torch.eye(4)[None]
    f = _wall(2.0)
    with torch.no_grad():
        plain = f.render(vm, K, 32, 32, with_features=True)
        out = f.render(vm, K, 32, 32, with_features=True, with_depth=True)
        T = torch.eye(4)
        T[2, 3] = 0.5  # move the wall 0.5 further away
        moved = f.render(vm, K, 32, 32, with_features=False, with_depth=True, transform=T)
    assert plain.depth is None
    assert torch.equal(out.rgb, plain.rgb) and torch.equal(out.features, plain.features)
    a = out.alpha[0, ..., 0]
    assert bool((a > 0.99).all())
    assert torch.allclose(out.depth[0] / a, torch.full_like(a, 2.0), atol=1e-4)
    assert torch.allclose(moved.depth[0] / moved.alpha[0, ..., 0], torch.full_like(a, 2.5), atol=1e-4)
    # the depth channel is differentiable in the means
    means = f.means
    out = f.render(vm, K, 32, 32, with_features=False, with_depth=True)
    depth_loss(out.depth[0], out.alpha[0, ..., 0], torch.full((32, 32), 2.2)).backward()
    assert float(means.grad[:, 2].sum()) < 0  # pulled towards 2.2: z grows


def _config(lambda_depth: float) -> TrainConfig:
    return TrainConfig(preset=get_preset("quick", lambda_depth=lambda_depth), single_state=True, seed=3)


@torch.no_grad()
def _depth_error(t: Trainer) -> float:
    d = t.data
    out = t.field.render(d.viewmats, d.Ks, d.width, d.height, with_features=False, with_depth=True)
    a = out.alpha[..., 0]
    ok = (d.depths > 0) & (a > 0.5)
    return float(((out.depth[ok] / a[ok] - d.depths[ok]).abs() / d.depths[ok]).mean())


def test_depth_term_pulls_the_field_onto_the_captured_depth(tiny):
    runs = {}
    for w in (0.0, 1.0):
        cfg = _config(w)
        t = Trainer(load_training_data(tiny, cfg), cfg)
        assert t.uses_depth == (w > 0)
        stats = t.train_step()
        assert ("depth" in stats) == (w > 0)
        t.train(progress=False)
        runs[w] = _depth_error(t)
        assert math.isfinite(runs[w])
    assert runs[1.0] < 0.7 * runs[0.0], runs


def test_depth_weight_option_and_validation(tiny):
    args = dual_parser().parse_args(
        [str(tiny), "--out", "w.dsgworld", "--preset", "quick", "--depth-weight", "0.3"]
    )
    assert config_from_args(args).base.preset.lambda_depth == 0.3
    args = dual_parser().parse_args([str(tiny), "--out", "w.dsgworld", "--preset", "quick"])
    assert config_from_args(args).base.preset.lambda_depth == 0.0  # off unless asked for
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="lambda_depth"):
            get_preset("quick", lambda_depth=bad)
