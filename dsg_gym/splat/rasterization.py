"""The public splat renderer: ``rasterize`` (gsplat ``rasterization()`` conventions)."""

from __future__ import annotations

import math
from typing import Any

import torch

from ..splat_options import DEFAULT_EPS2D, RASTERIZE_MODES, check_splat_options  # noqa: F401  (re-exported)
from . import _numba_backend, _torch_backend
from .finite import first_nonfinite
from .sh import _spherical_harmonics_torch, num_sh_bases, spherical_harmonics

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")
BACKENDS = ("auto", "numba", "torch")


def _check_tensor(name: str, t: Any, shape: tuple, dtype: torch.dtype | None = None) -> torch.Tensor:
    if not isinstance(t, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"{name} has dtype {t.dtype}, expected {dtype} (like means)")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    bad = first_nonfinite(t)
    if bad is not None:
        raise ValueError(f"{name} has a non-finite value (NaN or Inf) at index {list(bad)}")
    return t


def rasterize(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    backgrounds: torch.Tensor | None = None,
    render_mode: str = "RGB",
    sh_degree: int | None = None,
    backend: str = "auto",
    rasterize_mode: str = "classic",
    eps2d: float = DEFAULT_EPS2D,
    absgrad: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render 3D Gaussians into C cameras (differentiable).

    Conventions: quaternions are ``w, x, y, z``; cameras are OpenCV (x right, y down, z forward);
    pixel ``(x, y)`` has its centre at ``(x + 0.5, y + 0.5)``. Inputs are post-activation (linear
    scales, opacities in [0, 1]).

    Math (3DGS): EWA projection with an ``eps2d`` (0.3) px^2 low-pass on the 2D covariance (the x/z, y/z used
    by the Jacobian clamped to 1.3x the half field of view); Gaussians with depth outside
    ``[near_plane, far_plane]`` or whose footprint misses the image are culled; per pixel
    ``alpha = min(0.99, o * exp(-0.5 d^T Sigma^-1 d))``, skipped below 1/255; composited front to
    back by depth, a pixel stops when its transmittance would fall below 1e-4. Every pixel where a
    Gaussian reaches alpha >= 1/255 is rendered (the footprint is opacity-aware), independent of
    tiling, so all backends agree.

    Args:
        means: ``[N, 3]`` centres in world space.
        quats: ``[N, 4]`` rotations ``w, x, y, z`` (need not be normalised; zero means identity).
        scales: ``[N, 3]`` standard deviations along the local axes (linear).
        opacities: ``[N]`` (or ``[C, N]``) in [0, 1].
        colors: ``[N, D]`` or ``[C, N, D]`` with any D (e.g. RGB plus 16 identity channels in one
            pass); with ``sh_degree`` set, SH coefficients ``[N, K, 3]`` or ``[C, N, K, 3]``,
            evaluated per camera and offset by +0.5, clamped at 0 (as 3DGS).
        viewmats: ``[C, 4, 4]`` world-to-camera.
        Ks: ``[C, 3, 3]`` intrinsics.
        width, height: image size in pixels.
        near_plane, far_plane: depth range kept.
        backgrounds: ``[C, D]`` or ``[D]`` colour behind the Gaussians (default 0); depth
            channels have none.
        render_mode: "RGB", "D" (accumulated depth), "ED" (expected depth = D / alpha),
            "RGB+D" or "RGB+ED"; depth is appended as the last channel.
        sh_degree: None (``colors`` are final colours) or 0..3.
        backend: "auto" (numba on CPU, torch elsewhere), "numba" or "torch" (reference).
        rasterize_mode: "classic" (3DGS) or "antialiased" (gsplat's name for Mip-Splatting's 2D Mip
            filter): each Gaussian's opacity per camera is multiplied by
            ``sqrt(det Sigma2d / det(Sigma2d + eps2d I))``, so the low-pass keeps its integrated weight
            instead of inflating sub-pixel Gaussians; scenes trained this way render correctly when the
            scale changes (objects moved nearer or farther, other resolutions).
        eps2d: the low-pass, in px^2, added to each projected 2D covariance's diagonal (3DGS and gsplat:
            0.3; Mip-Splatting pairs 0.1 with its 3D filter).
        absgrad: after ``backward``, ``meta["means2d"].absgrad`` ``[C, N, 2]`` holds each Gaussian's sums over
            the pixels of the absolute per-pixel gradients of its 2D mean (AbsGS's densification statistic:
            opposite pixel gradients of a large Gaussian over texture do not cancel). Numba backend only.

    Returns:
        ``colors [C, H, W, D(+1)]``, ``alphas [C, H, W, 1]`` and ``meta`` with ``radii [C, N, 2]``
        int32 (half extents in pixels, 0 when culled), ``means2d [C, N, 2]`` (call
        ``retain_grad()`` on it for the 2D mean gradients used by densification), ``depths
        [C, N]``, ``conics [C, N, 3]``, ``opacities``, ``width``, ``height``, ``backend``.
    """
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be one of {RENDER_MODES}, got {render_mode!r}")
    rasterize_mode, eps2d = check_splat_options(rasterize_mode, eps2d)
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not isinstance(width, int) or not isinstance(height, int) or width < 1 or height < 1:
        raise ValueError(f"width and height must be positive ints, got {width!r}, {height!r}")
    if not (math.isfinite(near_plane) and near_plane > 0 and far_plane > near_plane):
        raise ValueError(f"need 0 < near_plane < far_plane, got {near_plane}, {far_plane}")
    _check_tensor("means", means, (None, 3))
    if means.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"means must be float32 or float64, got {means.dtype}")
    N = means.shape[0]
    dt = means.dtype
    _check_tensor("quats", quats, (N, 4), dt)
    _check_tensor("scales", scales, (N, 3), dt)
    _check_tensor("viewmats", viewmats, (None, 4, 4), dt)
    C = viewmats.shape[0]
    if C < 1:
        raise ValueError("viewmats must hold at least one camera")
    _check_tensor("Ks", Ks, (C, 3, 3), dt)
    if opacities.dim() == 1:
        _check_tensor("opacities", opacities, (N,), dt)
    else:
        _check_tensor("opacities", opacities, (C, N), dt)
    if N and (float(opacities.detach().min()) < 0 or float(opacities.detach().max()) > 1):
        raise ValueError("opacities must lie in [0, 1]")
    if N and float(scales.detach().min()) < 0:
        raise ValueError("scales must be non-negative (linear, post-activation)")
    if bool((Ks[:, 0, 0] <= 0).any() or (Ks[:, 1, 1] <= 0).any()):
        raise ValueError("Ks must have positive focal lengths")
    for name, t in (
        ("quats", quats),
        ("scales", scales),
        ("opacities", opacities),
        ("colors", colors),
        ("viewmats", viewmats),
        ("Ks", Ks),
    ):
        if isinstance(t, torch.Tensor) and t.device != means.device:
            raise ValueError(f"{name} is on {t.device}, means on {means.device}")

    if sh_degree is None:
        if colors.dim() == 2:
            _check_tensor("colors", colors, (N, None), dt)
        else:
            _check_tensor("colors", colors, (C, N, None), dt)
        cols = colors if colors.dim() == 3 else colors[None]
    else:
        k = num_sh_bases(sh_degree)
        if colors.dim() == 3:
            _check_tensor("colors", colors, (N, None, 3), dt)
        else:
            _check_tensor("colors", colors, (C, N, None, 3), dt)
        if colors.shape[-2] < k:
            raise ValueError(f"colors has {colors.shape[-2]} SH bases, sh_degree {sh_degree} needs {k}")
        campos = torch.linalg.inv(viewmats)[:, :3, 3]  # [C,3]
        dirs = means[None, :, :] - campos[:, None, :]
        sh_fn = (
            _spherical_harmonics_torch if backend == "torch" else spherical_harmonics
        )  # the reference stays torch
        cols = torch.clamp_min(sh_fn(sh_degree, dirs, colors) + 0.5, 0.0)
        if cols.dim() == 2:
            cols = cols[None]
    D = cols.shape[-1]
    if backgrounds is not None:
        if backgrounds.dim() == 1:
            backgrounds = backgrounds[None].expand(C, -1)
        if render_mode in ("D", "ED"):
            raise ValueError("backgrounds apply to colour channels; render_mode has none")
        _check_tensor("backgrounds", backgrounds, (C, D), dt)
        if "D" in render_mode:  # the depth channel has no background
            backgrounds = torch.cat([backgrounds, backgrounds.new_zeros(C, 1)], dim=-1)

    if backend == "auto":
        backend = "numba" if means.device.type == "cpu" else "torch"
    if backend == "numba" and means.device.type != "cpu":
        raise ValueError("the numba backend needs CPU tensors; use backend='torch' on other devices")
    impl = _numba_backend if backend == "numba" else _torch_backend
    if absgrad and impl is not _numba_backend:
        raise ValueError("absgrad needs the numba backend (backend='numba' or 'auto' on CPU)")

    opac2 = opacities if opacities.dim() == 2 else opacities[None]
    means2d, conics, depths, radii, rects = impl.project(
        means, quats, scales, opac2, viewmats, Ks, width, height, near_plane, far_plane, float(eps2d)
    )

    if rasterize_mode == "antialiased":
        opac2 = impl.antialias(conics, opac2, float(eps2d))
    if render_mode in ("D", "ED"):
        feats = depths[..., None]
    elif render_mode in ("RGB+D", "RGB+ED"):
        feats = torch.cat([cols.expand(C, -1, -1), depths[..., None]], dim=-1)
    else:
        feats = cols
    if feats.shape[0] not in (1, C):
        raise ValueError(f"colors has {feats.shape[0]} cameras, viewmats {C}")
    feats = feats.contiguous()
    extra = {"absgrad": True} if absgrad else {}
    render_colors, render_alphas = impl.composite(
        means2d, conics, opac2.contiguous(), feats, depths, rects, backgrounds, width, height, **extra
    )
    if render_mode.endswith("ED"):
        depth = render_colors[..., -1:] / render_alphas.clamp_min(1e-10)
        render_colors = torch.cat([render_colors[..., :-1], depth], dim=-1)
    meta = {
        "radii": radii,
        "means2d": means2d,
        "depths": depths,
        "conics": conics,
        "opacities": opac2,
        "rects": rects,
        "width": width,
        "height": height,
        "n_cameras": C,
        "backend": backend,
    }
    return render_colors, render_alphas, meta
