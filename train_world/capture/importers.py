"""``dsg-import``: bring real captures into the capture layout of :mod:`train_world.capture` as one state.

* ``dsg-import llff DIR --out OUT [--factor 8] [--threshold 127]``: an LLFF capture (``poses_bounds.npy``,
  ``images[_F]/``, optional ``masks[_F]/`` with one grey mask per image, matched by file stem).
* ``dsg-import transforms DIR --out OUT [--masks MASKDIR] [--threshold 127]``: a COLMAP-posed capture already
  processed to a nerfstudio ``transforms.json`` (masks from the frames' ``mask_path`` or from ``--masks``).

Masks are thresholded (``value > threshold``) into object id 1; ``scene.json`` gets one object ``object`` with
an identity pose and one state ``state1`` whose units are those of the source (COLMAP scale, not metres).

LLFF conventions: ``poses_bounds.npy`` is ``[N, 17]``; row ``i`` belongs to the ``i``-th image in **sorted**
filename order and holds a 3x5 matrix ``[R | t | hwf]`` (camera-to-world, columns of ``R`` are the camera's
down, right and backward axes) then near/far bounds. ``hwf`` is height, width, focal at full resolution; the
focal is scaled by (image width / full width). OpenGL axes are right, up, back: ``[r1, -r0, r2]``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from train_world.capture.cameras import check_rigid
from train_world.capture.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    atomic_write_bytes,
    atomic_write_json,
    encode_png,
    frame_entry,
    matrix_to_list,
    staged_directory,
    transforms_header,
)
from train_world.capture.loader import CaptureError

__all__ = ["import_llff", "import_transforms", "llff_to_opengl_c2w"]

IMAGE_EXTS = (".png", ".jpg", ".jpeg")
_INTRINSIC_KEYS = (
    "camera_model",
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
    "camera_angle_x",
    "camera_angle_y",
)


def llff_to_opengl_c2w(poses: np.ndarray) -> np.ndarray:
    """LLFF ``[N,3,4]`` (or ``[N,3,5]``) camera-to-world with ``[down, right, back]`` axes -> ``[N,4,4]``
    OpenGL camera-to-world (``[right, up, back]``)."""
    p = np.asarray(poses, dtype=np.float64)
    out = np.tile(np.eye(4), (p.shape[0], 1, 1))
    out[:, :3, 0] = p[:, :3, 1]
    out[:, :3, 1] = -p[:, :3, 0]
    out[:, :3, 2] = p[:, :3, 2]
    out[:, :3, 3] = p[:, :3, 3]
    return out


def _rigid(mat: np.ndarray, what: str) -> np.ndarray:
    try:
        return check_rigid(mat, what)
    except ValueError as e:
        raise CaptureError(str(e)) from e


def _list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise CaptureError(f"{folder}: image folder not found")
    files = sorted(
        p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTS and not p.name.startswith(".")
    )
    if not files:
        raise CaptureError(f"{folder}: no images ({', '.join(IMAGE_EXTS)})")
    return files


def _rgb(path: Path) -> np.ndarray:
    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"))
    except Exception as e:
        raise CaptureError(f"{path}: cannot read image ({e})") from e


def _binary_mask(path: Path, size: tuple[int, int], image: Path, threshold: int) -> np.ndarray:
    try:
        with Image.open(path) as im:
            if im.size != size:
                raise CaptureError(
                    f"{path}: mask is {im.width}x{im.height} but image {image.name} is "
                    f"{size[0]}x{size[1]} (image/mask size mismatch)"
                )
            grey = np.asarray(im.convert("L"))
    except CaptureError:
        raise
    except Exception as e:
        raise CaptureError(f"{path}: cannot read mask ({e})") from e
    return (grey > threshold).astype(np.uint8)


def _find_mask(folder: Path, stem: str) -> Path:
    for ext in (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG"):
        p = folder / f"{stem}{ext}"
        if p.is_file():
            return p
    raise CaptureError(f"{folder}: no mask for image {stem!r} (expected {stem}.png or .jpg)")


def _write_capture(
    out: Path,
    name: str,
    source: dict,
    header: dict,
    frames: list[tuple[str, Path, np.ndarray, np.ndarray | None, dict]],
    overwrite: bool,
) -> Path:
    """frames: (stem, source image, c2w_gl, mask or None, extra frame keys)."""
    with staged_directory(out, overwrite=overwrite) as stage:
        st = stage / "state1"
        entries = []
        for stem, img_path, c2w, mask, extra in frames:
            img_rel = f"images/{stem}.png"
            atomic_write_bytes(st / img_rel, encode_png(_rgb(img_path)))
            mask_rel = None
            if mask is not None:
                mask_rel = f"masks/{stem}.png"
                atomic_write_bytes(st / mask_rel, encode_png(mask))
            entry = frame_entry(img_rel, c2w, mask_rel)
            entry.update(extra)
            entries.append(entry)
        atomic_write_json(st / "transforms.json", {**header, "frames": entries})
        atomic_write_json(
            stage / "scene.json",
            {
                "format": FORMAT_NAME,
                "format_version": FORMAT_VERSION,
                "name": name,
                "units": "source units (COLMAP/LLFF scale, not metres)",
                "source": source,
                "objects": [{"id": 1, "name": "object"}],
                "states": {
                    "state1": {
                        "split": "train",
                        "num_views": len(entries),
                        "object_poses": [{"id": 1, "pose": matrix_to_list(np.eye(4))}],
                    }
                },
            },
        )
    return out


def import_llff(
    src: str | Path,
    out: str | Path,
    factor: int = 8,
    threshold: int = 127,
    masks: bool = True,
    overwrite: bool = False,
) -> Path:
    """Convert an LLFF capture at ``src`` (``images_{factor}``/``masks_{factor}``; factor 1 = ``images``) to
    our layout at ``out``. Returns ``out``."""
    src = Path(src)
    suffix = f"_{factor}" if factor > 1 else ""
    pb_path = src / "poses_bounds.npy"
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except FileNotFoundError as e:
        raise CaptureError(f"{pb_path}: file not found") from e
    except (OSError, ValueError) as e:
        raise CaptureError(f"{pb_path}: cannot read ({e})") from e
    if pb.ndim != 2 or pb.shape[1] != 17:
        raise CaptureError(f"{pb_path}: expected shape [N, 17], got {pb.shape}")
    if not np.all(np.isfinite(pb)):
        raise CaptureError(f"{pb_path}: non-finite values")
    images = _list_images(src / f"images{suffix}")
    if len(images) != pb.shape[0]:
        raise CaptureError(
            f"{pb_path}: camera count mismatch: {pb.shape[0]} poses but {len(images)} images in "
            f"{src / f'images{suffix}'}"
        )
    poses = pb[:, :15].reshape(-1, 3, 5)
    c2w = llff_to_opengl_c2w(poses)
    for i in range(len(c2w)):
        _rigid(c2w[i], f"{pb_path}: row {i} ({images[i].name})")
    hh, ww, ff = poses[0, :, 4]
    if not np.allclose(poses[:, :, 4], poses[:1, :, 4]):
        raise CaptureError(f"{pb_path}: images have different hwf; only one camera is supported")
    with Image.open(images[0]) as im:
        w, h = im.size
    for p in images[1:]:
        with Image.open(p) as im:
            if im.size != (w, h):
                raise CaptureError(f"{p}: image is {im.width}x{im.height} but {images[0].name} is {w}x{h}")
    sx, sy = w / ww, h / hh
    if abs(sx - sy) > 0.01 * max(sx, sy):
        raise CaptureError(
            f"{images[0]}: image size {w}x{h} is not a uniform scaling of the poses' {int(ww)}x{int(hh)}"
        )
    f = float(ff) * sx
    mask_dir = src / f"masks{suffix}"
    use_masks = masks and mask_dir.is_dir()
    frames = []
    for i, img in enumerate(images):
        m = _binary_mask(_find_mask(mask_dir, img.stem), (w, h), img, threshold) if use_masks else None
        frames.append((img.stem, img, c2w[i], m, {"near_far": [float(pb[i, 15]), float(pb[i, 16])]}))
    header = transforms_header(w, h, f, f, w / 2.0, h / 2.0)
    header.pop("depth_unit_scale_factor")
    source = {
        "kind": "llff",
        "folder": src.name,
        "factor": int(factor),
        "threshold": int(threshold),
        "full_resolution_hwf": [float(hh), float(ww), float(ff)],
    }
    return _write_capture(Path(out), src.name, source, header, frames, overwrite)


def import_transforms(
    src: str | Path,
    out: str | Path,
    masks_dir: str | Path | None = None,
    threshold: int = 127,
    overwrite: bool = False,
) -> Path:
    """Convert a capture described by ``src/transforms.json`` (nerfstudio / COLMAP-processed; camera-to-world
    OpenGL ``transform_matrix``) into our layout at ``out``."""
    src = Path(src)
    tj = src / "transforms.json" if src.is_dir() else src
    base = tj.parent
    from train_world.capture.files import read_json

    meta = read_json(tj)
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise CaptureError(f"{tj}: expected an object with a non-empty 'frames' list")
    header = {k: meta[k] for k in _INTRINSIC_KEYS if k in meta}
    frames = []
    seen = set()
    for i, fr in enumerate(meta["frames"]):
        where = f"{tj}: frames[{i}]"
        if not isinstance(fr, dict) or "file_path" not in fr or "transform_matrix" not in fr:
            raise CaptureError(f"{where}: needs 'file_path' and 'transform_matrix'")
        img = base / fr["file_path"]
        if not img.suffix and not img.exists():
            img = img.with_name(img.name + ".png")
        if not img.is_file():
            raise CaptureError(f"{img}: image file not found ({where})")
        try:
            mat = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (TypeError, ValueError) as e:
            raise CaptureError(f"{where}.transform_matrix: not a 4x4 matrix of numbers ({e})") from e
        c2w = _rigid(mat, f"{where}.transform_matrix")
        stem = img.stem if img.stem not in seen else f"{i:05d}_{img.stem}"
        seen.add(stem)
        with Image.open(img) as im:
            size = im.size
        mask = None
        if "mask_path" in fr:
            mask = _binary_mask(base / fr["mask_path"], size, img, threshold)
        elif masks_dir is not None:
            mask = _binary_mask(_find_mask(Path(masks_dir), img.stem), size, img, threshold)
        extra = {k: fr[k] for k in _INTRINSIC_KEYS if k in fr}
        frames.append((stem, img, c2w, mask, extra))
    n_masks = sum(f[3] is not None for f in frames)
    if 0 < n_masks < len(frames):
        raise CaptureError(f"{tj}: {n_masks} of {len(frames)} frames have masks; all or none must")
    source = {"kind": "transforms", "folder": base.name, "threshold": int(threshold)}
    return _write_capture(Path(out), base.name, source, header, frames, overwrite)
