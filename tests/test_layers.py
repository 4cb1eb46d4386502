"""Two-layer splatting (dsg_gym.splat.layers): background and objects merged per pixel by expected depth."""

from __future__ import annotations

import pytest
import torch

from dsg_gym.splat import rasterize
from dsg_gym.splat.layers import merge_layers, rasterize_layers
from dsg_gym.splat_options import LAYER_MARGIN


def _scene(n_front=60, n_back=90, front_z=1.5, back_z=3.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = n_front + n_back
    means = torch.rand(n, 3, generator=g) * 0.8 - 0.4
    means[:n_front, 2] = front_z + torch.rand(n_front, generator=g) * 0.2
    means[n_front:, 2] = back_z + torch.rand(n_back, generator=g) * 0.2
    quats = torch.randn(n, 4, generator=g)
    scales = torch.rand(n, 3, generator=g) * 0.04 + 0.01
    opac = torch.rand(n, generator=g) * 0.8 + 0.1
    cols = torch.rand(n, 3, generator=g)
    front = torch.arange(n) < n_front
    K = torch.tensor([[[48.0, 0, 24], [0, 48.0, 24], [0, 0, 1]]])
    return front, means, quats, scales, opac, cols, torch.eye(4)[None], K


@pytest.mark.parametrize("objects_in_front", [True, False])
def test_layers_apart_in_depth_render_as_one_sorted_list(objects_in_front):
    """When every Gaussian of one layer is nearer than every one of the other, the merge is the sorted render."""
    front, means, quats, scales, opac, cols, vm, K = _scene(
        front_z=1.5 if objects_in_front else 4.0, back_z=2.5
    )
    bg = torch.tensor([0.2, 0.3, 0.4])
    a, alpha_a, _ = rasterize(
        means, quats, scales, opac, cols, vm, K, 48, 48, backgrounds=bg, render_mode="RGB+D"
    )
    b, alpha_b, meta = rasterize_layers(
        front, means, quats, scales, opac, cols, vm, K, 48, 48, backgrounds=bg, render_mode="RGB+D"
    )
    assert b.shape == a.shape == (1, 48, 48, 4)
    assert float(alpha_a.max()) > 0.9  # the layers cover the view
    torch.testing.assert_close(b, a, atol=2e-5, rtol=1e-5)
    torch.testing.assert_close(alpha_b, alpha_a, atol=2e-6, rtol=0)
    assert [len(i) for i in meta["index"]] == [60, 90] and len(meta["layers"]) == 2


def _pixel(color, alpha, depth):
    return (
        torch.tensor(color).reshape(1, 1, 1, -1),
        torch.tensor([[[[alpha]]]]),
        torch.tensor([[[[depth]]]]),
    )


def test_merge_puts_the_layer_with_the_smaller_expected_depth_in_front():
    # layer a: alpha 0.5 at expected depth 2 (accumulated 1.0); layer b: alpha 0.8 at expected depth 1
    a = _pixel([0.5, 0.0, 0.0], 0.5, 1.0)
    b = _pixel([0.0, 0.8, 0.0], 0.8, 0.8)
    bg = torch.tensor([[0.0, 0.0, 1.0]])
    col, alpha, depth = merge_layers(*a, *b, backgrounds=bg)
    # b in front: b + (1 - 0.8) a + (1 - 0.8)(1 - 0.5) bg
    torch.testing.assert_close(col.reshape(3), torch.tensor([0.1, 0.8, 0.1]))
    assert float(alpha) == pytest.approx(0.9) and float(depth) == pytest.approx(0.8 + 0.2 * 1.0)
    # the same layers the other way round: a is now nearer
    a2 = _pixel([0.5, 0.0, 0.0], 0.5, 0.25)
    col, _, _ = merge_layers(*a2, *b, backgrounds=bg)
    torch.testing.assert_close(col.reshape(3), torch.tensor([0.5, 0.4, 0.1]))


def test_the_objects_layer_stays_in_front_within_the_margin():
    """At an object's base its expected depth lies just behind the table's: within LAYER_MARGIN of it, the objects'
    layer (a) stays in front; beyond it, the background goes over it."""
    b = _pixel([0.0, 0.9, 0.0], 0.9, 0.9)  # the table, expected depth 1.0
    within = _pixel([0.9, 0.0, 0.0], 0.9, 0.9 * (1.0 + 0.5 * LAYER_MARGIN))
    beyond = _pixel([0.9, 0.0, 0.0], 0.9, 0.9 * (1.0 + 2.0 * LAYER_MARGIN))
    assert 0 < LAYER_MARGIN < 0.05
    assert float(merge_layers(*within, *b)[0][..., 0]) == pytest.approx(0.9)  # the object in front
    assert float(merge_layers(*beyond, *b)[0][..., 0]) == pytest.approx(0.09)  # behind the table
    assert float(merge_layers(*within, *b, margin=0.0)[0][..., 0]) == pytest.approx(0.09)  # no margin: strict


def test_merge_of_an_empty_layer_is_the_other_layer():
    a = _pixel([0.0, 0.0, 0.0], 0.0, 0.0)  # covers nothing: its expected depth is infinite
    b = _pixel([0.3, 0.2, 0.1], 0.6, 1.8)
    col, alpha, depth = merge_layers(*a, *b)
    torch.testing.assert_close(col.reshape(3), torch.tensor([0.3, 0.2, 0.1]))
    assert float(alpha) == pytest.approx(0.6) and float(depth) == pytest.approx(1.8)
    col2, alpha2, _ = merge_layers(*b, *a)
    torch.testing.assert_close(col2, col)
    assert float(alpha2) == pytest.approx(0.6)
    none = merge_layers(*a, *a)
    assert all(bool(torch.isfinite(t).all()) for t in none) and float(none[1]) == 0.0


def test_a_faint_background_gaussian_centred_in_front_no_longer_veils_the_object():
    """The case one sorted list gets wrong: a faint, wide background Gaussian (a table disc) centred nearer than an
    object, in front of an opaque background farther away. The background layer's expected depth at the object
    (2.8 here) is behind the object (2.2), so two layers draw the object first; one list blends the disc over it."""
    means = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3.0], [0.0, 0.0, 2.2]])
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).expand(3, 4).contiguous()
    scales = torch.tensor([[0.5, 0.5, 0.001], [1.0, 1.0, 0.001], [0.2, 0.2, 0.2]])
    opac = torch.tensor([0.3, 0.95, 0.95])
    cols = torch.tensor(
        [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
    )  # blue disc, green wall, red object
    front = torch.tensor([False, False, True])
    vm, K = torch.eye(4)[None], torch.tensor([[[48.0, 0, 24], [0, 48.0, 24], [0, 0, 1]]])
    one, _, _ = rasterize(means, quats, scales, opac, cols, vm, K, 48, 48)
    two, _, _ = rasterize_layers(front, means, quats, scales, opac, cols, vm, K, 48, 48)
    red_one, red_two = float(one[0, 24, 24, 0]), float(two[0, 24, 24, 0])
    assert red_two > 0.9  # the object, drawn first
    assert red_one < 0.75 * red_two  # veiled by the disc's 0.3
    # away from the object both renders are the same two background Gaussians
    torch.testing.assert_close(two[0, 2, 2], one[0, 2, 2], atol=1e-6, rtol=0)


def test_layered_renders_are_differentiable_and_check_their_input():
    front, means, quats, scales, opac, cols, vm, K = _scene(front_z=2.6, back_z=2.5)  # layers interleave
    means = means.clone().requires_grad_(True)
    cols = cols.clone().requires_grad_(True)
    out, alpha, _ = rasterize_layers(
        front, means, quats, scales, opac, cols, vm, K, 48, 48, render_mode="RGB+D"
    )
    (out.sum() + alpha.sum()).backward()
    for t in (means.grad, cols.grad):
        assert bool(torch.isfinite(t).all())
        assert float(t[:60].abs().sum()) > 0 and float(t[60:].abs().sum()) > 0  # both layers get gradients
    with pytest.raises(ValueError, match="front must be"):
        rasterize_layers(front[:-1], means, quats, scales, opac, cols, vm, K, 48, 48)
    with pytest.raises(ValueError, match="render_mode"):
        rasterize_layers(front, means, quats, scales, opac, cols, vm, K, 48, 48, render_mode="ED")
