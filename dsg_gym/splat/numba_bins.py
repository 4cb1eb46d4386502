"""Numba kernels that build the per-tile Gaussian lists the compositing kernels read: a stable depth order
(LSD radix sort), tile binning (CSR lists per tile and per Gaussian) and the tile visiting order of
``prange`` loops."""

from __future__ import annotations

import numba as nb
import numpy as np

from .numba_raster import TILE


def balanced_order(n: int) -> np.ndarray:
    """Tile visiting order for ``prange``: thread chunks are contiguous ranges of iterations, so
    hand each thread a strided set of tiles spread over the image (balances the work)."""
    p = max(1, nb.get_num_threads())
    return np.concatenate([np.arange(r, n, p) for r in range(p)]).astype(np.int64)


@nb.njit(cache=True)
def depth_order(keys, rects):
    """Front-to-back order of each camera's visible Gaussians (stable LSD radix sort).

    keys [C,N] unsigned ints that order like the depths (the bit patterns of positive floats);
    rects [C,N,4] (x1 < x0: culled, left out). Returns order [C,N] int64 (visible Gaussians
    first, ties in index order) and counts [C] of visible Gaussians.
    """
    C = keys.shape[0]
    N = keys.shape[1]
    nbytes = keys.itemsize
    order = np.empty((C, N), dtype=np.int64)
    counts = np.zeros(C, dtype=np.int64)
    tmp = np.empty(N, dtype=np.int64)
    hist = np.zeros((nbytes, 256), dtype=np.int64)
    for c in range(C):
        n = 0
        for i in range(N):
            if rects[c, i, 1] >= rects[c, i, 0]:
                order[c, n] = i
                n += 1
        counts[c] = n
        hist[:, :] = 0
        for k in range(n):
            key = keys[c, order[c, k]]
            for b in range(nbytes):
                hist[b, (key >> (8 * b)) & 255] += 1
        src = order[c]
        dst = tmp
        swapped = False
        for b in range(nbytes):
            if hist[b].max() == n:
                continue  # every key has the same byte here: nothing to reorder
            pos = np.empty(256, dtype=np.int64)
            acc = 0
            for d in range(256):
                pos[d] = acc
                acc += hist[b, d]
            for k in range(n):
                i = src[k]
                d = (keys[c, i] >> (8 * b)) & 255
                dst[pos[d]] = i
                pos[d] += 1
            src, dst = dst, src
            swapped = not swapped
        if swapped:
            order[c, :n] = tmp[:n]
    return order, counts


@nb.njit(cache=True, inline="always")
def _tile_rect(rects, c, i):
    """Tile range ``(tx0, tx1, ty0, ty1)`` (inclusive) of Gaussian ``i``'s pixel rectangle in camera ``c``;
    ``tx1 < tx0`` when the rectangle is empty."""
    x0 = rects[c, i, 0]
    x1 = rects[c, i, 1]
    if x1 < x0:
        return 0, -1, 0, -1
    return x0 // TILE, x1 // TILE, rects[c, i, 2] // TILE, rects[c, i, 3] // TILE


@nb.njit(cache=True)
def bin_gaussians(rects, order, nvis, tiles_x, tiles_y):
    """Build per-tile lists of Gaussians in depth order.

    rects [C,N,4] int32 inclusive pixel rectangles (x1 < x0: culled); order [C,N] int64 and
    nvis [C] from ``depth_order``. Returns ``tile_offsets [C*T+1]`` (CSR over tiles),
    ``tile_gauss [P]`` (Gaussian index per pair), ``gauss_offsets [C*N+1]`` and
    ``gauss_pairs [P]`` (pair slots of each (camera, Gaussian), ascending tile order).
    """
    C = rects.shape[0]
    N = rects.shape[1]
    T = tiles_x * tiles_y
    counts = np.zeros(C * T, dtype=np.int64)
    gcounts = np.zeros(C * N + 1, dtype=np.int64)
    for c in range(C):
        for i in range(N):
            tx0, tx1, ty0, ty1 = _tile_rect(rects, c, i)
            if tx1 < tx0:
                continue
            gcounts[c * N + i + 1] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[c * T + ty * tiles_x + tx] += 1
    tile_offsets = np.zeros(C * T + 1, dtype=np.int64)
    for t in range(C * T):
        tile_offsets[t + 1] = tile_offsets[t] + counts[t]
    gauss_offsets = np.cumsum(gcounts)
    P = tile_offsets[C * T]
    tile_gauss = np.empty(P, dtype=np.int32)
    gauss_pairs = np.empty(P, dtype=np.int64)
    fill = tile_offsets[:-1].copy()
    gfill = gauss_offsets[:-1].copy()
    for c in range(C):
        for k in range(nvis[c]):
            i = order[c, k]
            tx0, tx1, ty0, ty1 = _tile_rect(rects, c, i)
            if tx1 < tx0:
                continue
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = c * T + ty * tiles_x + tx
                    slot = fill[t]
                    fill[t] += 1
                    tile_gauss[slot] = i
                    gauss_pairs[gfill[c * N + i]] = slot
                    gfill[c * N + i] += 1
    return tile_offsets, tile_gauss, gauss_offsets, gauss_pairs
