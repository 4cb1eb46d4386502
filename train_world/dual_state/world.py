"""The merged world of a two-state run (what ``dsg-train`` writes for a capture with two training states).

* **Background** (co-pasting, :func:`.merge.co_paste_background`): ``G1``'s background Gaussians outside the
  state-1 object footprints, plus ``G2``'s background Gaussians inside them (that table region was visible
  in state 2), minus any of those inside a state-2 footprint. Footprints are the table-plane convex hulls of
  both fields' object Gaussians placed at that state's poses, dilated by ``footprint_margin``.
* **Objects**: each object once, from the field that reproduces both training states better: starting from
  every object taken from ``G1``, object ``k`` is switched to ``G2``'s copy (moved by ``T_2->1``) when that
  lowers the L1 error of the merged scene rendered at both states' poses on a few training views of each.
  Object Gaussians are stored in the object's own frame (``inv(P_state1)``), as for single-state worlds.

The world's reference state is ``states[0]``; it stores the poses of every state in the capture and the
cameras of both training states; ``metadata["dual"]`` holds the two-state options, the per-object sources and
the co-pruning log.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from dsg_gym.cameras import Cameras
from dsg_gym.sh_basis import rotate_sh
from dsg_gym.world import World, build_world
from train_world.dual_state.merge import co_paste_background
from train_world.dual_state.transfer import gaussian_transforms, relative_transforms
from train_world.single_state.field import PARAM_NAMES, SegmentedField, rigid_transform_gaussians

__all__ = ["MergeInputs", "choose_object_sources", "merged_field", "merged_world"]


@dataclass(frozen=True)
class MergeInputs:
    """What merging needs of a finished two-state run (:meth:`DualTrainer.merge_inputs
    <train_world.dual_state.trainer.DualTrainer.merge_inputs>` makes it).

    ``fields``/``labels``: both fields and their per-Gaussian classes ``[N_i]``; ``P1``, ``P2``: object poses
    ``[K, 4, 4]`` of the two training states; ``T21``: per-object motions state 2 -> state 1 ``[K, 4, 4]``;
    ``footprints``: per state, each object's table-plane footprint points (or ``None``); ``data1``/``data2``:
    the two states' training data; ``background``: the render background colour; ``poses``: every state's
    object poses; ``classifier_weight``/``classifier_bias``: the shared classifier; ``config``: the two-state
    options (``DualConfig.to_dict()``) with ``ablation``, ``states``, ``footprint_margin`` and ``base`` (the
    single-state config dict); ``motions``: the motions between the two states as given and as trained
    (:func:`.motions.motions_record`, stored as ``metadata["motions"]``); ``camera_names``: per training
    state, the names of its cameras in the stored order (``metadata["camera_names"]``, what ``dsg-eval`` matches
    a ground-truth capture's cameras by); ``cameras``: per training state, how far camera refinement moved its
    cameras (``metadata["camera_refinement"]``; ``data1``/``data2`` then hold the refined cameras); the rest is
    bookkeeping copied into the world's metadata."""

    fields: tuple[SegmentedField, SegmentedField]
    labels: tuple[torch.Tensor, torch.Tensor]
    P1: np.ndarray
    P2: np.ndarray
    T21: Any
    footprints: tuple[list, list]
    data1: Any
    data2: Any
    background: Any
    poses: dict
    classifier_weight: np.ndarray
    classifier_bias: np.ndarray
    config: dict
    ablation: str
    states: tuple[str, str]
    footprint_margin: float
    base_config: dict
    extent: float
    step: int
    field_sizes: tuple[int, int]
    prune_log: list
    elapsed: float
    motions: dict | None = None
    camera_names: dict | None = None
    cameras: dict | None = None


def _rows(
    field: SegmentedField, mask: torch.Tensor, T: torch.Tensor | None = None
) -> dict[str, torch.Tensor]:
    out = {k: v[mask] for k, v in field.baked_params().items()}
    if T is not None and out["means"].shape[0]:
        out["means"], out["quats"] = rigid_transform_gaussians(out["means"], out["quats"], T)
        if out["shN"].shape[1]:  # the view-dependent colour turns with the object
            sh = rotate_sh(
                torch.cat([out["sh0"], out["shN"]], 1).double().numpy(), T[:3, :3].double().numpy()
            )
            out["shN"] = torch.from_numpy(sh[:, 1:]).to(out["shN"].dtype)
    return out


def _concat(parts: list[dict[str, torch.Tensor]], rasterize_mode: str, eps2d: float) -> SegmentedField:
    f = SegmentedField(*(torch.cat([p[k] for p in parts], dim=0) for k in PARAM_NAMES))
    f.configure_filters(rasterize_mode, eps2d=eps2d)  # the parts' 3D filter is baked in (baked_params)
    return f


@torch.no_grad()
def merged_field(
    run: MergeInputs, sources: list[int] | None = None
) -> tuple[SegmentedField, torch.Tensor, dict]:
    """The merged Gaussians in the frame of ``states[0]`` and their classes ``[N]``; ``sources[k]`` in
    ``{1, 2}`` picks the field object ``k`` comes from (default: all from ``G1``)."""
    f1, f2 = run.fields
    l1, l2 = run.labels
    k_obj = len(run.P1)
    sources = sources or [1] * k_obj
    fp1, fp2 = run.footprints
    bg1, bg2 = l1 == 0, l2 == 0
    keep1, keep2 = co_paste_background(
        f1.means.detach()[bg1].numpy(), f2.means.detach()[bg2].numpy(), fp1, fp2, run.footprint_margin
    )
    m1 = bg1.clone()
    m1[bg1] = torch.from_numpy(keep1)
    m2 = bg2.clone()
    m2[bg2] = torch.from_numpy(keep2)
    parts = [_rows(f1, m1), _rows(f2, m2)]
    classes = [torch.zeros(int(m1.sum()) + int(m2.sum()), dtype=torch.int64)]
    for k in range(k_obj):
        if sources[k] == 2:
            part = _rows(f2, l2 == k + 1, run.T21[k])
        else:
            part = _rows(f1, l1 == k + 1)
        parts.append(part)
        classes.append(torch.full((part["means"].shape[0],), k + 1, dtype=torch.int64))
    info = {
        "background_from_1": int(m1.sum()),
        "background_from_2": int(m2.sum()),
        "background_dropped_1": int(bg1.sum() - m1.sum()),
        "object_sources": [int(s) for s in sources],
    }
    return _concat(parts, f1.rasterize_mode, f1.eps2d), torch.cat(classes), info


@torch.no_grad()
def _scene_error(
    run: MergeInputs, field: SegmentedField, classes: torch.Tensor, views_per_state: int
) -> float:
    err = 0.0
    for d, P in ((run.data1, run.P1), (run.data2, run.P2)):
        T = gaussian_transforms(classes, relative_transforms(run.P1, P))
        idx = np.linspace(0, len(d) - 1, min(views_per_state, len(d))).round().astype(int)
        for i in idx:
            out = field.render(
                d.viewmats[i : i + 1],
                d.Ks[i : i + 1],
                d.width,
                d.height,
                transform=T,
                background=run.background,
                with_features=False,
            )
            err += float((out.rgb[0].clamp(0, 1) - d.images[i]).abs().mean())
    return err


def choose_object_sources(run: MergeInputs, views_per_state: int = 6) -> list[int]:
    """Per object, 1 or 2: the field whose copy gives the lower merged-scene error (greedy, module docstring)."""
    l1, l2 = run.labels
    sources = [1] * len(run.P1)
    field, classes, _ = merged_field(run, sources)
    best = _scene_error(run, field, classes, views_per_state)
    for k in range(len(sources)):
        if int((l2 == k + 1).sum()) == 0:
            continue
        trial = list(sources)
        trial[k] = 2
        if int((l1 == k + 1).sum()) == 0:
            sources = trial
            field, classes, _ = merged_field(run, sources)
            best = _scene_error(run, field, classes, views_per_state)
            continue
        field, classes, _ = merged_field(run, trial)
        e = _scene_error(run, field, classes, views_per_state)
        if e < best:
            best, sources = e, trial
    return sources


def merged_world(run: MergeInputs, extra_metadata: dict[str, Any] | None = None) -> World:
    """The world file content of a finished two-state run (module docstring)."""
    d1, d2 = run.data1, run.data2
    s1, s2 = run.states
    sources = choose_object_sources(run) if len(run.P1) else []
    field, classes, info = merged_field(run, sources)
    meta = {
        "format_note": "see dsg_gym.world",
        "num_classes": d1.num_classes,
        "object_ids": list(d1.object_ids),
        "object_names": list(d1.object_names),
        "train_config": run.base_config,
        "source": d1.source,
        "state": s1,
        "training_states": [s1, s2],
        "heldout_views": list(d1.heldout),
        "heldout_views_by_state": {s1: list(d1.heldout), s2: list(d2.heldout)},
        "background": list(d1.background),
        "image_size": [d1.width, d1.height],
        "iterations": run.step,
        "scene_extent": run.extent,
        "num_gaussians": field.num,
        "rasterize_mode": field.rasterize_mode,
        "eps2d": field.eps2d,
        "dual": {
            **run.config,
            "ablation": run.ablation,
            **info,
            "field_sizes": list(run.field_sizes),
            "co_prune_log": run.prune_log[-50:],
            "train_seconds": round(run.elapsed, 1),
        },
        **({"motions": run.motions} if run.motions is not None else {}),
        **({"camera_names": run.camera_names} if run.camera_names else {}),
        **({"camera_refinement": run.cameras} if run.cameras else {}),
        **(extra_metadata or {}),
    }
    if "name" in d1.source:
        meta["name"] = d1.source["name"]
    if d1.table_bounds is not None:
        meta["table"] = {"bounds": np.asarray(d1.table_bounds, dtype=np.float64).tolist()}
    cams = {
        s: Cameras(
            np.asarray(d.all_viewmats, np.float32), np.asarray(d.all_Ks, np.float32), d.width, d.height
        )
        for s, d in ((s1, d1), (s2, d2))
    }
    return build_world(
        field.to_gaussian_set(),
        classes.numpy(),
        d1.object_ids,
        d1.object_names,
        run.poses,
        s1,
        cams,
        run.classifier_weight,
        run.classifier_bias,
        d1.units,
        meta,
    )
