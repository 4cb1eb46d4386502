"""What a phone would give for a synthetic scene: a photo capture plus its ground truth (``dsg-synth --as-photos``).

::

    OUT/state1/images/NNNN.jpg     RGB as JPEG (quality 92 by default), optionally blurred and noisy
    OUT/state1/masks/NNNN.png      uint8 object ids (0 = background), the same ids in every view and state
    OUT/state2/...                 the same for the second state
    OUT/objects.json               [{"id": 1, "name": ...}, ...]
    OUT/ground_truth/              the full synthetic capture (scene.json, cameras, poses, depth, test states)

The photo folder is what ``dsg-capture`` reads (:mod:`train_world.capture.photos`); ``ground_truth/`` is what
its estimates are measured against. Everything is deterministic for a given seed.

Photos may be larger than the ground truth (``scale``), as a phone's photos are larger than the size a world
trains at: the same states and camera poses are rendered ``scale`` times as wide and high, with
``supersample // scale`` samples per photo pixel along each axis (at least one), so that a photo downscaled by
``scale`` (``dsg-train --downscale``) integrates over the same sensor area as a ground-truth pixel.
"""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
import zlib
from pathlib import Path

import numpy as np
from PIL import Image, ImageFilter

from train_world.capture.format import atomic_write_bytes, atomic_write_json, staged_directory
from train_world.synth.generate import GenerateConfig, generate_scene
from train_world.synth.spec import SceneSpec, resolve_scene

__all__ = ["PHOTO_STATES", "degrade_photo", "generate_photo_capture", "write_photos_from_capture"]

#: the states a photo capture holds (the two training states of the synthetic capture)
PHOTO_STATES = ("state1", "state2")
#: Gaussian blur radius (pixels) applied together with sensor noise
NOISE_BLUR_RADIUS = 0.5


def degrade_photo(
    rgb: np.ndarray, noise: float, rng: np.random.Generator, exposure: float = 0.0
) -> np.ndarray:
    """What a phone adds to ``rgb`` (uint8 ``[H,W,3]``): an exposure gain drawn uniformly from
    ``[1 - exposure, 1 + exposure]`` (auto-exposure differing from photo to photo), then a slight blur and
    Gaussian sensor noise of ``noise`` grey levels (standard deviation on the 0..255 scale). With ``noise <= 0``
    and ``exposure <= 0`` it returns ``rgb`` unchanged."""
    if noise <= 0 and exposure <= 0:
        return rgb
    a = rgb.astype(np.float64)
    if exposure > 0:
        a = a * rng.uniform(1.0 - exposure, 1.0 + exposure)
    if noise > 0:
        blurred = Image.fromarray(np.clip(np.rint(a), 0, 255).astype(np.uint8)).filter(
            ImageFilter.GaussianBlur(NOISE_BLUR_RADIUS)
        )
        a = np.asarray(blurred, dtype=np.float64) + rng.normal(0.0, float(noise), size=rgb.shape)
    return np.clip(np.rint(a), 0, 255).astype(np.uint8)


def _jpeg(rgb: np.ndarray, quality: int) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=int(quality), subsampling=0, optimize=False)
    return buf.getvalue()


def write_photos_from_capture(
    capture: str | os.PathLike,
    out: str | os.PathLike,
    *,
    quality: int = 92,
    noise: float = 0.0,
    exposure: float = 0.0,
    seed: int = 0,
) -> None:
    """Write the photo-capture layout of the module docstring under ``out`` from the synthetic capture
    folder ``capture`` (its ``state1`` and ``state2``): JPEG images, mask PNGs copied, ``objects.json``."""
    if not 1 <= int(quality) <= 100:
        raise ValueError(f"JPEG quality must be in 1..100, got {quality}")
    if noise < 0:
        raise ValueError(f"photo noise must be >= 0 grey levels, got {noise}")
    if not 0 <= exposure < 1:
        raise ValueError(f"photo exposure jitter must be in [0, 1), got {exposure}")
    capture, out = Path(capture), Path(out)
    scene = json.loads((capture / "scene.json").read_text(encoding="utf-8"))
    for state in PHOTO_STATES:
        doc = json.loads((capture / state / "transforms.json").read_text(encoding="utf-8"))
        for fr in doc["frames"]:
            src = capture / state / fr["file_path"]
            stem = Path(fr["file_path"]).stem
            rgb = np.asarray(Image.open(src).convert("RGB"))
            label = f"{int(seed) & 0xFFFFFFFF}/{state}/{stem}".encode()
            rng = np.random.default_rng(zlib.crc32(label))
            atomic_write_bytes(
                out / state / "images" / f"{stem}.jpg",
                _jpeg(degrade_photo(rgb, noise, rng, exposure), quality),
            )
            atomic_write_bytes(
                out / state / "masks" / f"{stem}.png", (capture / state / fr["mask_path"]).read_bytes()
            )
    atomic_write_json(out / "objects.json", [{"id": o["id"], "name": o["name"]} for o in scene["objects"]])


def generate_photo_capture(
    scene: SceneSpec | str,
    out: str | os.PathLike,
    config: GenerateConfig | None = None,
    *,
    overwrite: bool = False,
    quality: int = 92,
    noise: float = 0.0,
    exposure: float = 0.0,
    scale: int = 1,
) -> Path:
    """Render ``scene`` into ``out/ground_truth`` and write its photo capture beside it, atomically (the
    whole of ``out`` appears only when complete). ``scale``: the photos' size over the ground truth's (an
    integer >= 1; see the module docstring)."""
    if isinstance(scene, str):
        scene = resolve_scene(scene)
    cfg = GenerateConfig() if config is None else config
    if not (isinstance(scale, int) and not isinstance(scale, bool) and 1 <= scale <= 16):
        raise ValueError(f"the photos' scale must be an integer in 1..16, got {scale!r}")
    out = Path(out)
    with staged_directory(out, overwrite=overwrite) as stage:
        generate_scene(scene, stage / "ground_truth", cfg)
        source = stage / "ground_truth"
        if scale > 1:
            source = stage / ".photo_source"
            big = dataclasses.replace(
                cfg,
                width=cfg.width * scale,
                height=cfg.height * scale,
                supersample=max(1, cfg.supersample // scale),
            )
            generate_scene(scene, source, big)
            _check_same_views(stage / "ground_truth", source, scale)
        write_photos_from_capture(
            source, stage, quality=quality, noise=noise, exposure=exposure, seed=cfg.seed
        )
        if scale > 1:
            shutil.rmtree(source)
    return out


def _check_same_views(truth: Path, photos: Path, scale: int) -> None:
    """The larger render must show the ground truth's states from its cameras: the same object poses and
    camera poses, intrinsics ``scale`` times the ground truth's. Raises ``RuntimeError`` otherwise."""
    a = json.loads((truth / "scene.json").read_text(encoding="utf-8"))
    b = json.loads((photos / "scene.json").read_text(encoding="utf-8"))
    for state in PHOTO_STATES:
        ta = json.loads((truth / state / "transforms.json").read_text(encoding="utf-8"))
        tb = json.loads((photos / state / "transforms.json").read_text(encoding="utf-8"))
        same = len(ta["frames"]) == len(tb["frames"]) and all(
            fa["file_path"] == fb["file_path"]
            and np.allclose(fa["transform_matrix"], fb["transform_matrix"], atol=1e-12)
            for fa, fb in zip(ta["frames"], tb["frames"])
        )
        same = same and all(
            np.isclose(float(tb[k]), scale * float(ta[k]), rtol=1e-9) for k in ("fl_x", "fl_y", "cx", "cy")
        )
        if not same:
            raise RuntimeError(f"photos at {scale}x do not show {state} from the ground truth's cameras")
    if any(a["states"][state] != b["states"][state] for state in PHOTO_STATES):
        raise RuntimeError(f"photos at {scale}x do not show the ground truth's object poses")
