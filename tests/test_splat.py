"""Renderer correctness: numba vs the torch reference, gradcheck, analytic cases, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.splat_scenes import intrinsics, random_scene
from dsg_gym.splat import C0, rasterize, spherical_harmonics

DIFF_ARGS = ("means", "quats", "scales", "opacities", "colors")


def _render_with_grads(scene, backend, render_mode="RGB", backgrounds=None, seed=1, rasterize_mode="classic"):
    leaves = {k: scene[k].clone().requires_grad_(True) for k in DIFF_ARGS}
    bg = None if backgrounds is None else backgrounds.clone().requires_grad_(True)
    kw = {**scene, **leaves}
    out, alpha, meta = rasterize(
        **kw, backgrounds=bg, render_mode=render_mode, backend=backend, rasterize_mode=rasterize_mode
    )
    meta["means2d"].retain_grad()
    g = torch.Generator().manual_seed(seed)
    w_out = torch.randn(out.shape, generator=g, dtype=out.dtype)
    w_alpha = torch.randn(alpha.shape, generator=g, dtype=out.dtype)
    ((out * w_out).sum() + (alpha * w_alpha).sum()).backward()
    grads = {k: v.grad for k, v in leaves.items()}
    grads["means2d"] = meta["means2d"].grad
    if bg is not None:
        grads["backgrounds"] = bg.grad
    return out.detach(), alpha.detach(), meta, grads


def _assert_grads_close(a, b, rel=1e-4):
    for k in b:
        scale = b[k].abs().max().clamp_min(1e-6)
        err = (a[k] - b[k]).abs().max()
        assert err <= rel * scale, f"gradient of {k}: max error {err:.3g} vs scale {scale:.3g}"


@pytest.mark.parametrize(
    "seed,cameras,mode", [(0, 1, "RGB"), (1, 2, "RGB+ED"), (2, 1, "RGB+D"), (3, 3, "RGB")]
)
def test_numba_matches_torch_reference(seed, cameras, mode):
    scene = random_scene(1500, width=48, height=40, seed=seed, cameras=cameras)
    D = scene["colors"].shape[1]
    bg = torch.rand(D, generator=torch.Generator().manual_seed(seed))
    a_out, a_alpha, a_meta, a_grads = _render_with_grads(scene, "numba", mode, bg)
    b_out, b_alpha, b_meta, b_grads = _render_with_grads(scene, "torch", mode, bg)
    assert a_out.shape == (cameras, 40, 48, D + (1 if "D" in mode else 0))
    assert (a_out[..., :D] - b_out[..., :D]).abs().max() <= 1e-5
    if mode == "RGB+D":  # depths are metres (2..6 here): 1e-5 relative
        assert (a_out[..., D] - b_out[..., D]).abs().max() <= 1e-5 * b_out[..., D].abs().max()
    elif mode == "RGB+ED":  # depth / alpha: compare relative error where something was hit
        hit = b_alpha[..., 0] > 0.05
        assert ((a_out[..., D] - b_out[..., D]).abs()[hit] / b_out[..., D][hit]).max() <= 1e-5
    assert (a_alpha - b_alpha).abs().max() <= 1e-5
    assert torch.equal(a_meta["radii"], b_meta["radii"])
    assert (a_meta["means2d"] - b_meta["means2d"]).abs().max() <= 1e-4
    assert a_alpha.mean() > 0.5  # the scene really covers the view
    _assert_grads_close(a_grads, b_grads)


def test_per_camera_colors_and_opacities_match_reference():
    scene = random_scene(800, width=40, height=32, seed=5, cameras=2)
    g = torch.Generator().manual_seed(0)
    scene["colors"] = torch.rand(2, 800, 4, generator=g)
    scene["opacities"] = torch.rand(2, 800, generator=g) * 0.9 + 0.05
    a = _render_with_grads(scene, "numba")
    b = _render_with_grads(scene, "torch")
    assert (a[0] - b[0]).abs().max() <= 1e-5
    _assert_grads_close(a[3], b[3])


def test_torch_tiling_equals_dense_oracle():
    """The tiled torch reference equals a dense evaluation of every Gaussian on every pixel."""
    from dsg_gym.splat import _torch_backend as T

    s = random_scene(300, width=40, height=24, seed=7)
    op = s["opacities"][None]
    m2, cn, d, radii, rects = T.project(
        s["means"], s["quats"], s["scales"], op, s["viewmats"], s["Ks"], 40, 24, 0.01, 1e10
    )
    tiled = T.composite(m2, cn, op, s["colors"][None], d, rects, None, 40, 24, tile_size=16)
    dense = T.composite(m2, cn, op, s["colors"][None], d, rects, None, 40, 24, tile_size=None)
    assert (tiled[0] - dense[0]).abs().max() <= 1e-6
    # Rectangles are conservative: a Gaussian outside its rectangle has alpha < 1/255 there.
    every = torch.zeros_like(rects)
    every[..., 1] = 39
    every[..., 3] = 23
    every = torch.where((rects[..., 1:2] >= rects[..., 0:1]), every, rects)
    full = T.composite(m2, cn, op, s["colors"][None], d, every, None, 40, 24, tile_size=None)
    assert (full[0] - dense[0]).abs().max() <= 1e-6


@pytest.mark.parametrize("eps2d", [0.3, 0.1])
def test_antialiased_numba_matches_torch_reference(eps2d):
    scene = random_scene(1500, width=48, height=40, seed=11, cameras=2, scale_range=(0.002, 0.05))
    scene["eps2d"] = eps2d
    a = _render_with_grads(scene, "numba", "RGB+D", rasterize_mode="antialiased")
    b = _render_with_grads(scene, "torch", "RGB+D", rasterize_mode="antialiased")
    c = _render_with_grads(scene, "numba", "RGB+D")
    assert (a[0][..., :-1] - b[0][..., :-1]).abs().max() <= 1e-5
    assert (a[0][..., -1] - b[0][..., -1]).abs().max() <= 1e-5 * b[0][..., -1].abs().max()
    assert (a[1] - b[1]).abs().max() <= 1e-5
    _assert_grads_close(a[3], b[3])
    # Filtering only ever lowers opacity, and it changes the image where Gaussians are small.
    assert bool((a[2]["opacities"] <= scene["opacities"][None] + 1e-7).all())
    assert float((a[0] - c[0]).abs().max()) > 0.05
    assert float(a[1].mean()) < float(c[1].mean())


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
@pytest.mark.parametrize("mode", ["classic", "antialiased"])
def test_gradcheck_float64(backend, mode):
    s = random_scene(6, width=12, height=10, channels=4, seed=3, dtype=torch.float64)
    bg = torch.rand(4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    fixed = {k: s[k] for k in ("viewmats", "Ks", "width", "height")}

    def f(means, quats, scales, opacities, colors, backgrounds):
        out, alpha, _ = rasterize(
            means,
            quats,
            scales,
            opacities,
            colors,
            **fixed,
            backgrounds=backgrounds,
            render_mode="RGB+ED",
            backend=backend,
            rasterize_mode=mode,
        )
        return out, alpha

    inputs = [s[k].clone().requires_grad_(True) for k in DIFF_ARGS] + [bg.requires_grad_(True)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


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


def test_multi_camera_equals_separate_renders():
    s = random_scene(700, width=32, height=32, seed=11, cameras=3)
    out, alpha, _ = rasterize(**s)
    for c in range(3):
        one = {**s, "viewmats": s["viewmats"][c : c + 1], "Ks": s["Ks"][c : c + 1]}
        o1, a1, _ = rasterize(**one)
        assert torch.equal(o1[0], out[c]) and torch.equal(a1[0], alpha[c])


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


def test_deterministic_bit_for_bit():
    s = random_scene(3000, width=64, height=48, seed=4, cameras=2)
    r1 = _render_with_grads(s, "numba", "RGB+ED")
    r2 = _render_with_grads(s, "numba", "RGB+ED")
    assert torch.equal(r1[0], r2[0]) and torch.equal(r1[1], r2[1])
    for k in r1[3]:
        assert torch.equal(r1[3][k], r2[3][k]), k


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


def test_splat_rows_with_precomputed_spans_equals_splat_forward():
    """The incremental renderer composites with row spans computed ahead (``span_rows`` + ``splat_rows``);
    Gaussian after Gaussian, that leaves a tile's accumulators exactly as ``splat_forward`` does."""
    from dsg_gym.splat import numba_raster as raster

    rng = np.random.default_rng(3)
    consts = raster.make_consts(np.float32, 3.0 / 255.0, 1e-3)
    W = H = 40
    tiles_x = 3
    finished = 0
    for tile in range(9):  # interior, right and bottom border tiles (partial)
        a = raster.tile_state(tile, tiles_x, W, H, 3, np.float32)
        b = raster.tile_state(tile, tiles_x, W, H, 3, np.float32)
        px0, py0, pw, ph = a[:4]
        rows = np.zeros(raster.TILE, np.uint16)
        for _ in range(150):
            u, v = (np.array([px0, py0]) + rng.uniform(-6, 22, 2)).astype(np.float32)  # around this tile
            L = rng.normal(size=(2, 2)) * rng.uniform(0.5, 4.0)
            cov = L @ L.T + 0.3 * np.eye(2)
            ca, cb, cc = (np.linalg.inv(cov)[[0, 0, 1], [0, 1, 1]]).astype(np.float32)
            o = np.float32(rng.uniform(0.02, 0.99))
            r = int(math.ceil(3.0 * math.sqrt(np.linalg.eigvalsh(cov).max())))
            rect = (max(int(u) - r, 0), min(int(u) + r, W - 1), max(int(v) - r, 0), min(int(v) + r, H - 1))
            col = rng.uniform(0, 1, 3).astype(np.float32)
            f1 = raster.splat_forward(
                consts, u, v, ca, cb, cc, o, *rect, col, px0, py0, pw, ph, a[7], a[8], a[4], a[5], a[6]
            )
            raster.span_rows(consts, u, v, ca, cb, cc, o, *rect, px0, py0, pw, ph, b[8], rows)
            f2 = raster.splat_rows(
                consts,
                u,
                v,
                ca,
                cb,
                cc,
                o,
                rect[2],
                rect[3],
                rows,
                col,
                py0,
                ph,
                b[7],
                b[8],
                b[4],
                b[5],
                b[6],
            )
            assert f1 == f2
            finished += f1
        for x, y in zip(a[4:7], b[4:7]):
            np.testing.assert_array_equal(x, y)
    assert finished > 100  # pixels saturated, so the skipping of finished pixels was exercised


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


@pytest.mark.parametrize("per_camera", [False, True])
def test_pair_gather_and_gaussian_major_gradients(per_camera):
    """The compositing kernels read each (tile, Gaussian) pair's inputs from ``gather_pairs`` and write pair
    gradients in Gaussian-major rows (``pair_slots``): the image equals compositing each tile's list with
    ``splat_forward`` straight from the Gaussian arrays, and every pair's row holds its own Gaussian's data."""
    from dsg_gym.splat import _numba_backend as numba_backend
    from dsg_gym.splat import numba_bins as binning
    from dsg_gym.splat import numba_raster as raster
    from dsg_gym.splat.numba_raster_backward import pair_slots

    scene = random_scene(600, width=40, height=34, seed=7, cameras=2)
    g = torch.Generator().manual_seed(1)
    if per_camera:
        scene["colors"] = torch.rand(2, 600, 5, generator=g)
        scene["opacities"] = torch.rand(2, 600, generator=g) * 0.9 + 0.05
    colors = scene["colors"].numpy()
    colors = colors if colors.ndim == 3 else colors[None]
    opac = scene["opacities"].numpy()
    opac = opac if opac.ndim == 2 else opac[None]
    m2, cn, depths, _, rects = (
        t.detach().numpy()
        for t in numba_backend.project(
            scene["means"],
            scene["quats"],
            scene["scales"],
            torch.from_numpy(opac),
            scene["viewmats"],
            scene["Ks"],
            40,
            34,
            0.01,
            1e10,
        )
    )
    tx, ty = 3, 3
    order, counts = binning.depth_order(depths.view(np.uint32), rects)
    t_off, t_gauss, g_off, g_pairs = binning.bin_gaussians(rects, order, counts, tx, ty)
    P, D = t_gauss.shape[0], colors.shape[2]
    pairs = (np.empty((P, 6), np.float32), np.empty((P, 4), np.int32), np.empty((P, D), np.float32))
    raster.gather_pairs(m2, cn, opac, colors, rects, t_off, t_gauss, tx, ty, *pairs)
    cam = np.repeat(np.arange(2 * tx * ty) // (tx * ty), np.diff(t_off))
    ci = cam if per_camera else np.zeros_like(cam)
    np.testing.assert_array_equal(pairs[0][:, :2], m2[cam, t_gauss])
    np.testing.assert_array_equal(pairs[0][:, 2:5], cn[cam, t_gauss])
    np.testing.assert_array_equal(pairs[0][:, 5], opac[ci, t_gauss])
    np.testing.assert_array_equal(pairs[1], rects[cam, t_gauss])
    np.testing.assert_array_equal(pairs[2], colors[ci, t_gauss])
    consts = raster.make_consts(np.float32)
    out = np.empty((2, 34, 40, D), np.float32)
    out_T = np.empty((2, 34, 40), np.float32)
    raster.composite_forward(
        *pairs, t_off, tx, ty, 40, 34, consts, binning.balanced_order(2 * tx * ty), out, out_T
    )
    ref = np.empty_like(out)
    ref_T = np.empty_like(out_T)
    for ct in range(2 * tx * ty):  # the direct loop, one tile at a time
        c = ct // (tx * ty)
        px0, py0, pw, ph, acc, trans, row_done, xc, yc = raster.tile_state(
            ct % (tx * ty), tx, 40, 34, D, np.float32
        )
        for s in range(t_off[ct], t_off[ct + 1]):
            k = t_gauss[s]
            raster.splat_forward(
                consts,
                *m2[c, k],
                *cn[c, k],
                opac[c if per_camera else 0, k],
                *rects[c, k],
                colors[c if per_camera else 0, k],
                px0,
                py0,
                pw,
                ph,
                xc,
                yc,
                acc,
                trans,
                row_done,
            )
        raster.store_tile(c, px0, py0, pw, ph, acc, trans, ref, ref_T)
    np.testing.assert_array_equal(out, ref)
    np.testing.assert_array_equal(out_T, ref_T)
    assert (out_T < 0.5).mean() > 0.3  # the views are covered
    slot = pair_slots(g_pairs)
    np.testing.assert_array_equal(g_pairs[slot], np.arange(P))
    # Gaussian-major rows: pair s of camera c, Gaussian k lands inside k's range of gauss_offsets
    lo, hi = g_off[cam * 600 + t_gauss], g_off[cam * 600 + t_gauss + 1]
    assert ((slot >= lo) & (slot < hi)).all()
