"""Numba kernels for background tails: the background's own composite of the end of a tile's list.

In an incremental render most of a recomposited tile's background list lies behind the tile's last object
Gaussian (at 128 px on the bundled world about two thirds of the entries the merge visits, at 256 px about five
sixths). Behind that point each unfinished pixel only composites the background, so its result is

    C_end = C + T * C_tail,   T_end = T * T_tail,

where ``(C_tail, T_tail)`` is the background composited alone from that list position with T = 1. A tail
table holds ``(C_tail, T_tail)`` for every pixel of a tile at every ``stride``-th position of its list
(a checkpoint); the merge composites exactly up to the next checkpoint and then adds the table in one step.
The tables of a tile are built in one pass over its list, each segment between checkpoints composited alone and
chained to the tables after it.

The result differs from the exact merge by float32 rounding and by where the transmittance cut-off falls (it
applies within a segment, not to the running transmittance, and a Gaussian that would cross it is left out):
with t_min = 0 by a few 1e-7 in the accumulators, with the env's t_min by a few uint8 levels on about 1 % of the
pixels of the bundled world, no further from the uncut composite than the exact merge. Every path that
composites with the same tables (threaded or not, one scene or a batch) gives the same bits.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .numba_raster import FASTMATH, TILE, reset_tile, splat_rows

__all__ = ["tail_offsets", "build_tails", "build_tails_serial", "add_tail"]


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def add_tail(k, pw, ph, tail_col, tail_T, acc, trans, row_done):
    """Add tail table ``k`` (tail_col [M, 256, D], tail_T [M, 256]) to the tile's unfinished pixels."""
    D = acc.shape[1]
    for ly in range(ph):
        done = row_done[ly]
        for lx in range(pw):
            if (done >> lx) & 1:
                continue
            p = ly * TILE + lx
            tp = trans[p]
            for d in range(D):
                acc[p, d] += tp * tail_col[k, p, d]
            trans[p] = tp * tail_T[k, p]


def tail_offsets(a_off: np.ndarray, stride: int) -> np.ndarray:
    """CSR offsets [C*T + 1] of the tail tables: tile ``ct`` with a list of n entries has ``ceil(n / stride)``
    tables (checkpoints at list positions 0, stride, 2 stride, ...)."""
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    n = np.diff(a_off)
    return np.concatenate([[0], np.cumsum((n + stride - 1) // stride)]).astype(np.int64)


@nb.njit(cache=True, fastmath=FASTMATH)
def _build_tiles(tiles, background, stride, tables, grid, consts):
    """Fill the tables of ``tiles`` one tile at a time, from the tile's last segment to its first."""
    a_rec, a_rect, a_rows, a_off = background
    tail_off, tail_col, tail_T = tables
    tiles_x, tiles_y, width, height = grid
    D = tail_col.shape[2]
    T = tiles_x * tiles_y
    acc = np.empty((TILE * TILE, D), tail_col.dtype)
    trans = np.empty(TILE * TILE, tail_col.dtype)
    row_done = np.empty(TILE, np.int64)
    xc = np.empty(TILE, tail_col.dtype)
    yc = np.empty(TILE, tail_col.dtype)
    for ct in tiles:
        i0, ie = a_off[ct], a_off[ct + 1]
        nq = tail_off[ct + 1] - tail_off[ct]
        for q in range(nq - 1, -1, -1):
            px0, py0, pw, ph = reset_tile(ct % T, tiles_x, width, height, acc, trans, row_done, xc, yc)
            npix = pw * ph
            ndone = 0
            i = i0 + q * stride
            end = min(i + stride, ie)
            while i < end and ndone < npix:
                f = a_rec[i]
                ndone += splat_rows(consts, f[0], f[1], f[2], f[3], f[4], f[5], a_rect[i, 2], a_rect[i, 3],
                                    a_rows[i], f[8:], py0, ph, xc, yc, acc, trans, row_done, f[7])  # fmt: skip
                i += 1
            k = tail_off[ct] + q
            for ly in range(TILE):
                for lx in range(TILE):
                    p = ly * TILE + lx
                    tp = trans[p]
                    if (
                        q == nq - 1 or (row_done[ly] >> lx) & 1
                    ):  # the last segment, or finished inside this one
                        for d in range(D):
                            tail_col[k, p, d] = acc[p, d]
                        tail_T[k, p] = tp
                    else:
                        for d in range(D):
                            tail_col[k, p, d] = acc[p, d] + tp * tail_col[k + 1, p, d]
                        tail_T[k, p] = tp * tail_T[k + 1, p]


@nb.njit(parallel=True, cache=True)
def build_tails(tiles, background, stride, tables, grid, consts, nthreads):
    """Fill the tail tables of ``tiles`` (background tile indices ``c * T + t``), in parallel over the tiles.
    Table ``tail_off[ct] + q`` holds the background list of tile ``ct`` from entry ``q * stride`` on, composited
    alone (accumulators [256, D] into tail_col, transmittance [256] into tail_T). Each ``stride``-entry segment
    is composited alone and chained to the table after it (``C_q = C_seg + T_seg C_q+1``, ``T_q = T_seg
    T_q+1``; a pixel that finishes inside a segment takes nothing after it), so a tile costs one pass over its
    list.

    ``background``: (a_rec, a_rect, a_rows, a_off), the background as
    :func:`~dsg_gym.splat.numba_incremental.composite_merged`'s ``a`` set; ``tables``: (tail_off [C*T+1]
    (:func:`tail_offsets`), tail_col [M, 256, D], tail_T [M, 256]); ``grid``: (tiles_x, tiles_y, width, height);
    ``consts``: the compositing constants."""
    P = max(1, min(nthreads, tiles.shape[0]))
    for w in nb.prange(P):
        _build_tiles(tiles[w::P], background, stride, tables, grid, consts)


@nb.njit(cache=True)
def build_tails_serial(tiles, background, stride, tables, grid, consts, nthreads):
    """:func:`build_tails` on the calling thread (the same tables)."""
    _build_tiles(tiles, background, stride, tables, grid, consts)
