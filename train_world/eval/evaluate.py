"""``dsg-eval``: render a world's held-out views and compare them with the ground truth.

Metrics: PSNR and SSIM on RGB (scikit-image ``structural_similarity`` with the standard Gaussian window,
sigma 1.5, ``data_range=1``), and IoU per object on masks (predicted mask = argmax of the world's classifier
on the rendered identity features; IoU accumulated over all evaluated views per object; per view too).

Views: for a NeRF-Blender world the test split (``transforms_test_subset.json`` if present); for a capture
world the views of its training state held out during training (every n-th view), or with ``--state`` all
views of that state, objects placed at that state's poses (taken from the capture's ``scene.json`` when the
world does not hold them). At a state the world was trained on (either state of a two-state world) that is
the views it held out; ``--training-views`` scores all of them, the ones it was trained on included, so the
fit can be set beside the test states (the report says ``"training_views": true``).

``--state test`` evaluates at every test state of the capture (its ``"test"`` split), each as with
``--state``; that is the default for a two-state (DSG-World) world on a capture that has test states, and for
a world trained without held-out views (as ``dsg-train`` and the baselines train on such captures).

Writes ``DIR/report.json`` (per-view figures and ``"mean": {"psnr", "ssim", "mask_iou"}``), ``DIR/report.md``
(a Markdown table) and ``DIR/grid.png`` (rows of ground truth | ours | error [| GT mask | our mask], labelled
with the column names above and each row's state and view index on its left). With
``--state test`` each state's files go to ``DIR/<state>/`` and ``DIR/report.json`` holds each state's mean and
their mean (``"mean"``, the same keys).

A world trained on a ``dsg-capture`` capture lives in the frame estimated from its photos. Given the ground
truth of that capture instead (``dsg-synth --as-photos`` writes it to ``ground_truth/``), ``dsg-eval`` fits
the similarity between the two frames from the world's training cameras (:mod:`train_world.eval.frames`),
moves the ground truth's test cameras and object poses into the world's frame and scores the test states as
usual; the reports record the similarity and its residuals under ``"frame_alignment"``.

Views are scored at the size the world was trained at (its ``image_size``): views an integer multiple of that
size are downscaled to it, as training downscaled its own (a world trained with ``--downscale 2`` on photos twice
the ground truth's size is scored at the ground truth's own size); another size is refused.

``dsg-eval --suite [dsg-suite options]`` runs the DSG-World comparison on the default scenes
(:mod:`train_world.suite.runner`).

Example::

    dsg-eval worlds/four_mixed.dsgworld data/four_mixed --out eval/four_mixed
    dsg-eval worlds/two_blocks.dsgworld data/two_blocks --out eval/two_blocks --state test
    dsg-eval worlds/two_blocks.dsgworld data/two_blocks --out eval/fit --state state1 --training-views
    dsg-eval worlds/my_table.dsgworld photos/my_table/ground_truth --out eval/my_table
    dsg-eval --suite --out suite --scenes two_blocks,five_small
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dsg_gym.gaussians import GaussianSet
from dsg_gym.splat import rasterize, spherical_harmonics
from dsg_gym.splat.layers import rasterize_layers
from dsg_gym.world import World, load_world
from train_world.capture import load_capture
from train_world.capture.format import atomic_write_bytes, atomic_write_json, encode_png
from train_world.capture.loader import Capture
from train_world.eval.background_parts import capture_background_parts
from train_world.eval.frames import FrameAlignment, motion_errors
from train_world.eval.metrics import mask_iou, psnr, psnr_from_mse, ssim
from train_world.eval.regions import RegionErrors, capture_coverage, combine
from train_world.eval.report_files import fmt, grid, markdown, region_lines, u8
from train_world.eval.view_align import ViewAlignment, align_views
from train_world.single_state.data import eval_view_size, load_eval_views

__all__ = [
    "capture_test_states",
    "default_state",
    "evaluate",
    "evaluate_test_states",
    "layer_mask",
    "mask_iou",
    "mean_of_means",
    "render_gaussians",
]

_PALETTE = np.array(
    [
        [0, 0, 0],
        [230, 25, 75],
        [60, 180, 75],
        [255, 225, 25],
        [0, 130, 200],
        [245, 130, 48],
        [145, 30, 180],
        [70, 240, 240],
        [240, 50, 230],
        [210, 245, 60],
    ],
    np.uint8,
)


@torch.no_grad()
def render_gaussians(
    g: GaussianSet,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    background=(0.0, 0.0, 0.0),
    splat_options: dict | None = None,
    front: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """RGB ``[V,H,W,3]`` and identity features ``[V,H,W,F]`` of ``g`` (one rasterizer call per view), with the
    world's ``splat_options`` (``World.splat_options``: rasterize mode and 2D low-pass). ``front``: boolean
    ``[N]``, the object Gaussians of a world composited in two layers (:func:`layer_mask`)."""
    t = {
        k: torch.from_numpy(np.ascontiguousarray(getattr(g, k)))
        for k in ("means", "quats", "scales", "opacities", "sh", "features")
    }
    F = t["features"].shape[1]
    bg = torch.cat([torch.tensor(background, dtype=torch.float32), torch.zeros(F)])
    rgbs, feats = [], []
    for vm, K in zip(
        torch.from_numpy(np.asarray(viewmats, np.float32)), torch.from_numpy(np.asarray(Ks, np.float32))
    ):
        campos = torch.linalg.inv(vm)[:3, 3]
        rgb = torch.clamp_min(spherical_harmonics(g.sh_degree, t["means"] - campos, t["sh"]) + 0.5, 0.0)
        cols = torch.cat([rgb, t["features"]], -1)
        splat = rasterize if front is None else functools.partial(rasterize_layers, torch.from_numpy(front))
        out, _, _ = splat(
            t["means"],
            t["quats"],
            t["scales"],
            t["opacities"],
            cols,
            vm[None],
            K[None],
            int(width),
            int(height),
            backgrounds=bg,
            **(splat_options or {}),
        )
        rgbs.append(out[0, ..., :3].numpy())
        feats.append(out[0, ..., 3:].numpy())
    return np.stack(rgbs), np.stack(feats)


def layer_mask(world: World) -> np.ndarray | None:
    """Boolean ``[N]`` over ``world.gaussians()`` (background first), True for the object Gaussians, when the world
    composites in two layers (``World.compositing``); None for one sorted list."""
    if world.compositing != "layers":
        return None
    n = world.background.num + sum(o.gaussians.num for o in world.objects.values())
    return np.arange(n) >= world.background.num


def _depth_capture(capture: str | Path, states: list[str], downscale: int) -> Capture | None:
    """``states`` of the ground truth ``capture`` at ``downscale``, without masks, for the region split's depth
    maps, cameras and table; None when they cannot be loaded (the regions then go without that split)."""
    try:
        return load_capture(
            capture, states=list(dict.fromkeys(states)), downscale=downscale, load_masks=False
        )
    except ValueError:
        return None


def _truth_downscale(capture: str | Path, size: tuple[int, int], trained: Any) -> int:
    """The integer factor that brings the views to score (``size``, width and height) to the size the world
    was trained at (``trained``, its ``image_size``). ValueError when the views are not that size or an
    integer multiple of it."""
    tw, th = (int(v) for v in trained)
    k = size[0] // tw if tw else 0
    if k < 1 or (size[0], size[1]) != (tw * k, th * k):
        raise ValueError(
            f"{capture}: views are {size[0]}x{size[1]}, the world was trained at {tw}x{th}; score it against "
            "a ground truth of that size or an integer multiple of it"
        )
    return k


def _poses_for(
    world: World, capture: Path, state: str, alignment: FrameAlignment | None = None
) -> np.ndarray:
    """The world-frame object poses at ``state``. At a test state of the capture, the capture's (the truth the
    views are scored against, even where the world holds other poses under that name); at another state, the
    world's own when it holds the state and shares the capture's frame (they may be refined), else the
    capture's. Through ``alignment``, the capture's motion from the world's reference state moved into the
    world's frame (:meth:`FrameAlignment.poses`)."""
    cap = load_capture(capture, states=[], load_depth=False)
    is_test = cap.splits.get(state) == "test" and state in cap.poses
    if state in world.poses and not is_test and (alignment is None or alignment.identity):
        return world.poses[state]
    if state not in cap.poses:
        raise ValueError(f"{capture}: state {state!r} has no object poses in scene.json")
    if cap.object_ids != world.object_ids:
        raise ValueError(f"{capture}: objects {cap.object_ids} differ from the world's {world.object_ids}")
    truth = np.asarray(cap.poses[state], dtype=np.float64)
    if alignment is None:
        return truth
    ref = world.metadata.get("reference_state", next(iter(world.poses), None))
    if ref not in world.poses or ref not in cap.poses:
        raise ValueError(f"{capture}: no object poses of the world's reference state {ref!r} to align with")
    if alignment.identity and np.array_equal(cap.poses[ref], world.poses[ref]):
        return truth  # one frame, the same object frames
    return alignment.poses(truth, cap.poses[ref], world.poses[ref])


def evaluate(
    world_path: str | Path,
    capture: str | Path,
    out_dir: str | Path,
    *,
    state: str | None = None,
    max_grid_rows: int = 8,
    alignment: FrameAlignment | None = None,
    view_alignment: ViewAlignment | None = None,
    training_views: bool = False,
) -> dict[str, Any]:
    """Evaluate and write the report files; returns the report dictionary. At one of the world's training
    states the views it held out are scored; ``training_views``: every view of that state instead, the ones it
    was trained on included (how well the world fits what it saw, against how it does at new states; the
    report says ``"training_views": true``). ``alignment``: ``capture`` is a
    ground truth in another frame (:mod:`.frames`): all views of ``state`` are scored, its cameras and object
    poses moved into the world's frame, and the report records the similarity under ``"frame_alignment"``.
    ``view_alignment``: each camera is first aligned to the world against its image (:mod:`.view_align`); the
    report keeps the unaligned figures too (``"mean_unaligned"``, per view ``"psnr_unaligned"``) and each
    view's correction under ``"view_alignment"``."""
    world = load_world(world_path)
    meta = world.metadata
    src = meta.get("source", {})
    src = src if isinstance(src, Mapping) else {}  # geometry and PLY worlds name their source with a string
    trained_state = meta.get("state", meta.get("reference_state"))
    bg = tuple(meta.get("background", (0.0, 0.0, 0.0)))
    eval_state = state or trained_state
    trained = meta.get("training_states") or ([trained_state] if isinstance(trained_state, str) else [])
    held = (
        (meta.get("heldout_views_by_state") or {trained[0]: meta.get("heldout_views", ())}) if trained else {}
    )
    held = held if isinstance(held, Mapping) else {}  # per training state, the views it held out
    at_training_state = eval_state in trained
    if training_views and not at_training_state:
        raise ValueError(
            f"training views: {eval_state!r} is not a training state of this world ({', '.join(trained) or 'none'}); "
            "name one of them with --state, or drop --training-views"
        )
    if training_views and alignment is not None:
        raise ValueError(
            f"training views: {capture} is a ground truth in another frame; score the training views against "
            "the capture the world was trained on (or pass --same-frame)"
        )
    load = functools.partial(
        load_eval_views,
        capture,
        state=eval_state,
        heldout=tuple(held.get(eval_state, ())),
        background=bg,
        object_ids=world.object_ids,
        all_views=training_views or alignment is not None or (state is not None and not at_training_state),
    )
    trained_size = meta.get("image_size")
    if trained_size:  # the views are scored at the size the world was trained at
        downscale = _truth_downscale(capture, eval_view_size(capture, eval_state), trained_size)
    else:  # a world that does not record its size: its own capture's views at its training downscale
        downscale = int(src.get("downscale", 1)) if alignment is None else 1
    views = load(downscale=downscale)
    poses = _poses_for(world, Path(capture), eval_state, alignment) if world.num_objects else None
    g = world.gaussians(poses=poses) if poses is not None else world.gaussians(state=trained_state)
    viewmats = views.viewmats.numpy() if alignment is None else alignment.viewmats(views.viewmats.numpy())
    aligned = None
    front = layer_mask(world)
    render = functools.partial(render_gaussians, front=front)
    if view_alignment is not None:
        aligned = align_views(
            g, viewmats, views.Ks.numpy(), views.width, views.height, views.images.numpy(), bg,
            world.splat_options, view_alignment, render_gaussians, front,
        )  # fmt: skip
        viewmats = np.stack([a.viewmat for a in aligned])
    rgb, feats = render(g, viewmats, views.Ks.numpy(), views.width, views.height, bg, world.splat_options)
    pred_cls = world.classify(feats).argmax(-1) if world.num_objects else None
    gt_imgs = views.images.numpy()
    gt_cls = None if views.classes is None else views.classes.numpy()
    k = world.num_objects
    per_view, rows, row_labels = [], [], []
    inter = np.zeros(k + 1)
    union = np.zeros(k + 1)
    regions = RegionErrors(world.object_names) if gt_cls is not None else None
    seen = parts = None
    if regions is not None:  # the truth's depth maps, cameras and table, loaded once for both
        coverage = trained and src.get("kind") == "capture"
        truth = _depth_capture(capture, [eval_state, *trained], downscale) if coverage else None
        if truth is None:  # no coverage, or a truth without the training states: the parts still
            truth = _depth_capture(capture, [eval_state], downscale)
        if truth is not None:
            seen = capture_coverage(truth, eval_state, views.indices, trained, held) if coverage else None
            parts = capture_background_parts(truth, eval_state, views.indices)
    for i in range(len(gt_imgs)):
        ours = np.clip(rgb[i], 0, 1)
        entry: dict[str, Any] = {
            "view": views.names[i],
            "index": views.indices[i],
            "psnr": psnr(ours, gt_imgs[i]),
            "ssim": ssim(ours, gt_imgs[i]),
        }
        if aligned is not None:
            entry["psnr_unaligned"] = psnr_from_mse(aligned[i].mse_before)
        row = [
            u8(gt_imgs[i]),
            u8(ours),
            u8(np.abs(ours - gt_imgs[i]).mean(-1, keepdims=True).repeat(3, -1) * 4),
        ]
        if regions is not None:
            regions.add(ours, gt_imgs[i], gt_cls[i], None if seen is None else seen[i],
                        None if parts is None else parts[i])  # fmt: skip
        if pred_cls is not None and gt_cls is not None:
            ious = mask_iou(pred_cls[i], gt_cls[i], range(1, k + 1))
            entry["mask_iou"] = {world.object_names[c - 1]: v for c, v in ious.items()}
            vals = [v for v in ious.values() if v is not None]
            entry["mean_mask_iou"] = float(np.mean(vals)) if vals else None
            for c in range(1, k + 1):
                inter[c] += np.sum((pred_cls[i] == c) & (gt_cls[i] == c))
                union[c] += np.sum((pred_cls[i] == c) | (gt_cls[i] == c))
            row += [_PALETTE[gt_cls[i] % len(_PALETTE)], _PALETTE[pred_cls[i] % len(_PALETTE)]]
        per_view.append(entry)
        if len(rows) < max_grid_rows:
            rows.append(row)
            row_labels.append(f"{eval_state}\nview {views.indices[i]}")
    obj_iou = (
        {
            world.object_names[c - 1]: (float(inter[c] / union[c]) if union[c] > 0 else None)
            for c in range(1, k + 1)
        }
        if gt_cls is not None and k
        else {}
    )
    valid = [v for v in obj_iou.values() if v is not None]
    report = {
        "world": str(world_path),
        "capture": str(capture),
        "state": eval_state,
        "training_views": bool(training_views),
        "views": len(per_view),
        "image_size": [views.width, views.height],
        "num_gaussians": int(g.num),
        "object_iou": obj_iou,
        "per_view": per_view,
        "mean": {
            "psnr": float(np.mean([v["psnr"] for v in per_view])),
            "ssim": float(np.mean([v["ssim"] for v in per_view])),
            "mask_iou": float(np.mean(valid)) if valid else None,
        },
    }
    if regions is not None:
        report["error_by_region"] = regions.report()
    if aligned is not None:
        report["mean_unaligned"] = {"psnr": float(np.mean([v["psnr_unaligned"] for v in per_view]))}
        report["view_alignment"] = {
            "settings": asdict(view_alignment),
            "kept": sum(a.kept for a in aligned),
            "rotation_deg_rms": float(np.sqrt(np.mean([a.rotation_deg**2 for a in aligned]))),
            "translation_rms": float(np.sqrt(np.mean([a.translation**2 for a in aligned]))),
            "per_view": [a.to_dict() for a in aligned],
        }
    if alignment is not None:
        report["frame_alignment"] = alignment.to_dict()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out / "report.json", report)
    atomic_write_bytes(out / "report.md", markdown(report).encode("utf-8"))
    cols = ["ground truth", "ours", "error"] + (["GT mask", "our mask"] if len(rows[0]) > 3 else [])
    atomic_write_bytes(out / "grid.png", encode_png(grid(rows, cols, row_labels)))
    return report


def capture_test_states(capture: str | Path) -> list[str]:
    """The states of the capture's ``"test"`` split, in the capture's order."""
    splits = load_capture(capture, states=[], load_depth=False).splits
    return [s for s, split in splits.items() if split == "test"]


def mean_of_means(means: list[Mapping[str, float | None]]) -> dict[str, float | None]:
    """Per metric (psnr, ssim, mask_iou), the mean of the reports' ``"mean"`` values that are not None (None
    when all are)."""
    out: dict[str, float | None] = {}
    for k in ("psnr", "ssim", "mask_iou"):
        vals = [m[k] for m in means if m.get(k) is not None]
        out[k] = float(np.mean(vals)) if vals else None
    return out


def evaluate_test_states(
    world_path: str | Path,
    capture: str | Path,
    out_dir: str | Path,
    *,
    alignment: FrameAlignment | None = None,
    view_alignment: ViewAlignment | None = None,
) -> dict[str, Any]:
    """:func:`evaluate` at every test state of ``capture`` (into ``out_dir/<state>/``), then
    ``out_dir/report.json`` and ``report.md``: each state's view count, the size its views were scored at
    (``"image_size"``, also at the top) and mean, and ``"mean"``, the mean over
    the states of their means (a metric missing in a state is left out of its mean). ``alignment``,
    ``view_alignment``: as for :func:`evaluate` (``"mean_unaligned"`` too, the mean over the states).
    ValueError when the capture has no test states."""
    states = capture_test_states(capture)
    if not states:
        raise ValueError(f"{capture}: the capture has no test states to evaluate at")
    out = Path(out_dir)
    per_state = {}
    for s in states:
        r = evaluate(
            world_path, capture, out / s, state=s, alignment=alignment, view_alignment=view_alignment
        )
        per_state[s] = {"views": r["views"], "image_size": r["image_size"], "mean": r["mean"]}
        if "mean_unaligned" in r:
            per_state[s]["mean_unaligned"] = r["mean_unaligned"]
            per_state[s]["view_rotation_deg_rms"] = r["view_alignment"]["rotation_deg_rms"]
        if "error_by_region" in r:
            per_state[s]["error_by_region"] = r["error_by_region"]
    mean = mean_of_means([v["mean"] for v in per_state.values()])
    report = {
        "world": str(world_path),
        "capture": str(capture),
        "state": "test",
        "views": sum(v["views"] for v in per_state.values()),
        "image_size": next(iter(per_state.values()))["image_size"],
        "states": per_state,
        "mean": mean,
    }
    by_region = [v["error_by_region"] for v in per_state.values() if "error_by_region" in v]
    if by_region and len(by_region) == len(per_state):
        report["error_by_region"] = combine(by_region)
    unaligned = [v["mean_unaligned"]["psnr"] for v in per_state.values() if "mean_unaligned" in v]
    if unaligned:
        report["mean_unaligned"] = {"psnr": float(np.mean(unaligned))}
    if alignment is not None:
        report["frame_alignment"] = alignment.to_dict()
        errors = motion_errors(load_world(world_path), capture, alignment)
        if errors is not None:
            report["motion_errors"] = errors
    lines = [
        f"# Evaluation of `{Path(world_path).name}` at the test states",
        "",
        "| state | views | PSNR (dB) | SSIM | mask IoU |",
        "| --- | --- | --- | --- | --- |",
    ]
    for s, v in per_state.items():
        m = v["mean"]
        lines.append(f"| {s} | {v['views']} | {fmt(m['psnr'])} | {fmt(m['ssim'])} | {fmt(m['mask_iou'])} |")
    lines.append(
        f"| **mean** | {report['views']} | **{fmt(mean['psnr'])}** | **{fmt(mean['ssim'])}** | "
        f"**{fmt(mean['mask_iou'])}** |"
    )
    if "motion_errors" in report:
        me = report["motion_errors"]
        unit = "mm" if me["units"] == "metres" else me["units"]
        key = "mm" if me["units"] == "metres" else "translation"
        lines += ["", f"Object motions {me['src']} -> {me['dst']} against the ground truth's:", "",
                  f"| object | given ({unit}) | given (deg, modulo symmetry) | given (px, at most) | trained ({unit}) "
                  "| trained (deg) | trained (px) |", "| --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
        lines += [
            "| " + " | ".join([o["name"], *(
                "-" if o.get(f"{t}_{k}") is None else f"{o[f'{t}_{k}']:.3g}"
                for t in ("estimate", "refined") for k in (key, "rotation_mod_symmetry_deg", "px"))]) + " |"
            for o in me["objects"]
        ]  # fmt: skip
    if unaligned:
        u = float(np.mean(unaligned))
        lines += ["", f"Each camera aligned to the world first; unaligned mean PSNR {fmt(u)} dB."]
    lines += region_lines(report.get("error_by_region"))
    atomic_write_json(out / "report.json", report)
    atomic_write_bytes(out / "report.md", ("\n".join(lines) + "\n").encode("utf-8"))
    return report


def default_state(world_path: str | Path, capture: str | Path) -> str | None:
    """What ``dsg-eval`` evaluates when no state is named: ``"test"`` (every test state of the capture) for a
    two-state world or one trained without held-out views, on a capture with test states; ``None`` (the
    world's own held-out views, or a NeRF-Blender folder's test split) otherwise."""
    meta = load_world(world_path).metadata
    if "dual" not in meta and meta.get("heldout_views"):
        return None  # its own held-out views
    if not (Path(capture) / "scene.json").is_file():
        return None  # NeRF-Blender data: its test split
    return "test" if capture_test_states(capture) else None
