"""Render a static background plus rigidly moving objects, re-rendering only what changed.

``SceneRenderer`` keeps, per camera, the background's projection, colours and depth-sorted
tile lists, the objects' projections, and the last rendered image buffers. ``render(poses)``
re-projects only the objects whose pose changed and recomposites only the 16x16 tiles such an
object touches before or after its move; every other tile keeps its pixels. A recomposited
tile merges the background and object lists by depth exactly as a stable sort of the scene
``[background, objects...]`` would, and uses the renderer's single per-pixel routine, so the
result equals a full ``dsg_gym.splat.rasterize`` of the composed scene bit for bit (tested), unless
background tail tables are on (``tail_stride`` > 0: :mod:`dsg_gym.splat.numba_tails`).

Channels are composited only when asked for: RGB (3, from SH evaluated per camera, view
directions taken into each object's frame), the object-id weights (K+1, one-hot labels: 0 is
the background) and depth (1).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import numba as nb
import numpy as np

from .gaussians import GaussianSet
from .splat import numba_batch as batch
from .splat import numba_bins as binning
from .splat import numba_incremental as incr
from .splat import numba_layers as layers
from .splat import numba_project as projection
from .splat import numba_raster as raster
from .splat import numba_rigid as rigid
from .splat import numba_tails as ntails
from .splat.threads import ThreadChooser, min_parallel_work, parallel_allowed
from .splat_options import DEFAULT_EPS2D, check_compositing, check_splat_options

_FIXED_WORK = 8  # a render's fixed cost (projection, binning, Python) in units of one recomposited tile
_NO_TAILS: dict[int, tuple] = {}  # channel count -> the composite kernels' empty tail arguments (read-only)


@dataclass(frozen=True)
class RenderSettings:
    """Speed/accuracy knobs of the runtime renderer (``DSGWorld-v0``'s ``render_settings``).

    ``alpha_min``: a Gaussian is skipped at a pixel where its alpha is below this (3DGS: 1/255);
    ``t_min``: a pixel stops compositing once its transmittance would fall below this (3DGS: 1e-4);
    ``sh_degree``: highest SH degree evaluated (``None``: whatever the world carries);
    ``tail_stride``: background tail tables every this many list entries (0: exact merge; see
    :class:`SceneRenderer`).

    The defaults are the point ``python -m benchmarks.pareto`` recommends for the env: the fastest setting
    on the step-time/PSNR Pareto front within 0.1 dB of the most accurate one on the bundled world
    (docs/benchmarks.md). ``SceneRenderer``'s own defaults stay at the 3DGS values the training renderer uses.
    """

    alpha_min: float = 2.0 / 255.0
    t_min: float = 1e-3
    sh_degree: int | None = None
    tail_stride: int = 64

    def __post_init__(self):
        raster.check_thresholds(float(self.alpha_min), float(self.t_min))
        d = self.sh_degree
        if d is not None and (isinstance(d, bool) or not isinstance(d, (int, np.integer)) or not 0 <= d <= 3):
            raise ValueError(f"sh_degree must be None or an integer in 0..3, got {d!r}")
        n = self.tail_stride
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"tail_stride must be an integer >= 0 (0: exact merge), got {n!r}")

    def kwargs(self) -> dict:
        """Keyword arguments of :class:`SceneRenderer`."""
        return {"alpha_min": float(self.alpha_min), "t_min": float(self.t_min), "sh_degree": self.sh_degree,
                "tail_stride": int(self.tail_stride)}


@dataclass(frozen=True)
class RenderOutput:
    """One render of V cameras. ``mask`` ids: 0 background, k the k-th object (1-based)."""

    rgb: np.ndarray | None  # uint8 [V,H,W,3]
    mask: np.ndarray | None  # uint8 [V,H,W]
    depth: np.ndarray | None  # float32 [V,H,W] metres (expected depth), 0 where nothing was hit
    alpha: np.ndarray  # float32 [V,H,W]


@dataclass
class _Projected:
    means2d: np.ndarray
    conics: np.ndarray
    depths: np.ndarray
    radii: np.ndarray
    rects: np.ndarray


def _project(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
             alpha_min: float = raster.ALPHA_MIN, eps2d: float = projection.BLUR,
             parallel: bool = True) -> _Projected:
    V, n = viewmats.shape[0], means.shape[0]
    out = _Projected(np.empty((V, n, 2), np.float32), np.empty((V, n, 3), np.float32),
                     np.empty((V, n), np.float32), np.empty((V, n, 2), np.int32), np.empty((V, n, 4), np.int32))
    serial = not (parallel and V * n > min_parallel_work())
    kernel = projection.project_forward_serial if serial else projection.project_forward
    kernel(means, quats, scales, opacities[None], viewmats, Ks, float(width), float(height),
           float(near), float(far), out.means2d, out.conics, out.depths, out.radii, out.rects, float(alpha_min),
           float(eps2d))
    return out


def _antialias(conics: np.ndarray, opacities: np.ndarray, eps2d: float, parallel: bool = True) -> np.ndarray:
    """Per-camera opacities ``[V, n]`` after the Mip filter (one kernel for every renderer)."""
    out = np.empty(conics.shape[:2], np.float32)
    serial = not (parallel and out.size > min_parallel_work())
    kernel = projection.antialias_opacities_serial if serial else projection.antialias_opacities
    kernel(conics, opacities, out, float(eps2d))
    return out


def _bins(proj: _Projected, tiles_x: int, tiles_y: int):
    order, counts = binning.depth_order(proj.depths.view(np.uint32), proj.rects)
    offsets, gauss, _, _ = binning.bin_gaussians(proj.rects, order, counts, tiles_x, tiles_y)
    return offsets, gauss


def _rigid(poses, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate poses ``[k, 7]`` (x y z qw qx qy qz) or ``[k, 4, 4]`` (object-to-world) and return
    (unit quaternions [k,4] with w >= 0, rotations [k,3,3], translations [k,3]), float64."""
    poses = np.asarray(poses, dtype=np.float64)
    q, Rm, t = np.empty((k, 4)), np.empty((k, 3, 3)), np.empty((k, 3))
    if poses.shape == (k, 7):
        bad = rigid.rigid_from_pose7(np.ascontiguousarray(poses), q, Rm, t)
        if bad >= 0:
            raise ValueError(f"poses: object {bad} has a non-finite position or a zero/non-finite quaternion")
    elif poses.shape == (k, 4, 4):
        bad = rigid.rigid_from_matrices(np.ascontiguousarray(poses), q, Rm, t)
        if bad >= 0:
            if not np.isfinite(poses[bad]).all():
                raise ValueError(f"poses has a non-finite value at object {bad}")
            raise ValueError(f"pose rotation of object {bad} has determinant <= 0 (a reflection or degenerate)")
    else:
        raise ValueError(f"poses must have shape ({k}, 7) or ({k}, 4, 4), got {poses.shape}")
    return q, Rm, t


class SceneRenderer:
    """Incremental splat renderer of one background and K rigid objects seen by V cameras.

    Args:
        background: Gaussians that never move (world frame).
        objects: one GaussianSet per object, in the object's own frame.
        viewmats: ``[V, 4, 4]`` world-to-camera (OpenCV), Ks ``[V, 3, 3]``, width, height.
        background_color: RGB behind everything (0..1).
        alpha_min: a Gaussian is skipped where its alpha is below this (default 1/255, as 3DGS).
        t_min: a pixel stops compositing once its transmittance would drop below this (default 1e-4).
        sh_degree: highest SH degree evaluated (``None``: all the Gaussians carry; lower is cheaper
            and drops view-dependent detail).
        rasterize_mode: "classic" or "antialiased" (the Mip filter of :func:`dsg_gym.splat.rasterize`),
            eps2d: the 2D low-pass in px^2; a world must be rendered with the options it was trained with
            (``World.splat_options``).
        tail_stride: 0 (default): every recomposited tile is merged exactly, so the images equal a full render
            bit for bit. N > 0: behind a tile's last object Gaussian the background is taken from per-tile tail
            tables (:mod:`dsg_gym.splat.numba_tails`: checkpoints every N entries of the tile's background list,
            built the first time an object reaches the tile); faster. The images differ from the exact merge
            only where the ``t_min`` cut-off falls differently (with ``t_min`` 0: float32 rounding); see
            docs/renderer.md. Memory: up to (D + 1) KiB per checkpoint, D the composited channels.
        compositing: "sorted" (default: one depth-sorted list per tile) or "layers": the background and the
            objects are splatted apart and merged per pixel by expected depth (:mod:`dsg_gym.splat.layers`;
            ``World.compositing`` says which a world was trained with). With layers a recomposited tile splats
            only the objects and merges them with the background-only render; ``tail_stride`` is not used.
        parallel: run the kernels on numba's threads. ``None``: where threads are allowed (a main process,
            not one started by ``multiprocessing`` such as a vector-env worker), each render takes the threaded
            or the single-threaded kernels, whichever has been faster lately
            (:class:`~dsg_gym.splat.threads.ThreadChooser`: threads stall when other work holds a core);
            see :mod:`dsg_gym.splat.threads`. The images are the same either way.

    Raising ``alpha_min``/``t_min`` or lowering ``sh_degree`` trades accuracy for speed
    (``benchmarks/pareto.py`` measures the trade).
    """

    def __init__(self, background: GaussianSet, objects: Sequence[GaussianSet], viewmats, Ks, width: int,
                 height: int, background_color=(0.0, 0.0, 0.0), near_plane: float = 0.01,
                 far_plane: float = 1e10, alpha_min: float = raster.ALPHA_MIN, t_min: float = raster.T_MIN,
                 sh_degree: int | None = None, rasterize_mode: str = "classic", eps2d: float = DEFAULT_EPS2D,
                 tail_stride: int = 0, parallel: bool | None = None, compositing: str = "sorted"):
        self.rasterize_mode, self.eps2d = check_splat_options(rasterize_mode, eps2d)
        self.layers = check_compositing(compositing) == "layers"
        if parallel not in (None, True, False):
            raise ValueError(f"parallel must be None, True or False, got {parallel!r}")
        self.parallel = parallel
        #: chooses threaded or single-threaded kernels per render by their measured speed (``parallel=None``)
        self.threads = ThreadChooser()
        self._consts = raster.make_consts(np.float32, alpha_min, t_min)
        self.alpha_min, self.t_min = float(alpha_min), float(t_min)
        self.background = background
        self.objects = list(objects)
        self.K = len(self.objects)
        self.near, self.far = float(near_plane), float(far_plane)
        self.background_color = np.asarray(background_color, np.float32).reshape(3)
        sizes = [o.num for o in self.objects]
        self._slices = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        def cat(field, shape):
            parts = [getattr(o, field) for o in self.objects]
            return np.ascontiguousarray(np.concatenate(parts), np.float32) if parts else np.zeros(shape, np.float32)

        self._obj_means = cat("means", (0, 3))
        self._obj_quats = cat("quats", (0, 4))
        self._obj_scales = cat("scales", (0, 3))
        self._obj_opac = cat("opacities", (0,))
        RenderSettings(alpha_min, t_min, sh_degree, tail_stride)  # validates
        self.tail_stride = int(tail_stride)
        deg = max([background.sh_degree] + [o.sh_degree for o in self.objects])
        if sh_degree is not None:
            deg = min(deg, int(sh_degree))
        nb_ = (deg + 1) ** 2
        self._sh_degree = deg
        self._obj_sh = np.zeros((len(self._obj_means), nb_, 3), np.float32)
        for k, o in enumerate(self.objects):
            m = min(nb_, o.sh.shape[1])
            self._obj_sh[self._slices[k]:self._slices[k + 1], :m] = o.sh[:, :m]
        self._obj_label = np.concatenate([np.full(n, k + 1, np.int64) for k, n in enumerate(sizes)]) \
            if sizes else np.zeros(0, np.int64)
        self.set_cameras(viewmats, Ks, width, height)

    # ----------------------------------------------------------------------------------------
    def set_cameras(self, viewmats, Ks, width: int, height: int) -> None:
        """Change the cameras; the next render is a full one."""
        viewmats = np.asarray(viewmats, np.float64)
        Ks = np.asarray(Ks, np.float64)
        if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (viewmats.shape[0], 3, 3):
            raise ValueError(f"viewmats must be [V,4,4] and Ks [V,3,3], got {viewmats.shape}, {Ks.shape}")
        if not (np.isfinite(viewmats).all() and np.isfinite(Ks).all()):
            raise ValueError("viewmats/Ks have non-finite values")
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"width and height must be positive, got {width}, {height}")
        self.viewmats, self.Ks = np.ascontiguousarray(viewmats), np.ascontiguousarray(Ks)
        self.width, self.height = int(width), int(height)
        self.V = viewmats.shape[0]
        self.tiles_x = (self.width + raster.TILE - 1) // raster.TILE
        self.tiles_y = (self.height + raster.TILE - 1) // raster.TILE
        self._campos = np.stack([-(V[:3, :3].T @ V[:3, 3]) for V in self.viewmats])
        bg = self.background
        par = parallel_allowed(self.parallel)
        self._bg = _project(np.ascontiguousarray(bg.means, np.float32), np.ascontiguousarray(bg.quats, np.float32),
                            np.ascontiguousarray(bg.scales, np.float32), np.ascontiguousarray(bg.opacities, np.float32),
                            self.viewmats, self.Ks, self.width, self.height, self.near, self.far,
                            self.alpha_min, self.eps2d, par)
        self._bg_bins = _bins(self._bg, self.tiles_x, self.tiles_y)
        self._bg_opac = np.ascontiguousarray(bg.opacities, np.float32)[None]  # [1 or V, n]
        if self.rasterize_mode == "antialiased":
            self._bg_opac = _antialias(self._bg.conics, self._bg_opac, self.eps2d, par)
        self._bg_rgb = np.empty((self.V, bg.num, 3), np.float32)
        sh = np.zeros((bg.num, (self._sh_degree + 1) ** 2, 3), np.float32)
        m = min(sh.shape[1], bg.sh.shape[1])
        sh[:, :m] = bg.sh[:, :m]
        for v in range(self.V):
            incr.sh_to_rgb(bg.means, np.eye(3), self._campos[v], sh, self._sh_degree, self._bg_rgb[v])
        self._state = None  # (channels key, poses, object arrays, buffers)
        self._bg_lists = {}  # layout -> the background's packed tile lists
        self._bg_render = None  # (layout, accumulators, transmittance) of the background alone
        self._bg_tails = None  # ((layout, stride), offsets, colours, transmittance, built) of the tail tables

    # ----------------------------------------------------------------------------------------
    def _channels(self, rgb: bool, mask: bool, depth: bool) -> tuple[int, int, int, int]:
        """(D, rgb offset, mask offset, depth offset); offset -1 when absent. Two layers always composite depth
        (their merge reads it)."""
        depth = depth or self.layers
        d = 0
        offs = []
        for want, n in ((rgb, 3), (mask, self.K + 1), (depth, 1)):
            offs.append(d if want else -1)
            d += n if want else 0
        return (d, *offs)

    def _colors(self, layout, rgb_vals, labels, depths) -> np.ndarray:
        """``[V, n, D]`` per-Gaussian channels (:func:`numba_incremental.fill_colors` per camera) from
        rgb_vals [V, n, 3], labels [n] and depths [V, n]."""
        col = np.empty((self.V, labels.shape[0], max(layout[0], 1)), np.float32)
        for v in range(self.V):
            incr.fill_colors(rgb_vals[v], labels, depths[v], layout[1], layout[2], layout[3], col[v])
        return col

    def _update_objects(self, st, poses, moved, layout, dirty, par: bool) -> None:
        """Re-pose, re-project and re-colour the moved objects; mark their old and new tiles in ``dirty`` (``None``:
        a full render, nothing to mark) (:func:`dsg_gym.splat.numba_batch.update_objects`, one scene)."""
        if not moved:
            return
        pairs = np.zeros((len(moved), 2), np.int64)
        pairs[:, 1] = moved
        if dirty is None:
            dirty = np.zeros((self.V, self.tiles_x * self.tiles_y), np.bool_)
        q, Rm, t = poses
        b = st["proj"]
        update = batch.update_objects if par else batch.update_objects_serial
        chunk = batch.chunk_for(len(moved), self.V, nb.get_num_threads() if par else 1)
        update(pairs, q[None], Rm[None], t[None], self._obj_means, self._obj_quats, self._obj_scales,
               np.ascontiguousarray(self._obj_opac[None]), self._obj_sh, self._obj_label, self._slices, self.viewmats,
               self.Ks, self._campos, float(self.width), float(self.height), self.near, self.far, self.alpha_min,
               self.eps2d, self.rasterize_mode == "antialiased", self._sh_degree, layout[1], layout[2], layout[3],
               self.tiles_x, st["means"][None], st["quats"][None], b.means2d, b.conics, b.depths, b.radii, b.rects,
               st["opac"], st["colors"], st["tile_masks"][None], dirty, chunk)

    def render(self, poses, *, rgb: bool = True, mask: bool = True, depth: bool = False,
               incremental: bool = True) -> RenderOutput:
        """Render the objects at ``poses`` from every camera: ``[K, 7]`` (x y z qw qx qy qz, the quaternion
        is renormalised) or ``[K, 4, 4]`` object-to-world rigid transforms (the rotation is re-orthonormalised)."""
        poses = _rigid(poses, self.K)
        layout = self._channels(rgb, mask, depth)
        t0 = time.perf_counter()
        par = self._parallel()
        composite = incr.composite_merged if par else incr.composite_merged_serial
        st = self._state
        full = st is None or st["layout"] != layout or not incremental
        if full:
            n = len(self._obj_means)
            st = {"layout": layout, "poses": None,
                  "means": np.empty((n, 3), np.float32), "quats": np.empty((n, 4), np.float32),
                  "proj": _Projected(np.zeros((self.V, n, 2), np.float32), np.zeros((self.V, n, 3), np.float32),
                                     np.zeros((self.V, n), np.float32), np.zeros((self.V, n, 2), np.int32),
                                     np.zeros((self.V, n, 4), np.int32)),
                  "colors": np.zeros((self.V, n, max(layout[0], 1)), np.float32),
                  # the objects' opacities as composited: per camera after the Mip filter
                  "opac": (np.zeros((self.V, n), np.float32) if self.rasterize_mode == "antialiased"
                           else self._obj_opac[None]),
                  "out": np.zeros((self.V, self.height, self.width, max(layout[0], 1)), np.float32),
                  "T": np.ones((self.V, self.height, self.width), np.float32),
                  # per object: the tiles its Gaussians' rectangles touch at its current pose
                  "tile_masks": np.zeros((self.K, self.V, self.tiles_x * self.tiles_y), np.bool_)}
            st["bg_rec"], st["bg_rect"], st["bg_rows"] = self._background_lists(layout)
            moved = list(range(self.K))
            dirty = None
        else:
            old_q, _, old_t = st["poses"]
            moved = [k for k in range(self.K)
                     if not (np.array_equal(poses[0][k], old_q[k]) and np.array_equal(poses[2][k], old_t[k]))]
            dirty = np.zeros((self.V, self.tiles_x * self.tiles_y), np.bool_)
        self._update_objects(st, poses, moved, layout, dirty, par)
        st["poses"] = poses
        if full:
            tiles = np.arange(self.V * self.tiles_x * self.tiles_y, dtype=np.int64)
        else:
            tiles = np.flatnonzero(dirty.reshape(-1)).astype(np.int64)
        if (incremental or self.layers) and "bg_out" not in st:
            st["bg_out"], st["bg_T"] = self.background_render(layout)
        if tiles.size:
            if dirty is None:
                b_off, b_gauss = _bins(st["proj"], self.tiles_x, self.tiles_y)
            else:  # only the recomposited tiles' lists are read
                active = (st["tile_masks"] & dirty).reshape(self.K, -1).any(axis=1)
                binning = incr.bin_tiles_parallel if par and self.V > 1 else incr.bin_tiles
                b_off, b_gauss = binning(st["proj"].depths.view(np.uint32), st["proj"].rects, dirty,
                                             self.tiles_x, self.tiles_y, self._slices, active)
            b = st["proj"]
            if self.layers:
                if "layer" not in st:
                    st["layer"] = layers.ObjectLayer(self.V, self.V, self.height, self.width, st["out"].shape[3])
                st["layer"].composite(tiles, par, (self.tiles_x, self.tiles_y, self.width, self.height), self._consts,
                                      (b.means2d, b.conics, st["opac"], st["colors"], b.rects, b.depths),
                                      (b_off, b_gauss), (st["bg_out"], st["bg_T"], st["bg_rec"], st["bg_rect"],
                                      st["bg_rows"]), layout[3], (st["out"], st["T"]))
            else:
                # incremental: pixels that no object reaches come from the background-only render
                cache = (st["bg_out"], st["bg_T"]) if incremental else (st["out"], st["T"])
                threads = nb.get_num_threads() if par else 1
                plan = incr.plan_tiles(tiles, self._bg_bins[0], b_off, bool(incremental), threads)
                tails = self.background_tails(layout, tiles[b_off[tiles + 1] > b_off[tiles]], par) if incremental \
                    else self._no_tails(layout)
                composite(*plan, st["bg_rec"], st["bg_rect"], st["bg_rows"], self._bg_bins[0], b.means2d, b.conics,
                          st["opac"], st["colors"], b.rects, b.depths, b_off, b_gauss, self.tiles_x, self.tiles_y,
                          self.width, self.height, self._consts, bool(incremental), *cache, *tails, st["out"], st["T"])
        self._state = st
        self.last_dirty_tiles = int(tiles.size)
        out = self._outputs(st, layout, tiles, depth)
        self.threads.record(par, time.perf_counter() - t0, tiles.size + _FIXED_WORK)
        return out

    def _parallel(self) -> bool:
        """Threads for this render: as ``parallel`` says, or (``None``) as :attr:`threads` chooses."""
        allowed = parallel_allowed(self.parallel)
        return self.threads.choose(allowed) if self.parallel is None else allowed

    def _background_lists(self, layout) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The background's tile lists as records with ``layout``'s channels, in compositing order
        (:func:`numba_incremental.pack_lists`); built once per layout and camera set."""
        if layout not in self._bg_lists:
            bg_colors = self._colors(layout, self._bg_rgb, np.zeros(self.background.num, np.int64), self._bg.depths)
            a, (off, gauss) = self._bg, self._bg_bins
            rec = np.empty((gauss.size, 8 + bg_colors.shape[2]), np.float32)
            rect = np.empty((gauss.size, 4), np.int32)
            rows = np.empty((gauss.size, raster.TILE), np.uint16)
            incr.pack_lists(a.means2d, a.conics, self._bg_opac, bg_colors, a.rects, a.depths, off, gauss, self.tiles_x,
                         self.tiles_y, self.width, self.height, self._consts, rec, rect, rows)
            self._bg_lists = {layout: (rec, rect, rows)}  # one layout at a time (they are large)
        return self._bg_lists[layout]

    def background_render(self, layout) -> tuple[np.ndarray, np.ndarray]:
        """The background alone composited on every tile with ``layout``'s channels (:meth:`_channels`):
        accumulators ``[V,H,W,D]`` and transmittance ``[V,H,W]``, built once per layout (read-only)."""
        if self._bg_render is None or self._bg_render[0] != layout:
            par = parallel_allowed(self.parallel)
            composite = incr.composite_merged if par else incr.composite_merged_serial
            rec, rect, rows = self._background_lists(layout)
            V, D = self.V, max(layout[0], 1)
            out = np.zeros((V, self.height, self.width, D), np.float32)
            T = np.ones((V, self.height, self.width), np.float32)
            tiles = np.arange(V * self.tiles_x * self.tiles_y, dtype=np.int64)
            none = np.zeros(tiles.size + 1, np.int64)
            plan = incr.plan_tiles(tiles, self._bg_bins[0], none, False, nb.get_num_threads() if par else 1)
            composite(*plan, rec, rect, rows, self._bg_bins[0], np.zeros((V, 0, 2), np.float32),
                      np.zeros((V, 0, 3), np.float32), np.zeros((1, 0), np.float32), np.zeros((V, 0, D), np.float32),
                      np.zeros((V, 0, 4), np.int32), np.zeros((V, 0), np.float32), none, np.zeros(0, np.int32),
                      self.tiles_x, self.tiles_y, self.width, self.height, self._consts, False, out, T,
                      *self._no_tails(layout), out, T)
            out.flags.writeable = False
            T.flags.writeable = False
            self._bg_render = (layout, out, T)
        return self._bg_render[1], self._bg_render[2]

    def _no_tails(self, layout) -> tuple:
        """The composite kernels' tail arguments for an exact merge (empty tables, made once per channel count)."""
        D = max(layout[0], 1)
        if D not in _NO_TAILS:
            _NO_TAILS[D] = (0, np.zeros(1, np.int64), np.zeros((0, raster.TILE ** 2, D), np.float32),
                            np.zeros((0, raster.TILE ** 2), np.float32))
        return _NO_TAILS[D]

    def background_tails(self, layout, tiles: np.ndarray, par: bool) -> tuple:
        """The composite kernels' tail arguments ``(stride, offsets, colours, transmittance)`` with the tables of
        ``tiles`` (any camera index ``c * T + t``; the background's camera is ``c % V``) built; the exact merge's
        when ``tail_stride`` is 0. Only tiles an object's list reaches need tables (elsewhere every pixel comes
        from the background render). The tables are allocated once per layout and camera set (pages are
        touched only as tiles are built) and filled tile by tile as objects reach them."""
        if self.tail_stride <= 0:
            return self._no_tails(layout)
        key = (layout, self.tail_stride)
        if self._bg_tails is None or self._bg_tails[0] != key:
            off = ntails.tail_offsets(self._bg_bins[0], self.tail_stride)
            D = max(layout[0], 1)
            self._bg_tails = (key, off, np.empty((off[-1], raster.TILE ** 2, D), np.float32),
                              np.empty((off[-1], raster.TILE ** 2), np.float32), np.zeros(off.size - 1, np.bool_))
        _, off, col, T, built = self._bg_tails
        todo = np.unique(np.asarray(tiles, np.int64) % built.size)
        todo = todo[~built[todo]]
        if todo.size:
            rec, rect, rows = self._background_lists(layout)
            build = ntails.build_tails if par else ntails.build_tails_serial
            grid = (self.tiles_x, self.tiles_y, self.width, self.height)
            build(todo, (rec, rect, rows, self._bg_bins[0]), self.tail_stride, (off, col, T), grid, self._consts,
                  nb.get_num_threads() if par else 1)
            built[todo] = True
        return self.tail_stride, off, col, T

    def buffers(self) -> tuple[np.ndarray, np.ndarray]:
        """The raw accumulators of the last render: colours [V,H,W,D] (no background) and T [V,H,W]."""
        if self._state is None:
            raise RuntimeError("nothing rendered yet")
        return self._state["out"], self._state["T"]

    def _outputs(self, st, layout, tiles, want_depth: bool) -> RenderOutput:
        """Update the output images on the recomposited tiles; return copies (depth when ``want_depth``)."""
        D, o_rgb, o_mask, o_depth = layout
        shape = (self.V, self.height, self.width)
        if "rgb" not in st:
            st["rgb"] = np.zeros(shape + (3,), np.uint8)
            st["mask"] = np.zeros(shape, np.uint8)
            st["depth"] = np.zeros(shape, np.float32)
            st["alpha"] = np.zeros(shape, np.float32)
        incr.finish_tiles(tiles, self.tiles_x, self.tiles_y, self.width, self.height, st["out"], st["T"],
                       self.background_color, o_rgb, o_mask, self.K + 1, o_depth, st["rgb"], st["mask"],
                       st["depth"], st["alpha"])
        return RenderOutput(rgb=st["rgb"].copy() if o_rgb >= 0 else None,
                            mask=st["mask"].copy() if o_mask >= 0 else None,
                            depth=st["depth"].copy() if want_depth else None, alpha=st["alpha"].copy())
