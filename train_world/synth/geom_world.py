"""A geometry world: a :class:`~dsg_gym.world_model.WorldModel` built directly from a synthetic scene.

No training involved: Gaussians are laid out on the surfaces of the MuJoCo geoms of a ``dsg-synth`` scene
(boxes, spheres, cylinders, capsules, convex meshes and the floor plane, using MuJoCo's compiled geometry),
as thin discs tangent to the surface with a spacing chosen per kind of geom. Their colours are *baked* from
MuJoCo's own renders (so textures and the static lighting are MuJoCo's): every Gaussian takes the
cosine-weighted mean colour of the pixels it lands on in the views where it is visible (depth test); the
background is baked with the objects moved out of sight (so the table under them has its texture), the
objects in both captured states. Gaussians seen in no view take their geom's mean baked colour (or its
material colour). Background faces that face away from every bake camera (the outside of the walls, the
underside of the table) are dropped.

The world's states, cameras and table bounds are those ``dsg-synth`` writes for the same scene and seed, so a
geometry world is the ideal reconstruction of that capture: a stand-in for a trained world, and the reference
for the "splat render matches MuJoCo's render" test.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from dsg_gym.cameras import Cameras, intrinsics_from_fov  # noqa: E402
from dsg_gym.gaussians import GaussianSet  # noqa: E402
from dsg_gym.poses import rotmat_to_quat  # noqa: E402
from dsg_gym.world_model import TableBounds, WorldModel  # noqa: E402
from train_world.synth.build import build_scene, set_object_poses  # noqa: E402
from train_world.synth.cameras import orbit_c2w  # noqa: E402
from train_world.synth.generate import GenerateConfig, rng_for  # noqa: E402
from train_world.synth.render import SceneRenderer  # noqa: E402
from train_world.synth.spec import SceneSpec, resolve_scene  # noqa: E402
from train_world.synth.states import sample_states  # noqa: E402

__all__ = ["GeomWorldConfig", "build_geom_world", "capture_cameras", "opengl_to_viewmat"]

_G = mujoco.mjtGeom
_BOX, _SPHERE, _CYL, _CAPSULE, _MESH, _PLANE = (
    int(_G.mjGEOM_BOX), int(_G.mjGEOM_SPHERE), int(_G.mjGEOM_CYLINDER), int(_G.mjGEOM_CAPSULE),
    int(_G.mjGEOM_MESH), int(_G.mjGEOM_PLANE),
)  # fmt: skip


@dataclass(frozen=True)
class GeomWorldConfig:
    """Gaussian spacing (metres) per kind of geom, scaled by ``1 / detail``; bake renders' size and count.

    ``seed`` selects the states and cameras exactly as ``dsg-synth --seed`` does; ``width``/``height`` are
    the capture cameras' image size.
    """

    seed: int = 0
    detail: float = 1.0
    object_spacing: float = 0.005
    surface_spacing: float = 0.006
    prop_spacing: float = 0.008
    leg_spacing: float = 0.015
    floor_spacing: float = 0.035
    wall_spacing: float = 0.05
    bake_size: int = 160
    bake_views: int = 24
    width: int = 128
    height: int = 128
    opacity: float = 0.95
    radius_factor: float = 0.7
    thickness_factor: float = 0.15


# --------------------------------------------------------------------------------------------- sampling
def _grid(n0: int, n1: int, jitter: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    u = (np.arange(n0) + 0.5) / n0
    v = (np.arange(n1) + 0.5) / n1
    uu, vv = np.meshgrid(u, v, indexing="ij")
    return uu.ravel(), vv.ravel()


def _fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def _sunflower_disk(n: int, radius: float) -> np.ndarray:
    i = np.arange(n) + 0.5
    r = radius * np.sqrt(i / n)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.zeros(n)], axis=1)


def _box(half: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    pts, nrm = [], []
    for ax in range(3):
        a, b = [i for i in range(3) if i != ax]
        na, nb = max(1, int(np.ceil(2 * half[a] / s))), max(1, int(np.ceil(2 * half[b] / s)))
        u, v = _grid(na, nb)
        for sign in (-1.0, 1.0):
            p = np.zeros((u.size, 3))
            p[:, a] = (2 * u - 1) * half[a]
            p[:, b] = (2 * v - 1) * half[b]
            p[:, ax] = sign * half[ax]
            n = np.zeros_like(p)
            n[:, ax] = sign
            pts.append(p)
            nrm.append(n)
    return np.concatenate(pts), np.concatenate(nrm)


def _cylinder_side(r: float, h: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    na, nh = max(8, int(np.ceil(2 * np.pi * r / s))), max(1, int(np.ceil(2 * h / s)))
    u, v = _grid(na, nh)
    ang = 2 * np.pi * u
    n = np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], axis=1)
    p = n * r
    p[:, 2] = (2 * v - 1) * h
    return p, n


def _caps(r: float, h: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    d = _sunflower_disk(max(4, int(np.ceil(np.pi * r * r / (s * s)))), r)
    top, bot = d + [0, 0, h], d - [0, 0, h]
    n = np.zeros((2 * len(d), 3))
    n[: len(d), 2], n[len(d) :, 2] = 1.0, -1.0
    return np.concatenate([top, bot]), n


def _mesh(model: mujoco.MjModel, mid: int, s: float, rng: np.random.Generator):
    v0, nv = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
    f0, nf = model.mesh_faceadr[mid], model.mesh_facenum[mid]
    verts = model.mesh_vert[v0 : v0 + nv].astype(np.float64)
    tri = verts[model.mesh_face[f0 : f0 + nf]]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    cr = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(cr, axis=1)
    normal = cr / np.maximum(2 * area[:, None], 1e-12)
    centre = verts.mean(axis=0)
    flip = np.sum((tri.mean(axis=1) - centre) * normal, axis=1) < 0  # outward normals
    normal[flip] *= -1
    counts = np.floor(area / (s * s) + rng.random(nf)).astype(np.int64)
    pts, nrm = [], []
    for t in range(nf):
        c = max(int(counts[t]), 1)
        a, b = rng.random(c), rng.random(c)
        fold = a + b > 1
        a[fold], b[fold] = 1 - a[fold], 1 - b[fold]
        pts.append(tri[t, 0] + a[:, None] * e1[t] + b[:, None] * e2[t])
        nrm.append(np.repeat(normal[t][None], c, axis=0))
    return np.concatenate(pts), np.concatenate(nrm)


def _geom_surface(model, g: int, s: float, rng, plane_half: tuple[float, float]):
    """Points and outward normals on geom ``g``'s surface, in the geom frame, about ``s`` apart."""
    t, size = int(model.geom_type[g]), model.geom_size[g]
    if t == _BOX:
        return _box(size[:3].astype(np.float64), s)
    if t == _SPHERE:
        n = _fibonacci_sphere(max(12, int(np.ceil(4 * np.pi * size[0] ** 2 / s**2))))
        return n * size[0], n
    if t in (_CYL, _CAPSULE):
        r, h = float(size[0]), float(size[1])
        p, n = _cylinder_side(r, h, s)
        if t == _CYL:
            pc, nc = _caps(r, h, s)
        else:
            nc = _fibonacci_sphere(max(12, int(np.ceil(4 * np.pi * r * r / s**2))))
            pc = nc * r + np.where(nc[:, 2:3] >= 0, 1.0, -1.0) * np.array([0.0, 0.0, h])
        return np.concatenate([p, pc]), np.concatenate([n, nc])
    if t == _MESH:
        return _mesh(model, int(model.geom_dataid[g]), s, rng)
    if t == _PLANE:
        hx, hy = plane_half
        u, v = _grid(int(np.ceil(2 * hx / s)), int(np.ceil(2 * hy / s)))
        p = np.stack([(2 * u - 1) * hx, (2 * v - 1) * hy, np.zeros_like(u)], axis=1)
        return p, np.tile([0.0, 0.0, 1.0], (len(p), 1))
    raise ValueError(f"geom {model.geom(g).name!r}: unsupported geom type {int(t)}")


def _spacing(name: str, cfg: GeomWorldConfig) -> float:
    if name.startswith("geom:"):
        s = cfg.object_spacing
    elif name == "surface":
        s = cfg.surface_spacing
    elif name.startswith("prop:"):
        s = cfg.prop_spacing
    elif name == "floor":
        s = cfg.floor_spacing
    elif name.startswith("wall:"):
        s = cfg.wall_spacing
    else:
        s = cfg.leg_spacing
    return s / cfg.detail


def _frames(normals: np.ndarray) -> np.ndarray:
    """Rotations [N,3,3] whose third column is ``normals``."""
    helper = np.where(np.abs(normals[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(helper, normals)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return np.stack([t1, t2, normals], axis=2)


# --------------------------------------------------------------------------------------------- cameras
def opengl_to_viewmat(c2w_gl: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world ``[...,4,4]`` -> OpenCV world-to-camera viewmats (float64)."""
    c2w = np.asarray(c2w_gl, dtype=np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])
    return np.linalg.inv(c2w)


def capture_cameras(scene: SceneSpec, seed: int, state: str, n: int, width: int, height: int):
    """The OpenGL camera-to-world poses ``dsg-synth`` uses for ``state`` (``"test"`` for the test orbit),
    first ``n`` of its default count, and their :class:`Cameras`."""
    gc = GenerateConfig()
    if state == "test":
        c2w = orbit_c2w(scene.cameras.test, gc.test_views, rng_for(seed, "cameras/test"))
    else:
        phase = rng_for(seed, f"phase/{state}").uniform(0, 360)
        c2w = orbit_c2w(scene.cameras.train, gc.views, rng_for(seed, f"cameras/{state}"), phase)
    idx = np.linspace(0, len(c2w), n, endpoint=False).astype(int)
    c2w = c2w[idx]
    k = intrinsics_from_fov(scene.cameras.fovy_deg, width, height)
    return c2w, Cameras(opengl_to_viewmat(c2w), np.repeat(k[None], len(c2w), 0), width, height)


# --------------------------------------------------------------------------------------------- baking
class _Baker:
    def __init__(self, built, cfg: GeomWorldConfig, c2ws: np.ndarray):
        self.built, self.cfg = built, cfg
        self.data = mujoco.MjData(built.model)
        self.renderer = SceneRenderer(built, cfg.bake_size, cfg.bake_size)
        self.c2ws = c2ws
        fx, fy, cx, cy = self.renderer.intrinsics()
        self.k = (fx, fy, cx, cy)

    def bake(self, poses: np.ndarray, pts: np.ndarray, nrm: np.ndarray, acc: np.ndarray, wsum: np.ndarray):
        """Accumulate cosine-weighted colours of world points ``pts`` over all bake views with objects at
        ``poses``."""
        set_object_poses(self.built, self.data, poses)
        fx, fy, cx, cy = self.k
        size = self.cfg.bake_size
        for c2w in self.c2ws:
            rgb, _, depth = self.renderer.render(self.data, c2w, rgb=True, seg=True, depth=True)
            vm = opengl_to_viewmat(c2w)
            pc = pts @ vm[:3, :3].T + vm[:3, 3]
            z = pc[:, 2]
            ok = z > 0.02
            zs = np.where(ok, z, 1.0)
            u = np.floor(fx * pc[:, 0] / zs + cx).astype(np.int64)
            v = np.floor(fy * pc[:, 1] / zs + cy).astype(np.int64)
            ok &= (u >= 0) & (u < size) & (v >= 0) & (v < size)
            eye = c2w[:3, 3]
            view = eye - pts
            cos = np.sum(view * nrm, axis=1) / np.linalg.norm(view, axis=1)
            ok &= cos > 0.05
            uu, vv = np.where(ok, u, 0), np.where(ok, v, 0)
            d = depth[vv, uu]
            ok &= np.abs(d - z) < 0.004 + 0.01 * z
            w = np.where(ok, cos, 0.0)
            acc += w[:, None] * rgb[vv, uu].astype(np.float64) / 255.0
            wsum += w

    def facing_any(self, pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        out = np.zeros(len(pts), dtype=bool)
        for c2w in self.c2ws:
            out |= np.sum((c2w[:3, 3] - pts) * nrm, axis=1) > 0
        return out

    def close(self) -> None:
        self.renderer.close()


def _material_rgb(model, g: int) -> np.ndarray:
    mid = model.geom_matid[g]
    rgba = model.mat_rgba[mid] if mid >= 0 else model.geom_rgba[g]
    return np.asarray(rgba[:3], dtype=np.float64)


def build_geom_world(
    scene: SceneSpec | str = "two_blocks", config: GeomWorldConfig | None = None
) -> WorldModel:
    """Build the geometry world of ``scene`` (a spec, a default scene name or a JSON path); see the module
    docstring. Deterministic for a given config (and MuJoCo / GL driver)."""
    cfg = GeomWorldConfig() if config is None else config
    if cfg.detail <= 0 or cfg.bake_views < 1 or cfg.bake_size < 16:
        raise ValueError(f"GeomWorldConfig: bad values {cfg}")
    spec = resolve_scene(scene) if isinstance(scene, str) else scene
    built = build_scene(spec, max(cfg.bake_size, cfg.width), max(cfg.bake_size, cfg.height))
    model = built.model
    states = sample_states(spec, rng_for(cfg.seed, "states"), GenerateConfig().test_states)
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 0x6E0]))
    c_train, _ = capture_cameras(spec, cfg.seed, "state1", cfg.bake_views, cfg.width, cfg.height)
    c_test, _ = capture_cameras(spec, cfg.seed, "test", max(cfg.bake_views // 2, 1), cfg.width, cfg.height)
    c_train2, _ = capture_cameras(spec, cfg.seed, "state2", cfg.bake_views, cfg.width, cfg.height)
    baker = _Baker(built, cfg, np.concatenate([c_train, c_train2, c_test]))
    half = (2.0, 2.0)
    if spec.walls:  # the floor ends at the walls
        half = (
            max(abs(w.center[0]) for w in spec.walls) or 2.0,
            max(abs(w.center[1]) for w in spec.walls) or 2.0,
        )
    data = mujoco.MjData(model)
    set_object_poses(built, data, states["state1"])
    per_obj: dict[int, list] = {k: [] for k in range(1, built.num_objects + 1)}
    bg: list = []
    for g in range(model.ngeom):
        name = model.geom(g).name
        p, n = _geom_surface(model, g, _spacing(name, cfg), rng, half)
        rot = data.geom_xmat[g].reshape(3, 3)
        pw, nw = p @ rot.T + data.geom_xpos[g], n @ rot.T
        obj = int(built.geom_object_ids[g])
        item = (g, pw, nw, _spacing(name, cfg))
        (per_obj[obj] if obj else bg).append(item)
    # background: objects out of sight; one bake pass over all its points
    away = np.repeat(np.eye(4)[None], built.num_objects, 0)
    away[:, :3, 3] = np.array([50.0, 50.0, -50.0]) + 2.0 * np.arange(built.num_objects)[:, None]
    bg = [(g, pw[m], nw[m], s) for g, pw, nw, s in bg for m in [baker.facing_any(pw, nw)] if m.any()]
    bg_sets = _bake_sets(baker, model, bg, cfg, [(away, None)], 0)
    background = GaussianSet.concat(bg_sets)
    objects = []
    p1 = states["state1"]
    for k in range(1, built.num_objects + 1):
        # baked in both captured states (points moved rigidly from state1), then put in the object frame
        views = [(states[st], states[st][k - 1] @ np.linalg.inv(p1[k - 1])) for st in ("state1", "state2")]
        parts = _bake_sets(baker, model, per_obj[k], cfg, views, k)
        local = np.linalg.inv(p1[k - 1])
        objects.append(GaussianSet.concat([_moved(gs, local) for gs in parts]))
    baker.close()
    _, cams = capture_cameras(spec, cfg.seed, "state1", GenerateConfig().views, cfg.width, cfg.height)
    (x0, x1), (y0, y1) = spec.table_bounds
    table = TableBounds(x0, x1, y0, y1, 0.0)
    return WorldModel(
        background=background,
        objects=tuple(objects),
        object_names=tuple(o.name for o in spec.objects),
        table=table,
        cameras=cams,
        states={k: v for k, v in states.items()},
        metadata={
            "source": "geom_world",
            "scene": spec.name,
            "seed": int(cfg.seed),
            "detail": float(cfg.detail),
            "table": {"bounds": [[x0, y0, 0.0], [x1, y1, 0.0]], "top_z": 0.0},
        },
        name=f"geom:{spec.name}",
    )


def _bake_sets(baker: _Baker, model, items, cfg: GeomWorldConfig, views, label: int) -> list[GaussianSet]:
    """Bake the points of ``items`` [(geom, points, normals, spacing)] with objects at each ``views`` entry's
    poses (points moved by its rigid transform, if any) and make one GaussianSet per geom."""
    pts = np.concatenate([it[1] for it in items])
    nrm = np.concatenate([it[2] for it in items])
    acc, ws = np.zeros((len(pts), 3)), np.zeros(len(pts))
    for poses, rel in views:
        if rel is None:
            baker.bake(poses, pts, nrm, acc, ws)
        else:
            baker.bake(poses, pts @ rel[:3, :3].T + rel[:3, 3], nrm @ rel[:3, :3].T, acc, ws)
    out, i = [], 0
    for g, p, n, s in items:
        j = i + len(p)
        out.append(_gaussians(model, g, p, n, s, acc[i:j], ws[i:j], cfg, label))
        i = j
    return out


def _moved(gs: GaussianSet, m: np.ndarray) -> GaussianSet:
    from dsg_gym.poses import matrix_to_pose7
    from dsg_gym.world_model import transform_gaussians

    return transform_gaussians(gs, matrix_to_pose7(m))


def _gaussians(model, g, pts, nrm, s, acc, ws, cfg: GeomWorldConfig, label: int) -> GaussianSet:
    seen = ws > 0
    rgb = np.empty((len(pts), 3))
    rgb[seen] = acc[seen] / ws[seen, None]
    fallback = rgb[seen].mean(axis=0) if seen.any() else _material_rgb(model, g)
    rgb[~seen] = fallback
    quats = rotmat_to_quat(_frames(nrm))
    r = cfg.radius_factor * s
    scales = np.tile([r, r, cfg.thickness_factor * r], (len(pts), 1))
    return GaussianSet.from_rgb(
        pts,
        quats,
        scales,
        np.full(len(pts), cfg.opacity),
        np.clip(rgb, 0, 1),
        labels=np.full(len(pts), label),
    )


def to_world(model: WorldModel):
    """The :class:`dsg_gym.world.World` of a geometry world (for :func:`dsg_gym.world.write_world`):
    no identity features, so the classifier is empty (``[K+1, 0]``)."""
    from types import MappingProxyType

    from dsg_gym.world import World, WorldObject

    k = model.num_objects
    cams = model.cameras
    objects = {
        oid: WorldObject(n, g) for oid, n, g in zip(model.object_ids, model.object_names, model.objects)
    }
    return World(
        background=model.background,
        objects=MappingProxyType(objects),
        poses=MappingProxyType({s: np.asarray(p, dtype=np.float64) for s, p in model.states.items()}),
        cameras=MappingProxyType(
            {
                "state1": Cameras(
                    cams.viewmats.astype(np.float32), cams.Ks.astype(np.float32), cams.width, cams.height
                )
            }
        ),
        classifier_weight=np.zeros((k + 1, 0), np.float32),
        classifier_bias=np.zeros(k + 1, np.float32),
        metadata=MappingProxyType({**model.metadata, "reference_state": "state1", "name": model.name}),
        units="metres",
    )
