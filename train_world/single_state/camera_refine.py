"""Training cameras as parameters: per-view pose corrections (``dsg-train --refine-cameras``, off by default).

At 128 px a camera 0.2 degrees off moves its image by half a pixel. Where training cameras disagree with each
other by that much, the views disagree about where each textured point is, and the field blurs what they
disagree about. With camera refinement on, every training view ``i``
gets a rigid correction, a rotation vector ``w_i`` and a translation ``u_i`` in its camera's coordinates
(OpenCV: x right, y down, z forward), both zero at the start::

    viewmat'_i = D_i viewmat_i          D_i = [exp(w_i) | u_i]

``|w_i|`` is the angle the camera turns about its centre and ``u_i`` (scene units) how far it moves, seen from
the camera. The renderer takes no gradient in the view matrix, so the correction is applied to the Gaussians
instead: rendering the field moved by the world transform ``T_i = inv(viewmat_i) D_i viewmat_i`` from the given
camera is rendering the field from the corrected one (the view direction of the SH colours turns with it,
:meth:`SegmentedField.render`). Composition is in float64; the renderer's float32 copy is made last.

The corrections receive gradients through the view's reconstruction loss and have their own Adam
(:meth:`CameraCorrections.make_optimizer`). Training renders one view per step, so each view's correction is a
parameter of its own: Adam skips a parameter without a gradient, so a view's correction and its moments change
only at the steps that render it (one ``[V, 3]`` tensor would keep every view moving on its decaying momentum
between its renders, by several times the learning rate per visit). A correction and a shift of the whole
field are the same thing for one view, but not for all views at once: what the corrections learn is how the
views disagree.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from dsg_gym.cameras import camera_centres
from dsg_gym.geometry import axis_angle_to_quat, quat_to_rotmat
from train_world.capture.alignment import rotation_angle_deg

__all__ = ["CORRECTION_LR_FINAL_FACTOR", "CameraCorrections", "correction_lrs"]

#: the learning rates of rigid corrections (these cameras', :mod:`train_world.dual_state.motions`' objects')
#: decay exponentially over their refinement to this fraction of their start value
CORRECTION_LR_FINAL_FACTOR = 0.1


def correction_lrs(
    step: int, start: int, end: int, lr_translation: float, lr_rotation: float
) -> tuple[float, float]:
    """``(translation, rotation)`` learning rates of a rigid correction at ``step``: the start values at
    ``start``, decaying exponentially to :data:`CORRECTION_LR_FINAL_FACTOR` of them at ``end``."""
    t = min(max((step - start) / max(end - start, 1), 0.0), 1.0)
    f = CORRECTION_LR_FINAL_FACTOR**t
    return lr_translation * f, lr_rotation * f


class CameraCorrections:
    """The corrections of the module docstring for training cameras ``viewmats [V,4,4]`` (world-to-camera).

    The parameters are ``rotvecs[i]`` and ``translations[i]``, ``[3]`` float64 per view (zero: the cameras as
    given); :attr:`rotvec` and :attr:`translation` are them stacked ``[V,3]`` (detached)."""

    def __init__(self, viewmats: torch.Tensor | np.ndarray):
        vm = torch.as_tensor(np.asarray(viewmats, dtype=np.float64))
        if vm.ndim != 3 or vm.shape[1:] != (4, 4):
            raise ValueError(f"CameraCorrections: viewmats must be [V,4,4], got {tuple(vm.shape)}")
        self.base = vm
        self._base_inv = torch.linalg.inv(vm)
        v = len(vm)
        self.rotvecs = [torch.zeros(3, dtype=torch.float64, requires_grad=True) for _ in range(v)]
        self.translations = [torch.zeros(3, dtype=torch.float64, requires_grad=True) for _ in range(v)]

    def __len__(self) -> int:
        return len(self.base)

    @property
    def rotvec(self) -> torch.Tensor:
        return torch.stack(self.rotvecs).detach()

    @property
    def translation(self) -> torch.Tensor:
        return torch.stack(self.translations).detach()

    def named_parameters(self) -> list[tuple[str, torch.Tensor]]:
        return [(f"cameras.rotvec.{i}", p) for i, p in enumerate(self.rotvecs)] + [
            (f"cameras.translation.{i}", p) for i, p in enumerate(self.translations)
        ]

    def make_optimizer(self, lr_translation: float, lr_rotation: float) -> torch.optim.Adam:
        """One Adam with two groups: the rotations at ``lr_rotation`` (radians), the translations at
        ``lr_translation`` (scene units)."""
        return torch.optim.Adam(
            [
                {"params": self.rotvecs, "lr": lr_rotation},
                {"params": self.translations, "lr": lr_translation},
            ],
            eps=1e-15,
        )

    def _corrections(self, index: slice) -> torch.Tensor:
        """``D`` ``[n,4,4]`` float64 of the views ``index``, differentiable in the parameters."""
        w = torch.stack(self.rotvecs[index])
        u = torch.stack(self.translations[index])
        R = quat_to_rotmat(axis_angle_to_quat(w))
        top = torch.cat([R, u[:, :, None]], 2)
        bottom = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(len(R), 1, 4)
        return torch.cat([top, bottom], 1)

    def transform(self, i: int) -> torch.Tensor:
        """``T_i = inv(viewmat_i) D_i viewmat_i`` ``[4,4]`` float32: the world transform that, applied to the
        Gaussians, renders view ``i`` as its corrected camera sees them (with gradients to the parameters)."""
        D = self._corrections(slice(i, i + 1))[0]
        return (self._base_inv[i] @ D @ self.base[i]).float()

    @torch.no_grad()
    def viewmat(self, i: int) -> torch.Tensor:
        """View ``i``'s corrected camera ``[1,4,4]`` float32 (no gradient)."""
        return (self._corrections(slice(i, i + 1)) @ self.base[i : i + 1]).float()

    @torch.no_grad()
    def viewmats(self) -> torch.Tensor:
        """The corrected cameras ``D_i viewmat_i`` ``[V,4,4]`` float64 (rigid)."""
        return self._corrections(slice(None)) @ self.base

    @torch.no_grad()
    def summary(self, units: str) -> dict:
        """How far the corrections moved the cameras: the median and largest angle (degrees) and distance
        (scene units, and mm when ``units`` is metres) over the views."""
        new = self.viewmats().numpy()
        base = self.base.numpy()
        ang = rotation_angle_deg(new[:, :3, :3] @ np.swapaxes(base[:, :3, :3], 1, 2))
        dist = np.linalg.norm(camera_centres(new) - camera_centres(base), axis=1)
        out = {
            "views": len(new),
            "rotation_deg_median": float(np.median(ang)) if len(ang) else 0.0,
            "rotation_deg_max": float(ang.max()) if len(ang) else 0.0,
            "translation_median": float(np.median(dist)) if len(dist) else 0.0,
            "translation_max": float(dist.max()) if len(dist) else 0.0,
        }
        if units == "metres":
            out["translation_mm_median"] = out["translation_median"] * 1000.0
            out["translation_mm_max"] = out["translation_max"] * 1000.0
        return {k: (round(v, 6) if isinstance(v, float) and math.isfinite(v) else v) for k, v in out.items()}

    # ------------------------------------------------------------------ checkpoints
    def state_tensors(self) -> dict[str, torch.Tensor]:
        return {"cameras/rotvec": self.rotvec.detach(), "cameras/translation": self.translation.detach()}

    @torch.no_grad()
    def load_state_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        for key, ps in (("cameras/rotvec", self.rotvecs), ("cameras/translation", self.translations)):
            v = tensors[key]
            if tuple(v.shape) != (len(ps), 3):
                raise ValueError(f"checkpoint {key}: shape {tuple(v.shape)}, expected {(len(ps), 3)}")
            for p, row in zip(ps, v):
                p.copy_(row)
