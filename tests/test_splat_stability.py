"""Renderer numerical stability and input validation: one test per case."""

from __future__ import annotations

import pytest
import torch

from benchmarks.splat_scenes import intrinsics, random_scene
from dsg_gym.splat import rasterize

BACKENDS = ["numba", "torch"]


def _run(backend, means, quats, scales, opacities, width=24, height=20, **kw):
    n = means.shape[0]
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities)]
    colors = torch.rand(n, 4, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    out, alpha, meta = rasterize(
        *leaves,
        colors,
        torch.eye(4)[None],
        intrinsics(width, height)[None],
        width,
        height,
        backend=backend,
        render_mode="RGB+ED",
        **kw,
    )
    g = torch.Generator().manual_seed(1)
    loss = (out * torch.randn(out.shape, generator=g)).sum() + (
        alpha * torch.randn(alpha.shape, generator=g)
    ).sum()
    loss.backward()
    assert torch.isfinite(out).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all()
    for t in leaves + [colors]:
        assert torch.isfinite(t.grad).all()
    return out.detach(), alpha.detach(), meta, [t.grad for t in leaves + [colors]]


def _base(n=3):
    means = torch.tensor([[0.0, 0.0, 3.0], [0.3, -0.2, 2.5], [-0.4, 0.1, 4.0]])[:n]
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.9, 0.1, -0.2, 0.3], [0.5, 0.5, 0.5, 0.5]])[:n]
    scales = torch.full((n, 3), 0.1)
    opacities = torch.tensor([0.8, 0.6, 0.9])[:n]
    return means, quats, scales, opacities


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_quaternion_is_identity(backend):
    m, q, s, o = _base()
    s = torch.tensor([[0.2, 0.05, 0.1]] * 3)
    q0 = q.clone()
    q0[1] = 0.0
    qi = q.clone()
    qi[1] = torch.tensor([1.0, 0.0, 0.0, 0.0])
    a, _, _, grads = _run(backend, m, q0, s, o)
    b, _, _, _ = _run(backend, m, qi, s, o)
    assert (a - b).abs().max() <= 1e-6
    assert grads[1][1].abs().max() == 0  # no direction to move a zero quaternion


@pytest.mark.parametrize("backend", BACKENDS)
def test_unnormalised_quaternions_render_like_normalised(backend):
    m, q, s, o = _base()
    s = torch.tensor([[0.2, 0.05, 0.1]] * 3)
    a, _, _, _ = _run(backend, m, q * 7.5, s, o)
    b, _, _, _ = _run(backend, m, q / q.norm(dim=-1, keepdim=True), s, o)
    assert (a - b).abs().max() <= 1e-5


@pytest.mark.parametrize("backend", BACKENDS)
def test_degenerate_scales(backend):
    m, q, s, o = _base()
    s = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [1e-12, 1e-12, 0.2]])
    out, alpha, meta, _ = _run(backend, m, q, s, o)
    assert alpha.max() > 0.5  # the low-pass keeps even a point Gaussian visible
    assert (meta["radii"][0] > 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_huge_covariance(backend):
    m, q, s, o = _base()
    s = torch.tensor([[1e6, 1e6, 1e6], [1e3, 1e-3, 1.0], [0.1, 0.1, 0.1]])
    out, alpha, meta, _ = _run(backend, m, q, s, o)
    assert (meta["radii"] >= 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("z", [0.0, 0.01, 0.0100001, 1e-7, -1e-7])
def test_at_or_behind_camera_plane(backend, z):
    m, q, s, o = _base()
    m[0] = torch.tensor([0.0, 0.0, z])
    out, alpha, meta, _ = _run(backend, m, q, s, o)
    if z < 0.01:
        assert meta["radii"][0, 0].abs().max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_far_outside_the_image(backend):
    m, q, s, o = _base()
    m[0] = torch.tensor([1e6, -1e6, 3.0])
    m[1] = torch.tensor([50.0, 0.0, 0.011])  # projects ~1e5 px away
    out, alpha, meta, grads = _run(backend, m, q, s, o)
    assert meta["radii"][0, :2].abs().max() == 0
    assert grads[0][:2].abs().max() == 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_straddling_near_plane_large_gaussian(backend):
    m, q, s, o = _base()
    m[0] = torch.tensor([0.5, 0.0, 0.02])
    s[0] = torch.tensor([5.0, 5.0, 5.0])
    _run(backend, m, q, s, o)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_zero_and_one(backend):
    m, q, s, o = _base()
    o = torch.tensor([0.0, 1.0, 1.0])
    m[2] = m[1] + torch.tensor([0.0, 0.0, 0.5])  # opaque one behind an opaque one
    out, alpha, meta, grads = _run(backend, m, q, s, o)
    assert meta["radii"][0, 0].abs().max() == 0  # opacity 0 can never reach 1/255
    assert alpha.max() <= 1.0 and alpha.max() >= 0.99


def test_float32_agrees_with_float64():
    s64 = random_scene(800, width=40, height=32, seed=21, dtype=torch.float64)
    s32 = {k: (v.float() if isinstance(v, torch.Tensor) else v) for k, v in s64.items()}
    a, aa, _ = rasterize(**s64)
    b, ba, _ = rasterize(**s32)
    assert (a.float() - b).abs().max() <= 1e-5
    assert (aa.float() - ba).abs().max() <= 1e-5


# ---------------------------------------------------------------------------------------------
# Bad input: a ValueError naming the argument.


def _good():
    return random_scene(10, width=16, height=16, seed=0)


@pytest.mark.parametrize("name", ["means", "quats", "scales", "opacities", "colors", "viewmats", "Ks"])
@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_names_argument(name, bad):
    s = _good()
    t = s[name].clone()
    t.view(-1)[3] = bad
    s[name] = t
    with pytest.raises(ValueError, match=name):
        rasterize(**s)


@pytest.mark.parametrize(
    "name,shape",
    [
        ("means", (10, 2)),
        ("quats", (10, 3)),
        ("scales", (9, 3)),
        ("opacities", (10, 1)),
        ("colors", (9, 3)),
        ("viewmats", (1, 3, 4)),
        ("Ks", (2, 3, 3)),
    ],
)
def test_wrong_shape_names_argument(name, shape):
    s = _good()
    s[name] = torch.rand(shape)
    with pytest.raises(ValueError, match=name):
        rasterize(**s)


def test_wrong_dtypes_and_values():
    s = _good()
    with pytest.raises(ValueError, match="quats"):
        rasterize(**{**s, "quats": s["quats"].double()})
    with pytest.raises(ValueError, match="means"):
        rasterize(**{**s, "means": s["means"].long()})
    with pytest.raises(ValueError, match="opacities"):
        rasterize(**{**s, "opacities": s["opacities"] + 1.0})
    with pytest.raises(ValueError, match="scales"):
        rasterize(**{**s, "scales": -s["scales"]})
    with pytest.raises(ValueError, match="render_mode"):
        rasterize(**s, render_mode="RGBD")
    with pytest.raises(ValueError, match="backend"):
        rasterize(**s, backend="cuda")
    with pytest.raises(ValueError, match="width"):
        rasterize(**{**s, "width": 0})
    with pytest.raises(ValueError, match="near_plane"):
        rasterize(**s, near_plane=-1.0)
    with pytest.raises(ValueError, match="backgrounds"):
        rasterize(**s, backgrounds=torch.zeros(1, 5))
    with pytest.raises(ValueError, match="means"):
        rasterize(**{**s, "means": s["means"].tolist()})
