"""Scene descriptions for ``dsg-synth``: frozen dataclasses parsed from small JSON files.

The seven default scenes live in ``assets/scenes/*.json``. Lengths are metres, angles degrees, colours RGB(A)
in [0,1]. The resting surface's top is the plane ``z = 0`` of the world; ``+z`` is up. A scene file looks
like::

    {"name": "...", "description": "...", "texture_seed": 3,
     "surface": {"kind": "table" | "floor", "size": [0.8, 0.6], "height": 0.74,
                 "texture": {"cells": [32, 24], "color1": [...], "color2": [...], "noise": 0.3}},
     "floor": {"color1": [...], "color2": [...], "cells": 8},
     "walls": [{"name": "back", "center": [x, y, z], "extents": [dx, dy, dz], "rgba": [...]}],
     "props": [{"name": "vase", "shape": {...}, "position": [x, y], "on": "table" | "floor", "yaw_deg": 0}],
     "objects": [{"name": "red_box", "shape": {"type": "box", "extents": [0.06, 0.05, 0.07]},
                  "rgba": [...], "pattern": "stripes", "color2": [...], "cells": 3, "rest": "upright"}],
     "lights": [{"pos": [...], "dir": [...], "diffuse": [...], "directional": true}],
     "cameras": {"fovy_deg": 50, "train": {orbit}, "test": {orbit}},
     "placement": {"edge_margin": 0.03, "gap": 0.012, "visibility_margin": 0.01, "raster_cell": 0.004}}

Shapes: ``box`` (``extents``: full size), ``cylinder`` and ``capsule`` (``radius``, ``height``: full length
tip to tip), ``sphere`` (``radius``), ``mesh`` with ``mesh`` one of ``prism`` / ``frustum`` (``sides``,
``radius``, ``top_radius``, ``height``) or ``gem`` (``radius``, ``height``, ``sides`` random hull points,
``seed``). Objects ``rest`` ``upright`` (their z axis up) or on their ``side`` (rotated 90 degrees about x).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields
from pathlib import Path

from dsg_gym.assets import scene_names, scenes_dir
from train_world.synth import spec_values as check
from train_world.synth.spec_values import SpecError
from train_world.synth.textures import PATTERNS

__all__ = [
    "Appearance",
    "CameraSpec",
    "LightSpec",
    "ObjectSpec",
    "OrbitSpec",
    "PlacementSpec",
    "PropSpec",
    "SceneSpec",
    "Shape",
    "SurfaceSpec",
    "WallSpec",
    "default_scene_names",
    "default_scenes_dir",
    "load_scene_spec",
    "resolve_scene",
]

SHAPE_TYPES = ("box", "cylinder", "sphere", "capsule", "mesh")
MESH_KINDS = ("prism", "frustum", "gem")
RESTS = ("upright", "side")


@dataclass(frozen=True)
class Shape:
    """Geometry of one rigid part, centred on its frame origin (see module docstring for the fields used)."""

    type: str
    extents: tuple[float, float, float] = (0.0, 0.0, 0.0)
    radius: float = 0.0
    height: float = 0.0
    top_radius: float = 0.0
    sides: int = 0
    mesh: str = ""
    seed: int = 0


@dataclass(frozen=True)
class Appearance:
    """Base colour and an optional two-colour pattern (see :data:`textures.PATTERNS`)."""

    rgba: tuple[float, float, float, float] = (0.7, 0.7, 0.7, 1.0)
    pattern: str = "solid"
    color2: tuple[float, float, float] = (1.0, 1.0, 1.0)
    cells: int = 4


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    shape: Shape
    appearance: Appearance
    rest: str = "upright"


@dataclass(frozen=True)
class PropSpec:
    """A static background prop standing on the surface (``on="table"``) or on the floor."""

    name: str
    shape: Shape
    appearance: Appearance
    position: tuple[float, float] = (0.0, 0.0)
    yaw_deg: float = 0.0
    on: str = "floor"
    rest: str = "upright"


@dataclass(frozen=True)
class WallSpec:
    name: str
    center: tuple[float, float, float]
    extents: tuple[float, float, float]
    appearance: Appearance


@dataclass(frozen=True)
class LightSpec:
    pos: tuple[float, float, float]
    dir: tuple[float, float, float]
    diffuse: tuple[float, float, float] = (0.6, 0.6, 0.6)
    directional: bool = True


@dataclass(frozen=True)
class SurfaceSpec:
    kind: str = "table"
    size: tuple[float, float] = (0.8, 0.6)
    height: float = 0.74
    thickness: float = 0.03
    cells: tuple[int, int] = (32, 24)
    color1: tuple[float, float, float] = (0.78, 0.66, 0.50)
    color2: tuple[float, float, float] = (0.36, 0.27, 0.18)
    noise: float = 0.3


@dataclass(frozen=True)
class FloorSpec:
    color1: tuple[float, float, float] = (0.45, 0.45, 0.48)
    color2: tuple[float, float, float] = (0.30, 0.30, 0.33)
    cells: int = 10


@dataclass(frozen=True)
class OrbitSpec:
    """A handheld-looking orbit: mean radius/elevation plus smooth random wobble (angles in degrees)."""

    radius: float = 0.8
    radius_wobble: float = 0.05
    elevation_deg: float = 40.0
    elevation_wobble_deg: float = 6.0
    azimuth_offset_deg: float = 0.0
    azimuth_span_deg: float = 360.0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    target_jitter: float = 0.02
    roll_wobble_deg: float = 2.0


@dataclass(frozen=True)
class CameraSpec:
    fovy_deg: float = 55.0
    train: OrbitSpec = OrbitSpec()
    #: held-out cameras from the capture's own distribution (the training band, azimuths interleaved with
    #: the training views'); generator 1.0 used a higher orbit (57 deg), which mostly measured walls and
    #: floor that no training view saw: set ``"test": {"elevation_deg": 57}`` for that variant
    test: OrbitSpec = OrbitSpec(
        radius=0.8, radius_wobble=0.03, elevation_deg=40.0, elevation_wobble_deg=4.0, azimuth_offset_deg=17.0
    )


@dataclass(frozen=True)
class PlacementSpec:
    """``edge_margin``: keep-out band inside the surface edge; ``gap``: minimum distance between footprints in
    one state; ``visibility_margin``: minimum distance between footprints of the two training states;
    ``raster_cell``: cell size of the footprint rasters."""

    edge_margin: float = 0.05
    gap: float = 0.012
    visibility_margin: float = 0.01
    raster_cell: float = 0.004
    max_tries: int = 400


@dataclass(frozen=True)
class SceneSpec:
    name: str
    objects: tuple[ObjectSpec, ...]
    description: str = ""
    texture_seed: int = 0
    surface: SurfaceSpec = SurfaceSpec()
    floor: FloorSpec = FloorSpec()
    walls: tuple[WallSpec, ...] = ()
    props: tuple[PropSpec, ...] = ()
    lights: tuple[LightSpec, ...] = ()
    cameras: CameraSpec = CameraSpec()
    placement: PlacementSpec = field(default_factory=PlacementSpec)
    source: str = ""

    @property
    def table_bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """((xmin, xmax), (ymin, ymax)) of the resting surface's top (at z = 0)."""
        sx, sy = self.surface.size
        return ((-sx / 2, sx / 2), (-sy / 2, sy / 2))


# ----------------------------------------------------------------------------------------------- parsing
def _shape(d: dict, src: str, where: str) -> Shape:
    check.check_keys(d, {f.name for f in fields(Shape)}, src, where)
    t = d.get("type")
    if t not in SHAPE_TYPES:
        raise check.fail(src, f"{where}.type", f"expected one of {SHAPE_TYPES}, got {t!r}")
    kw: dict = {"type": t}
    need = {
        "box": ("extents",),
        "sphere": ("radius",),
        "cylinder": ("radius", "height"),
        "capsule": ("radius", "height"),
        "mesh": ("mesh", "radius", "height"),
    }[t]
    for k in need:
        if k not in d:
            raise check.fail(src, where, f"shape {t!r} needs {k!r}")
    if "extents" in d:
        ext = check.floats(d["extents"], 3, src, f"{where}.extents")
        if min(ext) <= 0:
            raise check.fail(src, f"{where}.extents", "must be positive")
        kw["extents"] = ext
    for k in ("radius", "height"):
        if k in d:
            kw[k] = check.positive(d[k], src, f"{where}.{k}")
    if "top_radius" in d:
        if not isinstance(d["top_radius"], int | float) or d["top_radius"] < 0:
            raise check.fail(src, f"{where}.top_radius", "expected a number >= 0")
        kw["top_radius"] = float(d["top_radius"])
    for k in ("sides", "seed"):
        if k in d:
            if not isinstance(d[k], int):
                raise check.fail(src, f"{where}.{k}", f"expected an integer, got {d[k]!r}")
            kw[k] = d[k]
    if t == "capsule" and kw["height"] < 2 * kw["radius"]:
        raise check.fail(src, where, "capsule height (tip to tip) must be at least 2 * radius")
    if t == "mesh":
        if d["mesh"] not in MESH_KINDS:
            raise check.fail(src, f"{where}.mesh", f"expected one of {MESH_KINDS}, got {d['mesh']!r}")
        kw["mesh"] = d["mesh"]
        kw.setdefault("sides", 6 if d["mesh"] != "gem" else 14)
        if kw["sides"] < 3:
            raise check.fail(src, f"{where}.sides", "needs at least 3")
    return Shape(**kw)


def _appearance(d: dict, src: str, where: str) -> Appearance:
    kw: dict = {}
    if "rgba" in d:
        kw["rgba"] = check.rgba(d["rgba"], src, f"{where}.rgba")
    if "pattern" in d:
        if d["pattern"] not in PATTERNS:
            raise check.fail(src, f"{where}.pattern", f"expected one of {PATTERNS}, got {d['pattern']!r}")
        kw["pattern"] = d["pattern"]
    if "color2" in d:
        kw["color2"] = check.floats(d["color2"], 3, src, f"{where}.color2")
    if "cells" in d:
        if not isinstance(d["cells"], int) or d["cells"] < 1:
            raise check.fail(src, f"{where}.cells", "expected a positive integer")
        kw["cells"] = d["cells"]
    return Appearance(**kw)


_APPEARANCE_KEYS = ("rgba", "pattern", "color2", "cells")


def _rest(v, src, where) -> str:
    if v not in RESTS:
        raise check.fail(src, where, f"expected one of {RESTS}, got {v!r}")
    return v


def _object(d: dict, src: str, where: str) -> ObjectSpec:
    check.check_keys(d, ("name", "shape", "rest", *_APPEARANCE_KEYS), src, where)
    if not isinstance(d.get("name"), str) or not d["name"]:
        raise check.fail(src, f"{where}.name", "expected a non-empty string")
    return ObjectSpec(
        name=d["name"],
        shape=_shape(d.get("shape"), src, f"{where}.shape"),
        appearance=_appearance(d, src, where),
        rest=_rest(d.get("rest", "upright"), src, where),
    )


def _prop(d: dict, src: str, where: str) -> PropSpec:
    check.check_keys(d, ("name", "shape", "rest", "position", "yaw_deg", "on", *_APPEARANCE_KEYS), src, where)
    on = d.get("on", "floor")
    if on not in ("table", "floor"):
        raise check.fail(src, f"{where}.on", f"expected 'table' or 'floor', got {on!r}")
    return PropSpec(
        name=str(d.get("name", where)),
        shape=_shape(d.get("shape"), src, f"{where}.shape"),
        appearance=_appearance(d, src, where),
        rest=_rest(d.get("rest", "upright"), src, where),
        position=check.floats(d.get("position", [0, 0]), 2, src, f"{where}.position"),
        yaw_deg=float(d.get("yaw_deg", 0.0)),
        on=on,
    )


def _wall(d: dict, src: str, where: str) -> WallSpec:
    check.check_keys(d, ("name", "center", "extents", *_APPEARANCE_KEYS), src, where)
    return WallSpec(
        name=str(d.get("name", where)),
        center=check.floats(d.get("center"), 3, src, f"{where}.center"),
        extents=check.floats(d.get("extents"), 3, src, f"{where}.extents"),
        appearance=_appearance(d, src, where),
    )


def _light(d: dict, src: str, where: str) -> LightSpec:
    return check.flat(
        LightSpec,
        d,
        src,
        where,
        {
            "pos": lambda v, s, w: check.floats(v, 3, s, w),
            "dir": lambda v, s, w: check.floats(v, 3, s, w),
            "diffuse": lambda v, s, w: check.floats(v, 3, s, w),
            "directional": lambda v, s, w: bool(v),
        },
    )


def _orbit(d: dict, src: str, where: str, base: OrbitSpec) -> OrbitSpec:
    conv = {f.name: check.number for f in fields(OrbitSpec)}
    conv["target"] = lambda v, s, w: check.floats(v, 3, s, w)
    o = check.flat(lambda **kw: kw, d, src, where, conv)
    merged = {f.name: getattr(base, f.name) for f in fields(OrbitSpec)} | o
    if merged["radius"] <= 0:
        raise check.fail(src, f"{where}.radius", "must be positive")
    return OrbitSpec(**merged)


def _cameras(d: dict, src: str, where: str) -> CameraSpec:
    check.check_keys(d, ("fovy_deg", "train", "test"), src, where)
    base = CameraSpec()
    fovy = float(d.get("fovy_deg", base.fovy_deg))
    if not 5.0 < fovy < 150.0:
        raise check.fail(src, f"{where}.fovy_deg", f"expected 5..150 degrees, got {fovy}")
    return CameraSpec(
        fovy_deg=fovy,
        train=_orbit(d.get("train", {}), src, f"{where}.train", base.train),
        test=_orbit(d.get("test", {}), src, f"{where}.test", base.test),
    )


def _surface(d: dict, src: str, where: str) -> SurfaceSpec:
    check.check_keys(d, ("kind", "size", "height", "thickness", "texture"), src, where)
    kw: dict = {}
    if "kind" in d:
        if d["kind"] not in ("table", "floor"):
            raise check.fail(src, f"{where}.kind", f"expected 'table' or 'floor', got {d['kind']!r}")
        kw["kind"] = d["kind"]
    if "size" in d:
        kw["size"] = check.floats(d["size"], 2, src, f"{where}.size")
    for k in ("height", "thickness"):
        if k in d:
            kw[k] = check.positive(d[k], src, f"{where}.{k}")
    tex = d.get("texture", {})
    check.check_keys(tex, ("cells", "color1", "color2", "noise"), src, f"{where}.texture")
    if "cells" in tex:
        kw["cells"] = tuple(int(c) for c in check.floats(tex["cells"], 2, src, f"{where}.texture.cells"))
    for k in ("color1", "color2"):
        if k in tex:
            kw[k] = check.floats(tex[k], 3, src, f"{where}.texture.{k}")
    if "noise" in tex:
        kw["noise"] = check.number(tex["noise"], src, f"{where}.texture.noise")
    return SurfaceSpec(**kw)


def scene_from_dict(d: dict, source: str = "<dict>") -> SceneSpec:
    """Parse and validate a scene description; errors are :class:`SpecError` naming ``source`` and the
    field."""
    top = (
        "name",
        "description",
        "texture_seed",
        "surface",
        "floor",
        "walls",
        "props",
        "objects",
        "lights",
        "cameras",
        "placement",
    )
    check.check_keys(d, top, source, "scene")
    name = d.get("name")
    if not isinstance(name, str) or not name:
        raise check.fail(source, "name", "expected a non-empty string")
    objs = d.get("objects")
    if not isinstance(objs, list) or not 1 <= len(objs) <= 255:
        raise check.fail(source, "objects", "expected a list of 1..255 objects")
    objects = tuple(_object(o, source, f"objects[{i}]") for i, o in enumerate(objs))
    names = [o.name for o in objects]
    if len(set(names)) != len(names):
        raise check.fail(source, "objects", f"object names must be unique, got {names}")
    floor = d.get("floor", {})
    check.check_keys(floor, ("color1", "color2", "cells"), source, "floor")
    floor_spec = FloorSpec(
        **{
            k: (check.floats(v, 3, source, f"floor.{k}") if k != "cells" else int(v))
            for k, v in floor.items()
        }
    )
    placement = check.flat(
        PlacementSpec,
        d.get("placement", {}),
        source,
        "placement",
        {
            f.name: (check.positive if f.name != "max_tries" else (lambda v, s, w: int(v)))
            for f in fields(PlacementSpec)
        },
    )
    return SceneSpec(
        name=name,
        objects=objects,
        description=str(d.get("description", "")),
        texture_seed=int(d.get("texture_seed", 0)),
        surface=_surface(d.get("surface", {}), source, "surface"),
        floor=floor_spec,
        walls=tuple(_wall(w, source, f"walls[{i}]") for i, w in enumerate(d.get("walls", []))),
        props=tuple(_prop(p, source, f"props[{i}]") for i, p in enumerate(d.get("props", []))),
        lights=tuple(_light(x, source, f"lights[{i}]") for i, x in enumerate(d.get("lights", []))),
        cameras=_cameras(d.get("cameras", {}), source, "cameras"),
        placement=placement,
        source=source,
    )


def load_scene_spec(path: str | Path) -> SceneSpec:
    """Read a scene description JSON file."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except OSError as e:
        raise SpecError(f"{path}: cannot read scene description ({e})") from e
    except json.JSONDecodeError as e:
        raise SpecError(f"{path}: invalid JSON ({e})") from e
    return scene_from_dict(data, str(path))


def default_scenes_dir() -> Path:
    """The default scene descriptions (the bundled ``assets/scenes``, :func:`dsg_gym.assets.scenes_dir`)."""
    return scenes_dir()


def default_scene_names() -> list[str]:
    """Names of the default scenes, sorted; :class:`SpecError` (one line, naming the folder) when there are
    none (an installation without its bundled assets)."""
    names = scene_names()
    if not names:
        raise SpecError(
            f"no default scene descriptions (*.json) in {default_scenes_dir()}; reinstall dsg-gym"
        )
    return names


def resolve_scene(name_or_path: str) -> SceneSpec:
    """A default scene by name, or a scene description file by path."""
    p = Path(name_or_path)
    if p.suffix == ".json" and p.exists():
        return load_scene_spec(p)
    cand = default_scenes_dir() / f"{name_or_path}.json"
    if not cand.exists():
        raise SpecError(f"unknown scene {name_or_path!r}; default scenes: {', '.join(default_scene_names())}")
    return load_scene_spec(cand)
