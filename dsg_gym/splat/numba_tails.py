"""Numba kernels for background tails: the background's own composite of the end of a tile's list.

In an incremental render most of a recomposited tile's background list lies behind the tile's last object
Gaussian (at 128 px on the bundled world about two thirds of the entries the merge visits, at 256 px about five
sixths). Behind that point each unfinished pixel only composites the background, so its result is

    C_end = C + T * C_tail,   T_end = T * T_tail,

where ``(C_tail, T_tail)`` is the background composited alone from that list position with T = 1. A tail
table holds ``(C_tail, T_tail)`` for every pixel of a tile at every ``stride``-th position of its list
(a checkpoint); the merge composites exactly up to the next checkpoint and then adds the table in one step.

The result differs from the exact merge by float32 rounding and by where the transmittance cut-off falls (the
tail stops at T_tail < t_min instead of T T_tail < t_min, and a Gaussian that would cross the cut-off is left
out): with t_min = 0 by a few 1e-7 in the accumulators, with the env's t_min by a few uint8 levels on about 1 %
of the pixels of the bundled world, no further from the uncut composite than the exact merge. Every path that
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
def _build_jobs(jobs, background, stride, tables, grid, consts):
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
    for m in range(jobs.shape[0]):
        ct, q = jobs[m, 0], jobs[m, 1]
        px0, py0, pw, ph = reset_tile(ct % T, tiles_x, width, height, acc, trans, row_done, xc, yc)
        npix = pw * ph
        ndone = 0
        i = a_off[ct] + q * stride
        ie = a_off[ct + 1]
        while i < ie and ndone < npix:
            f = a_rec[i]
            ndone += splat_rows(consts, f[0], f[1], f[2], f[3], f[4], f[5], a_rect[i, 2], a_rect[i, 3], a_rows[i],
                                f[8:], py0, ph, xc, yc, acc, trans, row_done, f[7])  # fmt: skip
            i += 1
        k = tail_off[ct] + q
        for p in range(TILE * TILE):
            for d in range(D):
                tail_col[k, p, d] = acc[p, d]
            tail_T[k, p] = trans[p]


@nb.njit(parallel=True, cache=True)
def build_tails(tiles, background, stride, tables, grid, consts, nthreads):
    """Fill the tail tables of ``tiles`` (background tile indices ``c * T + t``), in parallel over their
    checkpoints: table ``tail_off[ct] + q`` is the background list of tile ``ct`` composited alone from entry
    ``q * stride`` (accumulators [256, D] into tail_col, transmittance [256] into tail_T).

    ``background``: (a_rec, a_rect, a_rows, a_off), the background as
    :func:`~dsg_gym.splat.numba_incremental.composite_merged`'s ``a`` set; ``tables``: (tail_off [C*T+1]
    (:func:`tail_offsets`), tail_col [M, 256, D], tail_T [M, 256]); ``grid``: (tiles_x, tiles_y, width, height);
    ``consts``: the compositing constants."""
    jobs = _jobs(tiles, tables[0])
    P = max(1, min(nthreads, jobs.shape[0]))
    for w in nb.prange(P):
        _build_jobs(jobs[w::P], background, stride, tables, grid, consts)


@nb.njit(cache=True)
def build_tails_serial(tiles, background, stride, tables, grid, consts, nthreads):
    """:func:`build_tails` on the calling thread (the same tables)."""
    _build_jobs(_jobs(tiles, tables[0]), background, stride, tables, grid, consts)


@nb.njit(cache=True)
def _jobs(tiles, tail_off):
    """[J, 2] (tile, checkpoint) pairs of ``tiles``."""
    n = 0
    for ct in tiles:
        n += tail_off[ct + 1] - tail_off[ct]
    jobs = np.empty((n, 2), np.int64)
    n = 0
    for ct in tiles:
        for q in range(tail_off[ct + 1] - tail_off[ct]):
            jobs[n, 0] = ct
            jobs[n, 1] = q
            n += 1
    return jobs
