"""Render many copies of one scene, each with its own object poses, sharing the background.

``BatchSceneRenderer`` holds E scenes that share a :class:`~dsg_gym.scene_renderer.SceneRenderer`'s background
(its projection, packed tile lists and background-only render, built once per camera set) and keep their own
objects and images. ``render(poses [E, K, 7])`` re-poses the moved objects of every scene in one parallel kernel
call (:func:`dsg_gym.splat.numba_batch.update_objects`), bins and recomposites every scene's changed tiles in one
more, and finishes them in a third. Each scene's images equal those of its own ``SceneRenderer`` given the same
poses, bit for bit (tested).
"""

from __future__ import annotations

import time

import numba as nb
import numpy as np

from .scene_renderer import RenderOutput, SceneRenderer
from .splat import numba_batch as batch
from .splat import numba_incremental as incr
from .splat import numba_layers as layers
from .splat import numba_rigid as rigid
from .splat.threads import ThreadChooser, parallel_allowed

__all__ = ["BatchSceneRenderer"]


class BatchSceneRenderer:
    """E scenes of one world (one background, K objects, V cameras), each with its own object poses.

    Args:
        renderer: the one-scene renderer whose background, objects, cameras and settings are shared.
        num_scenes: E >= 1.
    """

    def __init__(self, renderer: SceneRenderer, num_scenes: int):
        if isinstance(num_scenes, bool) or not isinstance(num_scenes, (int, np.integer)) or num_scenes < 1:
            raise ValueError(f"num_scenes must be a positive integer, got {num_scenes!r}")
        self.base = renderer
        self.E = int(num_scenes)
        self.K, self.V = renderer.K, renderer.V
        self.width, self.height = renderer.width, renderer.height
        self._state = None
        #: threaded or single-threaded kernels per render (the base renderer's ``parallel`` rule)
        self.threads = ThreadChooser()

    def _new_state(self, layout) -> dict:
        r, E, V = self.base, self.E, self.V
        n, C, D = len(r._obj_means), E * V, max(layout[0], 1)
        shape = (C, r.height, r.width)
        return {
            "layout": layout,
            "poses": np.full((E, self.K, 7), np.nan),  # NaN: every object of every scene counts as moved
            "q": np.zeros((E, self.K, 4)), "R": np.zeros((E, self.K, 3, 3)), "t": np.zeros((E, self.K, 3)),
            "means": np.zeros((E, n, 3), np.float32), "quats": np.zeros((E, n, 4), np.float32),
            "m2": np.zeros((C, n, 2), np.float32), "conics": np.zeros((C, n, 3), np.float32),
            "depths": np.zeros((C, n), np.float32), "radii": np.zeros((C, n, 2), np.int32),
            "rects": np.zeros((C, n, 4), np.int32), "colors": np.zeros((C, n, D), np.float32),
            "opac": (np.zeros((C, n), np.float32) if r.rasterize_mode == "antialiased"
                     else np.ascontiguousarray(r._obj_opac[None])),
            "tile_masks": np.zeros((E, self.K, V, r.tiles_x * r.tiles_y), np.bool_),
            "out": np.zeros(shape + (D,), np.float32), "T": np.ones(shape, np.float32),
            "rgb": np.zeros(shape + (3,), np.uint8), "mask": np.zeros(shape, np.uint8),
            "depth": np.zeros(shape, np.float32), "alpha": np.zeros(shape, np.float32),
        }  # fmt: skip

    def render(
        self, poses, *, rgb: bool = True, mask: bool = True, depth: bool = False, fresh=None
    ) -> RenderOutput:
        """Render every scene: ``poses [E, K, 7]`` (x y z qw qx qy qz; quaternions renormalised).

        ``fresh``: ``None`` or bool ``[E]``; a fresh scene is recomposited on every tile (as after a reset).
        Returns images with a leading scene axis: rgb ``[E, V, H, W, 3]`` etc. (copies).
        """
        r, E, V, K = self.base, self.E, self.V, self.K
        p = np.ascontiguousarray(poses, dtype=np.float64)
        if p.shape != (E, K, 7):
            raise ValueError(f"poses must have shape ({E}, {K}, 7), got {p.shape}")
        layout = r._channels(rgb, mask, depth)
        st = self._state
        if st is None or st["layout"] != layout:
            st = self._new_state(layout)
            fresh = np.ones(E, bool)
        fresh = np.zeros(E, bool) if fresh is None else np.asarray(fresh, bool).reshape(E)
        q, R, t = np.empty((E * K, 4)), np.empty((E * K, 3, 3)), np.empty((E * K, 3))
        bad = rigid.rigid_from_pose7(p.reshape(E * K, 7), q, R, t)
        if bad >= 0:
            raise ValueError(
                f"poses: scene {bad // K} object {bad % K} has a non-finite position or a zero quaternion"
            )
        q, R, t = q.reshape(E, K, 4), R.reshape(E, K, 3, 3), t.reshape(E, K, 3)
        moved = fresh[:, None] | np.any(q != st["q"], axis=2) | np.any(t != st["t"], axis=2)
        st["q"][moved], st["R"][moved], st["t"][moved] = q[moved], R[moved], t[moved]
        st["poses"] = p.copy()
        pairs = np.argwhere(moved).astype(np.int64)
        T = r.tiles_x * r.tiles_y
        dirty = np.zeros((E * V, T), np.bool_)
        dirty.reshape(E, V, T)[fresh] = True
        t0 = time.perf_counter()
        allowed = parallel_allowed(r.parallel)
        par = self.threads.choose(allowed) if r.parallel is None else allowed
        update = batch.update_objects if par else batch.update_objects_serial
        chunk = batch.chunk_for(len(pairs), V, nb.get_num_threads() if par else 1)
        update(pairs, st["q"], st["R"], st["t"], r._obj_means, r._obj_quats, r._obj_scales,
               np.ascontiguousarray(r._obj_opac[None]), r._obj_sh, r._obj_label, r._slices, r.viewmats, r.Ks,
               r._campos, float(r.width), float(r.height), r.near, r.far, r.alpha_min, r.eps2d,
               r.rasterize_mode == "antialiased", r._sh_degree, layout[1], layout[2], layout[3], r.tiles_x,
               st["means"], st["quats"], st["m2"], st["conics"], st["depths"], st["radii"], st["rects"], st["opac"],
               st["colors"], st["tile_masks"], dirty, chunk)  # fmt: skip
        tiles = np.flatnonzero(dirty.reshape(-1)).astype(np.int64)
        if tiles.size:
            active = (st["tile_masks"] & dirty.reshape(E, 1, V, T)).any(axis=(0, 2, 3))
            binning = incr.bin_tiles_parallel if par else incr.bin_tiles
            b_off, b_gauss = binning(
                st["depths"].view(np.uint32), st["rects"], dirty, r.tiles_x, r.tiles_y, r._slices, active
            )
            bg_rec, bg_rect, bg_rows = r._background_lists(layout)
            bg_out, bg_T = r.background_render(layout)
            objects = (st["m2"], st["conics"], st["opac"], st["colors"], st["rects"], st["depths"])
            if r.layers:
                if "layer" not in st:
                    st["layer"] = layers.ObjectLayer(E * V, V, r.height, r.width, st["out"].shape[3])
                st["layer"].composite(tiles, par, (r.tiles_x, r.tiles_y, r.width, r.height), r._consts, objects,
                                      (b_off, b_gauss), (bg_out, bg_T, bg_rec, bg_rect, bg_rows), layout[3],
                                      (st["out"], st["T"]))  # fmt: skip
            else:
                threads = nb.get_num_threads() if par else 1
                plan = incr.plan_tiles(tiles, r._bg_bins[0], b_off, True, threads)
                composite = incr.composite_merged if par else incr.composite_merged_serial
                tails = r.background_tails(layout, tiles[b_off[tiles + 1] > b_off[tiles]], par)
                composite(*plan, bg_rec, bg_rect, bg_rows, r._bg_bins[0], *objects, b_off, b_gauss, r.tiles_x,
                          r.tiles_y, r.width, r.height, r._consts, True, bg_out, bg_T, *tails, st["out"],
                          st["T"])  # fmt: skip
            incr.finish_tiles(tiles, r.tiles_x, r.tiles_y, r.width, r.height, st["out"], st["T"], r.background_color,
                              layout[1], layout[2], K + 1, layout[3], st["rgb"], st["mask"], st["depth"],
                              st["alpha"])  # fmt: skip
        self._state = st
        self.last_dirty_tiles = int(tiles.size)
        self.threads.record(par, time.perf_counter() - t0, tiles.size + 8 * E)
        img = (E, V, r.height, r.width)
        return RenderOutput(rgb=st["rgb"].reshape(img + (3,)).copy() if layout[1] >= 0 else None,
                            mask=st["mask"].reshape(img).copy() if layout[2] >= 0 else None,
                            depth=st["depth"].reshape(img).copy() if depth else None,
                            alpha=st["alpha"].reshape(img).copy())  # fmt: skip
