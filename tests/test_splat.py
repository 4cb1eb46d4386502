"""Renderer correctness against the torch reference: numba values and gradients against torch's, gradcheck,
the tiled reference against a dense oracle, the compositing kernels, multi-camera renders, determinism."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from benchmarks.splat_scenes import random_scene
from dsg_gym.splat import rasterize

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


def test_multi_camera_equals_separate_renders():
    s = random_scene(700, width=32, height=32, seed=11, cameras=3)
    out, alpha, _ = rasterize(**s)
    for c in range(3):
        one = {**s, "viewmats": s["viewmats"][c : c + 1], "Ks": s["Ks"][c : c + 1]}
        o1, a1, _ = rasterize(**one)
        assert torch.equal(o1[0], out[c]) and torch.equal(a1[0], alpha[c])


def test_deterministic_bit_for_bit():
    s = random_scene(3000, width=64, height=48, seed=4, cameras=2)
    r1 = _render_with_grads(s, "numba", "RGB+ED")
    r2 = _render_with_grads(s, "numba", "RGB+ED")
    assert torch.equal(r1[0], r2[0]) and torch.equal(r1[1], r2[1])
    for k in r1[3]:
        assert torch.equal(r1[3][k], r2[3][k]), k


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
