"""Build a MuJoCo model of a scene description with ``mujoco.MjSpec``.

World frame: +z up, the resting surface's top is ``z = 0`` and centred on the origin. Movable objects are
bodies with a free joint (``qpos`` = position then quaternion w,x,y,z) so that poses are set per state and
MuJoCo's collision detection can verify them; everything else (surface, floor, walls, props) is static
background with object id 0. Shadows are off unless asked for (the method does not relight).

Lighting (``lighting``): ``"soft"`` (default) lights mostly from the camera plus ambient, with weak
world-fixed key lights; ``"spot"`` has the strong world-fixed spot lights of generator 1.0. The camera light is
a point light at the camera centre (generator 1.3; :data:`CAMERA_LIGHT`, moved with the camera per view), so
the shading of a surface point depends only on where the camera is relative to it, i.e. on the viewing ray in
the surface's own frame: a view-dependent colour (SH of the ray direction) represents it exactly, for a static
surface and for a moved object alike. ``"headlight"`` is generator 1.2's ``soft``: the same strengths from
MuJoCo's directional headlight, which shines along the camera *axis*; a point off the image centre is then lit
by a direction that is not its viewing ray, and no function of the ray direction reproduces that across
cameras, and worlds trained on such captures lose accuracy on held-out views and test states.
World-fixed lights shade a moved or turned object differently, which the method does not model (DSG-World's
stated limitation): they cap the object-pixel PSNR even of a perfect world model, far lower for ``spot`` than
for ``soft`` (``python -m benchmarks.lighting_ceiling``; figures in docs/benchmarks.md).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from train_world.synth.shapes import geom_size, mesh_vertices, rest_rotation, resting_height, yaw_rotation  # noqa: E402
from train_world.synth.spec import Appearance, LightSpec, SceneSpec, Shape  # noqa: E402
from train_world.synth.textures import pattern_texture, surface_texture  # noqa: E402

__all__ = ["CAMERA_LIGHT", "LIGHTING", "RENDER_CAMERA", "BuiltScene", "build_scene", "set_object_poses"]

RENDER_CAMERA = "render_cam"
SURFACE_GEOM = "surface"
#: contact margin on the resting surface so resting contacts (distance ~0) are reported for verification
SURFACE_MARGIN = 0.002
DEFAULT_LIGHTS = (
    LightSpec(pos=(0.6, -0.8, 2.0), dir=(-0.3, 0.4, -1.0), diffuse=(0.55, 0.55, 0.55)),
    LightSpec(pos=(-0.8, 0.6, 2.0), dir=(0.4, -0.3, -1.0), diffuse=(0.3, 0.3, 0.32)),
)
#: lighting presets: (scale of the world-fixed lights' diffuse and specular, camera light diffuse, whether the
#: camera light is a point light at the camera centre (else MuJoCo's directional headlight))
LIGHTING = {"soft": (0.25, 0.75, True), "spot": (1.0, 0.35, True), "headlight": (0.25, 0.75, False)}
#: name of the point light that :class:`~train_world.synth.render.SceneRenderer` puts at the camera centre
CAMERA_LIGHT = "camera_light"
_GEOM_TYPES = {
    "box": mujoco.mjtGeom.mjGEOM_BOX,
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "mesh": mujoco.mjtGeom.mjGEOM_MESH,
}


@dataclass(frozen=True)
class BuiltScene:
    """A compiled scene. Object ``k`` (1-based id) is body ``object_body_ids[k-1]``; ``geom_object_ids[g]`` is
    the object id of geom ``g`` (0 for background geoms)."""

    spec: SceneSpec
    model: mujoco.MjModel
    object_body_ids: np.ndarray
    object_qpos_adr: np.ndarray
    geom_object_ids: np.ndarray
    surface_geom_id: int
    camera_id: int

    @property
    def num_objects(self) -> int:
        return len(self.object_body_ids)


def _quat(rot: np.ndarray) -> list[float]:
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(rot, dtype=np.float64).ravel())
    return q.tolist()


class _Builder:
    def __init__(self, spec: SceneSpec, width: int, height: int, shadows: bool, lighting: str):
        if lighting not in LIGHTING:
            raise ValueError(f"lighting must be one of {sorted(LIGHTING)}, got {lighting!r}")
        self.scene = spec
        self.shadows = shadows
        self.fixed_scale, head, point = LIGHTING[lighting]
        self.camera_light = head if point else 0.0
        self.ms = mujoco.MjSpec()
        self.ms.modelname = f"dsg_synth_{spec.name}"
        self._n_assets = 0
        vis = self.ms.visual
        vis.global_.offwidth = max(int(width), 64)
        vis.global_.offheight = max(int(height), 64)
        vis.headlight.ambient = [0.25, 0.25, 0.25]
        vis.headlight.diffuse = [0.0, 0.0, 0.0] if point else [head, head, head]
        vis.headlight.specular = [0.0, 0.0, 0.0]
        vis.quality.shadowsize = 2048
        vis.map.znear = 0.01
        vis.map.zfar = 50.0
        self.ms.stat.extent = 2.0
        self.ms.stat.center = [0.0, 0.0, 0.0]

    # ------------------------------------------------------------------ assets
    def _name(self, prefix: str) -> str:
        self._n_assets += 1
        return f"{prefix}{self._n_assets}"

    def texture_2d(self, data: np.ndarray) -> str:
        name = self._name("tex2d_")
        t = self.ms.add_texture(
            name=name,
            type=mujoco.mjtTexture.mjTEXTURE_2D,
            width=data.shape[1],
            height=data.shape[0],
            nchannel=3,
        )
        t.data = np.ascontiguousarray(data).tobytes()
        return name

    def material(self, app: Appearance, seed: int) -> str:
        name = self._name("mat_")
        mat = self.ms.add_material(name=name)
        mat.specular = 0.15
        mat.shininess = 0.2
        mat.reflectance = 0.0
        if app.pattern == "solid":
            mat.rgba = list(app.rgba)
            return name
        data = pattern_texture(app.pattern, app.rgba[:3], app.color2, 64, app.cells, seed)
        tname = self._name("texcube_")
        t = self.ms.add_texture(
            name=tname, type=mujoco.mjtTexture.mjTEXTURE_CUBE, width=64, height=64, nchannel=3
        )
        t.data = data.tobytes()
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = tname
        mat.rgba = [1.0, 1.0, 1.0, app.rgba[3]]
        return name

    def add_geom(self, parent, shape: Shape, material: str, name: str, pos=(0, 0, 0), rot=None):
        kw = {}
        if shape.type == "mesh":
            mname = self._name("mesh_")
            mesh = self.ms.add_mesh(name=mname)
            mesh.uservert = mesh_vertices(shape).ravel().tolist()
            kw["meshname"] = mname
        else:
            kw["size"] = geom_size(shape)
        g = parent.add_geom(name=name, type=_GEOM_TYPES[shape.type], pos=list(pos), material=material, **kw)
        if rot is not None:
            g.quat = _quat(rot)
        return g

    # ------------------------------------------------------------------ scene parts
    def marker(self, side: float) -> None:
        """An ArUco marker (``DICT_4X4_50`` id 0) of black-square edge ``side`` on a white card a quarter wider,
        flat on the table a quarter of the way in from its (+x, -y) corner; visual only (no contacts), background
        in the masks."""
        import cv2

        cells = 6  # 4x4 bits and the black border
        px = 16 * cells
        img = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 0, px)
        pad = px // 8
        card = np.pad(img, pad, constant_values=255)
        rgb = np.repeat(card[:, :, None], 3, axis=2)
        mat = self.ms.add_material(name="marker_mat")
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = self.texture_2d(np.ascontiguousarray(rgb))
        mat.specular = 0.0
        mat.shininess = 0.0
        half = side * card.shape[0] / px / 2
        (x0, x1), (y0, y1) = self.scene.table_bounds
        self.ms.worldbody.add_geom(
            name="aruco_marker",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[half, half, 0.0005],
            pos=[x1 - 0.25 * (x1 - x0), y0 + 0.25 * (y1 - y0), 0.0005],
            material="marker_mat",
            contype=0,
            conaffinity=0,
        )

    def surface(self) -> None:
        s = self.scene.surface
        sx, sy = s.size
        px_per_m = 640.0
        tex = surface_texture(
            self.scene.texture_seed,
            int(round(sx * px_per_m)),
            int(round(sy * px_per_m)),
            s.cells[0],
            s.cells[1],
            s.color1,
            s.color2,
            s.noise,
        )
        mat = self.ms.add_material(name="surface_mat")
        mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = self.texture_2d(tex)
        mat.texuniform = True
        mat.texrepeat = [1.0 / sx, 1.0 / sy]
        mat.specular = 0.1
        mat.shininess = 0.1
        wb = self.ms.worldbody
        thick = s.thickness if s.kind == "table" else 0.004
        wb.add_geom(
            name=SURFACE_GEOM,
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[sx / 2, sy / 2, thick / 2],
            pos=[0, 0, -thick / 2],
            material="surface_mat",
            margin=SURFACE_MARGIN,
        )
        floor_z = -s.height if s.kind == "table" else -thick
        if s.kind == "table":
            leg_mat = self.material(Appearance(rgba=(0.25, 0.18, 0.12, 1.0)), 0)
            leg_h = s.height - thick
            for ix, iy in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
                wb.add_geom(
                    name=f"table_leg_{ix}_{iy}".replace("-", "m"),
                    type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=[0.02, 0.02, leg_h / 2],
                    material=leg_mat,
                    pos=[ix * (sx / 2 - 0.05), iy * (sy / 2 - 0.05), -thick - leg_h / 2],
                )
        f = self.scene.floor
        ftex = surface_texture(
            self.scene.texture_seed + 1, 256, 256, f.cells, f.cells, f.color1, f.color2, 0.15
        )
        fmat = self.ms.add_material(name="floor_mat")
        fmat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = self.texture_2d(ftex)
        fmat.texuniform = True
        fmat.texrepeat = [0.5, 0.5]
        wb.add_geom(
            name="floor",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            size=[4.0, 4.0, 0.1],
            pos=[0, 0, floor_z],
            material="floor_mat",
        )
        self.floor_z = floor_z

    def walls(self) -> None:
        for i, w in enumerate(self.scene.walls):
            mat = self.material(w.appearance, self.scene.texture_seed + 100 + i)
            self.ms.worldbody.add_geom(
                name=f"wall:{w.name}",
                type=mujoco.mjtGeom.mjGEOM_BOX,
                size=[e / 2 for e in w.extents],
                pos=list(w.center),
                material=mat,
            )

    def props(self) -> None:
        for i, p in enumerate(self.scene.props):
            rot = yaw_rotation(np.deg2rad(p.yaw_deg)) @ rest_rotation(p.rest)
            z0 = 0.0 if p.on == "table" else self.floor_z
            pos = (p.position[0], p.position[1], z0 + resting_height(p.shape, rot))
            mat = self.material(p.appearance, self.scene.texture_seed + 200 + i)
            self.add_geom(self.ms.worldbody, p.shape, mat, f"prop:{p.name}", pos, rot)

    def objects(self) -> list[str]:
        names = []
        for i, o in enumerate(self.scene.objects):
            body_name = f"object:{o.name}"
            body = self.ms.worldbody.add_body(name=body_name, pos=[0.0, 0.0, 0.5 + 0.3 * i])
            body.add_freejoint(name=f"free:{o.name}")
            mat = self.material(o.appearance, self.scene.texture_seed + 300 + i)
            self.add_geom(body, o.shape, mat, f"geom:{o.name}")
            names.append(body_name)
        return names

    def lights(self) -> None:
        wb = self.ms.worldbody
        # placed at the camera for every view (SceneRenderer.set_camera); its shadows would fall out of its sight
        if self.camera_light:
            wb.add_light(
                name=CAMERA_LIGHT,
                pos=[0.0, -1.0, 1.0],
                dir=[0.0, 1.0, -1.0],
                diffuse=[self.camera_light] * 3,
                specular=[0.0] * 3,
                ambient=[0.0] * 3,
                castshadow=False,
                cutoff=180.0,
                exponent=0.0,
                attenuation=[1.0, 0.0, 0.0],
                type=mujoco.mjtLightType.mjLIGHT_SPOT,
            )
        specs = self.scene.lights or DEFAULT_LIGHTS
        for i, ls in enumerate(specs):
            wb.add_light(
                name=f"light{i}",
                pos=list(ls.pos),
                dir=list(ls.dir),
                diffuse=[self.fixed_scale * c for c in ls.diffuse],
                specular=[0.1 * self.fixed_scale] * 3,
                castshadow=bool(self.shadows),
                type=(
                    mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
                    if ls.directional
                    else mujoco.mjtLightType.mjLIGHT_SPOT
                ),
            )


def build_scene(
    spec: SceneSpec,
    width: int = 128,
    height: int = 128,
    shadows: bool = False,
    lighting: str = "soft",
    marker: float = 0.0,
) -> BuiltScene:
    """Compile ``spec`` into a MuJoCo model with one movable camera :data:`RENDER_CAMERA`.

    ``width``/``height`` size the offscreen buffer; ``shadows`` turns on cast shadows of every light;
    ``lighting`` is a key of :data:`LIGHTING` (see the module docstring); ``marker`` > 0 lays an ArUco marker
    of that side (metres) on the table (``_Builder.marker``).
    """
    b = _Builder(spec, width, height, shadows, lighting)
    b.surface()
    if marker > 0:
        b.marker(marker)
    b.walls()
    b.props()
    body_names = b.objects()
    b.lights()
    b.ms.worldbody.add_camera(name=RENDER_CAMERA, pos=[0, -1, 1], fovy=float(spec.cameras.fovy_deg))
    model = b.ms.compile()
    body_ids = np.array([model.body(n).id for n in body_names], dtype=np.int64)
    qadr = np.array([model.jnt_qposadr[model.body_jntadr[bid]] for bid in body_ids], dtype=np.int64)
    geom_obj = np.zeros(model.ngeom, dtype=np.uint8)
    for k, bid in enumerate(body_ids):
        geom_obj[model.geom_bodyid == bid] = k + 1
    return BuiltScene(
        spec=spec,
        model=model,
        object_body_ids=body_ids,
        object_qpos_adr=qadr,
        geom_object_ids=geom_obj,
        surface_geom_id=model.geom(SURFACE_GEOM).id,
        camera_id=model.camera(RENDER_CAMERA).id,
    )


def set_object_poses(built: BuiltScene, data: mujoco.MjData, poses: np.ndarray) -> None:
    """Put object ``k`` at world pose ``poses[k-1]`` (4x4) and run ``mj_forward`` (kinematics + contacts)."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (built.num_objects, 4, 4):
        raise ValueError(f"expected poses of shape ({built.num_objects}, 4, 4), got {poses.shape}")
    for k, adr in enumerate(built.object_qpos_adr):
        data.qpos[adr : adr + 3] = poses[k, :3, 3]
        data.qpos[adr + 3 : adr + 7] = _quat(poses[k, :3, :3])
    data.qvel[:] = 0.0
    mujoco.mj_forward(built.model, data)
