"""A far shell behind the background for the directions no training view saw.

A splat world knows only what its training views saw; a camera that looks past them (above the captured part
of a wall, say) sees through to the render's background colour, a hole that no surface in the room has. The
shell fills those directions with what lies beside them: flat Gaussians on a sphere around the background,
each facing the sphere's centre and coloured like the background Gaussians farthest out in its direction.

- Centre and radius: the median of the background Gaussians' centres (those with opacity >=
  ``min_opacity``), and ``margin`` times the ``radius_percentile`` of their distances from it, so the shell
  lies behind nearly all of the background.
- Identity features, and the colour where the next item gives none: for each of ``directions`` evenly spread
  directions (a Fibonacci sphere), the ``neighbours`` background Gaussians nearest in direction; the mean DC
  colour and mean features of those among them at least ``far_fraction`` of the farthest one's distance out
  (the surface at the back, not the table in front). Higher SH bands are zero.
- Colour (``colours="render"``, the default, and at least one camera): the background rendered all around
  from the cameras' mean centre (:mod:`train_world.complete.panorama`, cube faces of ``panorama`` pixels) and
  resampled on an elevation x azimuth grid (``grid_rows`` x twice as many); a cell is known where the render
  is opaque (alpha >= ``known_alpha``) and its surface point lies in some camera's image. Every other cell
  takes the nearest known cell up or down its own azimuth, so a wall above the captured part continues the
  colour of its top (a room's walls are vertical), and a column with none known the nearest known
  direction. A shell Gaussian takes its cell's colour, in its direction from that centre, when the surface the
  colour comes from lies at least ``far_enough`` of the shell Gaussian's distance away (a wall, not the table
  seen from above); else the mean colour above. ``colours="mean"`` keeps the mean colour everywhere.
- A floor (``floor``, worlds whose z is up: those that record their table): the part of the sphere below the
  background's lowest level (the ``floor_percentile`` of its heights) is flattened onto that level, a disc of
  Gaussians on a square grid of the sphere's spacing, facing up; so a camera that looks past the captured
  floor sees the shell where the floor is, not below it. With ``colours="render"`` a floor Gaussian takes the
  mean colour of the ``neighbours`` known render cells whose surface lies on the floor (within
  ``floor_tolerance`` of the radius) nearest to it across the floor.
- Only the unseen part is kept: a shell Gaussian whose centre projects into the image of any of the world's
  cameras is dropped, so the shell stays out of what those views saw. Near the edge of a view, the disc of a
  shell Gaussian just outside it can still show where the surface in front is not quite opaque;
  ``cull_sigmas`` > 0 drops those too, and with them the shell just beyond the views' edges, which is where
  other views mostly look past them.

Deterministic; float64 inside. Conventions: quaternions wxyz, cameras OpenCV world-to-camera (as the world
file stores them).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from dsg_gym.cameras import Cameras
from dsg_gym.gaussians import GaussianSet, rgb_to_sh0
from dsg_gym.world import World
from train_world.complete.panorama import (
    continue_columns,
    equirect_cell,
    equirect_directions,
    render_cube,
    sample_cube,
    seen_by_cameras,
)

__all__ = [
    "ShellConfig",
    "background_shell",
    "fibonacci_directions",
    "rendered_colours",
    "with_background_shell",
    "without_background_shell",
]


@dataclass(frozen=True)
class ShellConfig:
    """Thresholds of :func:`background_shell`."""

    directions: int = 4000  # points on the sphere before the seen ones are dropped (the floor: fewer)
    neighbours: int = 16  # background Gaussians that colour one shell Gaussian
    far_fraction: float = 0.9  # of those, the ones at least this share of the farthest one's distance
    radius_percentile: float = 99.5  # the shell radius: this percentile of the background's distances ...
    margin: float = 1.1  # ... times this
    min_opacity: float = 0.3  # background Gaussians fainter than this are ignored
    spread: float = 0.7  # a shell Gaussian's extent, in units of the spacing between directions
    thickness: float = 0.05  # its extent along its normal, relative to its extent across
    opacity: float = 0.99
    cull_sigmas: float = 0.0  # dropped when its centre plus this many of its extents projects into a view
    colours: str = "render"  # "render" or "mean" (module docstring)
    panorama: int = 256  # cube face size of the render, pixels
    grid_rows: int = 360  # elevation rows of the grid the render is continued on (twice as many azimuths)
    known_alpha: float = 0.9  # a render cell with at least this alpha (and seen by a camera) is known
    far_enough: float = 0.5  # a colour's surface must lie this share of the shell Gaussian's distance away
    floor: bool = True  # z-up worlds: the sphere's part below the background's lowest level lies flat on it
    floor_percentile: float = 1.0  # that level: this percentile of the background Gaussians' heights
    floor_tolerance: float = 0.02  # render cells this share of the radius from the floor's height are floor

    def __post_init__(self) -> None:
        if self.directions < 1 or self.neighbours < 1:
            raise ValueError("ShellConfig: directions and neighbours must be >= 1")
        if not (0.0 < self.far_fraction <= 1.0 and 0.0 < self.radius_percentile <= 100.0):
            raise ValueError("ShellConfig: far_fraction must be in (0, 1] and radius_percentile in (0, 100]")
        if not (self.margin >= 1.0 and self.spread > 0 and self.thickness > 0 and 0 < self.opacity <= 1):
            raise ValueError("ShellConfig: need margin >= 1, spread > 0, thickness > 0 and opacity in (0, 1]")
        if self.cull_sigmas < 0:
            raise ValueError("ShellConfig: cull_sigmas must be >= 0")
        if self.colours not in ("render", "mean"):
            raise ValueError(f"ShellConfig: colours must be 'render' or 'mean', got {self.colours!r}")
        if self.panorama < 2 or self.grid_rows < 2:
            raise ValueError("ShellConfig: panorama and grid_rows must be >= 2")
        if not (0.0 < self.known_alpha <= 1.0 and self.far_enough >= 0.0):
            raise ValueError("ShellConfig: need known_alpha in (0, 1] and far_enough >= 0")
        if not (0.0 <= self.floor_percentile <= 100.0 and self.floor_tolerance >= 0.0):
            raise ValueError("ShellConfig: need floor_percentile in [0, 100] and floor_tolerance >= 0")


def fibonacci_directions(n: int) -> np.ndarray:
    """``n`` unit vectors ``[n, 3]`` spread evenly over the sphere (a Fibonacci lattice)."""
    i = np.arange(n, dtype=np.float64) + 0.5
    polar = np.arccos(1.0 - 2.0 * i / n)
    azimuth = np.pi * (1.0 + np.sqrt(5.0)) * i
    return np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1)


def _facing(normals: np.ndarray) -> np.ndarray:
    """Unit quaternions (wxyz) turning +z onto each unit vector of ``normals [N, 3]``."""
    q = np.stack([1.0 + normals[:, 2], -normals[:, 1], normals[:, 0], np.zeros(len(normals))], axis=1)
    q[q[:, 0] < 1e-9] = (0.0, 1.0, 0.0, 0.0)  # -z: half a turn about x
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _seen(points: np.ndarray, extent: float, cameras: Iterable[Cameras]) -> np.ndarray:
    """Bool ``[N]``: a disc of radius ``extent`` around the point reaches into some camera's image (the
    point's projection within the disc's projected radius of the image; behind-the-camera points count where
    the disc reaches in front)."""
    seen = np.zeros(len(points), bool)
    for cam in cameras:
        for vm, K in zip(cam.viewmats, cam.Ks):
            p = points @ vm[:3, :3].T + vm[:3, 3]
            z = p[:, 2]
            front = z > extent
            zf = np.where(front, z, 1.0)
            u = (K[0, 0] * p[:, 0] + K[0, 1] * p[:, 1]) / zf + K[0, 2]
            v = K[1, 1] * p[:, 1] / zf + K[1, 2]
            m = max(K[0, 0], K[1, 1]) * extent / np.where(front, z - extent, 1.0)
            near = ~front & (z > -extent)  # the disc straddles the camera plane: call it seen
            seen |= near | (front & (u >= -m) & (u <= cam.width + m) & (v >= -m) & (v <= cam.height + m))
    return seen


def _dome(
    centre: np.ndarray, radius: float, n: int, floor_z: float | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shell Gaussian centres ``[M, 3]``, their unit normals ``[M, 3]`` and whether each lies on the floor,
    bool ``[M]``: ``n`` Fibonacci points on the sphere, those below ``floor_z`` (None: none) replaced by a
    square grid of the same spacing on the plane ``z = floor_z`` inside the sphere."""
    dirs = fibonacci_directions(n)
    points = centre + radius * dirs
    if floor_z is None or not centre[2] - radius < floor_z < centre[2]:
        return points, dirs, np.zeros(n, bool)
    keep = points[:, 2] > floor_z
    spacing = radius * np.sqrt(4.0 * np.pi / n)
    reach = np.sqrt(radius**2 - (centre[2] - floor_z) ** 2)
    g = np.arange(-np.floor(reach / spacing), np.floor(reach / spacing) + 1) * spacing
    x, y = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    inside = x**2 + y**2 <= reach**2
    floor = np.stack([centre[0] + x[inside], centre[1] + y[inside], np.full(inside.sum(), floor_z)], 1)
    up = np.tile([0.0, 0.0, 1.0], (len(floor), 1))
    on_floor = np.concatenate([np.zeros(keep.sum(), bool), np.ones(len(floor), bool)])
    return np.concatenate([points[keep], floor]), np.concatenate([dirs[keep], up]), on_floor


def rendered_colours(
    background: GaussianSet,
    cameras: list[Cameras],
    points: np.ndarray,
    config: ShellConfig,
    splat_options: dict | None = None,
    floor: tuple[np.ndarray, float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``colours="render"`` colour (module docstring) of shell Gaussians at ``points [N, 3]``: RGB
    ``[N, 3]`` in [0, 1] and whether each has one, bool ``[N]`` (none without cameras or without a known
    cell). ``floor``: ``(on_floor [N] bool, height, tolerance)``; the points on the floor take the mean colour
    of the nearest known cells whose surface lies within ``tolerance`` of that height, when there are any."""
    c = config
    none = np.zeros((len(points), 3)), np.zeros(len(points), bool)
    if not cameras:
        return none
    origin = np.concatenate(
        [np.linalg.inv(np.asarray(cam.viewmats, np.float64))[:, :3, 3] for cam in cameras]
    )
    origin = origin.mean(axis=0)
    colour, alpha, distance = render_cube(background, origin, c.panorama, splat_options)
    rows, cols = c.grid_rows, 2 * c.grid_rows
    grid = equirect_directions(rows, cols)
    flat = grid.reshape(-1, 3)
    g = sample_cube(np.concatenate([colour, alpha[..., None], distance[..., None]], axis=-1), flat)
    g_colour, g_alpha, g_dist = g[:, :3], g[:, 3], g[:, 4]
    surface = origin + flat * g_dist[:, None]
    known = (g_alpha >= c.known_alpha) & seen_by_cameras(surface, cameras)
    if not known.any():
        return none
    src = continue_columns(known.reshape(rows, cols), grid).reshape(-1)
    offset = np.asarray(points, np.float64) - origin
    reach = np.linalg.norm(offset, axis=1)
    r, k = equirect_cell(offset / np.maximum(reach, 1e-12)[:, None], rows, cols)
    s = src[r * cols + k]
    rgb, ok = np.clip(g_colour[s], 0.0, 1.0), g_dist[s] >= c.far_enough * reach
    if floor is not None:
        on_floor, floor_z, tol = floor
        at = np.flatnonzero(known & (np.abs(surface[:, 2] - floor_z) <= tol))
        if len(at) and np.any(on_floor):
            k_near = min(c.neighbours, len(at))
            _, nn = cKDTree(surface[at, :2]).query(np.asarray(points, np.float64)[on_floor, :2], k=k_near)
            nn = np.asarray(nn).reshape(int(np.sum(on_floor)), k_near)
            rgb[on_floor] = np.clip(g_colour[at[nn]].mean(axis=1), 0.0, 1.0)
            ok[on_floor] = True
    return rgb, ok


def background_shell(
    background: GaussianSet,
    cameras: Iterable[Cameras],
    config: ShellConfig | None = None,
    splat_options: dict | None = None,
    z_up: bool = False,
) -> GaussianSet:
    """The shell Gaussians (module docstring) for ``background`` seen by ``cameras``, labelled background (0)
    with ``background``'s SH width and features. Empty when the background has fewer Gaussians than
    ``config.neighbours`` at ``config.min_opacity``. ``splat_options``: the world's (``World.splat_options``),
    for the render of ``colours="render"``. ``z_up``: the world's +z is up (it has a floor, ``config.floor``)."""
    c = config or ShellConfig()
    cameras = list(cameras)
    keep = np.flatnonzero(background.opacities >= c.min_opacity)
    F, k_sh = background.num_features, background.sh.shape[1]
    if len(keep) < c.neighbours:
        return GaussianSet.empty(background.sh_degree, F)
    means = background.means[keep].astype(np.float64)
    centre = np.median(means, axis=0)
    offset = means - centre
    dist = np.linalg.norm(offset, axis=1)
    unit = offset / np.maximum(dist, 1e-12)[:, None]
    radius = c.margin * float(np.percentile(dist, c.radius_percentile))
    floor_z = float(np.percentile(means[:, 2], c.floor_percentile)) if c.floor and z_up else None
    centres, normals, on_floor = _dome(centre, radius, c.directions, floor_z)
    dirs = centres - centre
    dirs /= np.maximum(np.linalg.norm(dirs, axis=1), 1e-12)[:, None]
    _, idx = cKDTree(unit).query(dirs, k=c.neighbours)
    idx = idx.reshape(len(dirs), c.neighbours)
    d = dist[idx]
    w = (d >= c.far_fraction * d.max(axis=1, keepdims=True)).astype(np.float64)
    w /= w.sum(axis=1, keepdims=True)
    colour = np.einsum("nk,nkc->nc", w, background.sh[keep][idx, 0].astype(np.float64))
    features = np.einsum("nk,nkf->nf", w, background.features[keep][idx].astype(np.float64))
    across = c.spread * radius * np.sqrt(4.0 * np.pi / c.directions)
    sh = np.zeros((len(dirs), k_sh, 3))
    sh[:, 0] = colour
    unseen = ~_seen(centres, c.cull_sigmas * across, cameras)
    if c.colours == "render" and unseen.any():
        fl = None if floor_z is None else (on_floor[unseen], floor_z, c.floor_tolerance * radius)
        rgb, ok = rendered_colours(background, cameras, centres[unseen], c, splat_options, fl)
        at = np.flatnonzero(unseen)[ok]
        sh[at, 0] = rgb_to_sh0(rgb[ok])
    shell = GaussianSet(
        means=centres,
        quats=_facing(normals),
        scales=np.tile([across, across, c.thickness * across], (len(dirs), 1)),
        opacities=np.full(len(dirs), c.opacity),
        sh=sh,
        features=features.reshape(len(dirs), F),
        labels=np.zeros(len(dirs), np.int32),
    )
    return shell.subset(unseen)


def with_background_shell(world: World, config: ShellConfig | None = None) -> World:
    """``world`` with :func:`background_shell` (against its own cameras; z up, so with a floor, when the world
    records its table) appended to its background, ``metadata["background_shell"]``: ``{"gaussians": n}`` and
    ``metadata["num_gaussians"]`` (where recorded) counting them. A world that has a shell already is returned
    as it is."""
    if "background_shell" in world.metadata:
        return world
    shell = background_shell(
        world.background, world.cameras.values(), config, world.splat_options, z_up="table" in world.metadata
    )
    meta = {**world.metadata, "background_shell": {"gaussians": int(shell.num)}}
    if "num_gaussians" in meta:
        meta["num_gaussians"] = int(meta["num_gaussians"]) + int(shell.num)
    bg = GaussianSet.concat([world.background, shell]) if shell.num else world.background
    return dataclasses.replace(world, background=bg, metadata=meta)


def without_background_shell(world: World) -> World:
    """``world`` as it was before :func:`with_background_shell`: the shell's rows (the last ones of the
    background) and its metadata removed. A world without a shell is returned as it is."""
    rec = world.metadata.get("background_shell")
    if rec is None:
        return world
    n = int(rec["gaussians"])
    if not 0 <= n <= world.background.num:
        raise ValueError(
            f"background_shell records {n} Gaussians but the background has {world.background.num}"
        )
    meta = {k: v for k, v in world.metadata.items() if k != "background_shell"}
    if "num_gaussians" in meta:
        meta["num_gaussians"] = int(meta["num_gaussians"]) - n
    bg = world.background.subset(slice(0, world.background.num - n))
    return dataclasses.replace(world, background=bg, metadata=meta)
