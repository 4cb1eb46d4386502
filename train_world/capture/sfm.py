"""Camera poses of a photo capture by joint structure from motion of both states (pycolmap, CPU).

Both states go into one reconstruction so that they share one world frame: the objects (which move between
the states) are masked out of the features, so only the static background is matched. One camera model
with lens distortion (``SIMPLE_RADIAL``) is shared by all photos, or one per state when the states were
taken at different sizes. Photos are matched exhaustively; a state of video frames is matched with its
neighbours in time and the states with each other (:func:`sequence_pairs`). The largest reconstruction is kept and
at least :data:`MIN_REGISTERED` of each state's photos must be in it.

Poses come out as OpenCV world-to-camera matrices ``[4,4]`` (float64) in the reconstruction's arbitrary
frame and scale; points are the background's 3D points ``[N,3]``. Deterministic for a given input (seeded
RANSAC and mapper; extraction, matching and mapping each on one thread, as their results on several threads
depend on the threads' timing).

Import numpy and Pillow before pycolmap (pycolmap first, then writing a PNG, aborts the process).
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter
from tqdm import tqdm

from train_world.capture.format import atomic_write_bytes, encode_png
from train_world.capture.photos import PHOTO_STATES, PhotoCapture, PhotoCaptureError, load_photo

__all__ = [
    "MIN_REGISTERED",
    "SEED",
    "SfmError",
    "SfmResult",
    "check_registration",
    "quiet_colmap",
    "run_sfm",
    "silenced_stderr",
]

#: fraction of each state's photos that must register
MIN_REGISTERED = 0.95
#: seed of every random choice in the reconstruction
SEED = 0
#: camera model with lens distortion estimated by bundle adjustment
CAMERA_MODEL = "SIMPLE_RADIAL"
#: longest side at which features are detected (bigger photos are scaled down for detection only)
MAX_FEATURE_IMAGE_SIZE = 2000
#: object masks are grown by this fraction of the longest image side (at least 2 px) before masking
#: features, so that no feature straddles an object's outline
MASK_MARGIN = 0.01
#: video frames: each is matched with this many next frames of its state ...
SEQUENCE_OVERLAP = 10
#: ... and every view with every CROSS_STEP-th view of the other state
CROSS_STEP = 3
#: reprojection errors (pixels) above which observations are dropped by the final refinement, pass by pass
REFINE_MAX_ERRORS = (1.5, 1.0)


class SfmError(PhotoCaptureError):
    """Structure from motion failed (views that did not register); the message names them."""


@dataclass(frozen=True)
class StateCamera:
    """The estimated camera of one state: COLMAP model name, its parameters (``f, cx, cy, k`` for
    ``SIMPLE_RADIAL``; pixel centres at +0.5) and the photo size."""

    model: str
    params: tuple[float, ...]
    width: int
    height: int


@dataclass(frozen=True)
class SfmResult:
    """Registered views and the background's 3D points in the reconstruction's frame.

    ``world_to_camera``: view key ``"<state>/<stem>"`` -> OpenCV world-to-camera ``[4,4]`` float64 (registered
    views only); ``cameras``: state -> :class:`StateCamera`; ``points``: ``[N,3]`` float64;
    ``point_errors``: ``[N]`` mean reprojection error of each point in pixels; ``unregistered``: state ->
    stems that did not register.
    """

    world_to_camera: dict[str, np.ndarray]
    cameras: dict[str, StateCamera]
    points: np.ndarray
    point_errors: np.ndarray
    mean_reprojection_error: float
    registered: dict[str, tuple[str, ...]]
    unregistered: dict[str, tuple[str, ...]]
    timings: dict[str, float] = field(default_factory=dict)


@contextlib.contextmanager
def silenced_stderr() -> Iterator[None]:
    """Discard what native code writes to the process's stderr while inside (some pycolmap calls log at
    INFO level whatever the log level is set to)."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


@contextlib.contextmanager
def quiet_colmap() -> Iterator[None]:
    """Only errors from COLMAP's log while inside (progress is reported by dsg-capture itself)."""
    import pycolmap

    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def check_registration(
    capture: PhotoCapture, registered_keys: set[str], min_fraction: float = MIN_REGISTERED
) -> dict[str, tuple[str, ...]]:
    """Stems of each state that are not in ``registered_keys``; raises :class:`SfmError` naming them when
    fewer than ``min_fraction`` of a state's photos registered."""
    missing = {}
    for s in PHOTO_STATES:
        views = capture.states[s]
        miss = [v for v in views if v.key not in registered_keys]
        missing[s] = tuple(v.stem for v in miss)
        need = math.ceil(min_fraction * len(views) - 1e-9)
        if len(views) - len(miss) < need:
            shown = ", ".join(str(v.image_path) for v in miss[:8]) + (
                f" and {len(miss) - 8} more" if len(miss) > 8 else ""
            )
            raise SfmError(
                f"{shown}: did not register ({len(views) - len(miss)} of {len(views)} {s} photos registered, "
                f"need {need}); retake or remove them: photos need overlap with their neighbours, sharp focus "
                "and textured, static background (table, surroundings) outside the object masks"
            )
    return missing


def _prepare(capture: PhotoCapture, work: Path, progress: bool) -> tuple[Path, Path, list[str]]:
    """Write the photos (EXIF orientation applied) and inverted, grown object masks (255 = background, where
    features may be detected) in the layout pycolmap reads."""
    images, masks, names = work / "images", work / "masks", []
    for v in tqdm(capture.views(), desc="dsg-capture: preparing photos", unit="photo", disable=not progress):
        rgb, ids = load_photo(v)
        name = f"{v.state}/{v.stem}.png"
        atomic_write_bytes(images / name, encode_png(rgb))
        margin = max(2, round(MASK_MARGIN * max(v.width, v.height)))
        obj = Image.fromarray(np.where(ids > 0, 255, 0).astype(np.uint8)).filter(
            ImageFilter.MaxFilter(2 * margin + 1)
        )
        keep = np.where(np.asarray(obj) > 0, 0, 255).astype(np.uint8)
        atomic_write_bytes(masks / f"{name}.png", encode_png(keep))
        names.append(name)
    return images, masks, names


def sequence_pairs(capture: PhotoCapture, overlap: int = SEQUENCE_OVERLAP, cross_step: int = CROSS_STEP):
    """Image pairs to match when a state's photos are a video's frames (``capture.sequences``): within such a
    state each frame with the next ``overlap`` (the walk closes on itself, so the last frames pair with the
    first); within a state of photos every pair; across the states each view with every ``cross_step``-th view of
    the other state, which ties both states into one frame. Names as pycolmap sees them (``state/stem.png``)."""
    pairs: set[tuple[str, str]] = set()
    names = {st: [f"{st}/{v.stem}.png" for v in capture.states[st]] for st in PHOTO_STATES}
    for st, ns in names.items():
        n = len(ns)
        for i in range(n):
            others = (
                [(i + k) % n for k in range(1, min(overlap, n - 1) + 1)]
                if st in capture.sequences
                else range(i + 1, n)
            )
            pairs.update((ns[i], ns[j]) for j in others if j != i)
    a, b = (names[st] for st in PHOTO_STATES)
    pairs.update((x, y) for x in a for j, y in enumerate(b) if j % cross_step == 0)
    pairs.update((x, y) for i, x in enumerate(a) if i % cross_step == 0 for y in b)
    return sorted((min(p), max(p)) for p in pairs)


def _options(pycolmap):
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 1  # one thread: with more, image ids follow completion order (not deterministic)
    extraction.max_image_size = MAX_FEATURE_IMAGE_SIZE
    extraction.use_gpu = False
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1  # one thread: with more, the matches differ now and then when the cores are busy
    matching.use_gpu = False
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = SEED
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.random_seed = SEED
    mapping.num_threads = 1  # one thread: with more, the result depends on thread timing
    mapping.mapper.random_seed = SEED
    mapping.mapper.num_threads = 1
    mapping.triangulation.random_seed = SEED
    return extraction, matching, verification, mapping


def _rigid(r) -> np.ndarray:
    m = np.eye(4)
    m[:3, :4] = np.asarray(r.matrix(), dtype=np.float64)
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return m


def _refine(pycolmap, rec) -> None:
    """Final bundle adjustment: robust (Cauchy) passes that drop observations off by more than
    :data:`REFINE_MAX_ERRORS` pixels, then a plain least-squares pass (halves the camera-centre error on
    low-resolution photos compared with the mapper's own last adjustment)."""
    for max_error in REFINE_MAX_ERRORS:
        opts = pycolmap.BundleAdjustmentOptions()
        opts.print_summary = False
        opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        opts.ceres.loss_function_scale = 0.5
        opts.ceres.solver_options.num_threads = 1
        with silenced_stderr():  # bundle_adjustment logs at INFO level regardless of minloglevel
            pycolmap.bundle_adjustment(rec, opts)
        pycolmap.ObservationManager(rec).filter_all_points3D(max_error, 1.5)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.print_summary = False
    opts.ceres.solver_options.num_threads = 1
    with silenced_stderr():
        pycolmap.bundle_adjustment(rec, opts)


def run_sfm(
    capture: PhotoCapture,
    work: str | Path,
    *,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    min_registered: float = MIN_REGISTERED,
) -> SfmResult:
    """Reconstruct the cameras of both states of ``capture`` jointly; ``work`` is an empty scratch folder.

    Raises :class:`SfmError` naming the photos that did not register when a state has fewer than
    ``min_registered`` of its photos in the largest reconstruction.
    """
    import time

    import pycolmap

    say = log or (lambda _m: None)
    work = Path(work)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    image_dir, mask_dir, names = _prepare(capture, work, progress)
    timings["prepare_s"] = time.perf_counter() - t0
    sizes = {capture.size(s) for s in PHOTO_STATES}
    mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.PER_FOLDER
    extraction, matching, verification, mapping = _options(pycolmap)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = CAMERA_MODEL
    reader.mask_path = str(mask_dir)
    db = work / "database.db"
    pycolmap.set_random_seed(SEED)
    with quiet_colmap():
        t = time.perf_counter()
        say(f"features: {len(names)} photos")
        pycolmap.extract_features(
            db,
            image_dir,
            image_names=names,
            camera_mode=mode,
            reader_options=reader,
            extraction_options=extraction,
            device=pycolmap.Device.cpu,
        )
        timings["features_s"] = time.perf_counter() - t
        t = time.perf_counter()
        if capture.sequences:
            pairs = sequence_pairs(capture)
            pair_file = work / "pairs.txt"
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs), encoding="utf-8")
            say(f"matching: {len(pairs)} pairs (video frames: neighbours in time, and across the states)")
            pycolmap.match_image_pairs(
                db,
                matching_options=matching,
                pairing_options=pycolmap.ImportedPairingOptions(match_list_path=pair_file),
                verification_options=verification,
                device=pycolmap.Device.cpu,
            )
        else:
            say(f"matching: {len(names) * (len(names) - 1) // 2} pairs (exhaustive)")
            pycolmap.match_exhaustive(
                db, matching_options=matching, verification_options=verification, device=pycolmap.Device.cpu
            )
        timings["matching_s"] = time.perf_counter() - t
        t = time.perf_counter()
        (work / "sparse").mkdir(exist_ok=True)
        with tqdm(
            total=len(names), desc="dsg-capture: registering", unit="photo", disable=not progress
        ) as bar:
            recs = pycolmap.incremental_mapping(
                db, image_dir, work / "sparse", options=mapping, next_image_callback=lambda: bar.update(1)
            )
        timings["mapping_s"] = time.perf_counter() - t
        if not recs:
            check_registration(capture, set(), min_registered)
            raise SfmError(f"{capture.root}: structure from motion found no reconstruction")
        rec = max(recs.values(), key=lambda r: (r.num_reg_images(), -min(r.reg_image_ids(), default=0)))
        t = time.perf_counter()
        _refine(pycolmap, rec)
        timings["refine_s"] = time.perf_counter() - t
    w2c: dict[str, np.ndarray] = {}
    cams: dict[str, StateCamera] = {}
    for img in rec.images.values():
        if not img.has_pose:
            continue
        key = img.name.removesuffix(".png")
        w2c[key] = _rigid(img.cam_from_world())
        cam = rec.cameras[img.camera_id]
        state = key.split("/", 1)[0]
        cams.setdefault(
            state,
            StateCamera(cam.model_name, tuple(float(x) for x in cam.params), int(cam.width), int(cam.height)),
        )
    unregistered = check_registration(capture, set(w2c), min_registered)
    ids = sorted(rec.points3D)
    pts = np.array([rec.points3D[i].xyz for i in ids], dtype=np.float64).reshape(-1, 3)
    errs = np.array([rec.points3D[i].error for i in ids], dtype=np.float64)
    registered = {s: tuple(v.stem for v in capture.states[s] if v.key in w2c) for s in PHOTO_STATES}
    say(
        f"registered {sum(len(r) for r in registered.values())} of {len(names)} photos, {len(ids)} points, "
        f"mean reprojection error {rec.compute_mean_reprojection_error():.3f} px"
    )
    return SfmResult(
        world_to_camera=dict(sorted(w2c.items())),
        cameras=cams,
        points=pts,
        point_errors=errs,
        mean_reprojection_error=float(rec.compute_mean_reprojection_error()),
        registered=registered,
        unregistered=unregistered,
        timings=timings,
    )
