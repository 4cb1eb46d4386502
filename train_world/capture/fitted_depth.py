"""Depth maps for a capture that has none, from a first reconstruction of each state.

A capture made from photos has cameras, masks and sparse points but no depth, so training starts from the
sparse points, the table top, the objects' visual hulls, points out to the room and random points, and much of
its Gaussian budget goes to what the random start leaves floating. :func:`fit_depth_maps` trains one field per
state on all of that state's views from that same start, renders the expected depth (accumulated depth over
alpha) of its Gaussians of opacity above ``min_opacity`` at every view where their alpha exceeds
``min_alpha``, and writes the maps into the capture (``<state>/depth/<stem>.png``, uint16 in ``DEPTH_SCALE``
units, 0 = none; each frame of ``transforms.json`` gains its ``depth_path``).
Where the capture has structure-from-motion points and a table top (``dsg-capture``'s), the floor they show
(:mod:`.floor`) then takes the background depth that lies near it: a depth fit leaves even a textured floor a
tenth of its depth off, the points pin it to a few millimetres. Last, with ``edge_angle_deg`` above 0, every
depth that differs from a 4-neighbour's by more than on a surface seen that many degrees from edge-on, or
borders a pixel without depth, is dropped (:func:`drop_depth_jumps`): a fit blends the near and the far side of
an outline into depths between them, points in the air that training would otherwise start from.
Training on the capture then starts from points back-projected from them, on every surface the photos show,
bare walls included, as it does from a capture with measured depth. Unlike multi-view stereo
(:mod:`.mvs`) the maps need no texture; they are only as right as the first fit, and serve only as the start
(``dsg-train`` uses depth for nothing else unless ``--depth-weight`` is given).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from train_world.capture.files import read_json
from train_world.capture.floor import Floor, fit_floor, floor_depth
from train_world.capture.format import (
    DEPTH_SCALE,
    atomic_write_bytes,
    atomic_write_json,
    depth_to_png_units,
    encode_png,
)
from train_world.capture.points import capture_points

if TYPE_CHECKING:
    import torch

__all__ = [
    "DepthFit",
    "capture_floor",
    "drop_depth_jumps",
    "fit_depth_maps",
    "fitted_depths",
    "jump_limits",
    "rendered_depths",
]


@dataclasses.dataclass(frozen=True)
class DepthFit:
    """The first reconstruction behind :func:`fit_depth_maps`: ``steps`` training steps at most
    ``max_gaussians`` Gaussians (densification until two thirds of the steps; the ``default`` preset's
    other settings) on the photos downscaled by the integer ``downscale`` (half their size by default); its
    depth rendered at the photos' own size from the Gaussians of opacity above ``min_opacity`` and kept where
    the render's alpha exceeds ``min_alpha``. The nearly transparent Gaussians that a fit leaves floating
    (what is left of the random start) would pull every expected depth towards the camera. Background depth
    within ``floor_tolerance`` (a fraction) of the floor is put on it (:mod:`.floor`; 0: never); depth at a
    jump to a neighbour steeper than a surface seen ``edge_angle_deg`` degrees from edge-on is dropped
    (:func:`drop_depth_jumps`; 0, the default: never)."""

    steps: int = 3000
    max_gaussians: int = 60_000
    min_alpha: float = 0.5
    min_opacity: float = 0.2
    seed: int = 0
    downscale: int = 2
    floor_tolerance: float = 0.3
    edge_angle_deg: float = 0.0

    def __post_init__(self) -> None:
        if self.steps < 100:
            raise ValueError(f"a depth fit needs at least 100 steps, got {self.steps}")
        if self.max_gaussians < 1000:
            raise ValueError(f"a depth fit needs at least 1000 Gaussians, got {self.max_gaussians}")
        if not 0.0 < self.min_alpha < 1.0:
            raise ValueError(f"min_alpha must lie in (0, 1), got {self.min_alpha}")
        if not 0.0 <= self.min_opacity < 1.0:
            raise ValueError(f"min_opacity must lie in [0, 1), got {self.min_opacity}")
        if not (isinstance(self.downscale, int) and self.downscale >= 1):
            raise ValueError(f"a depth fit's downscale must be an integer >= 1, got {self.downscale!r}")
        if not 0.0 <= self.floor_tolerance < 1.0:
            raise ValueError(f"floor_tolerance must lie in [0, 1), got {self.floor_tolerance}")
        if not 0.0 <= self.edge_angle_deg < 90.0:
            raise ValueError(f"edge_angle_deg must lie in [0, 90), got {self.edge_angle_deg}")


def rendered_depths(field, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                    background: torch.Tensor, min_alpha: float, min_opacity: float = 0.0) -> torch.Tensor:  # fmt: skip
    """Expected depth ``[V,H,W]`` float32 (camera z) of ``field``'s Gaussians of opacity above ``min_opacity``
    at cameras ``viewmats [V,4,4]``, ``Ks [V,3,3]``; 0 where their alpha is at most ``min_alpha``."""
    import torch

    out = torch.zeros(len(viewmats), height, width)
    with torch.no_grad():
        mask = field.opacities().detach() > min_opacity if min_opacity > 0 else None
        for i in range(len(viewmats)):
            r = field.render(viewmats[i : i + 1], Ks[i : i + 1], width, height, background=background,
                             with_features=False, with_depth=True, mask=mask)  # fmt: skip
            a = r.alpha[0, ..., 0]
            z = r.depth[0] / a.clamp_min(1e-6)
            out[i] = torch.where((a > min_alpha) & torch.isfinite(z) & (z > 0), z, torch.zeros_like(z))
    return out


def fitted_depths(
    capture: str | Path, state: str, fit: DepthFit, *, progress: bool = False, views=None
) -> torch.Tensor:
    """Depth ``[V,H,W]`` at every view of ``state`` (the order of its ``transforms.json``, the photos' size)
    from a field trained on all of them (:class:`DepthFit`). ``views``: the state's views at the photos' size
    (:class:`.loader.Views`, only their cameras are read), when the caller has them loaded already; otherwise
    the training views, or for a fit at a smaller size the capture's views loaded here."""
    from train_world.capture.loader import load_capture
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, get_preset
    from train_world.single_state.trainer import Trainer

    preset = get_preset("default", iterations=fit.steps, densify_until=max(1, round(2 * fit.steps / 3)),
                        max_gaussians=fit.max_gaussians, checkpoint_every=fit.steps)  # fmt: skip
    config = TrainConfig(preset=preset, seed=fit.seed, state=state, holdout_every=0, downscale=fit.downscale)
    data = load_training_data(capture, config)
    trainer = Trainer(data, config)
    trainer.train(progress=progress, label=f"depth fit {state}")
    if views is None:
        views = data  # the training views, or the photos' own size for a fit at a smaller one
        if fit.downscale > 1:
            views = load_capture(capture, states=[state], load_masks=False, load_depth=False).states[state]
    return rendered_depths(trainer.field, views.viewmats, views.Ks, views.width, views.height,
                           trainer.background, fit.min_alpha, fit.min_opacity)  # fmt: skip


def jump_limits(K: np.ndarray, edge_angle_deg: float) -> tuple[float, float]:
    """The largest relative depth change between vertical and between horizontal neighbours (``K [3,3]``'s
    pixels) of a plane seen ``edge_angle_deg`` from edge-on: ``sin(a + p) / sin(a) - 1`` for a pixel's angle
    ``p``, 1 / focal length (at 256 px and a 55 degree view, 4.7 % at 5 degrees). Faster changes are outlines."""
    a = np.radians(edge_angle_deg)
    fy, fx = float(K[1, 1]), float(K[0, 0])
    return tuple(float(np.sin(a + 1.0 / f) / np.sin(a) - 1.0) for f in (fy, fx))


def drop_depth_jumps(depth: np.ndarray, limits: tuple[float, float]) -> np.ndarray:
    """``depth [H,W]`` (0 = none) with 0 wherever a 4-neighbour inside the image has no depth, or one that
    differs by more than ``limits`` (vertical, horizontal neighbours: :func:`jump_limits`) times the nearer of
    the two: both sides of every jump go. ``depth`` itself is left as it is."""
    d = np.asarray(depth)
    keep = d > 0
    for axis, limit in enumerate(limits):
        a = np.moveaxis(d, axis, 0)
        lo, hi = a[:-1], a[1:]
        ok = (lo > 0) & (hi > 0) & (np.abs(lo - hi) <= limit * np.minimum(lo, hi))
        k = np.moveaxis(keep, axis, 0)  # a view: the updates land in keep
        k[:-1] &= ok
        k[1:] &= ok
    return np.where(keep, d, np.zeros_like(d))


def capture_floor(capture: str | Path) -> Floor | None:
    """The floor (:func:`.floor.fit_floor`) of the capture folder ``capture``'s structure-from-motion points
    and table, its lengths scaled by the median camera distance to the table top's centre; None when the
    capture has no points, no table bounds, or no floor in them."""
    from train_world.capture.loader import capture_states, frame_poses

    capture = Path(capture)
    scene = read_json(capture / "scene.json")
    points = capture_points(capture, scene)
    table = scene.get("table")
    if points is None or not isinstance(table, dict) or "bounds" not in table:
        return None
    bounds = np.asarray(table["bounds"], np.float64)
    centre = np.r_[(bounds[0, :2] + bounds[1, :2]) / 2, 0.0]
    states = capture_states(capture, scene)
    eyes = np.concatenate([frame_poses(capture / s / "transforms.json")[:, :3, 3] for s in states])
    ref = float(np.median(np.linalg.norm(eyes - centre, axis=1)))
    return fit_floor(points[0], bounds, ref)


def fit_depth_maps(capture: str | Path, states, fit: DepthFit, *, progress: bool = False) -> dict:
    """Write :func:`fitted_depths` of each of ``states`` into the capture folder ``capture``, the floor's
    background put on it (module docstring). The capture must have no depth maps yet. Returns each state's
    share of pixels with depth (``coverage``), the floor (``floor``: :meth:`.floor.Floor.to_dict`, or None)
    and each state's share of pixels put on it (``on_floor``); depth at jumps is dropped last
    (:func:`drop_depth_jumps`), each state's share of pixels that lost it is ``dropped``."""
    from train_world.capture.loader import load_capture

    capture = Path(capture)
    found = capture_floor(capture) if fit.floor_tolerance > 0 else None
    coverage, on_floor, dropped = {}, {}, {}
    for s in states:
        tj = capture / s / "transforms.json"
        doc = read_json(tj)
        frames = doc["frames"]
        if any("depth_path" in f for f in frames):
            raise ValueError(f"{tj}: the capture has depth maps already; a depth fit is for captures without")
        views = None  # the state's masks and intrinsics, needed only for the floor and the jumps
        if found is not None or fit.edge_angle_deg > 0:
            views = load_capture(capture, states=[s], load_depth=False).states[s]
        depth = fitted_depths(capture, s, fit, progress=progress, views=views).numpy()
        if len(depth) != len(frames):
            raise RuntimeError(f"{tj}: {len(frames)} frames but {len(depth)} depth maps")
        if found is not None:
            moved = 0
            for i in range(len(depth)):
                background = (
                    views.masks[i].numpy() == 0 if views.masks is not None else np.ones_like(depth[i], bool)
                )
                d, m = floor_depth(depth[i], background, views.viewmats[i].double().numpy(),
                                   views.Ks[i].double().numpy(), found, fit.floor_tolerance)  # fmt: skip
                depth[i], moved = d, moved + int(m.sum())
            on_floor[s] = round(moved / depth.size, 4)
        if fit.edge_angle_deg > 0:
            had = int((depth > 0).sum())
            depth = np.stack([drop_depth_jumps(d, jump_limits(views.Ks[i].double().numpy(), fit.edge_angle_deg))
                              for i, d in enumerate(depth)])  # fmt: skip
            dropped[s] = round((had - int((depth > 0).sum())) / depth.size, 4)
        units = depth_to_png_units(depth)
        for f, d in zip(frames, units, strict=True):
            rel = f"depth/{Path(f['file_path']).stem}.png"
            atomic_write_bytes(capture / s / rel, encode_png(d))
            f["depth_path"] = rel
        doc["depth_unit_scale_factor"] = DEPTH_SCALE
        atomic_write_json(tj, doc)
        coverage[s] = round(float((units > 0).mean()), 4)
    return {
        "coverage": coverage,
        "floor": None if found is None else found.to_dict(),
        "on_floor": on_floor,
        "dropped": dropped,
    }
