"""Renderer analytic cases: single Gaussians with known alpha profiles and footprints, the antialiasing
opacity factor and the low-pass variance, depth order, the pixel-centre convention, depth modes, empty scenes
and option validation."""

from __future__ import annotations

import math

import pytest
import torch

from benchmarks.splat_scenes import intrinsics, random_scene
from dsg_gym.splat import rasterize


def _single(
    mean,
    scale,
    opacity,
    color,
    width=33,
    height=33,
    quat=(1.0, 0.0, 0.0, 0.0),
    backend="numba",
    rasterize_mode="classic",
):
    K = intrinsics(width, height)[None]
    scale = list(scale) if isinstance(scale, (list, tuple)) else [scale] * 3
    return rasterize(
        torch.tensor([mean], dtype=torch.float32),
        torch.tensor([quat]),
        torch.tensor([scale]),
        torch.tensor([opacity]),
        torch.tensor([color]),
        torch.eye(4)[None],
        K,
        width,
        height,
        backend=backend,
        rasterize_mode=rasterize_mode,
    )


def test_antialiasing_factor_is_the_determinant_ratio():
    """Opacity x sqrt(det Sigma / det(Sigma + 0.3 I)), from the 2D covariance of one projected Gaussian."""
    from dsg_gym.splat.numba_project import BLUR

    for scale, rot in (
        (0.01, (1.0, 0.0, 0.0, 0.0)),
        (0.05, (0.9, 0.3, -0.2, 0.1)),
        (0.3, (0.6, 0.0, 0.8, 0.0)),
    ):
        out = _single(
            [0.05, -0.02, 2.0],
            [scale, 0.4 * scale, 1.5 * scale],
            0.7,
            [1.0, 1.0, 1.0],
            quat=rot,
            rasterize_mode="antialiased",
        )
        cn = out[2]["conics"][0, 0].double()
        sig = torch.linalg.inv(torch.tensor([[cn[0], cn[1]], [cn[1], cn[2]]]))  # blurred covariance
        want = 0.7 * math.sqrt(
            float(torch.det(sig - BLUR * torch.eye(2, dtype=torch.float64)) / torch.det(sig))
        )
        assert abs(float(out[2]["opacities"][0, 0]) - want) <= 1e-5
    # A Gaussian much smaller than a pixel keeps its integrated weight (~ o * 2 pi sqrt(det Sigma)) instead of
    # growing to the low-pass's size: total rendered alpha far below the classic mode's.
    tiny = [0.0005, 0.0005, 0.0005]
    aa = _single([0.0, 0.0, 2.0], tiny, 0.9, [1.0, 1.0, 1.0], rasterize_mode="antialiased")[1].sum()
    classic = _single([0.0, 0.0, 2.0], tiny, 0.9, [1.0, 1.0, 1.0])[1].sum()
    assert float(aa) < 0.1 * float(classic)


def test_rasterize_mode_and_eps2d_are_validated():
    s = random_scene(5)
    with pytest.raises(ValueError, match="rasterize_mode"):
        rasterize(**s, rasterize_mode="mip")
    for bad in (0.0, -0.1, float("nan"), "0.3"):
        with pytest.raises(ValueError, match="eps2d"):
            rasterize(**s, eps2d=bad)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_eps2d_is_the_low_pass_variance(backend):
    """A Gaussian's projected variance is (f s / z)^2 + eps2d: the rendered alpha profile follows it."""
    W = H = 33
    f = float(intrinsics(W, H)[0, 0])
    z, s, o = 3.0, 0.02, 0.8
    for eps in (0.1, 0.3, 1.0):
        K = intrinsics(W, H)[None]
        _, alpha, _ = rasterize(
            torch.tensor([[0.0, 0.0, z]]),
            torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
            torch.tensor([[s, s, s]]),
            torch.tensor([o]),
            torch.ones(1, 3),
            torch.eye(4)[None],
            K,
            W,
            H,
            backend=backend,
            eps2d=eps,
        )
        var = (f * s / z) ** 2 + eps
        assert float(alpha[0, 16, 17, 0]) == pytest.approx(o * math.exp(-0.5 / var), rel=1e-5)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_isotropic_gaussian_at_centre(backend):
    W = H = 33
    K = intrinsics(W, H)
    f = float(K[0, 0])
    z, s, o = 3.0, 0.05, 0.8
    # The principal point is at (16.5, 16.5): the centre of pixel (16, 16).
    out, alpha, meta = _single((0.0, 0.0, z), s, o, (1.0, 0.5, 0.25), W, H, backend=backend)
    img = alpha[0, :, :, 0]
    peak = torch.nonzero(img == img.max())
    assert peak.tolist() == [[16, 16]]
    assert img[16, 16] == pytest.approx(o, rel=1e-6)
    assert out[0, 16, 16].tolist() == pytest.approx([o, 0.5 * o, 0.25 * o], rel=1e-6)
    var = (f * s / z) ** 2 + 0.3  # projected variance plus the 0.3 px^2 low-pass
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    r2 = (xs - 16.5) ** 2 + (ys - 16.5) ** 2
    expect = o * torch.exp(-0.5 * r2 / var)
    expect = torch.where(expect >= 1 / 255, expect, torch.zeros_like(expect))
    assert (img - expect).abs().max() <= 1e-5
    # Footprint: zero exactly where alpha would fall below 1/255; radius from the covariance.
    assert torch.equal(img > 0, expect > 0)
    r_expect = math.sqrt(2 * math.log(255 * o) * var)
    assert int(meta["radii"][0, 0, 0]) == math.ceil(r_expect)


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_front_gaussian_wins(backend):
    W = H = 17
    K = intrinsics(W, H)[None]
    means = torch.tensor([[0.0, 0.0, 4.0], [0.0, 0.0, 2.0]])  # the second is in front
    colors = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    args = dict(
        quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
        scales=torch.full((2, 3), 0.2),
        opacities=torch.tensor([0.9, 0.7]),
        viewmats=torch.eye(4)[None],
        Ks=K,
        width=W,
        height=H,
        backend=backend,
    )
    out, alpha, meta = rasterize(means=means, colors=colors, **args)
    c = out[0, 8, 8]
    assert c[0] == pytest.approx(0.7, rel=1e-5)  # front: alpha 0.7, T = 1
    assert c[2] == pytest.approx(0.3 * 0.9, rel=1e-5)  # back: alpha 0.9 behind T = 0.3
    assert alpha[0, 8, 8, 0] == pytest.approx(1 - 0.3 * 0.1, rel=1e-5)
    assert meta["depths"][0].tolist() == pytest.approx([4.0, 2.0])
    # Swapping the list order changes nothing: order comes from depth.
    out2, _, _ = rasterize(
        means=means.flip(0), colors=colors.flip(0), **{**args, "opacities": args["opacities"].flip(0)}
    )
    assert torch.equal(out, out2) if backend == "numba" else (out - out2).abs().max() < 1e-6


@pytest.mark.parametrize("backend", ["numba", "torch"])
def test_gaussian_behind_camera_contributes_nothing(backend):
    leaves = [
        torch.tensor([[0.0, 0.0, -2.0]]),
        torch.tensor([[1.0, 0, 0, 0]]),
        torch.tensor([[0.5] * 3]),
        torch.tensor([0.9]),
        torch.tensor([[1.0, 1.0, 1.0]]),
    ]
    leaves = [t.requires_grad_(True) for t in leaves]
    out, alpha, meta = rasterize(
        *leaves, torch.eye(4)[None], intrinsics(16, 16)[None], 16, 16, backend=backend
    )
    assert alpha.abs().max() == 0 and out.abs().max() == 0
    assert meta["radii"].abs().max() == 0
    (out.sum() + alpha.sum()).backward()
    for t in leaves:
        assert t.grad.abs().max() == 0


def test_pixel_centre_convention():
    """A Gaussian projecting onto (10.5, 7.5) peaks at pixel (x=10, y=7)."""
    W, H = 24, 16
    K = intrinsics(W, H)
    f, cx, cy, z = float(K[0, 0]), float(K[0, 2]), float(K[1, 2]), 3.0
    mean = ((10.5 - cx) * z / f, (7.5 - cy) * z / f, z)
    _, alpha, meta = _single(mean, 0.02, 0.9, (1.0, 1.0, 1.0), W, H)
    img = alpha[0, :, :, 0]
    assert torch.nonzero(img == img.max()).tolist() == [[7, 10]]
    assert meta["means2d"][0, 0].tolist() == pytest.approx([10.5, 7.5], abs=1e-4)


def test_depth_modes():
    s = random_scene(1200, width=32, height=32, seed=9)
    rgb, alpha, _ = rasterize(**s, render_mode="RGB")
    both, alpha2, _ = rasterize(**s, render_mode="RGB+ED")
    d, _, _ = rasterize(**s, render_mode="D")
    ed, _, _ = rasterize(**s, render_mode="ED")
    assert torch.equal(both[..., :-1], rgb) and torch.equal(alpha, alpha2)
    covered = alpha[..., 0] > 0.5
    assert torch.allclose(ed[..., 0][covered], (d[..., 0] / alpha[..., 0])[covered], rtol=1e-5)
    assert torch.allclose(both[..., -1], ed[..., 0], rtol=1e-5, atol=1e-6)
    assert ed[..., 0][covered].min() >= 2.0 - 1e-3 and ed[..., 0][covered].max() <= 6.0 + 1e-3


def test_empty_scene_renders_background():
    z = torch.zeros
    out, alpha, _ = rasterize(
        z(0, 3),
        z(0, 4),
        z(0, 3),
        z(0),
        z(0, 3),
        torch.eye(4)[None],
        intrinsics(16, 8)[None],
        16,
        8,
        backgrounds=torch.tensor([0.2, 0.4, 0.6]),
    )
    assert out.shape == (1, 8, 16, 3) and alpha.abs().max() == 0
    assert torch.allclose(out[0, 3, 5], torch.tensor([0.2, 0.4, 0.6]))
