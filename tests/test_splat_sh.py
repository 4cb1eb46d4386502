"""Spherical harmonics of the renderer: the orthonormal basis, rotating coefficients with a Gaussian, the numba
evaluation against the torch reference with gradients, and degree 0 as the DC colour."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from benchmarks.splat_scenes import random_scene
from dsg_gym.splat import C0, rasterize, spherical_harmonics


def test_spherical_harmonics_orthonormal():
    """Real SH basis (degree 3, 3DGS order) is orthonormal on the sphere (Gauss-Legendre quadrature)."""
    import numpy as np

    xg, wg = np.polynomial.legendre.leggauss(16)
    nphi = 32
    phi = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    ct, ph = np.meshgrid(xg, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = torch.tensor(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    w = torch.tensor((wg[:, None] * np.full(nphi, 2 * np.pi / nphi)[None]).reshape(-1))
    basis = []
    for k in range(16):
        coeffs = torch.zeros(dirs.shape[0], 16, 1, dtype=torch.float64)
        coeffs[:, k, 0] = 1.0
        basis.append(spherical_harmonics(3, dirs, coeffs)[:, 0])
    B = torch.stack(basis, 1)  # [P, 16]
    gram = (B * w[:, None]).T @ B
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=1e-10)


def test_spherical_harmonics_gradients_and_broadcasting():
    """Per-camera directions [C, N, 3] against shared coefficients [1, N, K, 3]: value equals the explicit
    sum over the basis columns, and autograd's gradients (coefficients and directions) pass gradcheck."""
    from dsg_gym.sh_basis import basis_columns

    g = torch.Generator().manual_seed(5)
    dirs = torch.randn(2, 6, 3, generator=g, dtype=torch.float64, requires_grad=True)
    coeffs = torch.randn(1, 6, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    for deg in (1, 2, 3):
        got = spherical_harmonics(deg, dirs, coeffs)
        u = dirs / dirs.norm(dim=-1, keepdim=True)
        cols = basis_columns(deg, u[..., 0], u[..., 1], u[..., 2], torch.ones_like(u[..., 0]))
        want = sum(c[..., None] * coeffs[..., i, :] for i, c in enumerate(cols))
        assert got.shape == (2, 6, 3) and torch.allclose(got, want, atol=1e-12)
        assert torch.autograd.gradcheck(lambda d, c: spherical_harmonics(deg, d, c), (dirs, coeffs))


def test_sh_degree_zero_matches_dc_colour():
    s = random_scene(500, width=32, height=32, seed=2, channels=3)
    sh = torch.randn(500, 16, 3, generator=torch.Generator().manual_seed(0)) * 0.3
    a, _, _ = rasterize(**{**s, "colors": sh}, sh_degree=0)
    b, _, _ = rasterize(**{**s, "colors": torch.clamp_min(C0 * sh[:, 0] + 0.5, 0.0)})
    assert torch.equal(a, b)
    c, _, _ = rasterize(**{**s, "colors": sh}, sh_degree=3)
    assert not torch.allclose(a, c)  # higher degrees are view dependent


def test_sh_rotation_turns_the_colour_function_with_the_gaussian():
    from scipy.spatial.transform import Rotation

    from dsg_gym.sh_basis import rotate_sh, sh_basis, sh_rotation

    rng = np.random.default_rng(3)
    for deg in (1, 2, 3):
        k = (deg + 1) ** 2
        R1, R2 = (Rotation.random(random_state=deg + i).as_matrix() for i in (0, 10))
        c = rng.normal(size=(7, k, 3))
        d = rng.normal(size=(7, 3))
        ev = lambda coeffs, dirs: spherical_harmonics(
            deg, torch.from_numpy(dirs), torch.from_numpy(coeffs)
        ).numpy()  # noqa: E731
        # f'(d) = f(R^T d)
        assert np.allclose(ev(rotate_sh(c, R1), d), ev(c, d @ R1), atol=1e-12)
        D1, D2 = sh_rotation(R1, deg), sh_rotation(R2, deg)
        assert np.allclose(sh_rotation(R1 @ R2, deg), D1 @ D2, atol=1e-12)  # a representation
        assert np.allclose(D1 @ D1.T, np.eye(k), atol=1e-12) and np.allclose(
            sh_rotation(np.eye(3), deg), np.eye(k)
        )
        assert np.array_equal(D1[0], np.eye(k)[0])  # DC untouched
        # the torch-free basis (world-file reader) equals the renderer's torch SH
        u = d / np.linalg.norm(d, axis=1, keepdims=True)
        assert np.allclose(sh_basis(deg, u), ev(np.broadcast_to(np.eye(k), (7, k, k)).copy(), u), atol=1e-14)
    dc = rng.normal(size=(4, 1, 3)).astype(np.float32)
    assert rotate_sh(dc, Rotation.random(random_state=0).as_matrix()) is dc
    with pytest.raises(ValueError, match="5 bases"):
        rotate_sh(np.zeros((2, 5, 3)), np.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        sh_rotation(np.full((3, 3), np.nan), 2)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("degree", [1, 2, 3])
def test_numba_sh_matches_the_torch_reference_with_gradients(degree, dtype):
    from dsg_gym.splat.sh import _numba_shapes, _spherical_harmonics_torch

    g = torch.Generator().manual_seed(degree)
    dirs = torch.randn((2, 40, 3), generator=g, dtype=dtype)
    dirs[0, 0] = 0.0  # a zero direction: constant term only
    coeffs = torch.randn((1, 40, 16, 3), generator=g, dtype=dtype)  # more bases than the degree uses
    assert _numba_shapes(dirs, coeffs) == (2, 40)
    w = torch.randn((2, 40, 3), generator=g, dtype=dtype)
    outs, grads = [], []
    for fn in (spherical_harmonics, _spherical_harmonics_torch):
        d = dirs.clone().requires_grad_(True)
        c = coeffs.clone().requires_grad_(True)
        out = fn(degree, d, c)
        (out * w).sum().backward()
        outs.append(out.detach())
        grads.append((d.grad, c.grad))
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(outs[0], outs[1], rtol=tol, atol=tol)
    for a, b in zip(grads[0], grads[1]):
        torch.testing.assert_close(a, b, rtol=tol, atol=tol * max(1.0, float(b.abs().max())))
    unused = grads[0][1][:, :, (degree + 1) ** 2 :]
    assert unused.numel() == 0 or float(unused.abs().max()) == 0.0  # unused bases get no gradient


def test_numba_sh_gradcheck_and_fallbacks():
    from dsg_gym.splat.sh import _numba_shapes

    g = torch.Generator().manual_seed(5)
    d = torch.randn((3, 6, 3), generator=g, dtype=torch.float64, requires_grad=True)
    c = torch.randn((6, 16, 3), generator=g, dtype=torch.float64, requires_grad=True)
    assert _numba_shapes(d, c) == (3, 6)
    assert torch.autograd.gradcheck(lambda a, b: spherical_harmonics(3, a, b), (d, c))
    # per-view coefficients, other channel counts and mixed dtypes take the torch path
    assert _numba_shapes(d, c[None].expand(3, -1, -1, -1)) is None
    assert _numba_shapes(d, c[..., :2]) is None
    assert _numba_shapes(d.float(), c) is None
