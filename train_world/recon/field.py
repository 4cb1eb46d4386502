"""``SegmentedField``: a Gaussian field with identity features (Gaussian Grouping), stored raw.

Raw parameters (``nn.Parameter``): ``means [N,3]``, ``quats [N,4]`` (w, x, y, z; unnormalised),
``log_scales [N,3]``, ``opacity_logits [N]``, ``sh0 [N,1,3]``, ``shN [N,(d+1)^2-1,3]``, ``features [N,F]``.
Activation: scale = exp, opacity = sigmoid, rotation = normalised quaternion, rgb = SH(view dir) + 0.5
clamped at 0 (3DGS). RGB and the F identity channels are rendered in one rasterizer call.

``render(..., transform=...)`` moves Gaussians before rendering (the hook DSG-World's state transfer needs):
``transform`` is a ``[4,4]`` or per-Gaussian ``[N,4,4]`` rigid world transform, or a callable
``(means, quats) -> (means, quats)``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from dsg_gym.gaussians import GaussianSet
from dsg_gym.geometry import quat_multiply, rotmat_to_quat
from dsg_gym.splat import rasterize, spherical_harmonics

__all__ = ["PARAM_NAMES", "Classifier", "RenderOutput", "SegmentedField", "rigid_transform_gaussians"]

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh0", "shN", "features")

Transform = torch.Tensor | Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, torch.Tensor]]


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # [C,H,W,3]
    features: torch.Tensor | None  # [C,H,W,F]
    alpha: torch.Tensor  # [C,H,W,1]
    meta: dict[str, Any]


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
    ) -> RenderOutput:
        """Render RGB (+ identity features) into ``C`` cameras in one rasterizer call.

        ``transform``: a rigid transform ``[4,4]`` / ``[N,4,4]`` or a callable ``(means, quats) -> (means,
        quats)`` (with a ``rotations()`` method ``[N,3,3]`` when SH colours should turn with it, as
        :class:`train_world.dual.transfer.ObjectTransfer` has); ``sh_degree``: the SH degree used (default:
        the field's maximum); ``background``: ``[3]`` RGB (features get 0 behind); ``mask``: boolean ``[N]``
        selecting the Gaussians drawn.
        """
        means, quats = self.means, self.quats
        scales, opac = self.scales(), self.opacities()
        sh, feats = self.sh(), self.features
        if mask is not None:
            means, quats, scales, opac, sh, feats = (t[mask] for t in (means, quats, scales, opac, sh, feats))
        rot = None  # rotation of each Gaussian by the transform: SH colours turn with the Gaussians
        if transform is not None:
            if callable(transform) and not isinstance(transform, torch.Tensor):
                means, quats = transform(means, quats)
                rot = transform.rotations() if hasattr(transform, "rotations") else None
            else:
                T = transform if transform.dim() == 2 or mask is None else transform[mask]
                means, quats = rigid_transform_gaussians(means, quats, T)
                rot = T[..., :3, :3].to(means.dtype)
        deg = self.max_sh_degree if sh_degree is None else min(int(sh_degree), self.max_sh_degree)
        campos = torch.linalg.inv(viewmats.detach())[:, :3, 3]
        dirs = means[None, :, :] - campos[:, None, :]
        if rot is not None and deg > 0:  # view direction into each Gaussian's own (unmoved) frame: R^T d
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
        out, alpha, meta = rasterize(
            means, quats, scales, opac, cols, viewmats, Ks, int(width), int(height), backgrounds=bg
        )
        return RenderOutput(
            rgb=out[..., :3], features=out[..., 3:] if with_features else None, alpha=alpha, meta=meta
        )

    # ------------------------------------------------------------------ export
    @torch.no_grad()
    def to_gaussian_set(self, labels: np.ndarray | None = None) -> GaussianSet:
        """Activated numpy copy (``GaussianSet``), with the raw logits/log-scales kept as encodings."""
        q = self.quats.detach()
        q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return GaussianSet(
            means=self.means.detach().numpy(),
            quats=q.numpy(),
            scales=self.scales().detach().numpy(),
            opacities=self.opacities().detach().numpy(),
            sh=self.sh().detach().numpy(),
            features=self.features.detach().numpy(),
            labels=labels,
            opacity_logits=self.opacity_logits.detach().numpy(),
            log_scales=self.log_scales.detach().numpy(),
        )

    @torch.no_grad()
    def labels(self, classifier: nn.Module) -> torch.Tensor:
        """Per-Gaussian class (argmax of the classifier on its identity feature), ``[N]`` int64."""
        if self.num == 0:
            return torch.zeros(0, dtype=torch.int64)
        return classifier(self.features).argmax(dim=-1)
