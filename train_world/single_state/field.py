"""``SegmentedField``: a Gaussian field with identity features (Gaussian Grouping), stored raw.

Raw parameters (``nn.Parameter``): ``means [N,3]``, ``quats [N,4]`` (w, x, y, z; unnormalised),
``log_scales [N,3]``, ``opacity_logits [N]``, ``sh0 [N,1,3]``, ``shN [N,(d+1)^2-1,3]``, ``features [N,F]``.
Activation: scale = exp, opacity = sigmoid, rotation = normalised quaternion, rgb = SH(view dir) + 0.5
clamped at 0 (3DGS). RGB and the F identity channels are rendered in one rasterizer call.

Mip-Splatting (optional, ``configure_filters``): the renderer's antialiased mode (2D Mip filter, with its
low-pass ``eps2d``) and a 3D smoothing filter, a per-Gaussian isotropic variance ``filter3d [N]`` added to the
covariance, sized to the finest sampling interval (depth / focal) at which any training camera sees the Gaussian, times
``filter3d_scale`` (0.2 in the paper). The filtered scale is ``sqrt(scale^2 + f)`` and the opacity is
multiplied by ``sqrt(prod scale^2 / prod(scale^2 + f))``; both are baked into ``to_gaussian_set``, so the
runtime needs only the 2D mode. Densification sees the unfiltered parameters (as Mip-Splatting).

``render(..., transform=...)`` moves Gaussians before rendering (the hook DSG-World's state transfer needs):
``transform`` is a ``[4,4]`` or per-Gaussian ``[N,4,4]`` rigid world transform, or a callable
``(means, quats) -> (means, quats)``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from dsg_gym.gaussians import GaussianSet
from dsg_gym.geometry import quat_multiply, rotmat_to_quat
from dsg_gym.splat import rasterize, spherical_harmonics
from dsg_gym.splat.layers import rasterize_layers
from dsg_gym.splat_options import DEFAULT_EPS2D, check_splat_options

__all__ = [
    "PARAM_NAMES",
    "Classifier",
    "RenderOutput",
    "SegmentedField",
    "filter3d_variance",
    "rigid_transform_gaussians",
]

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN", "features")

Transform = torch.Tensor | Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # [C,H,W,3]
    features: torch.Tensor | None  # [C,H,W,F]
    alpha: torch.Tensor  # [C,H,W,1]
    meta: dict[str, Any]
    depth: torch.Tensor | None = None  # [C,H,W]: alpha-blended camera-space z (with_depth), 0 behind


def rigid_transform_gaussians(
    means: torch.Tensor, quats: torch.Tensor, T: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Apply a rigid transform ``T`` (``[4,4]`` or ``[N,4,4]``) to Gaussian centres and rotations."""
    T = T.to(means.dtype)
    R, t = T[..., :3, :3], T[..., :3, 3]
    if T.dim() == 2:
        new_means = means @ R.T + t
        qR = rotmat_to_quat(R[None]).expand(means.shape[0], 4)
    else:
        new_means = torch.einsum("nij,nj->ni", R, means) + t
        qR = rotmat_to_quat(R)
    return new_means, quat_multiply(qR, quats)


@torch.no_grad()
def filter3d_variance(
    means: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    scale: float = 0.2,
    near: float = 0.2,
    margin: float = 0.15,
) -> torch.Tensor:
    """Mip-Splatting's 3D filter variance per Gaussian ``[N]``: ``scale * (depth / focal)^2`` for the camera
    that samples the centre most finely, among the cameras that see it (depth > ``near``, inside the image
    widened by ``margin``); Gaussians no camera sees get the largest value. means ``[N,3]``, viewmats
    ``[V,4,4]``, Ks ``[V,3,3]``."""
    best = torch.full((means.shape[0],), float("inf"), dtype=torch.float64)
    m = means.double()
    for V, K in zip(viewmats.double(), Ks.double()):
        p = m @ V[:3, :3].T + V[:3, 3]
        z = p[:, 2]
        f = float(torch.minimum(K[0, 0], K[1, 1]))
        zs = z.clamp_min(1e-9)
        u = p[:, 0] / zs * K[0, 0] + K[0, 2]
        v = p[:, 1] / zs * K[1, 1] + K[1, 2]
        seen = (
            (z > near)
            & (u >= -margin * width)
            & (u <= (1 + margin) * width)
            & (v >= -margin * height)
            & (v <= (1 + margin) * height)
        )
        best = torch.where(seen, torch.minimum(best, z / f), best)
    seen = torch.isfinite(best)
    if not bool(seen.any()):
        return torch.zeros(means.shape[0], dtype=means.dtype)
    best = torch.where(seen, best, best[seen].max())
    return (scale * best * best).to(means.dtype)


class Classifier(nn.Linear):
    """Gaussian Grouping's identity classifier: a linear map F -> K+1 applied per pixel (or Gaussian)."""

    def __init__(self, num_features: int, num_classes: int):
        super().__init__(num_features, num_classes, bias=True)


class SegmentedField(nn.Module):
    """Raw Gaussian parameters with identity features (see the module docstring)."""

    def __init__(
        self,
        means: torch.Tensor,
        quats: torch.Tensor,
        log_scales: torch.Tensor,
        opacity_logits: torch.Tensor,
        sh0: torch.Tensor,
        shN: torch.Tensor,
        features: torch.Tensor,
    ):
        super().__init__()
        n = means.shape[0]
        vals = dict(zip(PARAM_NAMES, (means, quats, log_scales, opacity_logits, sh0, shN, features)))
        tails = {"means": (3,), "quats": (4,), "log_scales": (3,), "opacity_logits": (), "sh0": (1, 3)}
        for name, v in vals.items():
            if v.shape[0] != n:
                raise ValueError(f"SegmentedField.{name}: {v.shape[0]} rows, means has {n}")
            if name in tails and tuple(v.shape[1:]) != tails[name]:
                raise ValueError(
                    f"SegmentedField.{name}: shape {tuple(v.shape)}, expected [N, {tails[name]}]"
                )
        if shN.dim() != 3 or shN.shape[2] != 3 or (shN.shape[1] + 1) not in (1, 4, 9, 16):
            raise ValueError(f"SegmentedField.shN: shape {tuple(shN.shape)} is not [N, (d+1)^2 - 1, 3]")
        for name, v in vals.items():
            setattr(self, name, nn.Parameter(v.detach().to(torch.float32).contiguous().clone()))
        self.rasterize_mode = "classic"
        self.eps2d = DEFAULT_EPS2D
        self.filter3d_scale = 0.0
        self.filter3d: torch.Tensor | None = None  # [N] variance (world units^2), not trained
        self._filter_cameras: tuple | None = None

    # ------------------------------------------------------------------ Mip-Splatting filters
    def configure_filters(
        self,
        rasterize_mode: str = "classic",
        filter3d_scale: float = 0.0,
        cameras: tuple | None = None,
        eps2d: float = DEFAULT_EPS2D,
    ) -> None:
        """Select the 2D mode, its low-pass ``eps2d`` (px^2) and the 3D filter. ``cameras``: ``(viewmats [V,4,4],
        Ks [V,3,3], width, height)`` of the training views that set each Gaussian's sampling rate (needed when
        ``filter3d_scale > 0``)."""
        rasterize_mode, eps2d = check_splat_options(rasterize_mode, eps2d)
        if not filter3d_scale >= 0.0:
            raise ValueError(f"filter3d_scale must be >= 0, got {filter3d_scale}")
        if filter3d_scale > 0 and cameras is None:
            raise ValueError("the 3D filter needs the training cameras")
        self.rasterize_mode = rasterize_mode
        self.eps2d = eps2d
        self.filter3d_scale = float(filter3d_scale)
        self._filter_cameras = cameras
        self.filter3d = None
        if self.filter3d_scale > 0:
            self.update_filter3d()

    @torch.no_grad()
    def update_filter3d(self) -> None:
        """Recompute ``filter3d`` from the current means (call after densification, as Mip-Splatting does)."""
        if self.filter3d_scale <= 0 or self._filter_cameras is None:
            self.filter3d = None
            return
        viewmats, Ks, width, height = self._filter_cameras
        self.filter3d = filter3d_variance(
            self.means.detach(), viewmats, Ks, width, height, self.filter3d_scale
        )

    @torch.no_grad()
    def baked_params(self) -> dict[str, torch.Tensor]:
        """Detached raw parameters with the 3D filter folded into ``log_scales`` and ``opacity_logits`` (a field
        made of them renders the same without the 3D filter, in the same ``rasterize_mode``)."""
        out = {k: v.detach().clone() for k, v in self.params().items()}
        if self.filter3d_scale > 0:
            scales, opac = self.scales_opacities()
            out["log_scales"] = torch.log(scales)
            out["opacity_logits"] = torch.logit(opac.clamp(1e-7, 1 - 1e-7))
        return out

    def scales_opacities(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The scales ``[N,3]`` and opacities ``[N]`` that are rendered: after the 3D filter when it is on."""
        scales, opac = self.scales(), self.opacities()
        if self.filter3d_scale <= 0:
            return scales, opac
        if self.filter3d is None or self.filter3d.shape[0] != self.num:  # rows changed since the last update
            self.update_filter3d()
        s2 = scales * scales
        s2f = s2 + self.filter3d[:, None]
        return torch.sqrt(s2f), opac * torch.sqrt(torch.prod(s2 / s2f, dim=-1))

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_points(
        cls,
        points: torch.Tensor,
        rgb: torch.Tensor,
        scales: torch.Tensor,
        *,
        sh_degree: int = 3,
        num_features: int = 16,
        opacity: float = 0.1,
        features: torch.Tensor | None = None,
    ) -> SegmentedField:
        """Isotropic Gaussians at ``points`` with colours ``rgb [N,3]`` and scales ``[N]`` (metres)."""
        n = points.shape[0]
        quats = torch.zeros(n, 4)
        quats[:, 0] = 1.0
        log_scales = torch.log(scales.float().clamp_min(1e-7))[:, None].expand(n, 3)
        op = torch.full((n,), float(np.log(opacity / (1.0 - opacity))))
        sh0 = ((rgb.float() - 0.5) / 0.28209479177387814)[:, None, :]
        shN = torch.zeros(n, (sh_degree + 1) ** 2 - 1, 3)
        feats = torch.zeros(n, num_features) if features is None else features.float()
        return cls(points.float(), quats, log_scales, op, sh0, shN, feats)

    # ------------------------------------------------------------------ properties
    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def max_sh_degree(self) -> int:
        return round((self.shN.shape[1] + 1) ** 0.5) - 1

    @property
    def num_features(self) -> int:
        return int(self.features.shape[1])

    def params(self) -> dict[str, nn.Parameter]:
        return {name: getattr(self, name) for name in PARAM_NAMES}

    def set_param(self, name: str, value: torch.Tensor) -> nn.Parameter:
        """Replace parameter ``name`` (any row count; the caller keeps the others consistent)."""
        if name not in PARAM_NAMES:
            raise ValueError(f"unknown field parameter {name!r}")
        p = nn.Parameter(value.detach().contiguous())
        setattr(self, name, p)
        return p

    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    def sh(self) -> torch.Tensor:
        return torch.cat([self.sh0, self.shN], dim=1)

    # ------------------------------------------------------------------ rendering
    def render(
        self,
        viewmats: torch.Tensor,
        Ks: torch.Tensor,
        width: int,
        height: int,
        *,
        transform: Transform | None = None,
        sh_degree: int | None = None,
        background: torch.Tensor | None = None,
        with_features: bool = True,
        mask: torch.Tensor | None = None,
        with_depth: bool = False,
        absgrad: bool = False,
        layers: torch.Tensor | None = None,
    ) -> RenderOutput:
        """Render RGB (+ identity features) into ``C`` cameras in one rasterizer call.

        ``transform``: a rigid transform ``[4,4]`` / ``[N,4,4]`` or a callable ``(means, quats) -> (means,
        quats)``; SH colours turn with it when it has a ``rotate_dirs(dirs [C,N,3])`` or a ``rotations()``
        ``[N,3,3]`` method, as :class:`train_world.dual_state.transfer.ObjectTransfer` has; ``sh_degree``: the SH
        degree used (default:
        the field's maximum); ``background``: ``[3]`` RGB (features get 0 behind); ``mask``: boolean ``[N]``
        selecting the Gaussians drawn; ``with_depth``: also the accumulated depth (the rasterizer's ``RGB+D``
        mode, ``RenderOutput.depth``; divide by ``alpha`` for the expected depth), differentiable in the means;
        ``absgrad``: the rasterizer's (absolute 2D mean gradients for densification after ``backward``);
        ``layers``: boolean ``[N]``, the object Gaussians: render them and the others as two layers merged per
        pixel by expected depth (:func:`dsg_gym.splat.layers.rasterize_layers`; ``meta`` is then that
        function's).
        """
        means, quats = self.means, self.quats
        scales, opac = self.scales_opacities()
        sh, feats = self.sh(), self.features
        if mask is not None:
            means, quats, scales, opac, sh, feats = (t[mask] for t in (means, quats, scales, opac, sh, feats))
            layers = None if layers is None else layers[mask]
        rot = None  # rotation of each Gaussian by the transform: SH colours turn with the Gaussians
        turn_dirs = None
        if transform is not None:
            if callable(transform) and not isinstance(transform, torch.Tensor):
                means, quats = transform(means, quats)
                if mask is None and hasattr(transform, "rotate_dirs"):
                    turn_dirs = transform.rotate_dirs
                elif hasattr(transform, "rotations"):
                    rot = transform.rotations()
            else:
                T = transform if transform.dim() == 2 or mask is None else transform[mask]
                means, quats = rigid_transform_gaussians(means, quats, T)
                rot = T[..., :3, :3].to(means.dtype)
        deg = self.max_sh_degree if sh_degree is None else min(int(sh_degree), self.max_sh_degree)
        campos = torch.linalg.inv(viewmats.detach())[:, :3, 3]
        dirs = means[None, :, :] - campos[:, None, :]
        if turn_dirs is not None and deg > 0:
            dirs = turn_dirs(dirs)
        elif rot is not None and deg > 0:  # view direction into each Gaussian's own (unmoved) frame: R^T d
            dirs = dirs @ rot if rot.dim() == 2 else torch.einsum("cnj,nji->cni", dirs, rot)
        rgb = torch.clamp_min(spherical_harmonics(deg, dirs, sh[None]) + 0.5, 0.0)  # [C,N,3] (first k bases)
        C = viewmats.shape[0]
        rgb = rgb.expand(C, -1, -1)
        cols = torch.cat([rgb, feats[None].expand(C, -1, -1)], dim=-1) if with_features else rgb
        bg = None
        if background is not None:
            bg = background.to(means.dtype)
            if with_features:
                bg = torch.cat([bg, bg.new_zeros(feats.shape[1])])
        splat = rasterize if layers is None else functools.partial(rasterize_layers, layers)
        out, alpha, meta = splat(
            means,
            quats,
            scales,
            opac,
            cols,
            viewmats,
            Ks,
            int(width),
            int(height),
            backgrounds=bg,
            rasterize_mode=self.rasterize_mode,
            eps2d=self.eps2d,
            render_mode="RGB+D" if with_depth else "RGB",
            absgrad=absgrad,
        )
        nf = feats.shape[1] if with_features else 0
        return RenderOutput(
            rgb=out[..., :3],
            features=out[..., 3 : 3 + nf] if with_features else None,
            alpha=alpha,
            meta=meta,
            depth=out[..., 3 + nf] if with_depth else None,
        )

    # ------------------------------------------------------------------ export
    @torch.no_grad()
    def to_gaussian_set(self, labels: np.ndarray | None = None) -> GaussianSet:
        """Activated numpy copy (``GaussianSet``), with the raw logits/log-scales kept as encodings; with the 3D
        filter on, its effect is baked into the scales and opacities (and the raw encodings are dropped)."""
        q = self.quats.detach()
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        scales, opac = self.scales_opacities()
        raw = self.filter3d_scale <= 0
        return GaussianSet(
            means=self.means.detach().numpy(),
            quats=q.numpy(),
            scales=scales.detach().numpy(),
            opacities=opac.detach().numpy(),
            sh=self.sh().detach().numpy(),
            features=self.features.detach().numpy(),
            labels=labels,
            opacity_logits=self.opacity_logits.detach().numpy() if raw else None,
            log_scales=self.log_scales.detach().numpy() if raw else None,
        )

    @torch.no_grad()
    def labels(self, classifier: nn.Module) -> torch.Tensor:
        """Per-Gaussian class (argmax of the classifier on its identity feature), ``[N]`` int64."""
        if self.num == 0:
            return torch.zeros(0, dtype=torch.int64)
        return classifier(self.features).argmax(dim=-1)
