"""Aligning each evaluation camera to a world before scoring it (test-time pose alignment).

A world made from photos carries its structure-from-motion's camera errors: a ground-truth camera moved into
the world's frame by the similarity of :mod:`.frames` is still a few tenths of a degree off the cameras the
world was trained with, and at 128 px a 0.2 degree turn moves the image by half a pixel, which on a textured
table costs most of the PSNR. Pose-free novel-view evaluations (NeRF--, BARF, NoPe-NeRF) therefore optimise
each test camera's pose against its image, the world frozen, before scoring; :func:`align_view` does that.
Six numbers per view are fitted to the very image they are scored on, so an aligned score is reported beside
the unaligned one (``dsg-eval --align-views``), and a world and its reference are compared with the same
alignment.

The correction is a rigid motion ``D`` of the camera, ``viewmat' = D viewmat``, with ``D = [exp(w) | u]`` in
camera coordinates (OpenCV: x right, y down, z forward): ``w`` (radians) turns the camera about its centre,
``u`` moves it (scene units). The Gaussians are moved into the camera frame once (float64, then float32 for
the renderer), ``D`` is applied to them with gradients, and Adam minimises the mean squared RGB error: the
first half of the steps on both images blurred by a Gaussian of :attr:`ViewAlignment.blur_px` (a wider basin),
the second half on the images as they are. View-dependent colour is evaluated once at the given camera (the
correction is far too small to change it). The aligned pose is kept only when its exact render (the full
:func:`~train_world.eval.evaluate.render_gaussians` path) has a lower squared error than the given pose's; else
the given pose stays. Deterministic: a fixed number of steps, no randomness.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass

import numpy as np
import torch

from dsg_gym.cameras import camera_centres
from dsg_gym.gaussians import GaussianSet
from dsg_gym.geometry import axis_angle_to_quat, quat_multiply, quat_to_rotmat, rotmat_to_quat
from dsg_gym.splat import rasterize, spherical_harmonics
from dsg_gym.splat.layers import rasterize_layers

__all__ = ["AlignedView", "ViewAlignment", "align_view", "align_views", "correction_matrix"]


@dataclass(frozen=True)
class ViewAlignment:
    """Settings of :func:`align_view`: Adam ``steps`` (half blurred, half sharp); learning rates for the
    rotation (radians) and the translation (as a fraction of the median depth of the Gaussians in view),
    decaying exponentially to ``final_lr_factor`` of their start; the blur's standard deviation in pixels."""

    steps: int = 60
    lr_rotation: float = 4e-4
    lr_translation: float = 4e-4
    final_lr_factor: float = 0.1
    blur_px: float = 1.0

    def __post_init__(self):
        if not (isinstance(self.steps, int) and self.steps >= 1):
            raise ValueError(f"view alignment steps must be an integer >= 1, got {self.steps!r}")
        for k in ("lr_rotation", "lr_translation", "final_lr_factor", "blur_px"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"view alignment {k} must be finite and >= 0, got {v!r}")


@dataclass(frozen=True)
class AlignedView:
    """The result for one view: ``viewmat`` ``[4,4]`` float64 (the aligned one, or the given one when aligning
    did not lower the error), the correction's angle (degrees) and translation length (scene units), the
    squared errors before and after (``mse_after == mse_before`` when the given pose stayed) and whether the
    aligned pose was kept."""

    viewmat: np.ndarray
    rotation_deg: float
    translation: float
    mse_before: float
    mse_after: float
    kept: bool

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("viewmat")
        return d


def correction_matrix(rotvec: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``D`` ``[4,4]`` float64: rotation ``exp(rotvec)`` and ``translation`` (camera coordinates)."""
    q = axis_angle_to_quat(torch.as_tensor(np.asarray(rotvec, dtype=np.float64)))
    D = np.eye(4)
    D[:3, :3] = quat_to_rotmat(q).numpy()
    D[:3, 3] = np.asarray(translation, dtype=np.float64)
    return D


def _blur(img: torch.Tensor, sigma: float) -> torch.Tensor:
    """``[H,W,C]`` blurred by a separable Gaussian of ``sigma`` px (radius 3 sigma, edges replicated)."""
    if sigma <= 0:
        return img
    r = max(1, int(math.ceil(3 * sigma)))
    x = torch.arange(-r, r + 1, dtype=img.dtype)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    k = k / k.sum()
    c = img.shape[-1]
    t = img.permute(2, 0, 1)[None]  # [1,C,H,W]
    t = torch.nn.functional.pad(t, (r, r, r, r), mode="replicate")
    t = torch.nn.functional.conv2d(t, k.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    t = torch.nn.functional.conv2d(t, k.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return t[0].permute(1, 2, 0)


def align_view(
    g: GaussianSet,
    viewmat: np.ndarray,
    K: np.ndarray,
    width: int,
    height: int,
    target: np.ndarray,
    render,
    background=(0.0, 0.0, 0.0),
    splat_options: dict | None = None,
    config: ViewAlignment = ViewAlignment(),
    front: np.ndarray | None = None,
) -> AlignedView:
    """Align one camera to the world ``g`` against its image (module docstring).

    Args:
        g: the world's Gaussians at the view's state.
        viewmat: ``[4,4]`` world-to-camera (OpenCV), the pose to start from.
        K: ``[3,3]`` intrinsics; ``width``, ``height``: the image size.
        target: ``[H,W,3]`` the view's image in [0, 1].
        render: ``render(viewmat [4,4]) -> rgb [H,W,3]``, the exact render the evaluation scores.
        background, splat_options: as the world renders (``World.splat_options``).
        config: steps and learning rates.
        front: boolean ``[N]``, the object Gaussians of a world composited in two layers (None: one list).
    """
    vm = np.asarray(viewmat, dtype=np.float64)
    target64 = np.asarray(target, dtype=np.float64)
    gt = torch.from_numpy(np.ascontiguousarray(target, dtype=np.float32))

    def mse(v: np.ndarray) -> float:
        return float(np.mean((np.clip(render(v), 0, 1).astype(np.float64) - target64) ** 2))

    before = mse(vm)
    R, t = vm[:3, :3], vm[:3, 3]
    means_c = torch.from_numpy(np.asarray(g.means, dtype=np.float64) @ R.T + t)
    q_cam = rotmat_to_quat(torch.from_numpy(R.copy()))
    quats_c = quat_multiply(q_cam.expand(g.num, 4), torch.from_numpy(np.asarray(g.quats, dtype=np.float64)))
    campos = torch.from_numpy(camera_centres(vm)).float()
    means_w = torch.from_numpy(np.ascontiguousarray(g.means, dtype=np.float32))
    with torch.no_grad():
        sh = torch.from_numpy(np.ascontiguousarray(g.sh, dtype=np.float32))
        rgb = torch.clamp_min(spherical_harmonics(g.sh_degree, means_w - campos, sh) + 0.5, 0.0)
    scales = torch.from_numpy(np.ascontiguousarray(g.scales, dtype=np.float32))
    opac = torch.from_numpy(np.ascontiguousarray(g.opacities, dtype=np.float32))
    ahead = means_c[:, 2] > 0
    depth = float(torch.median(means_c[ahead, 2])) if bool(ahead.any()) else 1.0
    eye, Kt = torch.eye(4)[None], torch.from_numpy(np.asarray(K, dtype=np.float32))[None]
    bg = torch.tensor(background, dtype=torch.float32)
    splat = rasterize if front is None else functools.partial(rasterize_layers, torch.from_numpy(front))
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    u = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    lr_u = config.lr_translation * depth
    opt = torch.optim.Adam([{"params": [w], "lr": config.lr_rotation}, {"params": [u], "lr": lr_u}])
    half = config.steps // 2
    targets = (_blur(gt, config.blur_px), gt)
    for step in range(config.steps):
        f = config.final_lr_factor ** (step / max(config.steps - 1, 1))
        opt.param_groups[0]["lr"], opt.param_groups[1]["lr"] = config.lr_rotation * f, lr_u * f
        qd = axis_angle_to_quat(w)
        m = means_c @ quat_to_rotmat(qd).T + u
        q = quat_multiply(qd.expand(g.num, 4), quats_c)
        out, _, _ = splat(
            m.float(), q.float(), scales, opac, rgb, eye, Kt, int(width), int(height), backgrounds=bg,
            **(splat_options or {}),
        )  # fmt: skip
        sharp = step >= half
        pred = out[0, ..., :3] if sharp else _blur(out[0, ..., :3], config.blur_px)
        loss = torch.mean((pred - targets[int(sharp)]) ** 2)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    w_np, u_np = w.detach().numpy().copy(), u.detach().numpy().copy()
    aligned = correction_matrix(w_np, u_np) @ vm
    after = mse(aligned)
    kept = bool(np.isfinite(after) and after < before)
    return AlignedView(
        viewmat=aligned if kept else vm.copy(),
        rotation_deg=float(np.degrees(np.linalg.norm(w_np))) if kept else 0.0,
        translation=float(np.linalg.norm(u_np)) if kept else 0.0,
        mse_before=before,
        mse_after=after if kept else before,
        kept=kept,
    )


def align_views(
    g: GaussianSet,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    images: np.ndarray,
    background,
    splat_options: dict | None,
    config: ViewAlignment,
    render_gaussians,
    front: np.ndarray | None = None,
) -> list[AlignedView]:
    """:func:`align_view` for every camera: ``viewmats [V,4,4]``, ``Ks [V,3,3]``, ``images [V,H,W,3]``;
    ``render_gaussians`` is :func:`train_world.eval.evaluate.render_gaussians` (the exact render); ``front`` as
    :func:`align_view`'s."""
    out = []
    for vm, K, img in zip(np.asarray(viewmats), np.asarray(Ks), np.asarray(images)):

        def render(v, K=K):
            return render_gaussians(
                g, v[None], K[None], width, height, background, splat_options, front=front
            )[0][0]

        out.append(align_view(g, vm, K, width, height, img, render, background, splat_options, config, front))
    return out
