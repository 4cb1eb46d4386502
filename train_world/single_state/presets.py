"""Training presets and configuration (frozen dataclasses, JSON round-trippable).

``quick`` is for tests (seconds on 32x32 data), ``default`` gives the best result in about 15 minutes on a
2-core CPU at 128-200 px, ``paper`` uses DSG-World's iteration count (20k) with the 3DGS schedule scaled to
it. Schedules follow 3DGS (densify every 100 steps from 500 to half the run, opacity reset every 3000, SH
degree up every 1000), scaled to each preset's length.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

from dsg_gym.splat_options import DEFAULT_EPS2D, check_splat_options

__all__ = [
    "MIP_EPS2D",
    "MIP_FILTER3D_SCALE",
    "PRESETS",
    "LearningRates",
    "Preset",
    "TrainConfig",
    "get_preset",
    "mip_overrides",
]


@dataclass(frozen=True)
class LearningRates:
    """Adam learning rates (3DGS / Gaussian Grouping defaults); ``means`` is multiplied by the scene
    extent and decays exponentially to ``means_final`` (also times the extent)."""

    means: float = 1.6e-4
    means_final: float = 1.6e-6
    quats: float = 1e-3
    scales: float = 5e-3
    opacities: float = 5e-2
    sh0: float = 2.5e-3
    shN: float = 2.5e-3 / 20
    features: float = 2.5e-3
    classifier: float = 5e-4


@dataclass(frozen=True)
class Preset:
    """One training schedule. Step counts are iterations (one view per iteration)."""

    name: str
    iterations: int
    sh_degree: int = 3
    sh_degree_every: int = 1000
    num_init_points: int = 50_000
    init_opacity: float = 0.1
    # densification (3DGS)
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    grad_threshold: float = 2e-4
    percent_dense: float = 0.01
    prune_opacity: float = 0.005
    prune_big_world: float = 0.1
    reset_every: int = 3000
    max_gaussians: int = 300_000
    # AbsGS: densify on the sums of absolute per-pixel 2D mean gradients, against ``absgrad_threshold``
    # instead of ``grad_threshold`` (gsplat's 4x the 3DGS threshold)
    absgrad: bool = False
    absgrad_threshold: float = 8e-4
    # losses (Gaussian Grouping)
    lambda_dssim: float = 0.2
    lambda_identity: float = 1.0
    reg3d_every: int = 2
    reg3d_weight: float = 2.0
    reg3d_k: int = 5
    reg3d_samples: int = 1000
    # not DSG-World's: relative expected-depth L1 against the capture's depth where it has depth (0: off)
    lambda_depth: float = 0.0
    checkpoint_every: int = 500
    # Mip-Splatting: the renderer's mode ("antialiased" = 2D Mip filter), its 2D low-pass in px^2 (3DGS 0.3,
    # Mip-Splatting 0.1) and the 3D filter's variance factor (0: off; the paper's 0.2)
    rasterize_mode: str = "classic"
    eps2d: float = DEFAULT_EPS2D
    filter3d_scale: float = 0.0
    # two-state training (DSG-World, ``dsg-train`` on a capture with state1 and state2): every step trains
    # both fields, and a joint step renders up to six views, so it has its own step count (the schedule above is
    # scaled to it) and field-size cap; None: the single-state ones
    dual_iterations: int | None = None
    dual_max_gaussians: int | None = None
    # fraction of the two-state steps that is reconstruction only (DSG-World: 0.5, 10k + 10k)
    dual_joint_from: float = 0.5
    # not DSG-World's: Adam steps refining the merged world on both states' training views after training
    # (:mod:`train_world.dual_state.refine`; 0: off, as in the paper)
    dual_refine_steps: int = 0
    # not DSG-World's either: the refinement in two layers, background and objects merged per pixel by expected
    # depth (``dsg-train --layers``), and the weight of the support term in the joint phase and the refinement
    # (``--support-weight``; 0: off)
    dual_layers: bool = False
    dual_support_weight: float = 0.0
    lrs: LearningRates = field(default_factory=LearningRates)

    def __post_init__(self) -> None:
        if self.iterations < 1:
            raise ValueError(f"preset {self.name!r}: iterations must be >= 1, got {self.iterations}")
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"preset {self.name!r}: sh_degree must be 0..3, got {self.sh_degree}")
        try:
            check_splat_options(self.rasterize_mode, self.eps2d)
        except ValueError as e:
            raise ValueError(f"preset {self.name!r}: {e}") from None
        if not (math.isfinite(self.lambda_depth) and self.lambda_depth >= 0):
            raise ValueError(
                f"preset {self.name!r}: lambda_depth must be a finite number >= 0, got {self.lambda_depth}"
            )
        if not (math.isfinite(self.absgrad_threshold) and self.absgrad_threshold > 0):
            raise ValueError(
                f"preset {self.name!r}: absgrad_threshold must be a finite number > 0, got {self.absgrad_threshold}"
            )
        if not self.filter3d_scale >= 0:
            raise ValueError(f"preset {self.name!r}: filter3d_scale must be >= 0, got {self.filter3d_scale}")
        for name in ("densify_every", "sh_degree_every", "checkpoint_every", "reg3d_every", "reset_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"preset {self.name!r}: {name} must be >= 1")
        if not 0.0 <= self.dual_joint_from <= 1.0:
            raise ValueError(
                f"preset {self.name!r}: dual_joint_from must be in [0, 1], got {self.dual_joint_from}"
            )
        if not (math.isfinite(self.dual_support_weight) and self.dual_support_weight >= 0):
            raise ValueError(
                f"preset {self.name!r}: dual_support_weight must be a finite number >= 0, "
                f"got {self.dual_support_weight}"
            )
        if self.dual_refine_steps < 0:
            raise ValueError(
                f"preset {self.name!r}: dual_refine_steps must be >= 0, got {self.dual_refine_steps}"
            )
        for name in ("dual_iterations", "dual_max_gaussians"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"preset {self.name!r}: {name} must be >= 1 or None")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Preset:
        d = dict(d)
        d["lrs"] = LearningRates(**d.get("lrs", {}))
        return cls(**d)


MIP_FILTER3D_SCALE = 0.2  # Mip-Splatting's 3D filter variance factor (``--mip``)
MIP_EPS2D = 0.1  # and its 2D Mip filter's variance (px^2)
_MIP = {"rasterize_mode": "antialiased", "eps2d": MIP_EPS2D, "filter3d_scale": MIP_FILTER3D_SCALE}
_AA = {"rasterize_mode": "antialiased", "eps2d": MIP_EPS2D, "filter3d_scale": 0.0}

# ``default`` and ``paper`` train with Mip-Splatting's antialiased rasterizer and 2D Mip filter but without its
# 3D smoothing filter: on the synthetic scenes held-out views score higher without it, and objects seen from
# nearer cameras lose little. ``--mip`` adds the 3D filter (0.2). ``quick`` keeps 3DGS's classic rasterizer: on
# its 32-pixel test data the filters cost 2 dB.
# ``default`` trains two states (DSG-World) for 4500 steps, the first 3000 reconstruction only (a reconstruction
# step renders two views, a joint step about five), with at most 60k Gaussians per field, then refines the merged
# world on both states' views for 4000 steps (:mod:`train_world.dual_state.refine`), in two layers, with the
# support term at 0.1 in the joint phase and the refinement. The schedule was chosen against shorter and
# differently split ones on the synthetic scenes, the layers and the support term against one sorted list
# without it (docs/training.md; figures in docs/benchmarks.md). ``quick`` and ``paper`` leave both off.
PRESETS: dict[str, Preset] = {
    "quick": Preset(
        name="quick",
        iterations=300,
        sh_degree=1,
        sh_degree_every=100,
        num_init_points=3000,
        densify_from=50,
        densify_until=220,
        densify_every=25,
        reset_every=150,
        max_gaussians=8000,
        reg3d_every=5,
        reg3d_samples=200,
        checkpoint_every=50,
        dual_refine_steps=40,
    ),
    "default": Preset(
        name="default",
        iterations=5000,
        sh_degree=3,
        sh_degree_every=1000,
        num_init_points=50_000,
        densify_from=500,
        densify_until=3000,
        densify_every=100,
        reset_every=2000,
        max_gaussians=250_000,
        reg3d_every=5,
        reg3d_samples=1000,
        checkpoint_every=500,
        dual_iterations=4500,
        dual_max_gaussians=60_000,
        dual_joint_from=2 / 3,
        dual_refine_steps=4000,
        dual_layers=True,
        dual_support_weight=0.1,
        **_AA,
    ),
    "paper": Preset(
        name="paper",
        iterations=20_000,
        sh_degree=3,
        sh_degree_every=1000,
        num_init_points=100_000,
        densify_from=500,
        densify_until=10_000,
        densify_every=100,
        reset_every=3000,
        max_gaussians=1_000_000,
        reg3d_every=2,
        checkpoint_every=1000,
        **_AA,
    ),
}


def mip_overrides(mip: bool | None) -> dict[str, Any]:
    """Preset fields for ``--mip`` (all of Mip-Splatting: antialiased rasterizer, 2D Mip filter and 3D
    filter), ``--no-mip`` (3DGS's classic rasterizer, no 3D filter) or neither (``None``: the preset's own
    choice, which for ``default`` and ``paper`` is the antialiased rasterizer without the 3D filter)."""
    if mip is None:
        return {}
    if mip:
        return dict(_MIP)
    return {"rasterize_mode": "classic", "eps2d": DEFAULT_EPS2D, "filter3d_scale": 0.0}


def get_preset(name: str, **overrides: Any) -> Preset:
    """The named preset with fields replaced by ``overrides`` (e.g. ``iterations=100``)."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides) if overrides else PRESETS[name]


@dataclass(frozen=True)
class TrainConfig:
    """Everything a run depends on besides the capture itself (stored in checkpoints and the world file).

    ``state``: the capture state to train (None: the first training state); ``holdout_every``: when the state
    has no held-out views of its own configuration, every n-th view (indices 0, n, 2n, ...) is held out for
    evaluation (0: none); ``background``: colour behind the Gaussians (None: white for NeRF-Blender data,
    black otherwise); ``num_features``: identity feature width (16 in Gaussian Grouping).

    ``refine_cameras``: make the training cameras parameters (:mod:`.camera_refine`; for captures whose cameras
    are estimates). Their Adam runs from the preset's ``densify_from`` step to the end, starting at
    ``camera_lr_rotation`` (radians per step) and ``camera_lr_translation`` times the scene extent (scene
    units per step), both decaying exponentially to a tenth.
    """

    preset: Preset
    seed: int = 0
    downscale: int = 1
    state: str | None = None
    single_state: bool = False
    holdout_every: int = 8
    background: tuple[float, float, float] | None = None
    num_features: int = 16
    refine_cameras: bool = False
    camera_lr_rotation: float = 1e-4
    camera_lr_translation: float = 1e-4

    def __post_init__(self) -> None:
        for name in ("camera_lr_rotation", "camera_lr_translation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a finite number > 0, got {v}")
        if self.downscale < 1:
            raise ValueError(f"downscale must be a positive integer, got {self.downscale}")
        if self.holdout_every < 0 or self.holdout_every == 1:
            raise ValueError(f"holdout_every must be 0 (none) or >= 2, got {self.holdout_every}")
        if self.num_features < 1:
            raise ValueError(f"num_features must be >= 1, got {self.num_features}")
        if self.background is not None and len(self.background) != 3:
            raise ValueError(f"background must be three values, got {self.background}")

    def to_dict(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["background"] = None if self.background is None else list(self.background)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainConfig:
        d = dict(d)
        d["preset"] = Preset.from_dict(d["preset"])
        if d.get("background") is not None:
            d["background"] = tuple(float(x) for x in d["background"])
        return cls(**d)


def absgrad_overrides(absgrad: bool, threshold: float | None = None) -> dict[str, Any]:
    """Preset fields for ``--absgrad`` and ``--absgrad-threshold`` (none when neither is given)."""
    out: dict[str, Any] = {"absgrad": True} if absgrad else {}
    if threshold is not None:
        out["absgrad_threshold"] = float(threshold)
    return out


def depth_overrides(weight: float | None) -> dict[str, float]:
    """Preset fields for ``--depth-weight`` (none when not given)."""
    return {} if weight is None else {"lambda_depth": float(weight)}


_SCHEDULE = (
    "densify_from",
    "densify_until",
    "densify_every",
    "reset_every",
    "sh_degree_every",
    "checkpoint_every",
)


def scaled_preset(
    name: str, iterations: int | None = None, max_gaussians: int | None = None, *, two_state: bool = False
) -> Preset:
    """Preset ``name``; with ``iterations``, every schedule step count scaled by ``iterations / preset's``
    (so an opacity reset never lands at the end of a shortened run); ``max_gaussians``: the field size cap.
    ``two_state``: the defaults are the preset's two-state step count and cap (``dual_iterations``,
    ``dual_max_gaussians``) where it has them."""
    p = get_preset(name)
    if two_state:
        iterations = p.dual_iterations if iterations is None else iterations
        max_gaussians = p.dual_max_gaussians if max_gaussians is None else max_gaussians
    if max_gaussians is not None:
        if max_gaussians < 1000:
            raise ValueError(f"--max-gaussians must be at least 1000, got {max_gaussians}")
        p = dataclasses.replace(p, max_gaussians=int(max_gaussians))
    if iterations is None or iterations == p.iterations:
        return p
    if iterations < 1:
        raise ValueError(f"--iterations must be at least 1, got {iterations}")
    f = iterations / p.iterations
    return dataclasses.replace(
        p, iterations=int(iterations), **{k: max(1, round(getattr(p, k) * f)) for k in _SCHEDULE}
    )
