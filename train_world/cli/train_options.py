"""Options ``dsg-train`` shares between its single-state and two-state command lines."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from train_world.dual_state.views import motions_estimated

__all__ = [
    "add_camera_argument",
    "add_depth_argument",
    "add_mip_argument",
    "add_shell_argument",
    "camera_options",
]


def add_mip_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--mip",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="--mip: all of Mip-Splatting (antialiased rasterizer, 2D Mip filter, 3D smoothing filter 0.2); "
        "--no-mip: 3DGS's classic rasterizer (default: the preset's; default/paper: antialiased, no 3D filter)",
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
    cams = p.add_mutually_exclusive_group()
    cams.add_argument(
        "--refine-cameras",
        dest="refine_cameras",
        action="store_true",
        default=None,
        help="optimise a pose correction of every training camera (train_world.single_state.camera_refine; "
        "default when the capture's cameras are estimates, i.e. made by dsg-capture)",
    )
    cams.add_argument(
        "--fixed-cameras",
        dest="refine_cameras",
        action="store_false",
        help="take the capture's cameras as exact (default for synthetic captures and NeRF-Blender data)",
    )


def camera_options(args: argparse.Namespace, capture: Path) -> dict[str, Any]:
    """``TrainConfig`` fields for ``--refine-cameras`` / ``--fixed-cameras`` / neither (refined when
    ``capture`` was made by ``dsg-capture``)."""
    refine = motions_estimated(capture) if args.refine_cameras is None else bool(args.refine_cameras)
    return {"refine_cameras": refine}
