"""A MuJoCo physics proxy of a Gaussian world: collision queries and settling under gravity.

Every object becomes a body with a free joint whose collision geom is the convex hull of (a filtered subset
of) its Gaussian means (a mesh geom: MuJoCo builds the hull of a mesh's vertices itself); the table is a box
whose top is the world's table height, with a floor plane one metre below to catch what falls off. A trained
object's Gaussians can reach a few millimetres into the table it stood on (contact blur, shadows); hull points
that lie below the table top in a captured state where the object rests on the table (its lowest point within
``rest_tolerance`` of the top) are lifted onto the top, so the captured states are contact-free. Poses
are set by *teleporting* the free joints through ``qpos`` (never mocap bodies, which do not collide with static
geometry). :meth:`PhysicsProxy.check` also reports the objects outside the world's workspace
(:class:`~dsg_gym.world_model.Workspace`: the box over the table up to 0.5 m above it). Everything is deterministic:
the same query gives the same answer bit for bit; every query sets the whole simulation state it reads, so one
proxy serves any number of envs.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numba as nb  # noqa: E402
import numpy as np  # noqa: E402

from .poses import as_poses7, quat_normalize, quat_to_rotmat  # noqa: E402
from .world_model import WorldModel  # noqa: E402

__all__ = ["BOUNDS_TOL", "CollisionReport", "PhysicsProxy", "SETTLE_TOLERANCE", "TABLE"]

#: index used for the table (and floor) in :attr:`CollisionReport.penetrating`
TABLE = -1
#: how far (metres) a collision hull may reach past the workspace's x/y bounds or top before it is out of bounds
BOUNDS_TOL = 1e-3
#: the deepest penetration (metres) a configuration that :meth:`PhysicsProxy.settle` brought to rest may keep
SETTLE_TOLERANCE = 2e-3


@nb.njit(cache=True)
def _hull_boxes(p7, pts, off, out):
    """out [K, 6] = (x min, x max, y min, y max, z min, z max) of each object's hull points pts[off[k]:off[k+1]]
    (object frame) posed by p7 [K, 7] (unit quaternions, wxyz), in the world frame."""
    for k in range(p7.shape[0]):
        w, x, y, z = p7[k, 3], p7[k, 4], p7[k, 5], p7[k, 6]
        r00, r01, r02 = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
        r10, r11, r12 = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        r20, r21, r22 = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
        xlo = ylo = zlo = np.inf
        xhi = yhi = zhi = -np.inf
        for i in range(off[k], off[k + 1]):
            px, py, pz = pts[i, 0], pts[i, 1], pts[i, 2]
            hx = px * r00 + py * r01 + pz * r02
            hy = px * r10 + py * r11 + pz * r12
            hz = px * r20 + py * r21 + pz * r22
            xlo, xhi = min(xlo, hx), max(xhi, hx)
            ylo, yhi = min(ylo, hy), max(yhi, hy)
            zlo, zhi = min(zlo, hz), max(zhi, hz)
        out[k, 0], out[k, 1] = xlo + p7[k, 0], xhi + p7[k, 0]
        out[k, 2], out[k, 3] = ylo + p7[k, 1], yhi + p7[k, 1]
        out[k, 4], out[k, 5] = zlo + p7[k, 2], zhi + p7[k, 2]


@dataclass(frozen=True)
class CollisionReport:
    """Result of :meth:`PhysicsProxy.check`.

    ``penetrating``: sorted pairs ``(i, j)`` of 0-based object indices (``j`` may be :data:`TABLE`) that
    interpenetrate by more than the tolerance; ``depths``: the penetration depth of each pair (metres);
    ``out_of_bounds``: objects outside the workspace (:class:`~dsg_gym.world_model.Workspace`: the origin outside
    the box above the table, or the hull past its x/y bounds or top); ``min_distance``: the smallest
    signed distance between two objects (negative = penetration; ``inf`` for a single object, capped at
    the query range otherwise).
    """

    penetrating: tuple[tuple[int, int], ...]
    depths: tuple[float, ...]
    out_of_bounds: tuple[int, ...]
    min_distance: float

    @property
    def ok(self) -> bool:
        """No penetration and nothing outside the workspace."""
        return not self.penetrating and not self.out_of_bounds

    def objects_in_collision(self) -> tuple[int, ...]:
        return tuple(sorted({i for p in self.penetrating for i in p if i != TABLE}))


def _hull_points(means: np.ndarray, opacities: np.ndarray, max_points: int) -> np.ndarray:
    """Vertices for an object's collision hull: opaque-enough means without far outliers, reduced to the
    convex hull's vertices and, if still many, a deterministic subsample of them."""
    pts = means.astype(np.float64)
    keep = opacities >= 0.2
    if keep.sum() >= 4:
        pts = pts[keep]
    c = np.median(pts, axis=0)
    r = np.linalg.norm(pts - c, axis=1)
    pts = pts[r <= 1.5 * np.percentile(r, 99.0) + 1e-9]
    try:
        from scipy.spatial import ConvexHull

        pts = pts[np.sort(ConvexHull(pts).vertices)]
    except Exception:  # degenerate (flat) sets or no scipy: MuJoCo takes the hull of all points
        pass
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(np.int64)]
    return pts


class PhysicsProxy:
    """Collision and settling proxy of a :class:`WorldModel` (see the module docstring).

    Args:
        world: the world model.
        max_hull_points: at most this many hull vertices per object.
        expand: grow every hull vertex away from the object's centre by this many metres (e.g. ~1 sigma of
            the Gaussians' scale for trained worlds, whose means lie slightly inside the surface).
        friction: sliding friction of all geoms.
        timestep: simulation step (seconds) used by :meth:`settle`.
        rest_tolerance: an object whose lowest hull point is at most this far (metres) below the table top
            in a captured state rests there; its hull is lifted onto the top (module docstring).
    """

    def __init__(
        self,
        world: WorldModel,
        *,
        max_hull_points: int = 160,
        expand: float = 0.0,
        friction: float = 0.8,
        timestep: float = 0.002,
        rest_tolerance: float = 0.03,
    ):
        self.world = world
        self.num_objects = world.num_objects
        self.hulls: list[np.ndarray] = []
        for k, obj in enumerate(world.objects):
            pts = _hull_points(obj.means, obj.opacities, max_hull_points)
            for P in world.states.values():  # lift what a resting object pushes into the table
                w = pts @ P[k, :3, :3].T + P[k, :3, 3]
                low = w[:, 2] < world.table.z
                if low.any() and w[:, 2].min() >= world.table.z - rest_tolerance:
                    w[low, 2] = world.table.z
                    pts = (w - P[k, :3, 3]) @ P[k, :3, :3]
            if expand:
                c = pts.mean(axis=0)
                d = pts - c
                pts = pts + expand * d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
            self.hulls.append(pts)
        t = world.table
        spec = mujoco.MjSpec()
        spec.modelname = "dsg_physics_proxy"
        spec.option.timestep = float(timestep)
        spec.option.gravity = [0.0, 0.0, -9.81]
        wb = spec.worldbody
        thick = 0.05
        wb.add_geom(
            name="table",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[0.5 * (t.xmax - t.xmin), 0.5 * (t.ymax - t.ymin), 0.5 * thick],
            pos=[0.5 * (t.xmin + t.xmax), 0.5 * (t.ymin + t.ymax), t.z - 0.5 * thick],
            friction=[friction, 0.005, 0.0001],
        )
        wb.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], pos=[0, 0, t.z - 1.0])
        for k, pts in enumerate(self.hulls):
            mesh = spec.add_mesh(name=f"hull{k}")
            mesh.uservert = pts.ravel().tolist()
            body = wb.add_body(name=f"object{k}", pos=[0.0, 0.0, 10.0 + k])
            body.add_freejoint(name=f"free{k}")
            body.add_geom(
                name=f"object{k}",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=f"hull{k}",
                density=500.0,
                friction=[friction, 0.005, 0.0001],
            )
        try:
            self.model = spec.compile()
        except Exception as e:  # a degenerate hull (all points coplanar) fails to compile
            raise ValueError(f"PhysicsProxy: cannot build the collision model: {e}") from None
        m = self.model
        m.dof_damping[:] = 0.05
        self.data = mujoco.MjData(m)
        self._geom = np.array([m.geom(f"object{k}").id for k in range(self.num_objects)], dtype=np.int64)
        self._obj_of_geom = {int(g): k for k, g in enumerate(self._geom)}
        self._body = np.array([m.body(f"object{k}").id for k in range(self.num_objects)], dtype=np.int64)
        self._qadr = np.array([m.jnt_qposadr[m.body_jntadr[b]] for b in self._body], dtype=np.int64)
        self._vadr = np.array([m.jnt_dofadr[m.body_jntadr[b]] for b in self._body], dtype=np.int64)
        self._qidx = np.concatenate([np.arange(a, a + 7) for a in self._qadr])
        self._hull_pts = np.ascontiguousarray(np.concatenate(self.hulls), np.float64)
        self._hull_off = np.concatenate([[0], np.cumsum([len(h) for h in self.hulls])]).astype(np.int64)
        self._boxes = np.empty((self.num_objects, 6))
        #: the box the objects stay in (:attr:`WorldModel.workspace`)
        self.workspace = world.workspace

    # ------------------------------------------------------------------ state
    def _set(self, p7: np.ndarray, full: bool = True) -> None:
        """Teleport the objects; ``full``: also reset the simulation state and run ``mj_forward``, else only
        kinematics and collision detection (what :meth:`check` needs)."""
        d = self.data
        if full:
            mujoco.mj_resetData(self.model, d)
        d.qpos[self._qidx] = p7.ravel()
        if full:
            mujoco.mj_forward(self.model, d)
        else:
            mujoco.mj_kinematics(self.model, d)
            mujoco.mj_collision(self.model, d)

    def _get(self) -> np.ndarray:
        out = np.empty((self.num_objects, 7))
        for k, a in enumerate(self._qadr):
            out[k] = self.data.qpos[a : a + 7]
        out[:, 3:] = quat_normalize(out[:, 3:])
        return out

    # ------------------------------------------------------------------ queries
    def hull_world(self, k: int, pose7: np.ndarray) -> np.ndarray:
        """Object ``k``'s hull vertices at ``pose7`` (world frame)."""
        r = quat_to_rotmat(pose7[3:7])
        return self.hulls[k] @ r.T + pose7[:3]

    def resting_z(self, k: int, quat: np.ndarray) -> float:
        """Height of object ``k``'s frame origin at which its hull, rotated by ``quat``, touches the table."""
        return float(self.world.table.z - (self.hulls[k] @ quat_to_rotmat(quat).T)[:, 2].min())

    def check(
        self,
        poses,
        *,
        tol: float = 1e-3,
        bounds_tol: float = BOUNDS_TOL,
        distance: bool = True,
        distance_range: float = 0.05,
    ) -> CollisionReport:
        """Collision report of the configuration ``poses`` (``[K,7]`` or ``[K,4,4]``); see
        :class:`CollisionReport`. Penetrations shallower than ``tol`` (resting contact) are ignored;
        ``distance=False`` skips the pairwise distance queries (``min_distance`` is then ``nan``)."""
        p7 = as_poses7(poses, self.num_objects, "poses")
        self._set(p7, full=False)
        d, m = self.data, self.model
        deepest: dict[tuple[int, int], float] = {}
        ncon = d.ncon
        if ncon:
            con = d.contact  # field arrays over the active contacts (no per-contact Python objects)
            dist = np.array(con.dist[:ncon], dtype=np.float64)
            geoms = np.array(con.geom[:ncon], dtype=np.int64).reshape(ncon, 2)
            for i in np.flatnonzero(dist < -tol):
                o1, o2 = self._obj_of_geom.get(int(geoms[i, 0])), self._obj_of_geom.get(int(geoms[i, 1]))
                if o1 is None and o2 is None:
                    continue
                a = TABLE if o1 is None else o1
                b = TABLE if o2 is None else o2
                key = (max(a, b), min(a, b)) if TABLE in (a, b) else (min(a, b), max(a, b))
                deepest[key] = max(deepest.get(key, 0.0), -float(dist[i]))
        pairs = tuple(sorted(deepest))
        b = self._boxes
        _hull_boxes(p7, self._hull_pts, self._hull_off, b)
        oob = np.flatnonzero(self.workspace.outside(p7[:, :3], b[:, 0::2], b[:, 1::2], bounds_tol)).tolist()
        dmin = np.inf if distance else np.nan
        for i in range(self.num_objects if distance else 0):
            for j in range(i + 1, self.num_objects):
                dist = mujoco.mj_geomDistance(
                    m, d, int(self._geom[i]), int(self._geom[j]), distance_range, None
                )
                dmin = min(dmin, float(dist))
        return CollisionReport(pairs, tuple(deepest[p] for p in pairs), tuple(oob), dmin)

    def workspace_problems(self, poses, *, bounds_tol: float = BOUNDS_TOL) -> dict[int, str]:
        """``{k: what takes object k out of the workspace}`` for the objects that :meth:`check` reports in
        ``out_of_bounds`` (the same rule and tolerance); empty when all are inside."""
        p7 = as_poses7(poses, self.num_objects, "poses")
        b = np.empty((self.num_objects, 6))
        _hull_boxes(p7, self._hull_pts, self._hull_off, b)
        ws = self.workspace
        out = {}
        for k in np.flatnonzero(ws.outside(p7[:, :3], b[:, 0::2], b[:, 1::2], bounds_tol)):
            out[int(k)] = ws.problem(p7[k, :3], b[k, 0::2], b[k, 1::2], bounds_tol)
        return out

    def settle(
        self,
        poses,
        *,
        max_time: float = 1.5,
        lin_tol: float = 2e-3,
        ang_tol: float = 2e-2,
        calm_steps: int = 25,
    ) -> np.ndarray:
        """Let every object fall and come to rest under gravity from ``poses`` (zero initial velocity);
        returns the resting poses ``[K,7]`` float64 (unit quaternions). Stops when all linear / angular
        speeds stay below ``lin_tol`` m/s / ``ang_tol`` rad/s for ``calm_steps`` steps, or after
        ``max_time`` simulated seconds."""
        p7 = as_poses7(poses, self.num_objects, "poses")
        if not np.isfinite(max_time) or max_time < 0:
            raise ValueError(f"settle: max_time must be a finite number >= 0, got {max_time}")
        self._set(p7)
        m, d = self.model, self.data
        steps = int(round(max_time / m.opt.timestep))
        calm = 0
        lin = np.concatenate([np.arange(a, a + 3) for a in self._vadr])
        ang = lin + 3
        for _ in range(steps):
            mujoco.mj_step(m, d)
            if np.abs(d.qvel[lin]).max() < lin_tol and np.abs(d.qvel[ang]).max() < ang_tol:
                calm += 1
                if calm >= calm_steps:
                    break
            else:
                calm = 0
        if not np.all(np.isfinite(d.qpos)):
            raise RuntimeError("settle: the simulation diverged")
        return self._get()
