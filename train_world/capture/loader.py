"""Loading captures (synthetic or real) into tensors for training and evaluation.

A capture folder holds ``scene.json`` and one folder per state with a ``transforms.json`` (see
:mod:`train_world.capture.format` and docs/captures.md). :func:`load_views` reads one ``transforms.json`` (ours,
nerfstudio's or NeRF-Blender's); :func:`load_capture` reads a whole capture; :func:`load_blender` reads a
NeRF-Blender split (RGBA composited over a background colour).

Cameras come out in the renderer's convention: OpenCV axes (x right, y down, z forward), ``viewmats`` are
world-to-camera ``[V,4,4]``, ``Ks`` ``[V,3,3]`` with pixel ``(u, v)`` centred at ``(u + 0.5, v + 0.5)``.
Object poses are world-from-object 4x4 float64 matrices; :meth:`Capture.relative_transform` gives ``T_src->dst
= P_dst @ inv(P_src)`` so that ``x_dst = T @ x_src`` for points on the object.

Bad input raises :class:`CaptureError` (a ``ValueError``) naming the file and the problem.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from train_world.capture.cameras import check_rigid, focal_from_fov, intrinsics_matrix, opengl_c2w_to_viewmat
from train_world.capture.files import CaptureError, image_size, read_depth, read_json, read_mask, read_rgb
from train_world.capture.format import DEPTH_SCALE, FORMAT_NAME, FORMAT_VERSION

__all__ = [
    "Capture",
    "CaptureError",
    "ObjectInfo",
    "Views",
    "capture_states",
    "frame_intrinsics",
    "frame_poses",
    "load_blender",
    "load_capture",
    "load_views",
    "view_size",
]

_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "p1", "p2")
_PINHOLE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL")


@dataclass(frozen=True)
class Views:
    """The views of one state.

    ``images`` float32 ``[V,H,W,3]`` in [0,1]; ``masks`` uint8 ``[V,H,W]`` object ids (0 = background) or
    None; ``depths`` float32 ``[V,H,W]`` metres along the optical axis (0 = unknown) or None; ``viewmats``
    float32 ``[V,4,4]`` OpenCV world-to-camera; ``Ks`` float32 ``[V,3,3]``; ``c2w_opengl`` float64 ``[V,4,4]``
    the ``transform_matrix`` values as read (camera-to-world, OpenGL axes).
    """

    images: torch.Tensor
    viewmats: torch.Tensor
    Ks: torch.Tensor
    width: int
    height: int
    image_paths: tuple[Path, ...]
    c2w_opengl: np.ndarray
    masks: torch.Tensor | None = None
    depths: torch.Tensor | None = None

    def __len__(self) -> int:
        return int(self.images.shape[0])


@dataclass(frozen=True)
class ObjectInfo:
    id: int
    name: str


@dataclass(frozen=True)
class Capture:
    """A loaded capture: objects ``1..K`` (0 is background), views and object poses per state."""

    root: Path
    name: str
    units: str
    objects: tuple[ObjectInfo, ...]
    states: Mapping[str, Views]
    poses: Mapping[str, np.ndarray]
    splits: Mapping[str, str]
    table_bounds: np.ndarray | None = None
    metadata: Mapping[str, Any] = field(default_factory=dict)
    supplied_transforms: Mapping[tuple[str, str], np.ndarray] = field(default_factory=dict)

    @property
    def object_ids(self) -> tuple[int, ...]:
        return tuple(o.id for o in self.objects)

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    @property
    def train_states(self) -> tuple[str, ...]:
        return tuple(s for s in self.states if self.splits.get(s, "train") == "train")

    @property
    def test_states(self) -> tuple[str, ...]:
        return tuple(s for s in self.states if self.splits.get(s) == "test")

    def relative_transform(self, src: str, dst: str) -> np.ndarray:
        """``[K,4,4]`` float64 ``T_src->dst = P_dst @ inv(P_src)`` per object (rows follow :attr:`objects`).

        Uses the per-state poses when both states have them, else a transform supplied in ``scene.json``'s
        ``relative_transforms`` (or the inverse of the one supplied for ``dst -> src``).
        """
        if src in self.poses and dst in self.poses:
            return self.poses[dst] @ np.linalg.inv(self.poses[src])
        if (src, dst) in self.supplied_transforms:
            return self.supplied_transforms[(src, dst)].copy()
        if (dst, src) in self.supplied_transforms:
            return np.linalg.inv(self.supplied_transforms[(dst, src)])
        if src == dst:
            return np.tile(np.eye(4), (len(self.objects), 1, 1))
        raise KeyError(
            f"{self.root / 'scene.json'}: no object poses or relative transforms for {src!r} -> {dst!r}"
        )


# --------------------------------------------------------------------------------------------- files
def _resolve(base: Path, rel: Any, blender_ext: str | None, root: Path, where: str, key: str) -> Path:
    """``rel`` (a frame's ``file_path``, ``mask_path`` or ``depth_path``) as a path under ``base``; a capture
    names only files inside its own folder ``root``, so any other path is refused (nothing outside is read)."""
    if not isinstance(rel, str) or not rel:
        raise CaptureError(f"{where}: '{key}' must be a non-empty relative path, got {rel!r}")
    p = Path(rel)
    p = p if p.is_absolute() else base / p
    if blender_ext and not p.suffix and not p.exists():
        p = p.with_name(p.name + blender_ext)
    if not p.resolve().is_relative_to(root.resolve()):
        raise CaptureError(
            f"{where}: '{key}' {rel!r} leaves the capture folder {root}; keep every file inside it "
            "and name it relative to its transforms.json"
        )
    return p


def _intrinsics(meta: Mapping, frame: Mapping, w: int, h: int, src: str) -> np.ndarray:
    def get(key):
        return frame.get(key, meta.get(key))

    model = get("camera_model")
    if model is not None and model not in _PINHOLE_MODELS:
        raise CaptureError(f"{src}: camera_model {model!r} is not supported (pinhole cameras only)")
    for k in _DISTORTION_KEYS:
        v = get(k)
        if v is not None and float(v) != 0.0:
            raise CaptureError(f"{src}: lens distortion {k}={v} is not supported; undistort the images first")
    jw, jh = get("w"), get("h")
    if (jw is not None and int(jw) != w) or (jh is not None and int(jh) != h):
        raise CaptureError(f"{src}: w x h = {jw} x {jh} in the JSON but the images are {w} x {h}")
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        ang = get("camera_angle_x")
        if ang is None:
            raise CaptureError(f"{src}: no intrinsics (need fl_x/fl_y/cx/cy or camera_angle_x)")
        fx = focal_from_fov(float(ang), w)
        ang_y = get("camera_angle_y")
        fy = focal_from_fov(float(ang_y), h) if ang_y is not None and get("fl_y") is None else fx
    fy = fx if fy is None else fy
    cx = get("cx")
    cy = get("cy")
    vals = [float(fx), float(fy), w / 2.0 if cx is None else float(cx), h / 2.0 if cy is None else float(cy)]
    if not all(np.isfinite(vals)) or vals[0] <= 0 or vals[1] <= 0:
        raise CaptureError(f"{src}: invalid intrinsics fx, fy, cx, cy = {vals}")
    return intrinsics_matrix(*vals)


def _read_transforms(tj: Path) -> dict:
    """``tj``'s JSON: an object with a non-empty ``frames`` list, else a CaptureError."""
    meta = read_json(tj)
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise CaptureError(f"{tj}: expected an object with a non-empty 'frames' list")
    return meta


def _frame_c2w(fr: Any, where: str, rigid_tol: float) -> np.ndarray:
    """A frame's ``transform_matrix`` ``[4,4]`` float64, checked rigid; a CaptureError naming ``where``."""
    if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
        raise CaptureError(f"{where}: needs 'file_path' and 'transform_matrix'")
    try:
        return check_rigid(
            np.asarray(fr["transform_matrix"], dtype=np.float64), f"{where}.transform_matrix", rigid_tol
        )
    except (TypeError, ValueError) as e:
        raise CaptureError(str(e) if str(e).startswith(where) else f"{where}.transform_matrix: {e}") from e


def frame_poses(transforms_json: str | Path, *, rigid_tol: float = 1e-4) -> np.ndarray:
    """The frames' ``transform_matrix`` values ``[V,4,4]`` float64 (camera-to-world, OpenGL axes; the
    camera centres are ``[:, :3, 3]``), checked as :func:`load_views` checks them, without reading an image."""
    tj = Path(transforms_json)
    frames = _read_transforms(tj)["frames"]
    return np.stack([_frame_c2w(fr, f"{tj}: frames[{i}]", rigid_tol) for i, fr in enumerate(frames)])


def frame_intrinsics(transforms_json: str | Path) -> np.ndarray:
    """The frames' intrinsics ``[V,3,3]`` float64 at the images' own size (:func:`view_size`, the first
    image's header), as :func:`load_views` reads them at ``downscale`` 1, without decoding an image."""
    tj = Path(transforms_json)
    meta, (w, h) = _read_transforms(tj), view_size(tj)
    return np.stack(
        [_intrinsics(meta, fr, w, h, f"{tj}: frames[{i}]") for i, fr in enumerate(meta["frames"])]
    )


def view_size(
    transforms_json: str | Path, *, blender_ext: str | None = ".png", root: str | Path | None = None
) -> tuple[int, int]:
    """``(width, height)`` of the first frame's image of ``transforms_json``, read from its header: the size
    :func:`load_views` loads at ``downscale`` 1 (it refuses frames of other sizes); ``blender_ext`` and
    ``root`` as there."""
    tj = Path(transforms_json)
    root = tj.parent if root is None else Path(root)
    meta = _read_transforms(tj)
    fr = meta["frames"][0]
    if not isinstance(fr, dict) or "file_path" not in fr:
        raise CaptureError(f"{tj}: frames[0]: needs 'file_path'")
    return image_size(
        _resolve(tj.parent, fr["file_path"], blender_ext, root, f"{tj}: frames[0]", "file_path")
    )


def load_views(
    transforms_json: str | Path,
    *,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: int = 1,
    load_masks: bool = True,
    load_depth: bool = True,
    valid_ids: Iterable[int] | None = None,
    expected_count: int | None = None,
    max_views: int | None = None,
    blender_ext: str | None = ".png",
    rigid_tol: float = 1e-4,
    root: str | Path | None = None,
) -> Views:
    """Load the frames of one ``transforms.json`` (ours, nerfstudio or NeRF-Blender).

    ``downscale``: integer factor (images area-averaged, masks/depth nearest, intrinsics scaled);
    ``valid_ids``: object ids allowed in masks (besides 0); ``expected_count``: number of frames required;
    ``max_views``: keep only the first frames; ``blender_ext``: extension added to ``file_path`` without one;
    ``root``: the folder every frame's files must lie in (default: the one holding ``transforms_json``).
    """
    tj = Path(transforms_json)
    meta = _read_transforms(tj)
    frames = meta["frames"]
    if expected_count is not None and len(frames) != expected_count:
        raise CaptureError(
            f"{tj}: camera count mismatch: {len(frames)} frames but scene.json says {expected_count} views"
        )
    if max_views is not None:
        frames = frames[:max_views]
    downscale = int(downscale)
    if downscale < 1:
        raise ValueError("downscale must be a positive integer")
    ids = None if valid_ids is None else np.asarray(sorted(set(int(i) for i in valid_ids)), dtype=np.int64)
    base = tj.parent
    root = base if root is None else Path(root)
    with_masks = load_masks and any("mask_path" in f for f in frames)
    with_depth = load_depth and any("depth_path" in f for f in frames)
    depth_scale = float(meta.get("depth_unit_scale_factor", DEPTH_SCALE))
    images, masks, depths, c2ws, Ks, paths = [], [], [], [], [], []
    size = None
    for i, fr in enumerate(frames):
        where = f"{tj}: frames[{i}]"
        c2w = _frame_c2w(fr, where, rigid_tol)
        ipath = _resolve(base, fr["file_path"], blender_ext, root, where, "file_path")
        rgb, (full_w, full_h) = read_rgb(ipath, background, downscale)
        h, w = rgb.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise CaptureError(
                f"{ipath}: image is {full_w}x{full_h} but earlier images are "
                f"{size[0] * downscale}x{size[1] * downscale}"
            )
        K = _intrinsics(meta, fr, full_w, full_h, where)
        if downscale > 1:
            K[0, :] *= w / full_w
            K[1, :] *= h / full_h
        if with_masks:
            if "mask_path" not in fr:
                raise CaptureError(f"{where}: has no mask_path but other frames do (mask count mismatch)")
            masks.append(
                read_mask(
                    _resolve(base, fr["mask_path"], None, root, where, "mask_path"),
                    ipath,
                    (full_w, full_h),
                    (w, h),
                    downscale,
                    ids,
                )
            )
        if with_depth:
            if "depth_path" not in fr:
                raise CaptureError(f"{where}: has no depth_path but other frames do (depth count mismatch)")
            depths.append(
                read_depth(
                    _resolve(base, fr["depth_path"], None, root, where, "depth_path"),
                    ipath,
                    (full_w, full_h),
                    (w, h),
                    downscale,
                    depth_scale,
                )
            )
        images.append(rgb)
        c2ws.append(c2w)
        Ks.append(K)
        paths.append(ipath)
    c2w_all = np.stack(c2ws)
    c2w_all.setflags(write=False)
    return Views(
        images=torch.from_numpy(np.stack(images)),
        viewmats=torch.from_numpy(opengl_c2w_to_viewmat(c2w_all).astype(np.float32)),
        Ks=torch.from_numpy(np.stack(Ks).astype(np.float32)),
        width=size[0],
        height=size[1],
        image_paths=tuple(paths),
        c2w_opengl=c2w_all,
        masks=torch.from_numpy(np.stack(masks)) if with_masks else None,
        depths=torch.from_numpy(np.stack(depths)) if with_depth else None,
    )


def load_blender(
    transforms_json: str | Path,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: int = 1,
    max_views: int | None = None,
) -> Views:
    """Load a NeRF-Blender split (``transforms_*.json``, RGBA PNGs composited over ``background``)."""
    return load_views(
        transforms_json,
        background=background,
        downscale=downscale,
        load_masks=False,
        load_depth=False,
        max_views=max_views,
        blender_ext=".png",
    )


# --------------------------------------------------------------------------------------------- scene.json
def _objects(meta: Mapping, src: Path) -> tuple[ObjectInfo, ...]:
    objs = meta.get("objects")
    if not isinstance(objs, list) or not objs:
        raise CaptureError(f"{src}: 'objects' must be a non-empty list of {{id, name}}")
    out = []
    for i, o in enumerate(objs):
        if not isinstance(o, dict) or not isinstance(o.get("id"), int) or not isinstance(o.get("name"), str):
            raise CaptureError(f"{src}: objects[{i}] needs an integer 'id' and a string 'name'")
        if not 1 <= o["id"] <= 255:
            raise CaptureError(f"{src}: objects[{i}].id = {o['id']} is outside 1..255 (0 is the background)")
        out.append(ObjectInfo(int(o["id"]), o["name"]))
    ids = [o.id for o in out]
    if len(set(ids)) != len(ids) or len({o.name for o in out}) != len(out):
        raise CaptureError(f"{src}: object ids and names must be unique")
    return tuple(sorted(out, key=lambda o: o.id))


def _pose_list(
    entries, objects: tuple[ObjectInfo, ...], src: Path, where: str, key: str, tol: float
) -> np.ndarray:
    if not isinstance(entries, list):
        raise CaptureError(f"{src}: {where} must be a list of {{id, {key}}}")
    by_id = {}
    for j, e in enumerate(entries):
        if not isinstance(e, dict) or "id" not in e or key not in e:
            raise CaptureError(f"{src}: {where}[{j}] needs 'id' and '{key}'")
        try:
            by_id[int(e["id"])] = check_rigid(
                np.asarray(e[key], dtype=np.float64), f"{src}: {where}[{j}]", tol
            )
        except (TypeError, ValueError) as err:
            msg = str(err)
            raise CaptureError(msg if msg.startswith(str(src)) else f"{src}: {where}[{j}]: {msg}") from err
    want = [o.id for o in objects]
    if sorted(by_id) != want:
        raise CaptureError(f"{src}: {where} lists ids {sorted(by_id)} but the objects are {want}")
    return np.stack([by_id[i] for i in want])


def _check_format(meta: Mapping, src: Path) -> None:
    """Refuse a ``scene.json`` of another format, or of a newer format version than this loader reads."""
    if "format" in meta and meta["format"] != FORMAT_NAME:
        raise CaptureError(f"{src}: format {meta['format']!r} is not a {FORMAT_NAME!r} capture")
    if "format_version" not in meta:
        return
    v = meta["format_version"]
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise CaptureError(f"{src}: format_version must be a positive integer, got {v!r}")
    if v > FORMAT_VERSION:
        raise CaptureError(
            f"{src}: format_version {v} is newer than this dsg-gym reads ({FORMAT_VERSION}); upgrade dsg-gym"
        )


def capture_states(root: Path, meta: Mapping) -> Any:
    """``scene.json``'s ``states`` (``meta``) of the capture folder ``root``; without them, every folder of
    ``root`` holding a ``transforms.json``, by name, each with an empty description."""
    states = meta.get("states")
    if states is None:
        states = {p.parent.name: {} for p in sorted(root.glob("*/transforms.json"))}
    return states


def load_capture(
    path: str | Path,
    states: Sequence[str] | None = None,
    *,
    downscale: int = 1,
    load_masks: bool = True,
    load_depth: bool = True,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    rigid_tol: float = 1e-4,
) -> Capture:
    """Load a capture folder (``scene.json`` + ``<state>/transforms.json``), all states or the ones named."""
    root = Path(path)
    src = root / "scene.json"
    meta = read_json(src)
    if not isinstance(meta, dict):
        raise CaptureError(f"{src}: expected a JSON object")
    _check_format(meta, src)
    objects = _objects(meta, src)
    state_meta = capture_states(root, meta)
    if not isinstance(state_meta, dict) or not state_meta:
        raise CaptureError(f"{src}: 'states' must map state names to their description")
    names = list(state_meta) if states is None else list(states)
    for n in names:
        if n not in state_meta:
            raise CaptureError(f"{src}: no state {n!r} (states: {list(state_meta)})")
    views: dict[str, Views] = {}
    poses: dict[str, np.ndarray] = {}
    splits: dict[str, str] = {}
    ids = [o.id for o in objects]
    for n in state_meta:
        sm = state_meta[n]
        if not isinstance(sm, dict):
            raise CaptureError(f"{src}: states.{n} must be an object")
        splits[n] = str(sm.get("split", "train"))
        if "object_poses" in sm:
            poses[n] = _pose_list(
                sm["object_poses"], objects, src, f"states.{n}.object_poses", "pose", rigid_tol
            )
            poses[n].setflags(write=False)
    for n in names:
        sm = state_meta[n]
        count = sm.get("num_views")
        views[n] = load_views(
            root / n / "transforms.json",
            background=background,
            downscale=downscale,
            load_masks=load_masks,
            load_depth=load_depth,
            valid_ids=ids,
            expected_count=None if count is None else int(count),
            rigid_tol=rigid_tol,
            root=root,
        )
    supplied: dict[tuple[str, str], np.ndarray] = {}
    for j, rt in enumerate(meta.get("relative_transforms", [])):
        if not isinstance(rt, dict) or not {"src", "dst", "transforms"} <= set(rt):
            raise CaptureError(f"{src}: relative_transforms[{j}] needs 'src', 'dst' and 'transforms'")
        t = _pose_list(
            rt["transforms"], objects, src, f"relative_transforms[{j}].transforms", "transform", rigid_tol
        )
        t.setflags(write=False)
        supplied[(str(rt["src"]), str(rt["dst"]))] = t
    bounds = None
    table = meta.get("table")
    if isinstance(table, dict) and "bounds" in table:
        bounds = np.asarray(table["bounds"], dtype=np.float64)
        if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)):
            raise CaptureError(f"{src}: table.bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]]")
    return Capture(
        root=root,
        name=str(meta.get("name", root.name)),
        units=str(meta.get("units", "unknown")),
        objects=objects,
        states=MappingProxyType(views),
        poses=MappingProxyType(poses),
        splits=MappingProxyType(splits),
        table_bounds=bounds,
        metadata=MappingProxyType(meta),
        supplied_transforms=MappingProxyType(supplied),
    )
