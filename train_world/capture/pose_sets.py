"""One capture state in another set of camera poses, or restricted to named views.

:func:`write_estimated_capture` writes the views of one state in camera poses estimated from its images (e.g.
by :func:`train_world.capture.pose_check.estimate_state_poses`): the registered views only, photos and
object-id masks undistorted with the estimated lens to a pinhole camera
(:class:`~train_world.capture.undistort.Undistorter`, as ``dsg-capture`` does), the cameras' OpenGL
camera-to-world ``transform_matrix`` from the estimated OpenCV world-to-camera. The estimated frame differs
from the capture's by a similarity; the object poses are carried into it through the similarity fitted to the
camera centres (Umeyama), so each object sits where the estimated cameras see it, and so are the capture's
sparse points (``scene.json`` ``"points"``, :mod:`train_world.capture.points`). Depth maps and table bounds
are not carried over. :func:`subset_capture` writes a capture holding the named views of one state, in the
order named, files (and the sparse points) copied byte for byte. Both write one state (the output's
``scene.json`` lists that state only, with no relative transforms) into a folder renamed into place at the end
(:func:`~train_world.capture.format.staged_directory`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
from PIL import Image

from train_world.capture.alignment import umeyama
from train_world.capture.cameras import GL_TO_CV
from train_world.capture.files import CaptureError, read_json
from train_world.capture.format import (
    atomic_write_bytes,
    atomic_write_json,
    encode_png,
    frame_entry,
    matrix_to_list,
    staged_directory,
    transforms_header,
)
from train_world.capture.loader import load_capture
from train_world.capture.points import POINTS_FILE, capture_points, write_points_ply
from train_world.capture.undistort import Undistorter

__all__ = ["subset_capture", "write_estimated_capture"]


def _state_docs(capture: Path, state: str) -> tuple[dict, dict]:
    """``scene.json`` and ``<state>/transforms.json`` of ``capture`` as dicts."""
    scene = read_json(capture / "scene.json")
    if not isinstance(scene, dict) or not isinstance(scene.get("states"), dict):
        raise CaptureError(f"{capture / 'scene.json'}: expected an object with a 'states' mapping")
    if state not in scene["states"]:
        raise CaptureError(
            f"{capture / 'scene.json'}: no state {state!r}; name one of {list(scene['states'])}"
        )
    tj = read_json(capture / state / "transforms.json")
    if not isinstance(tj, dict) or not isinstance(tj.get("frames"), list):
        raise CaptureError(f"{capture / state / 'transforms.json'}: expected an object with a 'frames' list")
    return scene, tj


def _one_state_scene(scene: dict, state: str, num_views: int, **extra) -> dict:
    """``scene`` with only ``state`` (its view count set to ``num_views``) and no relative transforms."""
    out = {k: v for k, v in scene.items() if k not in ("states", "relative_transforms")}
    out.update(extra)
    out["states"] = {state: {**scene["states"][state], "num_views": int(num_views)}}
    return out


def subset_capture(
    capture: str | os.PathLike,
    out: str | os.PathLike,
    stems: Sequence[str],
    state: str = "state1",
    overwrite: bool = False,
) -> Path:
    """Write at ``out`` a capture of the views of ``state`` whose image file stems are ``stems`` (in that
    order), their image, mask and depth files copied unchanged. Returns ``out``."""
    capture, out = Path(capture), Path(out)
    scene, tj = _state_docs(capture, state)
    base = capture / state
    by_stem: dict[str, dict] = {}
    for i, fr in enumerate(tj["frames"]):
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            raise CaptureError(f"{base / 'transforms.json'}: frames[{i}] needs a 'file_path'")
        stem = Path(fr["file_path"]).stem
        if stem in by_stem:
            raise CaptureError(f"{base / 'transforms.json'}: two frames have the image stem {stem!r}")
        by_stem[stem] = fr
    missing = [s for s in stems if s not in by_stem]
    if missing:
        raise CaptureError(
            f"{base / 'transforms.json'}: no view {missing[0]!r}; name views by image file stem"
        )
    if len(set(stems)) != len(stems) or not stems:
        raise ValueError(f"stems must name at least one view, each once; got {list(stems)}")
    root = capture.resolve()
    with staged_directory(out, overwrite=overwrite) as stage:
        frames = []
        for s in stems:
            fr = dict(by_stem[s])
            for key in ("file_path", "mask_path", "depth_path"):
                if key not in fr:
                    continue
                src = (base / fr[key]).resolve()
                if not src.is_relative_to(root) or not src.is_file():
                    where = f"{base / 'transforms.json'}: {key} {fr[key]!r} of view {s!r}"
                    raise CaptureError(
                        f"{where} is not a file inside {capture}; keep the capture's files in it"
                    )
                rel = src.relative_to(root)  # the same place in the new capture
                atomic_write_bytes(stage / rel, src.read_bytes())
                fr[key] = Path(os.path.relpath(rel, state)).as_posix()
            frames.append(fr)
        atomic_write_json(stage / state / "transforms.json", {**tj, "frames": frames})
        if capture_points(capture, scene) is not None:  # checks the entry names a file inside the capture
            rel = (capture / scene["points"]["path"]).resolve().relative_to(root)
            atomic_write_bytes(stage / rel, (root / rel).read_bytes())
        atomic_write_json(stage / "scene.json", _one_state_scene(scene, state, len(frames)))
    return out


def _read_rgb_u8(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("RGB"))


def write_estimated_capture(
    capture: str | os.PathLike,
    state: str,
    out: str | os.PathLike,
    world_to_camera: Mapping[str, np.ndarray],
    camera_model: str,
    camera_params: Sequence[float],
    overwrite: bool = False,
) -> Path:
    """Write at ``out`` the views of ``state`` of ``capture`` whose image stems are keys of
    ``world_to_camera`` (stem -> OpenCV ``[4,4]``), in the capture's order, in those poses (module docstring).
    ``camera_model``/``camera_params``: the COLMAP camera estimated for the capture's images at their size
    (e.g. ``SIMPLE_RADIAL``, ``(f, cx, cy, k)``). Returns ``out``."""
    capture, out = Path(capture), Path(out)
    scene, _ = _state_docs(capture, state)
    views = load_capture(capture, [state], load_depth=False).states[state]
    stems = [p.stem for p in views.image_paths]
    unknown = sorted(set(world_to_camera) - set(stems))
    if unknown:
        raise ValueError(f"{capture}: {state} has no view {unknown[0]!r}; pose only the capture's own views")
    keep = [i for i, s in enumerate(stems) if s in world_to_camera]
    if len(keep) < 3:
        raise ValueError(
            f"{capture}: {len(keep)} posed views of {state}; need 3 to carry the object poses over"
        )
    und = Undistorter.for_camera(camera_model, tuple(camera_params), views.width, views.height)
    w2c = np.stack([np.asarray(world_to_camera[stems[i]], np.float64) for i in keep])
    c2w_cv = np.linalg.inv(w2c)
    s, rot, t = umeyama(views.c2w_opengl[keep, :3, 3], c2w_cv[:, :3, 3])  # capture frame -> estimated frame
    poses = []
    for e in scene["states"][state].get("object_poses", []):
        p = np.asarray(e["pose"], np.float64)
        q = np.eye(4)
        q[:3, :3] = rot @ p[:3, :3]
        q[:3, 3] = s * rot @ p[:3, 3] + t
        poses.append({"id": e["id"], "pose": matrix_to_list(q)})
    with staged_directory(out, overwrite=overwrite) as stage:
        frames = []
        for j, i in enumerate(keep):
            img_rel = f"images/{stems[i]}.png"
            atomic_write_bytes(
                stage / state / img_rel, encode_png(und.rgb(_read_rgb_u8(views.image_paths[i])))
            )
            mask_rel = None
            if views.masks is not None:
                mask_rel = f"masks/{stems[i]}.png"
                ids = und.ids(views.masks[i].numpy())
                atomic_write_bytes(stage / state / mask_rel, encode_png(ids))
            frames.append(frame_entry(img_rel, c2w_cv[j] @ GL_TO_CV, mask_rel))
        K = und.K
        header = transforms_header(und.width, und.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        header.pop("depth_unit_scale_factor")
        atomic_write_json(stage / state / "transforms.json", {**header, "frames": frames})
        points = capture_points(capture, scene)
        if points is not None:
            rgb = np.rint(points[1] * 255).astype(np.uint8)  # as written: 8 bits a channel
            write_points_ply(stage / POINTS_FILE, s * points[0] @ rot.T + t, rgb)
        doc = _one_state_scene(
            {k: v for k, v in scene.items() if k not in ("table", "points")},  # a box does not carry over
            state,
            len(frames),
            units=f"the estimated cameras' (one unit is {1 / s:.6g} of {capture.name}'s units)",
            camera_poses={
                "kind": "estimated from the images",
                "from": capture.name,
                "camera_model": camera_model,
                "camera_params": [float(x) for x in camera_params],
                "undistorted_K": matrix_to_list(K),
                "similarity_from_capture": {"scale": float(s), "rotation": rot.tolist(),
                                            "translation": t.tolist()},
            },
        )  # fmt: skip
        if points is not None:
            doc["points"] = {"path": POINTS_FILE}
        doc["states"][state]["object_poses"] = poses
        if not poses:
            doc["states"][state].pop("object_poses")
        atomic_write_json(stage / "scene.json", doc)
    return out
