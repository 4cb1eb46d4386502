"""Object states of a synthetic scene: sampling and independent checks.

Every state puts each movable object at a random yaw about +z (in its rest orientation), resting on the
surface (its lowest point exactly at ``z = 0``), inside the surface bounds minus ``edge_margin``, and away
from other objects and table props. The two training states are also *complementary*: no surface region under
an object in ``state1`` is under an object in ``state2`` (so every hole left by a moved object is seen in the
other state). All of this is checked on **footprint rasters** of the surface (cell ``raster_cell``): an
object's footprint is the vertical projection of its convex hull, described by its support function in
:data:`NUM_DIRECTIONS` horizontal directions (an outer polygon, hence conservative). MuJoCo's collision
detection verifies the final states once more (:func:`verify_with_mujoco`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from train_world.synth.shapes import (
    mesh_vertices,
    pose_matrix,
    rest_rotation,
    resting_height,
    support,
    yaw_rotation,
)
from train_world.synth.spec import SceneSpec, Shape

__all__ = [
    "Grid",
    "StateError",
    "check_complementary_visibility",
    "check_state",
    "footprint_raster",
    "sample_states",
    "surface_grid",
    "verify_with_mujoco",
]

NUM_DIRECTIONS = 64
_ANGLES = np.arange(NUM_DIRECTIONS) * (2.0 * np.pi / NUM_DIRECTIONS)
_DIRS2 = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)
_DIRS3 = np.column_stack([_DIRS2, np.zeros(NUM_DIRECTIONS)])
_PX, _NX, _PY, _NY = 0, NUM_DIRECTIONS // 2, NUM_DIRECTIONS // 4, 3 * NUM_DIRECTIONS // 4


class StateError(ValueError):
    """A state violates a placement rule (collision, out of bounds, not resting, not complementary)."""


@dataclass(frozen=True)
class Grid:
    """Raster over the surface: cell ``(j, i)`` has centre ``(x0 + (i + .5) cell, y0 + (j + .5) cell)``."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int

    def centres(self, i0: int, i1: int, j0: int, j1: int) -> tuple[np.ndarray, np.ndarray]:
        xs = self.x0 + (np.arange(i0, i1) + 0.5) * self.cell
        ys = self.y0 + (np.arange(j0, j1) + 0.5) * self.cell
        return xs, ys


def surface_grid(scene: SceneSpec) -> Grid:
    (x0, x1), (y0, y1) = scene.table_bounds
    c = scene.placement.raster_cell
    return Grid(x0, y0, c, int(np.ceil((x1 - x0) / c)), int(np.ceil((y1 - y0) / c)))


class _Footprints:
    """Caches mesh vertices per shape so support functions are cheap."""

    def __init__(self) -> None:
        self._verts: dict[Shape, np.ndarray] = {}

    def support2(self, shape: Shape, rot: np.ndarray) -> np.ndarray:
        """Horizontal support of ``shape`` rotated by ``rot`` (origin at 0), [NUM_DIRECTIONS]."""
        verts = None
        if shape.type == "mesh":
            verts = self._verts.setdefault(shape, mesh_vertices(shape))
        return support(shape, _DIRS3 @ rot, verts)  # (R^T n) for each row n


_FP = _Footprints()


def footprint_raster(
    grid: Grid, shape: Shape, pose: np.ndarray, dilate: float = 0.0, h: np.ndarray | None = None
) -> np.ndarray:
    """Boolean [ny, nx] raster of cells whose centre lies in the footprint of ``shape`` at ``pose``, grown by
    ``dilate`` metres."""
    pose = np.asarray(pose, dtype=np.float64)
    if h is None:
        h = _FP.support2(shape, pose[:3, :3])
    h = h + dilate
    tx, ty = pose[0, 3], pose[1, 3]
    out = np.zeros((grid.ny, grid.nx), dtype=bool)
    i0 = max(int(np.floor((tx - h[_NX] - grid.x0) / grid.cell)), 0)
    i1 = min(int(np.ceil((tx + h[_PX] - grid.x0) / grid.cell)) + 1, grid.nx)
    j0 = max(int(np.floor((ty - h[_NY] - grid.y0) / grid.cell)), 0)
    j1 = min(int(np.ceil((ty + h[_PY] - grid.y0) / grid.cell)) + 1, grid.ny)
    if i1 <= i0 or j1 <= j0:
        return out
    xs, ys = grid.centres(i0, i1, j0, j1)
    px = (xs - tx)[None, :, None] * _DIRS2[None, None, :, 0]
    py = (ys - ty)[:, None, None] * _DIRS2[None, None, :, 1]
    out[j0:j1, i0:i1] = np.all(px + py <= h[None, None, :], axis=2)
    return out


def _prop_obstacles(scene: SceneSpec, grid: Grid, dilate: float) -> np.ndarray:
    occ = np.zeros((grid.ny, grid.nx), dtype=bool)
    for p in scene.props:
        if p.on != "table":
            continue
        rot = yaw_rotation(np.deg2rad(p.yaw_deg)) @ rest_rotation(p.rest)
        pose = pose_matrix(rot, (p.position[0], p.position[1], resting_height(p.shape, rot)))
        occ |= footprint_raster(grid, p.shape, pose, dilate)
    return occ


def _place(
    rng: np.random.Generator,
    scene: SceneSpec,
    grid: Grid,
    occupied: np.ndarray,
    avoid: np.ndarray | None = None,
) -> np.ndarray | None:
    """Sample one state by rejection; ``avoid``: cells the visibility-grown footprints must not touch."""
    pl = scene.placement
    (xmin, xmax), (ymin, ymax) = scene.table_bounds
    occupied = occupied.copy()
    k = len(scene.objects)
    poses = np.zeros((k, 4, 4))
    # big objects first: they are the hardest to fit
    sizes = [float(_FP.support2(o.shape, rest_rotation(o.rest)).max()) for o in scene.objects]
    for idx in sorted(range(k), key=lambda i: (-sizes[i], i)):
        obj = scene.objects[idx]
        rest = rest_rotation(obj.rest)
        for _ in range(pl.max_tries):
            rot = yaw_rotation(rng.uniform(0.0, 2.0 * np.pi)) @ rest
            h = _FP.support2(obj.shape, rot)
            lo_x, hi_x = xmin + pl.edge_margin + h[_NX], xmax - pl.edge_margin - h[_PX]
            lo_y, hi_y = ymin + pl.edge_margin + h[_NY], ymax - pl.edge_margin - h[_PY]
            if lo_x > hi_x or lo_y > hi_y:
                continue
            pos = (rng.uniform(lo_x, hi_x), rng.uniform(lo_y, hi_y), resting_height(obj.shape, rot))
            pose = pose_matrix(rot, pos)
            r_gap = footprint_raster(grid, obj.shape, pose, 0.5 * pl.gap, h)
            if (r_gap & occupied).any():
                continue
            if (
                avoid is not None
                and (footprint_raster(grid, obj.shape, pose, 0.5 * pl.visibility_margin, h) & avoid).any()
            ):
                continue
            occupied |= r_gap
            poses[idx] = pose
            break
        else:
            return None
    return poses


def _union(scene: SceneSpec, grid: Grid, poses: np.ndarray, dilate: float) -> np.ndarray:
    out = np.zeros((grid.ny, grid.nx), dtype=bool)
    for obj, pose in zip(scene.objects, poses, strict=True):
        out |= footprint_raster(grid, obj.shape, pose, dilate)
    return out


def sample_states(
    scene: SceneSpec, rng: np.random.Generator, num_test_states: int = 3, max_restarts: int = 200
) -> dict[str, np.ndarray]:
    """Sample ``state1``, ``state2`` (complementary) and ``test_0..`` poses, each [K,4,4] float64, checked."""
    grid = surface_grid(scene)
    pl = scene.placement
    obstacles = _prop_obstacles(scene, grid, 0.5 * pl.gap)
    states: dict[str, np.ndarray] = {}
    for _ in range(max_restarts):
        p1 = _place(rng, scene, grid, obstacles)
        if p1 is None:
            continue
        avoid = _union(scene, grid, p1, 0.5 * pl.visibility_margin)
        p2 = None
        for _ in range(5):
            p2 = _place(rng, scene, grid, obstacles, avoid)
            if p2 is not None:
                break
        if p2 is not None:
            states["state1"], states["state2"] = p1, p2
            break
    else:
        raise StateError(
            f"scene {scene.name!r}: could not find two complementary states in {max_restarts} "
            "restarts; use fewer or smaller objects or a larger surface"
        )
    for t in range(num_test_states):
        for _ in range(max_restarts):
            p = _place(rng, scene, grid, obstacles)
            if p is not None:
                states[f"test_{t}"] = p
                break
        else:
            raise StateError(f"scene {scene.name!r}: could not place the objects for test state {t}")
    for name, poses in states.items():
        check_state(scene, poses, name)
    check_complementary_visibility(scene, states["state1"], states["state2"])
    return states


def check_state(scene: SceneSpec, poses: np.ndarray, name: str = "state") -> None:
    """Raise :class:`StateError` unless every object rests on the surface, inside the bounds, with footprints
    disjoint from each other and from table props."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(scene.objects), 4, 4) or not np.all(np.isfinite(poses)):
        raise StateError(f"{name}: expected finite poses of shape ({len(scene.objects)}, 4, 4)")
    grid = surface_grid(scene)
    (xmin, xmax), (ymin, ymax) = scene.table_bounds
    occ = _prop_obstacles(scene, grid, 0.0)
    owner = np.zeros((grid.ny, grid.nx), dtype=np.int64)
    for k, (obj, pose) in enumerate(zip(scene.objects, poses, strict=True)):
        rot = pose[:3, :3]
        if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-6:
            raise StateError(f"{name}: pose of {obj.name!r} is not a rotation")
        z = resting_height(obj.shape, rot)
        if abs(pose[2, 3] - z) > 1e-6:
            raise StateError(
                f"{name}: {obj.name!r} does not rest on the surface (z={pose[2, 3]:.4f}, resting z={z:.4f})"
            )
        h = _FP.support2(obj.shape, rot)
        tx, ty = pose[0, 3], pose[1, 3]
        if tx - h[_NX] < xmin or tx + h[_PX] > xmax or ty - h[_NY] < ymin or ty + h[_PY] > ymax:
            raise StateError(f"{name}: {obj.name!r} sticks out of the surface bounds")
        r = footprint_raster(grid, obj.shape, pose, 0.0, h)
        if (r & occ).any():
            raise StateError(f"{name}: {obj.name!r} collides with a table prop")
        clash = owner[r]
        clash = clash[clash > 0]
        if clash.size:
            other = scene.objects[int(clash[0]) - 1].name
            raise StateError(f"{name}: footprints of {obj.name!r} and {other!r} overlap")
        owner[r] = k + 1


def check_complementary_visibility(
    scene: SceneSpec, poses1: np.ndarray, poses2: np.ndarray, margin: float | None = None
) -> None:
    """Raise :class:`StateError` if any surface cell is covered by an object in both states.

    Footprints are grown by ``margin / 2`` (default ``placement.visibility_margin``) before the test, so the
    covered regions of the two states are at least ``margin`` apart.
    """
    grid = surface_grid(scene)
    m = scene.placement.visibility_margin if margin is None else margin
    r1 = [footprint_raster(grid, o.shape, p, 0.5 * m) for o, p in zip(scene.objects, poses1, strict=True)]
    r2 = [footprint_raster(grid, o.shape, p, 0.5 * m) for o, p in zip(scene.objects, poses2, strict=True)]
    bad = []
    for a, ra in zip(scene.objects, r1, strict=True):
        for b, rb in zip(scene.objects, r2, strict=True):
            n = int((ra & rb).sum())
            if n:
                bad.append(f"{a.name!r} in state 1 / {b.name!r} in state 2 ({n} cells)")
    if bad:
        raise StateError(
            "complementary visibility violated: surface covered in both states by " + "; ".join(bad)
        )


def verify_with_mujoco(
    built, data, poses: np.ndarray, name: str = "state", rest_tol: float = 5e-4, pen_tol: float = 1e-4
) -> None:
    """Set ``poses`` in MuJoCo and check its contacts: no object penetrates anything, and every object touches
    the surface (contact distance within ``rest_tol``)."""
    from train_world.synth.build import set_object_poses

    set_object_poses(built, data, poses)
    gobj = built.geom_object_ids
    names = [o.name for o in built.spec.objects]
    touching = np.zeros(built.num_objects, dtype=bool)
    for c in data.contact[: data.ncon]:
        g1, g2 = int(c.geom[0]), int(c.geom[1])
        o1, o2 = int(gobj[g1]), int(gobj[g2])
        if o1 == 0 and o2 == 0:
            continue
        if built.surface_geom_id in (g1, g2):
            obj = o1 or o2
            if abs(c.dist) <= rest_tol:
                touching[obj - 1] = True
            elif c.dist < -rest_tol:
                raise StateError(f"{name}: {names[obj - 1]!r} penetrates the surface by {-c.dist:.4g} m")
            continue
        if c.dist < -pen_tol:
            what = [names[o - 1] if o else built.model.geom(g).name for o, g in ((o1, g1), (o2, g2))]
            raise StateError(
                f"{name}: MuJoCo reports {what[0]!r} and {what[1]!r} in collision (depth {-c.dist:.4g} m)"
            )
    if not touching.all():
        missing = [n for n, t in zip(names, touching, strict=True) if not t]
        raise StateError(f"{name}: objects {missing} do not rest on the surface according to MuJoCo")
