"""Single-state baselines for the DSG-World comparison (the paper's Table 1, segmentation rows).

* **(a) segmentation only** (:func:`train_single_state`): one segmented field trained on ``state1``
  (:class:`train_world.single_state.trainer.Trainer`); its world moves the segmented object Gaussians to any
  configuration and leaves the hole they covered on the table.
* **(b) + kNN background completion** (:func:`knn_complete`): Gaussian Grouping's completion of the hole:
  new flat Gaussians on a regular grid over each object's footprint at the reference state (on the table
  plane), each taking colour, identity feature and opacity averaged over its ``k`` nearest background
  Gaussians near the table plane outside the footprints. Only the hole is filled: a grid point with an
  opaque table Gaussian within one grid step (table the capture saw around the object's base) gets none.

Both are world files, so ``dsg-eval WORLD CAPTURE --state test_0`` evaluates them like the DSG-World result.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import World, transform_gaussians

__all__ = ["knn_complete", "reference_footprints", "train_single_state"]


def train_single_state(
    capture: str | Path,
    out: str | Path,
    *,
    preset: str = "default",
    iterations: int | None = None,
    seed: int = 0,
    state: str = "state1",
    progress: bool = False,
    max_gaussians: int | None = None,
    mip: bool | None = None,
    checkpoint: str | Path | None = None,
    resume: bool = False,
    holdout_every: int | None = None,
) -> dict:
    """Baseline (a): train one field on ``state`` (schedule scaled to ``iterations`` as in the two-state
    CLI; ``mip`` as ``dsg-train --mip/--no-mip``) and write its world to ``out``; returns ``{"world",
    "train_seconds", "gaussians"}``. ``checkpoint``: where checkpoints go (None: none); ``resume``: continue
    from it when it exists (a killed run; ``train_seconds`` counts every part); ``holdout_every``: views held
    out of the state (None: as ``dsg-train``'s two-state default, none when the capture has test states)."""
    from train_world.dual_state.views import default_holdout_every
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, mip_overrides, scaled_preset
    from train_world.single_state.trainer import Trainer

    p = dataclasses.replace(scaled_preset(preset, iterations, max_gaussians), **mip_overrides(mip))
    if holdout_every is None:
        holdout_every = default_holdout_every(capture)
    cfg = TrainConfig(preset=p, seed=seed, state=state, holdout_every=holdout_every)
    data = load_training_data(capture, cfg)
    tr = Trainer(data, cfg, checkpoint=checkpoint)
    if resume and checkpoint is not None and Path(checkpoint).exists():
        tr.load_checkpoint()
    tr.train(progress=progress)
    tr.write_world(out, {"baseline": "a: single-state segmentation"})
    return {
        "world": str(out),
        "train_seconds": round(tr.elapsed, 1),
        "gaussians": tr.field.num,
        "holdout_every": holdout_every,
        "training_views": [len(data)],
    }


def reference_footprints(world: World, state: str | None = None):
    """Table-plane footprints (:func:`train_world.dual_state.merge.object_footprints_xy`) of the world's objects
    at ``state`` (default: its reference state)."""
    from train_world.dual_state.merge import object_footprints_xy, robust_object_points

    state = state or world.metadata.get("reference_state")
    poses = world.poses[state]
    pts = []
    for row, oid in enumerate(world.object_ids):
        g = world.objects[oid].gaussians
        keep = g.opacities > 0.1
        placed = transform_gaussians(g.subset(np.nonzero(keep)[0]), poses[row]).means
        pts.append(robust_object_points(placed))
    return object_footprints_xy(pts)


def knn_complete(
    world: World,
    *,
    k: int = 8,
    spacing: float | None = None,
    margin: float = 0.01,
    band: float = 0.01,
    covered_opacity: float = 0.5,
) -> World:
    """Baseline (b): ``world`` with its reference-state object footprints filled (module docstring).

    ``spacing``: grid step (default: from the background Gaussians near the table, 2 x their median largest
    scale, clipped to [2 mm, 2 cm]); ``margin``: footprint dilation; ``band``: how far from the table plane
    (``metadata.table.bounds`` z, else the median height of the background near the footprints) a
    background Gaussian may be to act as a source; ``covered_opacity``: a grid point within one grid step (in
    the table plane) of a background Gaussian in that band at least this opaque is already covered and gets
    no new Gaussian (1.01: fill the whole dilated footprint).
    """
    from scipy.spatial import cKDTree

    from train_world.dual_state.merge import footprint_contains

    bg = world.background
    fps = [f for f in reference_footprints(world) if f is not None]
    if not fps or bg.num == 0:
        return world
    table = world.metadata.get("table", {}).get("bounds")
    xy = bg.means[:, :2].astype(np.float64)
    near_fp = footprint_contains(fps, xy, margin + 0.05)
    z0 = float(table[0][2]) if table else float(np.median(bg.means[near_fp, 2]) if near_fp.any() else 0.0)
    inside = footprint_contains(fps, xy, margin)
    src = (np.abs(bg.means[:, 2] - z0) < band) & ~inside & (bg.opacities > 0.05)
    if src.sum() < k:
        return world
    if spacing is None:
        ref_scale = np.median(bg.scales[src & near_fp].max(-1)) if (src & near_fp).any() else 0.0025
        spacing = float(np.clip(2.0 * ref_scale, 0.002, 0.02))
    # grid over the bounding box of the objects' Gaussians at the reference poses, kept inside a footprint
    ref = world.poses[world.metadata.get("reference_state") or next(iter(world.poses))]
    obj_xy = np.concatenate(
        [
            transform_gaussians(world.objects[oid].gaussians, ref[row]).means[:, :2]
            for row, oid in enumerate(world.object_ids)
        ]
    )
    lo = obj_xy.min(0) - margin
    hi = obj_xy.max(0) + margin
    gx = np.arange(lo[0], hi[0] + spacing, spacing)
    gy = np.arange(lo[1], hi[1] + spacing, spacing)
    grid = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
    grid = grid[footprint_contains(fps, grid, margin)]
    covering = (np.abs(bg.means[:, 2] - z0) < band) & (bg.opacities >= covered_opacity)
    if len(grid) and covering.any():  # fill the hole only, not the table seen around the object
        d, _ = cKDTree(xy[covering]).query(grid, k=1)
        grid = grid[d > spacing]
    if len(grid) == 0:
        return world
    sidx = np.nonzero(src)[0]
    _, nn = cKDTree(xy[sidx]).query(grid, k=k)
    nn = sidx[np.asarray(nn).reshape(len(grid), k)]
    n = len(grid)
    means = np.concatenate([grid, np.full((n, 1), z0)], 1).astype(np.float32)
    quats = np.tile(np.array([1.0, 0.0, 0.0, 0.0], np.float32), (n, 1))
    scales = np.tile(np.array([0.75 * spacing, 0.75 * spacing, 0.15 * spacing], np.float32), (n, 1))
    new = GaussianSet(
        means=means,
        quats=quats,
        scales=scales,
        opacities=np.clip(bg.opacities[nn].mean(1), 0.05, 0.99).astype(np.float32),
        sh=bg.sh[nn].mean(1).astype(np.float32),
        features=bg.features[nn].mean(1).astype(np.float32),
        labels=np.zeros(n, np.int32),
    )
    meta = {
        **dict(world.metadata),
        "baseline": "b: single-state + kNN completion",
        "knn_completion": {"added": n, "k": k, "spacing": spacing},
    }
    return dataclasses.replace(
        world, background=GaussianSet.concat([bg.without_encodings(), new]), metadata=meta
    )
