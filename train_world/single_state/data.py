"""What a reconstruction run trains on: the views of one state, split into training and held-out views.

Sources:

* a capture folder (``scene.json``): one state (``--state``, default the first training state). The
  synthetic captures hold no extra views of the training states (``test_*`` states show other object
  poses), so every ``holdout_every``-th view (indices 0, n, 2n, ...) is held out for evaluation and not
  trained on; ``holdout_every=0`` trains on all views.
* NeRF-Blender: a ``transforms_*.json`` file or a folder with ``transforms_train.json``; trains on the train
  split and evaluates on ``transforms_test_subset.json`` (if present) else ``transforms_test.json``. No
  masks: K = 0 (one class, the background), composited over white by default.

Mask ids (any of 1..255) map to contiguous classes ``1..K`` in the order of the capture's sorted object ids.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from train_world.capture import load_blender, load_capture
from train_world.capture.files import area_resize
from train_world.capture.loader import view_size
from train_world.capture.points import capture_points

__all__ = ["TrainData", "eval_view_size", "load_eval_views", "load_training_data", "resolve_source"]


@dataclass(frozen=True)
class TrainData:
    """Training views (``images [V,H,W,3]``, ``classes [V,H,W]`` int64 or None, ``depths`` or None) and the
    description of the source stored in the world file."""

    images: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    classes: torch.Tensor | None
    depths: torch.Tensor | None
    object_ids: tuple[int, ...]
    object_names: tuple[str, ...]
    background: tuple[float, float, float]
    units: str
    state: str
    # all views of the state (train + held out), for the world file
    all_viewmats: np.ndarray = field(repr=False, default=None)
    all_Ks: np.ndarray = field(repr=False, default=None)
    heldout: tuple[int, ...] = ()
    poses: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    source: dict[str, Any] = field(default_factory=dict)
    table_bounds: np.ndarray | None = None
    silhouettes: torch.Tensor | None = None  # [V,H,W] alpha in [0,1] (NeRF-Blender RGBA), for the init
    # the capture's sparse points (:mod:`train_world.capture.points`): [P,3] float64 and [P,3] colours in [0,1]
    points: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def num_classes(self) -> int:
        return len(self.object_ids) + 1

    def __len__(self) -> int:
        return int(self.images.shape[0])


def resolve_source(path: str | Path) -> tuple[str, Path]:
    """``("capture", folder)`` or ``("blender", transforms_train.json)``; ValueError otherwise."""
    p = Path(path)
    if p.is_dir() and (p / "scene.json").is_file():
        return "capture", p
    if p.is_dir() and (p / "transforms_train.json").is_file():
        return "blender", p / "transforms_train.json"
    if p.is_file() and p.suffix == ".json" and p.name != "scene.json":
        return "blender", p
    raise ValueError(f"{p}: not a capture (no scene.json) nor NeRF-Blender data (no transforms_train.json)")


def blender_test_json(train_json: Path) -> Path | None:
    for name in ("transforms_test_subset.json", "transforms_test.json"):
        q = train_json.parent / name
        if q.is_file():
            return q
    return None


def class_map(object_ids: tuple[int, ...]) -> np.ndarray:
    """Lookup ``[256]`` from mask id to class index (0 = background)."""
    lut = np.zeros(256, np.int64)
    for i, oid in enumerate(object_ids):
        lut[oid] = i + 1
    return lut


def heldout_indices(n: int, every: int) -> tuple[int, ...]:
    return tuple(range(0, n, every)) if every >= 2 and n >= 2 else ()


def _alphas(paths, downscale: int) -> torch.Tensor | None:
    """Alpha channels ``[V,H,W]`` of RGBA images (None if any image has no alpha)."""
    out = []
    for q in paths:
        with Image.open(q) as img:
            if img.mode != "RGBA":
                return None
            a = np.asarray(img.getchannel("A"), dtype=np.float32)
            if downscale > 1:
                a = area_resize(a[..., None], (img.width // downscale, img.height // downscale))[..., 0]
            out.append(a / 255.0)
    return torch.from_numpy(np.stack(out))


def _capture_source(p: Path, cap, downscale: int) -> dict:
    """The world's ``metadata.source`` for a capture: where it came from and, for a synthetic capture, the
    generator settings (lighting, test cameras' seed...) needed to regenerate its ground truth."""
    src = {"kind": "capture", "path": str(p.resolve()), "downscale": downscale, "name": cap.name}
    gen = cap.metadata.get("generator") if isinstance(cap.metadata, Mapping) else None
    if isinstance(gen, Mapping):
        src["generator"] = {
            k: gen[k]
            for k in (
                "name",
                "version",
                "seed",
                "scene_spec",
                "views",
                "test_views",
                "test_states",
                "shadows",
                "lighting",
                "supersample",
            )
            if k in gen
        }
    return src


def load_training_data(path: str | Path, config) -> TrainData:
    """Load the training views described by ``config`` (a :class:`TrainConfig`)."""
    kind, p = resolve_source(path)
    if kind == "blender":
        bg = config.background or (1.0, 1.0, 1.0)
        v = load_blender(p, background=bg, downscale=config.downscale)
        return TrainData(
            images=v.images,
            viewmats=v.viewmats,
            Ks=v.Ks,
            width=v.width,
            height=v.height,
            classes=None,
            depths=None,
            object_ids=(),
            object_names=(),
            background=tuple(bg),
            units="unknown",
            state="train",
            all_viewmats=v.viewmats.numpy(),
            all_Ks=v.Ks.numpy(),
            heldout=(),
            poses={"train": np.zeros((0, 4, 4))},
            source={"kind": "blender", "path": str(p.resolve()), "downscale": config.downscale},
            silhouettes=_alphas(v.image_paths, config.downscale),
        )
    bg = config.background or (0.0, 0.0, 0.0)
    cap = load_capture(p, states=[], load_depth=False)  # metadata only
    meta_states = list(cap.splits)
    train_states = [s for s in meta_states if cap.splits[s] == "train"]
    state = config.state or (train_states[0] if train_states else (meta_states[0] if meta_states else None))
    if state is None:
        raise ValueError(f"{p}: the capture lists no states")
    if state not in meta_states:
        raise ValueError(f"{p}: no state {state!r} (states: {meta_states})")
    n_train = len(train_states)
    if n_train > 1 and not config.single_state and config.state is None:
        raise ValueError(
            f"{p}: the capture has {n_train} training states; two-state training is not part of single-field "
            "reconstruction: pass --single-state (trains the first state) or --state NAME"
        )
    cap = load_capture(p, states=[state], downscale=config.downscale, background=bg)
    v = cap.states[state]
    ids = cap.object_ids
    held = heldout_indices(len(v), config.holdout_every)
    train = np.array([i for i in range(len(v)) if i not in set(held)], dtype=np.int64)
    if train.size == 0:
        raise ValueError(f"{p}: state {state!r} has no training views left after holding out {held}")
    tidx = torch.from_numpy(train)
    classes = None
    if v.masks is not None and ids:
        classes = torch.from_numpy(class_map(ids)[v.masks[tidx].numpy()])
    poses = {s: np.asarray(P, dtype=np.float64) for s, P in cap.poses.items()}
    if state not in poses:
        poses[state] = np.tile(np.eye(4), (len(ids), 1, 1))
    return TrainData(
        images=v.images[tidx].contiguous(),
        viewmats=v.viewmats[tidx].contiguous(),
        Ks=v.Ks[tidx].contiguous(),
        width=v.width,
        height=v.height,
        classes=classes,
        depths=None if v.depths is None else v.depths[tidx].contiguous(),
        object_ids=ids,
        object_names=cap.object_names,
        background=tuple(bg),
        units=cap.units,
        state=state,
        all_viewmats=v.viewmats.numpy(),
        all_Ks=v.Ks.numpy(),
        heldout=held,
        poses=poses,
        source=_capture_source(p, cap, config.downscale),
        table_bounds=cap.table_bounds,
        points=capture_points(p, cap.metadata),
    )


@dataclass(frozen=True)
class EvalViews:
    images: torch.Tensor
    classes: torch.Tensor | None
    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    state: str
    indices: tuple[int, ...]
    names: tuple[str, ...]


def _eval_json(path: str | Path) -> tuple[str, Path]:
    """The kind of ``path`` (:func:`resolve_source`) and, for NeRF-Blender data, its test split's JSON."""
    kind, p = resolve_source(path)
    if kind == "blender":
        tj = blender_test_json(p) if p.name == "transforms_train.json" else p
        if tj is None:
            raise ValueError(
                f"{p.parent}: no transforms_test_subset.json or transforms_test.json to evaluate on"
            )
        return kind, tj
    return kind, p


def eval_view_size(path: str | Path, state: str | None) -> tuple[int, int]:
    """``(width, height)`` of the views :func:`load_eval_views` loads from ``path`` at ``downscale`` 1, read from
    one image's header."""
    kind, p = _eval_json(path)
    if kind == "blender":
        return view_size(p)
    cap = load_capture(p, states=[], load_depth=False)  # metadata only
    if state not in cap.splits:
        raise ValueError(f"{p}: no state {state!r} (states: {list(cap.splits)})")
    return view_size(p / state / "transforms.json", root=p)


def load_eval_views(
    path: str | Path,
    *,
    state: str | None,
    heldout: tuple[int, ...],
    downscale: int,
    background: tuple[float, float, float],
    object_ids: tuple[int, ...],
    all_views: bool = False,
) -> EvalViews:
    """Held-out views: the Blender test split, or the ``heldout`` views of ``state`` (all its views when
    ``all_views``, e.g. a test state)."""
    kind, p = _eval_json(path)
    if kind == "blender":
        v = load_blender(p, background=background, downscale=downscale)
        idx = tuple(range(len(v)))
        return EvalViews(
            v.images,
            None,
            v.viewmats,
            v.Ks,
            v.width,
            v.height,
            "test",
            idx,
            tuple(q.stem for q in v.image_paths),
        )
    cap = load_capture(p, states=[state], downscale=downscale, background=background, load_depth=False)
    v = cap.states[state]
    idx = tuple(range(len(v))) if all_views else tuple(heldout)
    if not idx:
        raise ValueError(
            f"{p}: no held-out views of state {state!r} to evaluate (trained with holdout 0?); evaluate a test "
            "state, or score the views it was trained on with --training-views"
        )
    t = torch.tensor(idx, dtype=torch.int64)
    classes = None
    if v.masks is not None and object_ids:
        classes = torch.from_numpy(class_map(tuple(object_ids))[v.masks[t].numpy()])
    return EvalViews(
        v.images[t],
        classes,
        v.viewmats[t],
        v.Ks[t],
        v.width,
        v.height,
        state,
        idx,
        tuple(f"{state}/{v.image_paths[i].stem}" for i in idx),
    )
