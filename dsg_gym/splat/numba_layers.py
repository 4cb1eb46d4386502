"""Numba kernel of the runtime renderer's two-layer compositing (:mod:`dsg_gym.splat.layers` is the torch one).

The background layer is rendered once per camera set (every tile); the objects' layer only on the tiles the
objects reach. :func:`merge_tiles` merges the two per pixel on the listed tiles, the layer with the smaller
expected depth (accumulated depth over alpha) in front, as :func:`dsg_gym.splat.layers.merge_layers` does (with
its margin, :data:`dsg_gym.splat_options.LAYER_MARGIN`).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..splat_options import LAYER_MARGIN
from . import numba_incremental as incr
from .numba_raster import TILE

__all__ = ["ObjectLayer", "composite_layers", "merge_tiles"]

_EMPTY = np.float32(1e-6)  # a layer whose alpha is below this does not cover the pixel (dsg_gym.splat.layers)
_FAR = np.float32(3.0e38)  # the expected depth of a layer that does not cover a pixel
_AHEAD = np.float32(1.0 + LAYER_MARGIN)  # the objects go in front unless the background is nearer than this


@nb.njit(cache=True)
def _merge_tile(ct, tiles_x, width, height, o_depth, obj_out, obj_T, bg_out, bg_T, out, T):
    nt = tiles_x * ((height + TILE - 1) // TILE)
    c = ct // nt
    t = ct - c * nt
    ty = t // tiles_x
    tx = t - ty * tiles_x
    cb = c % bg_T.shape[0]
    D = out.shape[3]
    one = np.float32(1.0)
    for y in range(ty * TILE, min((ty + 1) * TILE, height)):
        for x in range(tx * TILE, min((tx + 1) * TILE, width)):
            ta = obj_T[c, y, x]
            tb = bg_T[cb, y, x]
            ea = obj_out[c, y, x, o_depth] / (one - ta) if one - ta > _EMPTY else _FAR
            eb = bg_out[cb, y, x, o_depth] / (one - tb) if one - tb > _EMPTY else _FAR
            if ea < eb * _AHEAD:
                for ch in range(D):
                    out[c, y, x, ch] = obj_out[c, y, x, ch] + ta * bg_out[cb, y, x, ch]
            else:
                for ch in range(D):
                    out[c, y, x, ch] = bg_out[cb, y, x, ch] + tb * obj_out[c, y, x, ch]
            T[c, y, x] = ta * tb


@nb.njit(cache=True)
def merge_tiles(tiles, tiles_x, width, height, o_depth, obj_out, obj_T, bg_out, bg_T, out, T):
    """Merge the objects' layer (obj_out [C,H,W,D], obj_T [C,H,W]) and the background's (bg_out [V,H,W,D], bg_T
    [V,H,W]; camera ``c`` reads the background's camera ``c % V``, so several scenes may share one) into out
    [C,H,W,D] and T [C,H,W] on ``tiles`` (each ``c * tiles + t``). Channel ``o_depth`` holds the accumulated
    depth; every channel is merged, the nearer layer's plus its transmittance times the other's. One thread: the
    work is a few operations per pixel of the recomposited tiles."""
    for m in range(tiles.shape[0]):
        _merge_tile(tiles[m], tiles_x, width, height, o_depth, obj_out, obj_T, bg_out, bg_T, out, T)


def composite_layers(
    tiles, par: bool, grid, consts, objects, bins, background, blank, o_depth, obj_buf, out
) -> None:
    """Recomposite ``tiles`` (each ``c * tiles + t``) in two layers: the objects alone into ``obj_buf``, then
    merged with the background-only render into ``out``.

    ``grid``: (tiles_x, tiles_y, width, height); ``consts``: the renderer's thresholds; ``objects``: (means2d,
    conics, opacities, colors, rects, depths) of every object Gaussian per camera, as
    :func:`~dsg_gym.splat.numba_incremental.composite_merged` takes them; ``bins``: their tile lists (offsets,
    indices); ``background``: (colours [V,H,W,D], transmittance [V,H,W], packed records, rects, rows) of the
    background alone (``SceneRenderer.background_render`` and its packed lists; only their shapes are read of the
    lists); ``blank``: zeros [V,H,W,D] and ones [V,H,W], the empty layer the objects' pixels start from (the
    compositing kernel's cache path: pixels no object reaches are copied from it, the others reuse the row spans
    it computes); ``o_depth``: the accumulated depth channel; ``obj_buf`` and ``out``: (colours [C,H,W,D],
    transmittance [C,H,W]). ``par``: threaded or single-threaded compositing (the same bits); the merge
    (:func:`merge_tiles`) runs on the calling thread.
    """
    tiles_x, tiles_y, width, height = grid
    bg_out, bg_T, a_rec, a_rect, a_rows = background
    obj_out, obj_T = obj_buf
    V, nt = bg_T.shape[0], tiles_x * tiles_y
    empty = np.zeros(V * nt + 1, np.int64)  # no background Gaussians in the objects' layer
    plan = incr.plan_tiles(tiles, empty, bins[0], True, nb.get_num_threads() if par else 1)
    composite = incr.composite_merged if par else incr.composite_merged_serial
    D = obj_out.shape[3]
    no_tails = (0, np.zeros(1, np.int64), np.zeros((0, TILE * TILE, D), np.float32),
                np.zeros((0, TILE * TILE), np.float32))  # fmt: skip
    composite(*plan, a_rec, a_rect, a_rows, empty, *objects, *bins, tiles_x, tiles_y, width, height, consts, True,
              *blank, *no_tails, obj_out, obj_T)  # fmt: skip
    merge_tiles(tiles, tiles_x, width, height, o_depth, obj_out, obj_T, bg_out, bg_T, out[0], out[1])


class ObjectLayer:
    """The objects' layer of C images (colours ``[C,H,W,D]``, transmittance ``[C,H,W]``) and the blank layer of
    the V background cameras it starts from (zeros and ones, read-only; image ``c`` reads camera ``c % V``).

    A renderer keeps one per render state (C = V for one scene, E * V for E scenes sharing the background) and
    recomposites through :meth:`composite`.
    """

    def __init__(self, images: int, cameras: int, height: int, width: int, channels: int):
        self.out = np.zeros((images, height, width, channels), np.float32)
        self.T = np.ones((images, height, width), np.float32)
        self.blank = (np.zeros((cameras, height, width, channels), np.float32),
                      np.ones((cameras, height, width), np.float32))  # fmt: skip
        for a in self.blank:
            a.flags.writeable = False

    def composite(self, tiles, par: bool, grid, consts, objects, bins, background, o_depth, out) -> None:
        """:func:`composite_layers` into this layer's buffers, from its blank layer."""
        composite_layers(tiles, par, grid, consts, objects, bins, background, self.blank, o_depth, (self.out, self.T),
                         out)  # fmt: skip
