"""Numba CPU backend: autograd Functions around the hand-written kernels."""

from __future__ import annotations

import numpy as np
import torch

from . import _torch_backend
from . import numba_bins as binning
from . import numba_project as projection
from . import numba_raster as raster
from . import numba_raster_backward as raster_backward
from . import numba_sh as sh_kernels

_consts = raster.make_consts


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d):
        C, N = viewmats.shape[0], means.shape[0]
        dt = means.dtype
        m, q, s = _np(means), _np(quats), _np(scales)
        vm = _np(viewmats).astype(np.float64, copy=False)
        K = _np(Ks).astype(np.float64, copy=False)
        means2d = torch.empty((C, N, 2), dtype=dt)
        conics = torch.empty((C, N, 3), dtype=dt)
        depths = torch.empty((C, N), dtype=dt)
        radii = torch.empty((C, N, 2), dtype=torch.int32)
        rects = torch.empty((C, N, 4), dtype=torch.int32)
        projection.project_forward(
            m,
            q,
            s,
            _np(opacities),
            vm,
            K,
            float(width),
            float(height),
            float(near),
            float(far),
            means2d.numpy(),
            conics.numpy(),
            depths.numpy(),
            radii.numpy(),
            rects.numpy(),
            projection.ALPHA_MIN,
            float(eps2d),
        )
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, radii)
        ctx.size = (width, height)
        ctx.eps2d = float(eps2d)
        ctx.mark_non_differentiable(radii, rects)
        return means2d, conics, depths, radii, rects

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_rects):
        means, quats, scales, viewmats, Ks, radii = ctx.saved_tensors
        width, height = ctx.size
        C, N = viewmats.shape[0], means.shape[0]
        dt = means.dtype

        def grad_or_zeros(g, shape):
            return np.zeros(shape, dtype=dt_np) if g is None else _np(g)

        dt_np = np.float64 if dt == torch.float64 else np.float32
        v_means = torch.empty((N, 3), dtype=dt)
        v_quats = torch.empty((N, 4), dtype=dt)
        v_scales = torch.empty((N, 3), dtype=dt)
        projection.project_backward(
            _np(means),
            _np(quats),
            _np(scales),
            _np(viewmats).astype(np.float64, copy=False),
            _np(Ks).astype(np.float64, copy=False),
            float(width),
            float(height),
            radii.numpy(),
            grad_or_zeros(v_means2d, (C, N, 2)),
            grad_or_zeros(v_conics, (C, N, 3)),
            grad_or_zeros(v_depths, (C, N)),
            v_means.numpy(),
            v_quats.numpy(),
            v_scales.numpy(),
            ctx.eps2d,
        )
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None, None


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, depths, rects, width, height, absgrad):
        C = means2d.shape[0]
        D = colors.shape[2]
        dt = means2d.dtype
        tiles_x = (width + raster.TILE - 1) // raster.TILE
        tiles_y = (height + raster.TILE - 1) // raster.TILE
        d = _np(depths)
        r = _np(rects)
        # Visible depths are >= near > 0, so their bit patterns sort like the values; the radix
        # sort is stable (equal depths keep index order): the result is deterministic.
        keys = d.view(np.uint32 if d.dtype == np.float32 else np.uint64)
        order, counts = binning.depth_order(keys, r)
        tile_offsets, tile_gauss, gauss_offsets, gauss_pairs = binning.bin_gaussians(
            r, order, counts, tiles_x, tiles_y
        )
        out = torch.empty((C, height, width, D), dtype=dt)
        out_T = torch.empty((C, height, width), dtype=dt)
        m2 = _np(means2d)
        P = tile_gauss.shape[0]
        pairs = (
            np.empty((P, 6), dtype=m2.dtype),
            np.empty((P, 4), dtype=r.dtype),
            np.empty((P, D), dtype=m2.dtype),
        )
        raster.gather_pairs(
            m2,
            _np(conics),
            _np(opacities),
            _np(colors),
            r,
            tile_offsets,
            tile_gauss,
            tiles_x,
            tiles_y,
            *pairs,
        )
        raster.composite_forward(
            *pairs,
            tile_offsets,
            tiles_x,
            tiles_y,
            width,
            height,
            _consts(m2.dtype),
            binning.balanced_order(C * tiles_x * tiles_y),
            out.numpy(),
            out_T.numpy(),
        )
        if backgrounds is not None:
            out += out_T[..., None] * backgrounds[:, None, None, :].detach()
        alphas = (1.0 - out_T)[..., None]
        ctx.bins = (tile_offsets, gauss_offsets, gauss_pairs, tiles_x, tiles_y, pairs)
        ctx.size = (width, height)
        ctx.has_bg = backgrounds is not None
        ctx.absgrad = bool(absgrad)
        ctx.save_for_backward(means2d, colors, opacities, out, out_T)
        return out, alphas

    @staticmethod
    def backward(ctx, v_out, v_alphas):
        means2d, colors, opacities, out, out_T = ctx.saved_tensors
        tile_offsets, gauss_offsets, gauss_pairs, tiles_x, tiles_y, pairs = ctx.bins
        width, height = ctx.size
        C, N = means2d.shape[:2]
        D = colors.shape[2]
        dt = means2d.dtype
        if v_out is None:
            v_out = torch.zeros_like(out)
        if v_alphas is None:
            v_alphas = torch.zeros_like(out_T)[..., None]
        vo = _np(v_out)
        pair_grads = np.zeros((pairs[0].shape[0], D + (8 if ctx.absgrad else 6)), dtype=vo.dtype)
        raster_backward.composite_backward(
            *pairs,
            tile_offsets,
            tiles_x,
            tiles_y,
            width,
            height,
            _consts(out.numpy().dtype),
            binning.balanced_order(C * tiles_x * tiles_y),
            out.numpy(),
            out_T.numpy(),
            vo,
            _np(v_alphas[..., 0]),
            raster_backward.pair_slots(gauss_pairs),
            pair_grads,
        )
        v_means2d = torch.empty((C, N, 2), dtype=dt)
        v_conics = torch.empty((C, N, 3), dtype=dt)
        v_colors = torch.empty(colors.shape, dtype=dt)
        v_opac = torch.empty(opacities.shape, dtype=dt)
        abs_m2 = torch.zeros((C if ctx.absgrad else 0, N, 2), dtype=dt)
        raster_backward.reduce_pairs(
            pair_grads,
            gauss_offsets,
            C,
            N,
            D,
            v_means2d.numpy(),
            v_conics.numpy(),
            v_colors.numpy(),
            v_opac.numpy(),
            abs_m2.numpy(),
        )
        if ctx.absgrad:  # read by densification as ``meta["means2d"].absgrad`` (gsplat's convention)
            means2d.absgrad = abs_m2
        v_bg = None
        if ctx.has_bg and ctx.needs_input_grad[4]:
            v_bg = (v_out * out_T[..., None]).sum(dim=(1, 2))
        return v_means2d, v_conics, v_colors, v_opac, v_bg, None, None, None, None, None


class _Antialias(torch.autograd.Function):
    """Forward with the runtime's kernel (same bits as ``SceneRenderer``), backward through the torch
    reference's formula (one definition of the derivative)."""

    @staticmethod
    def forward(ctx, conics, opacities, eps2d):
        out = torch.empty(conics.shape[:2], dtype=conics.dtype)
        projection.antialias_opacities(_np(conics), _np(opacities), out.numpy(), float(eps2d))
        ctx.save_for_backward(conics, opacities)
        ctx.eps2d = float(eps2d)
        return out

    @staticmethod
    def backward(ctx, v_out):
        conics, opacities = ctx.saved_tensors
        with torch.enable_grad():
            c = conics.detach().requires_grad_(True)
            o = opacities.detach().requires_grad_(True)
            out = _torch_backend.antialias(c, o, ctx.eps2d)
            v_conics, v_op = torch.autograd.grad(out, (c, o), v_out)
        return v_conics, v_op, None


def antialias(conics, opacities, eps2d=projection.BLUR):
    return _Antialias.apply(conics, opacities, eps2d)


def project(means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d=projection.BLUR):
    return _Project.apply(means, quats, scales, opacities, viewmats, Ks, width, height, near, far, eps2d)


def composite(means2d, conics, opacities, colors, depths, rects, backgrounds, width, height, absgrad=False):
    return _Composite.apply(
        means2d, conics, colors, opacities, backgrounds, depths, rects, width, height, absgrad
    )


class _SH(torch.autograd.Function):
    """SH colours of N Gaussians seen in C views (:mod:`.numba_sh`): dirs [C,N,3], coeffs [N,K,3]."""

    @staticmethod
    def forward(ctx, degree, dirs, coeffs):
        out = torch.empty(dirs.shape, dtype=dirs.dtype)
        sh_kernels.sh_forward(int(degree), _np(dirs), _np(coeffs), out.numpy())
        ctx.save_for_backward(dirs, coeffs)
        ctx.degree = int(degree)
        return out

    @staticmethod
    def backward(ctx, v_out):
        dirs, coeffs = ctx.saved_tensors
        v_dirs = torch.empty(dirs.shape, dtype=dirs.dtype)
        v_coeffs = torch.empty(coeffs.shape, dtype=coeffs.dtype)
        sh_kernels.sh_backward(
            ctx.degree, _np(dirs), _np(coeffs), _np(v_out), v_dirs.numpy(), v_coeffs.numpy()
        )
        return None, v_dirs, v_coeffs


def sh_colors(degree: int, dirs: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """``[C, N, 3]`` SH values (no +0.5) at view directions ``dirs [C, N, 3]`` of coefficients ``[N, K, 3]``."""
    return _SH.apply(degree, dirs, coeffs)
