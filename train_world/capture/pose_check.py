"""Camera poses of one capture state from its images alone, compared with the poses it ships with.

:func:`estimate_state_poses` runs the same structure from motion as ``dsg-capture`` (pycolmap, CPU, one
``SIMPLE_RADIAL`` camera, exhaustive matching, seeded) on one state's images, features everywhere (nothing moves
within a state). :func:`compare_poses` fits the similarity between the estimated and the shipped frame to the
camera centres (Umeyama) and reports centre errors (in the shipped units and in percent of the scene radius, the
median distance of the shipped centres from their mean) and rotation errors (degrees). For a real capture such as
an LLFF scene, whose shipped poses were themselves estimated, the figures say how well the two estimates agree.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from train_world.capture.alignment import rotation_angle_deg, umeyama
from train_world.capture.cameras import GL_TO_CV
from train_world.capture.format import atomic_write_bytes, encode_png
from train_world.capture.loader import load_capture
from train_world.capture.sfm import CAMERA_MODEL, SEED, _options, _rigid, quiet_colmap

__all__ = ["FEATURES", "PoseEstimate", "compare_poses", "estimate_state_poses"]


@dataclass(frozen=True)
class PoseEstimate:
    """``world_to_camera``: stem -> OpenCV ``[4, 4]`` of the registered views; ``shipped_c2w``: stem -> the
    capture's own OpenCV camera-to-world ``[4, 4]``; camera model parameters; seconds taken."""

    world_to_camera: dict[str, np.ndarray]
    shipped_c2w: dict[str, np.ndarray]
    camera_params: tuple[float, ...]
    views: int
    seconds: float


FEATURES = ("all", "object", "background")


def estimate_state_poses(
    capture: str | Path, state: str, work: str | Path, features: str = "all"
) -> PoseEstimate:
    """Reconstruct the cameras of ``state`` of the capture folder ``capture`` from its images (``work``: an
    empty scratch folder). ``features``: where features are detected: ``"all"``; ``"object"`` (inside the
    capture's object masks: a turntable capture, where the object turns and the room stays); ``"background"``."""
    import pycolmap

    if features not in FEATURES:
        raise ValueError(f"features must be one of {FEATURES}, got {features!r}")
    t0 = time.perf_counter()
    cap = load_capture(capture, [state], load_depth=False)
    views = cap.states[state]
    if features != "all" and views.masks is None:
        raise ValueError(f"{capture}: {state} has no masks; features={features!r} needs them")
    work = Path(work)
    images, masks = work / "images", work / "masks"
    names, shipped = [], {}
    for i, (path, c2w_gl) in enumerate(zip(views.image_paths, views.c2w_opengl, strict=True)):
        with Image.open(path) as im:
            rgb = np.asarray(im.convert("RGB"))
        atomic_write_bytes(images / f"{path.stem}.png", encode_png(rgb))
        if features != "all":
            obj = np.asarray(views.masks[i]) > 0
            keep = obj if features == "object" else ~obj
            atomic_write_bytes(
                masks / f"{path.stem}.png.png", encode_png(np.where(keep, 255, 0).astype(np.uint8))
            )
        names.append(f"{path.stem}.png")
        shipped[path.stem] = np.asarray(c2w_gl, np.float64) @ GL_TO_CV
    extraction, matching, verification, mapping = _options(pycolmap)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = CAMERA_MODEL
    if features != "all":
        reader.mask_path = str(masks)
    db = work / "database.db"
    pycolmap.set_random_seed(SEED)
    with quiet_colmap():
        pycolmap.extract_features(db, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                                  reader_options=reader, extraction_options=extraction,
                                  device=pycolmap.Device.cpu)  # fmt: skip
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)  # fmt: skip
        (work / "sparse").mkdir(exist_ok=True)
        recs = pycolmap.incremental_mapping(db, images, work / "sparse", options=mapping)
    if not recs:
        raise ValueError(f"{capture}: structure from motion found no reconstruction of {state}")
    rec = max(recs.values(), key=lambda r: r.num_reg_images())
    w2c = {
        img.name.removesuffix(".png"): _rigid(img.cam_from_world())
        for img in rec.images.values()
        if img.has_pose
    }
    params = tuple(float(x) for x in next(iter(rec.cameras.values())).params)
    return PoseEstimate(dict(sorted(w2c.items())), shipped, params, len(names), time.perf_counter() - t0)


def compare_poses(est: PoseEstimate) -> dict:
    """Similarity-aligned errors of the estimated cameras against the shipped ones (module docstring)."""
    keys = [k for k in est.world_to_camera if k in est.shipped_c2w]
    if len(keys) < 3:
        raise ValueError(f"only {len(keys)} registered views; need 3 to compare")
    e_c2w = {k: np.linalg.inv(est.world_to_camera[k]) for k in keys}
    src = np.array([e_c2w[k][:3, 3] for k in keys])
    dst = np.array([est.shipped_c2w[k][:3, 3] for k in keys])
    s, rot, t = umeyama(src, dst)
    moved = (s * (rot @ src.T)).T + t
    err = np.linalg.norm(moved - dst, axis=1)
    radius = float(np.median(np.linalg.norm(dst - dst.mean(axis=0), axis=1)))
    rerr = np.array([float(rotation_angle_deg((rot @ e_c2w[k][:3, :3]).T @ est.shipped_c2w[k][:3, :3]))
                     for k in keys])  # fmt: skip
    return {
        "views": est.views,
        "registered": len(keys),
        "scene_radius": radius,
        "similarity_scale": float(s),
        "camera_centre_error_median": float(np.median(err)),
        "camera_centre_error_max": float(err.max()),
        "camera_centre_error_median_percent_of_radius": float(100 * np.median(err) / radius),
        "camera_rotation_error_median_deg": float(np.median(rerr)),
        "camera_rotation_error_max_deg": float(rerr.max()),
        "camera_params": list(est.camera_params),
        "seconds": round(est.seconds, 1),
    }
