"""Reading a photo capture: two states of a real tabletop as plain images plus object-id masks.

::

    PHOTOS/state1/images/<stem>.jpg|.jpeg|.png   the photos of the first state (any size, all the same size)
    PHOTOS/state1/masks/<stem>.png               uint8 object ids per pixel: 0 = background, 1..255 objects
    PHOTOS/state2/...                            the same for the second state
    PHOTOS/objects.json                          optional names: [{"id": 1, "name": "mug"}, ...] or {"1": "mug"}

A state may start as one video (``PHOTOS/state1/walk.mp4``): ``dsg-capture --extract-frames N`` samples it to
``images/`` plus ``frames.json`` (:mod:`train_world.capture.video`); masks are then made for those frames.

Every object id must mean the same object in every view of both states, and every object must appear in
both states. :func:`read_photo_capture` checks the whole folder (every image and mask is decoded once) and
raises :class:`PhotoCaptureError` naming the offending file and what to do; :func:`load_photo` gives one
view's pixels with the photo's EXIF orientation applied.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageOps

from train_world.capture.loader import CaptureError, ObjectInfo

__all__ = [
    "FRAMES_FILE",
    "IMAGE_SUFFIXES",
    "MIN_VIEWS",
    "PHOTO_STATES",
    "PhotoCapture",
    "PhotoCaptureError",
    "PhotoView",
    "VIDEO_SUFFIXES",
    "load_photo",
    "read_photo_capture",
]

PHOTO_STATES = ("state1", "state2")
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
#: a state folder may hold one video of these instead of images/ (:mod:`train_world.capture.video`)
VIDEO_SUFFIXES = (".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm")
#: written beside images/ when the images are a video's frames (:mod:`train_world.capture.video`)
FRAMES_FILE = "frames.json"
#: fewest photos per state that structure from motion can work with
MIN_VIEWS = 3


class PhotoCaptureError(CaptureError):
    """Bad photo-capture input; the message names the file or object and the fix."""


@dataclass(frozen=True)
class PhotoView:
    """One photo: its state, file stem, image and mask paths, and its size after EXIF orientation."""

    state: str
    stem: str
    image_path: Path
    mask_path: Path
    width: int
    height: int

    @property
    def key(self) -> str:
        """``"<state>/<stem>"``, unique within a capture."""
        return f"{self.state}/{self.stem}"


@dataclass(frozen=True)
class PhotoCapture:
    """A checked photo capture: views per state (sorted by stem) and the objects seen in both states."""

    root: Path
    states: dict[str, tuple[PhotoView, ...]]
    objects: tuple[ObjectInfo, ...]
    #: states whose images are frames of a video, in order (their folder has ``frames.json``)
    sequences: frozenset[str] = frozenset()

    def views(self) -> tuple[PhotoView, ...]:
        """All views, state by state."""
        return tuple(v for s in PHOTO_STATES for v in self.states[s])

    def size(self, state: str) -> tuple[int, int]:
        """(width, height) of the photos of ``state``."""
        v = self.states[state][0]
        return v.width, v.height


def _open(path: Path, what: str) -> Image.Image:
    try:
        img = Image.open(path)
        img.load()
    except Exception as e:  # Pillow raises many types for corrupt files
        raise PhotoCaptureError(
            f"{path}: cannot decode this {what} ({e}); re-export it as a JPEG or PNG or remove it "
            "(with its mask)"
        ) from e
    return img


def _rgb(img: Image.Image) -> np.ndarray:
    img = ImageOps.exif_transpose(img)
    if img.mode in ("I;16", "I;16B", "I", "F"):
        a = np.asarray(img, dtype=np.float64)
        a = a / max(float(a.max(initial=0.0)), 1.0) * 255.0
        img = Image.fromarray(np.clip(np.rint(a), 0, 255).astype(np.uint8))
    return np.ascontiguousarray(np.asarray(img.convert("RGB"), dtype=np.uint8))


def _ids(img: Image.Image, path: Path) -> np.ndarray:
    if img.mode in ("L", "P"):
        return np.asarray(img if img.mode == "L" else Image.fromarray(np.asarray(img)), dtype=np.uint8)
    if img.mode == "1":
        return np.asarray(img, dtype=np.uint8)
    if img.mode in ("I", "I;16", "I;16B"):
        a = np.asarray(img)
        if a.min(initial=0) < 0 or a.max(initial=0) > 255:
            raise PhotoCaptureError(f"{path}: mask ids must be in 0..255; save the mask as an 8-bit grey PNG")
        return a.astype(np.uint8)
    if img.mode in ("RGB", "RGBA"):
        a = np.asarray(img)
        if np.array_equal(a[..., 0], a[..., 1]) and np.array_equal(a[..., 0], a[..., 2]):
            return np.ascontiguousarray(a[..., 0])
    raise PhotoCaptureError(
        f"{path}: mask has mode {img.mode}; save it as a one-channel 8-bit PNG of object ids (0 = background)"
    )


def load_photo(view: PhotoView) -> tuple[np.ndarray, np.ndarray]:
    """``(rgb uint8 [H,W,3], ids uint8 [H,W])`` of one view (EXIF orientation applied to the photo)."""
    rgb = _rgb(_open(view.image_path, "image"))
    ids = _ids(_open(view.mask_path, "mask"), view.mask_path)
    return rgb, ids


def _files(folder: Path, suffixes: tuple[str, ...], what: str) -> dict[str, Path]:
    out: dict[str, Path] = {}
    for p in sorted(folder.iterdir()):
        if not p.is_file() or p.name.startswith(".") or p.suffix.lower() not in suffixes:
            continue
        if p.stem in out:
            raise PhotoCaptureError(
                f"{p}: two {what} files share the stem {p.stem!r} ({out[p.stem].name}, {p.name}); keep one"
            )
        out[p.stem] = p
    return out


def _folder(path: Path, fix: str) -> Path:
    if not path.is_dir():
        raise PhotoCaptureError(f"{path}: folder not found; {fix}")
    return path


def _list_names(stems: list[str], folder: Path, suffix: str) -> str:
    shown = ", ".join(str(folder / f"{s}{suffix}") for s in stems[:3])
    return shown + (f" and {len(stems) - 3} more" if len(stems) > 3 else "")


def _state_views(root: Path, state: str) -> tuple[tuple[PhotoView, ...], dict[int, Path]]:
    sdir = _folder(root / state, f"a photo capture needs {PHOTO_STATES[0]}/ and {PHOTO_STATES[1]}/ folders")
    if not (sdir / "images").is_dir():
        videos = sorted(p.name for p in sdir.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
        if videos:
            raise PhotoCaptureError(
                f"{sdir}: holds a video ({videos[0]}) but no images/; sample it to frames first "
                f"(dsg-capture --extract-frames 40 {root}), then make masks/ for those frames"
            )
    idir = _folder(sdir / "images", "put this state's photos (JPEG or PNG) there")
    mdir = _folder(sdir / "masks", "put one object-id mask PNG per photo there, with the photo's file stem")
    images = _files(idir, IMAGE_SUFFIXES, "image")
    masks = _files(mdir, (".png",), "mask")
    if len(images) < MIN_VIEWS:
        raise PhotoCaptureError(
            f"{idir}: {len(images)} photos; structure from motion needs at least {MIN_VIEWS} per state "
            "(about 40 around the table works well)"
        )
    no_mask = sorted(set(images) - set(masks))
    no_image = sorted(set(masks) - set(images))
    if no_mask or no_image:
        counts = f"{len(images)} images but {len(masks)} masks"
        if no_mask:
            raise PhotoCaptureError(
                f"{_list_names(no_mask, mdir, '.png')}: missing ({counts} in {sdir}); every photo needs a mask "
                "PNG with the same file stem"
            )
        raise PhotoCaptureError(
            f"{_list_names(no_image, mdir, '.png')}: mask without a photo ({counts} in {sdir}); remove it or "
            "add the photo with the same file stem"
        )
    views, first_seen = [], {}
    size = None
    for stem, ipath in images.items():
        img = _open(ipath, "image")
        rgb = _rgb(img)
        h, w = rgb.shape[:2]
        mpath = masks[stem]
        ids = _ids(_open(mpath, "mask"), mpath)
        if ids.shape != (h, w):
            raise PhotoCaptureError(
                f"{mpath}: mask is {ids.shape[1]}x{ids.shape[0]} but its photo {ipath.name} is {w}x{h} "
                "(after EXIF rotation); make the mask from the photo as displayed, at the same size"
            )
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise PhotoCaptureError(
                f"{ipath}: photo is {w}x{h} but the other photos of {state} are {size[0]}x{size[1]}; "
                "take one state's photos with one camera setting, or crop/resize them to one size"
            )
        for k in np.unique(ids).tolist():
            if k and k not in first_seen:
                first_seen[int(k)] = mpath
        views.append(PhotoView(state, stem, ipath, mpath, w, h))
    return tuple(views), first_seen


def _read_names(path: Path) -> dict[int, str]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PhotoCaptureError(
            f'{path}: cannot read ({e}); expected [{{"id": 1, "name": "mug"}}, ...]'
        ) from e
    items = doc.get("objects", doc) if isinstance(doc, dict) and "objects" in doc else doc
    pairs = []
    if isinstance(items, dict):
        pairs = list(items.items())
    elif isinstance(items, list):
        for i, o in enumerate(items):
            if not isinstance(o, dict) or "id" not in o or "name" not in o:
                raise PhotoCaptureError(
                    f'{path}: entry {i} needs \'id\' and \'name\', e.g. {{"id": 1, "name": "mug"}}'
                )
            pairs.append((o["id"], o["name"]))
    else:
        raise PhotoCaptureError(f"{path}: expected a list of {{id, name}} or a mapping id -> name")
    names: dict[int, str] = {}
    for k, name in pairs:
        try:
            oid = int(k)
        except (TypeError, ValueError):
            raise PhotoCaptureError(f"{path}: object id {k!r} is not an integer in 1..255") from None
        if not 1 <= oid <= 255 or isinstance(k, bool):
            raise PhotoCaptureError(f"{path}: object id {k!r} is outside 1..255 (0 is the background)")
        if not isinstance(name, str) or not name:
            raise PhotoCaptureError(f"{path}: object {oid} needs a non-empty string name")
        if oid in names:
            raise PhotoCaptureError(f"{path}: object id {oid} is listed twice")
        names[oid] = name
    if len(set(names.values())) != len(names):
        raise PhotoCaptureError(f"{path}: object names must be unique")
    return names


def read_photo_capture(root: str | Path) -> PhotoCapture:
    """Check the photo capture folder ``root`` (module docstring) and list its views and objects."""
    root = Path(root)
    if not root.is_dir():
        raise PhotoCaptureError(f"{root}: folder not found; pass the folder holding state1/ and state2/")
    states, seen = {}, {}
    for s in PHOTO_STATES:
        states[s], seen[s] = _state_views(root, s)
    a, b = PHOTO_STATES
    for only, other in ((a, b), (b, a)):
        missing = sorted(set(seen[only]) - set(seen[other]))
        if missing:
            k = missing[0]
            raise PhotoCaptureError(
                f"{seen[only][k]}: object id {k} appears in {only} but in no mask of {other}; ids must mean the "
                f"same object in both states and every object must be seen in both (fix the ids in the masks of "
                f"{other}, or set id {k} to 0 in {only} if that object is not one of the moved objects)"
            )
    ids = sorted(seen[a])
    if not ids:
        raise PhotoCaptureError(
            f"{root / a / 'masks'}: no object ids in any mask (all 0); mark the objects 1..K"
        )
    names = {k: f"object_{k}" for k in ids}
    npath = root / "objects.json"
    if npath.is_file():
        given = _read_names(npath)
        unnamed = [k for k in ids if k not in given]
        if unnamed:
            raise PhotoCaptureError(
                f"{npath}: no name for object id {unnamed[0]} (seen in {seen[a][unnamed[0]]}); list every id "
                "that appears in the masks"
            )
        unseen = sorted(set(given) - set(ids))
        if unseen:
            raise PhotoCaptureError(
                f"{npath}: object {unseen[0]} ({given[unseen[0]]!r}) appears in no mask; remove it from "
                "objects.json or mark it in the masks of both states"
            )
        names = {k: given[k] for k in ids}
    objects = tuple(ObjectInfo(k, names[k]) for k in ids)
    seq = frozenset(st for st in PHOTO_STATES if (root / st / FRAMES_FILE).is_file())
    return PhotoCapture(root=root, states=states, objects=objects, sequences=seq)
