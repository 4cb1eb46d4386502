"""From a photo capture (two states of a real tabletop) to a standard capture, with an estimation report.

:func:`build_capture` checks the photos (:mod:`.photos`), reconstructs the cameras of both states jointly
(:mod:`.sfm`), undistorts photos and masks to a pinhole camera (:mod:`.undistort`), fits the table frame
(:mod:`.frame`), estimates every object's rigid motion (:mod:`.motions`) and writes, atomically::

    OUT/scene.json                 objects, table bounds, units, per-state object poses, relative_transforms
    OUT/<state>/transforms.json    pinhole intrinsics + registered frames (OpenGL camera-to-world)
    OUT/<state>/images/<stem>.png  undistorted photos (with ``max_size``: shrunk, area-averaged)
    OUT/<state>/masks/<stem>.png   undistorted object-id masks (likewise, nearest pixel)
    OUT/<state>/depth/<stem>.png   with ``stereo``: depth from multi-view stereo (uint16, 0 = none; :mod:`.mvs`);
                                   with ``depth_fit``: depth of a first reconstruction (:mod:`.fitted_depth`)
    OUT/points3d.ply               the background's structure-from-motion points (table frame, coloured)
    OUT/report.json                registered views, reprojection error, table fit, per-object estimates, scale

Object poses: in ``state1`` each object sits at its centre (visual hull centroid) with the table frame's
orientation; in ``state2`` it is that pose moved by the estimated motion, so ``relative_transforms`` equal
``P2 @ inv(P1)``. Nothing is written at ``OUT`` unless everything succeeds.
"""

from __future__ import annotations

import dataclasses
import os
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from train_world.capture.appearance import ColourView
from train_world.capture.cameras import GL_TO_CV
from train_world.capture.features import ViewFeatures, extract_view_features
from train_world.capture.files import area_resize, label_resize
from train_world.capture.fitted_depth import DepthFit, fit_depth_maps
from train_world.capture.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    atomic_write_bytes,
    atomic_write_json,
    depth_to_png_units,
    encode_png,
    frame_entry,
    matrix_to_list,
    staged_directory,
    transforms_header,
)
from train_world.capture.frame import FrameError, fit_table_plane, table_frame
from train_world.capture.marker import (
    DICTIONARY,
    MarkerObservation,
    detect_marker,
    marker_detector,
    marker_scale,
)
from train_world.capture.motions import ObjectMotion, estimate_object_motion
from train_world.capture.mvs import stereo_depths
from train_world.capture.photos import (
    PHOTO_STATES,
    PhotoCapture,
    PhotoCaptureError,
    load_photo,
    read_photo_capture,
)
from train_world.capture.points import POINTS_FILE, point_colours, write_points_ply
from train_world.capture.sfm import SfmResult, quiet_colmap, run_sfm, silenced_stderr
from train_world.capture.shrink import shrink_capture
from train_world.capture.silhouettes import object_centre
from train_world.capture.undistort import Undistorter

__all__ = ["CAPTURE_TOOL_VERSION", "build_capture"]

CAPTURE_TOOL_VERSION = "1.0"
#: longest side of the masks used for visual hulls (larger masks are reduced, nearest pixel)
SILHOUETTE_SIZE = 640
#: feature localisation tolerance in pixels at the size features are detected
FEATURE_TOLERANCE_PX = 1.5
#: longest side at which object features are detected
FEATURE_SIZE = 1600
#: photos with a longer side than this get a hint to shrink the capture (``max_size``)
LARGE_PHOTO = 1024


def _extractor(long_side: int):
    import pycolmap

    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = 1
    opts.use_gpu = False
    opts.sift.max_num_orientations = 1
    opts.sift.first_octave = -2 if long_side <= 800 else -1  # small photos: detect on a 4x upsampled image
    with silenced_stderr():  # creation logs at INFO level
        return pycolmap.FeatureExtractor.create(opts, pycolmap.Device.cpu)


def _photo_view(rgb: np.ndarray, ids: np.ndarray, K: np.ndarray, w2c: np.ndarray) -> ColourView:
    """The photo with its masks, at most :data:`SILHOUETTE_SIZE` pixels on the long side (for the objects'
    motions: its silhouettes and colours)."""
    h, w = ids.shape
    s = min(1.0, SILHOUETTE_SIZE / max(h, w))
    if s < 1.0:
        size = (max(1, round(w * s)), max(1, round(h * s)))
        ids = label_resize(ids, size)
        rgb = np.clip(np.rint(area_resize(rgb, size)), 0, 255).astype(np.uint8)
        K = K.copy()
        K[0] *= size[0] / w
        K[1] *= size[1] / h
    return ColourView(np.ascontiguousarray(ids), K, w2c, np.ascontiguousarray(rgb))


def _write_views(
    capture: PhotoCapture,
    sfm: SfmResult,
    stage: Path,
    progress: bool,
    marker: list | None = None,
    marker_id=None,
) -> tuple[
    dict[str, Undistorter],
    dict[str, list[ViewFeatures]],
    dict[str, list[ColourView]],
]:
    """Undistorted photos and masks into ``stage/<state>/``; object features and the photos with their masks
    (for silhouettes and colours) per state; with a list ``marker``, the views that see the ArUco marker are
    appended to it (:class:`MarkerObservation`)."""
    unds, feats, views = {}, {}, {}
    detector = marker_detector() if marker is not None else None
    total = sum(len(sfm.registered[s]) for s in PHOTO_STATES)
    with tqdm(
        total=total, desc="dsg-capture: undistorting + object features", unit="photo", disable=not progress
    ) as bar:
        for s in PHOTO_STATES:
            cam = sfm.cameras[s]
            und = unds[s] = Undistorter.for_camera(cam.model, cam.params, cam.width, cam.height)
            ex = _extractor(max(und.width, und.height))
            feats[s], views[s] = [], []
            for v in capture.states[s]:
                if v.key not in sfm.world_to_camera:
                    continue
                rgb, ids = load_photo(v)
                rgb, ids = und.rgb(rgb), und.ids(ids)
                atomic_write_bytes(stage / s / "images" / f"{v.stem}.png", encode_png(rgb))
                atomic_write_bytes(stage / s / "masks" / f"{v.stem}.png", encode_png(ids))
                w2c = sfm.world_to_camera[v.key]
                gray = np.asarray(Image.fromarray(rgb).convert("L"))
                feats[s].append(extract_view_features(gray, ids, und.K, w2c, ex, FEATURE_SIZE))
                views[s].append(_photo_view(rgb, ids, und.K, w2c))
                if marker is not None:
                    seen = detect_marker(rgb, marker_id, detector)
                    if seen is not None and (not marker or seen[0] == marker[0].marker_id):
                        marker.append(MarkerObservation(v.key, seen[0], seen[1], und.K, w2c))
                bar.update(1)
    return unds, feats, views


def _finite(x: float, digits: int) -> float | None:
    """``x`` rounded, or None (JSON null) when it is not a finite number."""
    return round(float(x), digits) if np.isfinite(x) else None


def _motion_report(obj, m: ObjectMotion, T_world: np.ndarray, scale: float) -> dict:
    return {
        "id": obj.id,
        "name": obj.name,
        "method": m.method,
        "feature_matches": m.matches,
        "feature_inliers": m.inliers,
        "feature_rms_px": _finite(m.rms_px, 4),
        "hull_alignment_rms": _finite(m.hull_rms * scale, 6),
        "views_seen": {"state1": m.views[0], "state2": m.views[1]},
        "appearance": None
        if m.appearance is None
        else {
            "photo_pairs": m.appearance.pairs,
            "colour_rms_before": _finite(m.appearance.rms_before, 5),
            "colour_rms_after": _finite(m.appearance.rms_after, 5),
            "turn_deg": _finite(m.appearance.turn_deg, 4),
            "kept": m.appearance.accepted,
            "symmetric_candidates": m.appearance.candidates,
            "chosen_turn_deg": _finite(m.appearance.chosen_turn_deg, 4),
        },
        "rotation_deg": round(
            float(np.degrees(np.arccos(np.clip((np.trace(T_world[:3, :3]) - 1) / 2, -1, 1)))), 4
        ),
        "translation": [round(float(x), 6) for x in T_world[:3, 3]],
    }


def build_capture(
    photos: str | os.PathLike,
    out: str | os.PathLike,
    *,
    metres_per_unit: float | None = None,
    marker_size: float | None = None,
    marker_id: int | None = None,
    overwrite: bool = False,
    stereo: bool = False,
    depth_fit: DepthFit | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    reconstruct: Callable[..., SfmResult] = run_sfm,
    max_size: int | None = None,
) -> dict:
    """Turn the photo capture ``photos`` into a standard capture at ``out`` (module docstring); returns the
    report written to ``out/report.json``. Bad input raises :class:`PhotoCaptureError` (a ``ValueError``)
    naming the file or object; an existing non-empty ``out`` raises ``FileExistsError`` unless ``overwrite``.

    Metric scale: ``metres_per_unit``, or ``marker_size`` (the black square's edge in metres of an ArUco
    ``DICT_4X4_50`` marker lying in the scene, id ``marker_id`` or the lowest id seen; :mod:`.marker`).
    ``stereo``: depth maps of every view from multi-view stereo (:mod:`.mvs`); training on the capture then
    starts from them instead of the table top, hulls, room points and random points. ``depth_fit``: depth
    maps of every view from a first reconstruction of each state (:mod:`.fitted_depth`), likewise the
    training's start (the default of ``dsg-capture``, ``--depth fit``; none here unless given). ``reconstruct``: the
    structure-from-motion step, called as :func:`.sfm.run_sfm` is (a benchmark passes one that puts known
    cameras in place, :func:`.compare.with_true_cameras`). ``max_size``: the capture's views are shrunk to at
    most this many pixels on the long side (:mod:`.shrink`; images area-averaged, intrinsics scaled) before
    any depth fit; poses, the frame, the marker and the motions are still estimated on the whole photos."""
    if metres_per_unit is not None and not (np.isfinite(metres_per_unit) and metres_per_unit > 0):
        raise ValueError(f"metres per unit must be a positive number, got {metres_per_unit}")
    if marker_size is not None and not (np.isfinite(marker_size) and marker_size > 0):
        raise ValueError(f"marker size must be a positive number of metres, got {marker_size}")
    if marker_size is not None and metres_per_unit is not None:
        raise ValueError("give the scale once: a marker size or metres per unit, not both")
    if stereo and depth_fit is not None:
        raise ValueError("choose one source of depth maps: stereo or a depth fit, not both")
    if max_size is not None and not (isinstance(max_size, int) and max_size >= 16):
        raise ValueError(
            f"the capture's largest side must be an integer of at least 16 pixels, got {max_size!r}"
        )
    say = log or (lambda _m: None)
    t_start = time.perf_counter()
    capture = read_photo_capture(photos)
    out = Path(out)
    say(
        f"{sum(len(v) for v in capture.states.values())} photos, objects: "
        + ", ".join(f"{o.id}={o.name}" for o in capture.objects)
    )
    with (
        staged_directory(out, overwrite=overwrite) as stage,
        tempfile.TemporaryDirectory(prefix=f".{out.name}.work.", dir=out.absolute().parent) as work,
    ):
        sfm = reconstruct(capture, work, progress=progress, log=say)
        photo_side = max(max(c.width, c.height) for c in sfm.cameras.values())
        if max_size is None and photo_side > LARGE_PHOTO:
            say(
                f"the photos are {photo_side} px on the long side and so is the capture; --max-size PX shrinks it"
            )
        t = time.perf_counter()
        marker_obs = [] if marker_size is not None else None
        with quiet_colmap():
            unds, feats, photo_views = _write_views(capture, sfm, stage, progress, marker_obs, marker_id)
        t_views = time.perf_counter() - t
        centres = np.array([np.linalg.inv(w)[:3, 3] for w in sfm.world_to_camera.values()])
        anchors = [object_centre(photo_views[s], o.id)[0] for s in PHOTO_STATES for o in capture.objects]
        anchors = np.array([a for a in anchors if np.all(np.isfinite(a))]).reshape(-1, 3)
        if len(anchors) == 0:
            raise PhotoCaptureError(
                f"{capture.root}: no object is seen whole in two registered photos of a state"
            )
        try:
            plane = fit_table_plane(sfm.points, anchors, centres)
        except FrameError as e:
            raise PhotoCaptureError(f"{capture.root}: cannot find the table plane: {e}") from e
        say(f"table plane: {int(plane.inliers.sum())} of {len(sfm.points)} background points")
        t = time.perf_counter()
        motions = {}
        for o in tqdm(
            capture.objects, desc="dsg-capture: object motions", unit="object", disable=not progress
        ):
            long_side = max(unds["state1"].width, unds["state1"].height)
            tol = FEATURE_TOLERANCE_PX * max(1.0, long_side / FEATURE_SIZE)
            motions[o.id] = estimate_object_motion(
                o,
                (feats["state1"], feats["state2"]),
                (photo_views["state1"], photo_views["state2"]),
                (plane.normal, plane.offset),
                tol,
                seed=o.id,
                colours=(photo_views["state1"], photo_views["state2"]),
            )
        t_motions = time.perf_counter() - t
        obj_centres = np.array([m.centre for m in motions.values()])
        scale_info = None
        if marker_obs is not None:
            ms = marker_scale(marker_obs, marker_size)  # metres per unit of the reconstruction
            unit = table_frame(
                plane, sfm.points, obj_centres, centres, None
            ).scale  # frame units per SfM unit
            metres_per_unit = ms.metres_per_unit / unit
            scale_info = {
                "source": f"ArUco marker {DICTIONARY} id {ms.marker_id}, {ms.size_m} m, seen in {ms.views} photos",
                "marker_edge_units": round(ms.edge_units * unit, 6),
                "marker_reprojection_rms_px": round(ms.rms_px, 4),
            }
            say(
                f"scale: {scale_info['source']}; {metres_per_unit:.5f} m per unit, corners {ms.rms_px:.2f} px rms"
            )
        frame = table_frame(plane, sfm.points, obj_centres, centres, metres_per_unit)
        t = time.perf_counter()
        depth = _write_depths(stage, sfm, unds, frame, progress) if stereo else None
        t_depth = time.perf_counter() - t
        report = _write(capture, sfm, unds, frame, motions, stage, metres_per_unit, photos, scale_info, depth)
        size = shrink_capture(stage, PHOTO_STATES, max_size) if max_size else None
        report["capture_size"] = list(size or (unds["state1"].width, unds["state1"].height))
        if size:
            say(f"capture shrunk to {size[0]}x{size[1]}")
        t = time.perf_counter()
        report["fitted_depth"] = None
        if depth_fit is not None:
            say(f"depth fit: {depth_fit.steps} steps per state")
            fitted = fit_depth_maps(stage, PHOTO_STATES, depth_fit, progress=progress)
            report["fitted_depth"] = {**dataclasses.asdict(depth_fit), **fitted}
        t_fit = time.perf_counter() - t
        report["timings_s"] = {
            **{k: round(v, 2) for k, v in sfm.timings.items()},
            "undistort_and_features_s": round(t_views, 2),
            "motions_s": round(t_motions, 2),
            "stereo_depth_s": round(t_depth, 2),
            "depth_fit_s": round(t_fit, 2),
            "total_s": round(time.perf_counter() - t_start, 2),
        }
        atomic_write_json(stage / "report.json", report)
    return report


def _write_points(stage: Path, sfm: SfmResult, unds: dict, frame) -> int:
    """The background's structure-from-motion points in the table frame, coloured from every 4th undistorted
    view of each state, to ``stage/points3d.ply`` (:mod:`.points`); returns their count."""
    images, w2c = [], []
    for s in PHOTO_STATES:
        for stem in sfm.registered[s][::4]:
            with Image.open(stage / s / "images" / f"{stem}.png") as im:
                images.append(np.asarray(im.convert("RGB")))
            w2c.append(np.linalg.inv(frame.camera_to_world(sfm.world_to_camera[f"{s}/{stem}"])))
    xyz = frame.points(sfm.points)
    write_points_ply(stage / POINTS_FILE, xyz, point_colours(xyz, images, w2c, unds["state1"].K))
    return int(len(xyz))


def _write_depths(stage: Path, sfm: SfmResult, unds: dict, frame, progress: bool) -> dict[str, float]:
    """Every registered view's depth in the table frame by multi-view stereo within its state (:mod:`.mvs`),
    written to ``stage/<state>/depth/<stem>.png`` (uint16 in ``DEPTH_SCALE`` units, 0 = none: also depths
    the format cannot hold); returns each state's share of pixels with depth."""
    points = frame.points(sfm.points)
    coverage = {}
    total = sum(len(sfm.registered[s]) for s in PHOTO_STATES)
    with tqdm(total=total, desc="dsg-capture: stereo depth", unit="photo", disable=not progress) as bar:
        for s in PHOTO_STATES:
            stems = sfm.registered[s]
            images = []
            for stem in stems:
                with Image.open(stage / s / "images" / f"{stem}.png") as im:
                    images.append(np.asarray(im.convert("RGB")))
            w2c = np.stack(
                [np.linalg.inv(frame.camera_to_world(sfm.world_to_camera[f"{s}/{k}"])) for k in stems]
            )
            Ks = np.repeat(unds[s].K[None], len(stems), axis=0)
            depth = stereo_depths(np.stack(images), Ks, w2c, points, progress=lambda: bar.update(1))
            units = depth_to_png_units(depth)
            for stem, d in zip(stems, units, strict=True):
                atomic_write_bytes(stage / s / "depth" / f"{stem}.png", encode_png(d))
            coverage[s] = round(float((units > 0).mean()), 4)
    return coverage


def _write(
    capture, sfm, unds, frame, motions, stage, metres_per_unit, photos, scale_info=None, depth=None
) -> dict:
    poses, rel, objects_report = {"state1": [], "state2": []}, [], []
    for o in capture.objects:
        m = motions[o.id]
        T = frame.rigid(m.transform)
        u, _, vt = np.linalg.svd(T[:3, :3])
        T[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        T[3] = [0.0, 0.0, 0.0, 1.0]
        p1 = np.eye(4)
        p1[:3, 3] = frame.points(m.centre)[0]
        poses["state1"].append({"id": o.id, "pose": matrix_to_list(p1)})
        poses["state2"].append({"id": o.id, "pose": matrix_to_list(T @ p1)})
        rel.append({"id": o.id, "transform": matrix_to_list(T)})
        objects_report.append(_motion_report(o, m, T, frame.scale))
    for s in PHOTO_STATES:
        und = unds[s]
        frames = []
        for stem in sfm.registered[s]:
            c2w_gl = frame.camera_to_world(sfm.world_to_camera[f"{s}/{stem}"]) @ GL_TO_CV
            d_path = f"depth/{stem}.png" if depth is not None else None
            frames.append(frame_entry(f"images/{stem}.png", c2w_gl, f"masks/{stem}.png", d_path))
        doc = transforms_header(und.width, und.height, und.K[0, 0], und.K[1, 1], und.K[0, 2], und.K[1, 2])
        doc["frames"] = frames
        atomic_write_json(stage / s / "transforms.json", doc)
    points = _write_points(stage, sfm, unds, frame)
    scale_source = "--metres-per-unit" if metres_per_unit else "none (units are arbitrary)"
    if scale_info:
        scale_source = scale_info["source"]
    scene = {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "name": Path(photos).absolute().name,
        "description": f"estimated by dsg-capture from the photos in {Path(photos).absolute()}",
        "units": frame.units,
        "up_axis": "+z",
        "generator": {
            "name": "dsg-capture",
            "version": CAPTURE_TOOL_VERSION,
            "camera_model": sfm.cameras["state1"].model,
            "scale_source": scale_source,
            "metres_per_unit": metres_per_unit,
        },
        "objects": [{"id": o.id, "name": o.name} for o in capture.objects],
        "table": {"bounds": matrix_to_list(frame.bounds), "top_z": 0.0, "kind": "estimated"},
        "states": {
            s: {"split": "train", "num_views": len(sfm.registered[s]), "object_poses": poses[s]}
            for s in PHOTO_STATES
        },
        "relative_transforms": [{"src": "state1", "dst": "state2", "transforms": rel}],
        "points": {"path": POINTS_FILE, "kind": "sfm background", "count": points},
    }
    atomic_write_json(stage / "scene.json", scene)
    extent = frame.bounds[1] - frame.bounds[0]
    return {
        "tool": {"name": "dsg-capture", "version": CAPTURE_TOOL_VERSION},
        "photos": str(Path(photos).absolute()),
        "registered": {
            s: {
                "views": len(sfm.registered[s]),
                "of": len(capture.states[s]),
                "not_registered": list(sfm.unregistered[s]),
            }
            for s in PHOTO_STATES
        },
        "mean_reprojection_error_px": round(sfm.mean_reprojection_error, 4),
        "background_points": int(len(sfm.points)),
        "stereo_depth_coverage": depth,
        "cameras": {
            s: {
                "model": c.model,
                "params": [round(x, 6) for x in c.params],
                "width": c.width,
                "height": c.height,
                "undistorted_K": matrix_to_list(unds[s].K),
                "undistorted_size": [unds[s].width, unds[s].height],
            }
            for s, c in sfm.cameras.items()
        },
        "table": {
            "plane_inliers": int(frame.plane.inliers.sum()),
            "plane_rms": round(frame.plane.rms * frame.scale, 6),
            "bounds": matrix_to_list(frame.bounds),
            "extent": [round(float(extent[0]), 6), round(float(extent[1]), 6)],
        },
        "units": frame.units,
        "scale": {
            "source": scale_source,
            "metres_per_unit": metres_per_unit,
            "note": "unit = median camera distance from the table origin, times --metres-per-unit when given; "
            "measure a known length in these units and pass --metres-per-unit = metres / units to make it metric",
            **({k: v for k, v in scale_info.items() if k != "source"} if scale_info else {}),
        },
        "objects": objects_report,
    }
