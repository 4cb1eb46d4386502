"""Options ``dsg-train`` shares between its single-state and two-state command lines."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from train_world.dual_state.refine import RefineConfig
    from train_world.single_state.presets import Preset

__all__ = [
    "add_absgrad_argument",
    "add_camera_argument",
    "add_depth_argument",
    "add_mip_argument",
    "add_shell_argument",
    "camera_options",
    "refine_config",
]


def add_mip_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--mip: all of Mip-Splatting (antialiased rasterizer, 2D Mip filter, 3D smoothing filter 0.2); "
        "--no-mip: 3DGS's classic rasterizer (default: the preset's; default/paper: antialiased, no 3D filter)",
    )


def add_absgrad_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--absgrad",
        action="store_true",
        help="densify on absolute per-pixel 2D mean gradients (AbsGS; splits large Gaussians that blur texture; "
        "off by default)",
    )
    p.add_argument(
        "--absgrad-threshold",
        type=float,
        default=None,
        metavar="G",
        help="with --absgrad: the densification threshold (default: the preset's, 8e-4)",
    )


def add_depth_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--depth-weight",
        type=float,
        default=None,
        metavar="W",
        help="weight of an expected-depth term against the capture's depth, where it has depth (relative L1; "
        "not part of DSG-World; default: the preset's, 0 = off)",
    )


def add_shell_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--no-shell",
        action="store_true",
        help="do not add the far shell that fills directions no training view saw (train_world.complete.shell; "
        "added by default, except to worlds of NeRF-Blender captures, whose background is a plain colour)",
    )


def add_camera_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--refine-cameras",
        action="store_true",
        help="optimise a pose correction of every training camera (train_world.single_state.camera_refine; off "
        "by default: on dsg-capture captures it measured no gain, docs/benchmarks.md)",
    )
    p.add_argument(
        "--camera-lr-rotation",
        type=float,
        default=1e-4,
        help="with --refine-cameras: rotation learning rate in radians (default 1e-4)",
    )
    p.add_argument(
        "--camera-lr-translation",
        type=float,
        default=1e-4,
        help="with --refine-cameras: translation learning rate, times the scene extent (default 1e-4)",
    )


def camera_options(args: argparse.Namespace) -> dict[str, Any]:
    """``TrainConfig`` fields for ``--refine-cameras`` and the camera learning rates."""
    return {
        "refine_cameras": bool(args.refine_cameras),
        "camera_lr_rotation": args.camera_lr_rotation,
        "camera_lr_translation": args.camera_lr_translation,
    }


def refine_config(args: argparse.Namespace, preset: Preset) -> RefineConfig:
    """The merged world's refinement: ``--refine-steps`` and ``--layers`` or the preset's (``--layers`` without
    a refinement is a ``ValueError``; the preset's layers without one are off). The support weight is set once the
    capture is known to have a table and masks."""
    from train_world.dual_state.refine import RefineConfig

    steps = preset.dual_refine_steps if args.refine_steps is None else args.refine_steps
    if args.layers and steps == 0:
        raise ValueError("--layers acts in the refinement; this run has none: drop --layers or refine")
    layers = preset.dual_layers if args.layers is None else args.layers
    return RefineConfig(steps=steps, seed=args.seed, layers=bool(layers) and steps > 0)
