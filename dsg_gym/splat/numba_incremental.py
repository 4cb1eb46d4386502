"""Numba kernels for incremental rendering of a static background plus moving objects.

The background and the objects are two Gaussian sets ``a`` and ``b``, each with its own
projection and per-tile depth-sorted lists. A tile is composited by merging the two lists by
depth (ties: background first, exactly like a stable sort of the concatenation
``[background, objects]``), so a tile recomposited here equals the same tile of a full
``rasterize`` of the concatenated scene bit for bit: both call ``splat_forward``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .numba_bins import depth_order
from .numba_intrinsics import borrow
from .numba_raster import (
    FASTMATH,
    TILE,
    reset_tile,
    sigma_cutoff,
    span_rows,
    splat_forward,
    splat_rows,
    store_tile,
    tile_state,
)
from .numba_sh import sh_basis
from .numba_tails import add_tail

_TILE_BITS = TILE.bit_length() - 1  # tile index of a pixel (>= 0): p >> _TILE_BITS
assert 1 << _TILE_BITS == TILE


@nb.njit(cache=True, inline="always")
def _copy_uncovered(c, ca, ct, px0, py0, pw, ph, yc, b_m2, b_cn, b_op, b_rect, b_off, b_gauss, consts,
                    bg_colors, bg_T, acc, trans, row_done, b_rows, cover):
    """Fill the tile pixels no object Gaussian can reach from the background-only render and mark them
    finished (the cache's camera is ``ca``); returns how many. Leaves in b_rows [>= list length, 16] each listed object Gaussian's row spans
    (:func:`span_rows`), which its compositing reuses; cover [16] is scratch."""
    D = acc.shape[1]
    for ly in range(TILE):
        cover[ly] = 0  # bit lx of row ly: an object may blend into that pixel
    cb = 0 if b_op.shape[0] == 1 else c
    j0 = b_off[ct]
    for s in range(j0, b_off[ct + 1]):
        g = b_gauss[s]
        rows = b_rows[s - j0]
        span_rows(consts, b_m2[c, g, 0], b_m2[c, g, 1], b_cn[c, g, 0], b_cn[c, g, 1], b_cn[c, g, 2], b_op[cb, g],
                  b_rect[c, g, 0], b_rect[c, g, 1], b_rect[c, g, 2], b_rect[c, g, 3], px0, py0, pw, ph, yc, rows)
        for ly in range(TILE):
            cover[ly] |= rows[ly]
    n = 0
    for ly in range(ph):
        for lx in range(pw):
            if (cover[ly] >> lx) & 1:
                continue
            p = ly * TILE + lx
            for d in range(D):
                acc[p, d] = bg_colors[ca, py0 + ly, px0 + lx, d]
            trans[p] = bg_T[ca, py0 + ly, px0 + lx]
            row_done[ly] |= np.int64(1) << lx
            n += 1
    return n


@nb.njit(cache=True)
def pack_lists(m2, cn, op, col, rect, depth, off, gauss, tiles_x, tiles_y, width, height, consts, rec, rec_rect,
               rec_rows):
    """Gather a Gaussian set's per-tile lists into records in list order, so that compositing a tile reads
    its Gaussians' data front to back from consecutive memory instead of gathering by index.

    Inputs as ``composite_merged``'s ``b`` set (means2d [C,N,2], conics [C,N,3], opacities [Co,N], colors
    [C,N,D], rects [C,N,4], depths [C,N], tile CSR offsets [C*T+1] and indices), the image size and the
    compositing constants. Writes rec [E, 8 + D] float32 (u, v, conic a, b, c, opacity, depth, sigma cut-off
    (:func:`~dsg_gym.splat.numba_raster.sigma_cutoff`), colour channels), rec_rect [E, 4] int32 and
    rec_rows [E, 16] uint16 (the entry's row spans in its tile, :func:`span_rows`) for the E list entries.
    """
    T = tiles_x * tiles_y
    D = col.shape[2]
    for ct in range(off.shape[0] - 1):
        c = ct // T
        co = 0 if op.shape[0] == 1 else c
        px0, py0, pw, ph, _, _, _, _, yc = tile_state(ct - c * T, tiles_x, width, height, 1, rec.dtype)
        for s in range(off[ct], off[ct + 1]):
            g = gauss[s]
            rec[s, 0] = m2[c, g, 0]
            rec[s, 1] = m2[c, g, 1]
            rec[s, 2] = cn[c, g, 0]
            rec[s, 3] = cn[c, g, 1]
            rec[s, 4] = cn[c, g, 2]
            rec[s, 5] = op[co, g]
            rec[s, 6] = depth[c, g]
            rec[s, 7] = sigma_cutoff(consts, rec[s, 5])
            for d in range(D):
                rec[s, 8 + d] = col[c, g, d]
            for j in range(4):
                rec_rect[s, j] = rect[c, g, j]
            span_rows(consts, rec[s, 0], rec[s, 1], rec[s, 2], rec[s, 3], rec[s, 4], rec[s, 5], rect[c, g, 0],
                      rect[c, g, 1], rect[c, g, 2], rect[c, g, 3], px0, py0, pw, ph, yc, rec_rows[s])


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def _composite_tile(ct, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off,
                    b_gauss, tiles_x, tiles_y, width, height, consts, use_cache, cache, out_colors, out_T, acc, trans,
                    row_done, xc, yc, b_rows, cover):
    bg_colors, bg_T, tail_stride, tail_off, tail_col, tail_T = cache
    T = tiles_x * tiles_y
    c = ct // T
    ca = c % ((a_off.shape[0] - 1) // T)  # the background's camera: several scenes may share one background
    px0, py0, pw, ph = reset_tile(ct - c * T, tiles_x, width, height, acc, trans, row_done, xc, yc)
    npix = pw * ph
    cb = 0 if b_op.shape[0] == 1 else c
    ndone = 0
    i = i0 = a_off[ct - (c - ca) * T]
    ie = a_off[ct - (c - ca) * T + 1]
    j0 = j = b_off[ct]
    je = b_off[ct + 1]
    if use_cache:
        ndone = _copy_uncovered(c, ca, ct, px0, py0, pw, ph, yc, b_m2, b_cn, b_op, b_rect, b_off, b_gauss, consts,
                                bg_colors, bg_T, acc, trans, row_done, b_rows, cover)
    while j < je and ndone < npix:
        if i < ie and a_rec[i, 6] <= b_depth[c, b_gauss[j]]:
            f = a_rec[i]
            ndone += splat_rows(consts, f[0], f[1], f[2], f[3], f[4], f[5], a_rect[i, 2], a_rect[i, 3], a_rows[i],
                                f[8:], py0, ph, xc, yc, acc, trans, row_done, f[7])
            i += 1
        else:
            g = b_gauss[j]
            if use_cache:
                ndone += splat_rows(consts, b_m2[c, g, 0], b_m2[c, g, 1], b_cn[c, g, 0], b_cn[c, g, 1],
                                    b_cn[c, g, 2], b_op[cb, g], b_rect[c, g, 2], b_rect[c, g, 3], b_rows[j - j0],
                                    b_col[c, g], py0, ph, xc, yc, acc, trans, row_done)
            else:
                ndone += splat_forward(consts, b_m2[c, g, 0], b_m2[c, g, 1], b_cn[c, g, 0], b_cn[c, g, 1],
                                       b_cn[c, g, 2], b_op[cb, g], b_rect[c, g, 0], b_rect[c, g, 1],
                                       b_rect[c, g, 2], b_rect[c, g, 3], b_col[c, g], px0, py0, pw, ph, xc, yc,
                                       acc, trans, row_done)
            j += 1
    # the objects are done: the background's rest, exactly up to the next tail checkpoint (if any)
    stop = ie
    if use_cache and tail_stride > 0 and i < ie:
        q = (i - i0 + tail_stride - 1) // tail_stride
        stop = min(i0 + q * tail_stride, ie)
    while i < stop and ndone < npix:
        f = a_rec[i]
        ndone += splat_rows(consts, f[0], f[1], f[2], f[3], f[4], f[5], a_rect[i, 2], a_rect[i, 3], a_rows[i], f[8:],
                            py0, ph, xc, yc, acc, trans, row_done, f[7])
        i += 1
    if i < ie and ndone < npix:  # only with tails: the rest from the table
        add_tail(tail_off[ct - (c - ca) * T] + (i - i0) // tail_stride, pw, ph, tail_col, tail_T, acc, trans,
                 row_done)
    store_tile(c, px0, py0, pw, ph, acc, trans, out_colors, out_T)


@nb.njit(cache=True, fastmath=FASTMATH)
def _composite_tiles(tiles, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off, b_gauss,
                     tiles_x, tiles_y, width, height, consts, use_cache, cache, out_colors, out_T, acc, trans,
                     row_done, xc, yc, b_rows, cover):
    """Recomposite ``tiles`` one after the other in the scratch arrays acc [256, D], trans [256], row_done,
    xc, yc, cover [16] and b_rows [>= longest object list with the cache, 16]; ``cache`` holds
    (bg_colors, bg_T, tail_stride, tail_off, tail_col, tail_T) (a tuple: calls of more than 30 arguments compile to
    a ``*args`` call, which numba cannot inline). Every argument is borrowed
    (:func:`~dsg_gym.splat.numba_intrinsics.borrow`; the caller holds them): the per-Gaussian and per-row views
    then cost no reference counting. Per-tile allocations with their counted views made the single-threaded
    kernel 2x slower than the threaded one run on one thread."""
    tiles, a_rec, a_rect, a_rows, a_off = borrow(tiles), borrow(a_rec), borrow(a_rect), borrow(a_rows), borrow(a_off)
    b_m2, b_cn, b_op, b_col, b_rect = borrow(b_m2), borrow(b_cn), borrow(b_op), borrow(b_col), borrow(b_rect)
    b_depth, b_off, b_gauss, consts = borrow(b_depth), borrow(b_off), borrow(b_gauss), borrow(consts)
    bg_colors, bg_T, tail_stride, tail_off, tail_col, tail_T = cache
    bg_colors, bg_T, out_colors, out_T = borrow(bg_colors), borrow(bg_T), borrow(out_colors), borrow(out_T)
    acc, trans, row_done, xc, yc = borrow(acc), borrow(trans), borrow(row_done), borrow(xc), borrow(yc)
    b_rows, cover = borrow(b_rows), borrow(cover)
    cache = (bg_colors, bg_T, tail_stride, borrow(tail_off), borrow(tail_col), borrow(tail_T))
    for m in range(tiles.shape[0]):
        _composite_tile(tiles[m], a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off,
                        b_gauss, tiles_x, tiles_y, width, height, consts, use_cache, cache, out_colors, out_T, acc,
                        trans, row_done, xc, yc, b_rows, cover)


@nb.njit(cache=True)
def _composite_chunk(tiles, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off, b_gauss,
                     tiles_x, tiles_y, width, height, consts, use_cache, bg_colors, bg_T, tail_stride, tail_off,
                     tail_col, tail_T, out_colors, out_T):
    """:func:`_composite_tiles` with scratch arrays made for ``tiles`` (once, not per tile)."""
    D = out_colors.shape[3]
    longest = 0
    if use_cache:
        for m in range(tiles.shape[0]):
            longest = max(longest, b_off[tiles[m] + 1] - b_off[tiles[m]])
    _composite_tiles(tiles, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off, b_gauss,
                     tiles_x, tiles_y, width, height, consts, use_cache,
                     (bg_colors, bg_T, tail_stride, tail_off, tail_col, tail_T), out_colors, out_T,
                     np.empty((TILE * TILE, D), out_colors.dtype), np.empty(TILE * TILE, out_colors.dtype),
                     np.empty(TILE, np.int64), np.empty(TILE, out_colors.dtype), np.empty(TILE, out_colors.dtype),
                     np.empty((longest, TILE), np.uint16), np.empty(TILE, np.int64))


@nb.njit(cache=True)
def plan_tiles(tiles, a_off, b_off, use_cache, nthreads):
    """Split the tiles to recomposite among ``nthreads`` threads (longest first, each to the least loaded
    thread). A tile's estimated cost is its object-list length plus, without the background cache, its
    background-list length (with the cache only object-covered pixels blend the background: a constant).
    Returns ``order`` [M] (the tiles, thread by thread) and ``starts`` [nthreads + 1]."""
    M = tiles.shape[0]
    P = max(1, min(nthreads, M))
    cost = np.empty(M, np.int64)
    for m in range(M):
        ct = tiles[m]
        cost[m] = b_off[ct + 1] - b_off[ct] + (40 if use_cache else a_off[ct + 1] - a_off[ct])
    rank = np.argsort(-cost, kind="mergesort")
    owner = np.empty(M, np.int64)
    load = np.zeros(P, np.int64)
    count = np.zeros(P + 1, np.int64)
    for r in range(M):
        m = rank[r]
        t = 0
        for q in range(1, P):
            if load[q] < load[t]:
                t = q
        owner[m] = t
        load[t] += cost[m]
        count[t + 1] += 1
    starts = np.cumsum(count)
    fill = starts[:-1].copy()
    order = np.empty(M, np.int64)
    for r in range(M):
        m = rank[r]
        order[fill[owner[m]]] = tiles[m]
        fill[owner[m]] += 1
    return order, starts


@nb.njit(parallel=True, cache=True, fastmath=FASTMATH)
def composite_merged(order, starts, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect, b_depth, b_off,
                     b_gauss, tiles_x, tiles_y, width, height, consts, use_cache, bg_colors, bg_T, tail_stride,
                     tail_off, tail_col, tail_T, out_colors, out_T):
    """Recomposite tiles (each ``c * T + t``) into out_colors/out_T; thread ``k`` takes
    ``order[starts[k]:starts[k + 1]]`` (:func:`plan_tiles`).

    Background ``a``: its tile lists as records (:func:`pack_lists`: a_rec [E, 8 + D], a_rect [E, 4], row
    spans a_rows [E, 16]) and CSR offsets a_off [Ca*T+1]; with the cache, C may be a multiple of Ca (scenes that
    share the background: camera c composites over the background's camera ``c % Ca``), else Ca = C. Objects
    ``b``: means2d [C,N,2], conics [C,N,3], opacities [Co,N] (Co in {1, C}), colors [C,N,D], rects [C,N,4],
    depths [C,N], tile CSR offsets [C*T+1] and Gaussian indices.

    ``use_cache``: reuse a background-only render (bg_colors [Ca,H,W,D], bg_T [Ca,H,W]; ignored
    otherwise). A pixel that no object Gaussian's footprint reaches (the row spans where its alpha
    can reach alpha_min, with the 1 px margin of ``row_pixel_range``) receives exactly the
    background-only sequence of blends, so its accumulators are copied from the cache and marked
    finished; only object-covered pixels are composited, and the objects' row spans computed for the
    cover are reused. The result is the same bit for bit.

    ``tail_stride`` > 0 (with the cache): behind a tile's last object Gaussian the background is composited up
    to the next multiple of ``tail_stride`` in its list and the rest added from the tile's tail table
    (:mod:`.numba_tails`: tail_off [Ca*T+1], tail_col [M, 256, D], tail_T [M, 256], built for every tile
    listed here); the result then differs from the exact merge by float32 rounding. 0: no tables (pass empty
    arrays).
    """
    for k in nb.prange(starts.shape[0] - 1):
        _composite_chunk(order[starts[k]:starts[k + 1]], a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col,
                         b_rect, b_depth, b_off, b_gauss, tiles_x, tiles_y, width, height, consts, use_cache,
                         bg_colors, bg_T, tail_stride, tail_off, tail_col, tail_T, out_colors, out_T)


@nb.njit(cache=True)
def composite_merged_serial(order, starts, a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect,
                            b_depth, b_off, b_gauss, tiles_x, tiles_y, width, height, consts, use_cache, bg_colors,
                            bg_T, tail_stride, tail_off, tail_col, tail_T, out_colors, out_T):
    """``composite_merged`` on the calling thread (:func:`dsg_gym.splat.threads.parallel_allowed`): the same
    tiles with the same arithmetic, so the same bits."""
    _composite_chunk(order[starts[0]:starts[-1]], a_rec, a_rect, a_rows, a_off, b_m2, b_cn, b_op, b_col, b_rect,
                     b_depth, b_off, b_gauss, tiles_x, tiles_y, width, height, consts, use_cache, bg_colors, bg_T,
                     tail_stride, tail_off, tail_col, tail_T, out_colors, out_T)


@nb.njit(cache=True)
def mark_tiles(rects, tiles_x, dirty):
    """dirty [C, T] |= tiles touched by any rectangle in rects [C, n, 4]."""
    C = rects.shape[0]
    for c in range(C):
        for i in range(rects.shape[1]):
            x0 = rects[c, i, 0]
            x1 = rects[c, i, 1]
            if x1 < x0:
                continue
            for ty in range(rects[c, i, 2] // TILE, rects[c, i, 3] // TILE + 1):
                for tx in range(x0 // TILE, x1 // TILE + 1):
                    dirty[c, ty * tiles_x + tx] = True


@nb.njit(cache=True)
def sh_to_rgb(means_w, R, campos, sh, degree, out):
    """RGB = max(0, SH(dir) + 0.5) for Gaussians of one object seen from ``campos``.

    means_w [n,3] world centres, R [3,3] the object's rotation (the view direction is taken
    into the object frame, where the coefficients live), sh [n,K,3], out [n,3]. The basis is
    :mod:`.numba_sh`'s (the training kernels'), evaluated in float64.
    """
    K = (degree + 1) * (degree + 1)
    b = np.empty(16)
    for i in range(means_w.shape[0]):
        wx = np.float64(means_w[i, 0]) - campos[0]
        wy = np.float64(means_w[i, 1]) - campos[1]
        wz = np.float64(means_w[i, 2]) - campos[2]
        x = R[0, 0] * wx + R[1, 0] * wy + R[2, 0] * wz
        y = R[0, 1] * wx + R[1, 1] * wy + R[2, 1] * wz
        z = R[0, 2] * wx + R[1, 2] * wy + R[2, 2] * wz
        n = math.sqrt(x * x + y * y + z * z)
        s = 1.0 / n if n > 0 else 1.0
        sh_basis(degree, x * s, y * s, z * s, b)
        for ch in range(3):
            v = 0.0
            for k in range(K):
                v += b[k] * np.float64(sh[i, k, ch])
            out[i, ch] = max(v + 0.5, 0.0)


@nb.njit(cache=True)
def finish_tiles(tiles, tiles_x, tiles_y, width, height, out, T, bg_rgb, o_rgb, o_mask, n_mask, o_depth,
                 rgb, mask, depth, alpha):
    """Turn the accumulators of the listed tiles into outputs (in place).

    rgb uint8 = round(255 clip(C + T bg)); mask = argmax of the id weights with T added to the
    background's; depth = accumulated depth / alpha (0 where alpha <= 1e-6); alpha = 1 - T.
    """
    nt = tiles_x * tiles_y
    for m in range(tiles.shape[0]):
        ct = tiles[m]
        c = ct // nt
        t = ct - c * nt
        ty = t // tiles_x
        tx = t - ty * tiles_x
        for y in range(ty * TILE, min((ty + 1) * TILE, height)):
            for x in range(tx * TILE, min((tx + 1) * TILE, width)):
                tr = T[c, y, x]
                a = np.float32(1.0) - tr
                alpha[c, y, x] = a
                if o_rgb >= 0:
                    for ch in range(3):
                        v = out[c, y, x, o_rgb + ch] + tr * bg_rgb[ch]
                        v = min(max(v, np.float32(0.0)), np.float32(1.0))
                        rgb[c, y, x, ch] = np.uint8(v * np.float32(255.0) + np.float32(0.5))
                if o_mask >= 0:
                    best = out[c, y, x, o_mask] + tr
                    arg = 0
                    for k in range(1, n_mask):
                        w = out[c, y, x, o_mask + k]
                        if w > best:
                            best = w
                            arg = k
                    mask[c, y, x] = arg
                if o_depth >= 0:
                    depth[c, y, x] = out[c, y, x, o_depth] / a if a > 1e-6 else np.float32(0.0)


@nb.njit(cache=True)
def _bin_select(c, rects, dc, tiles_x, T, slices, active, counts, sel):
    """Camera c: count the flagged tiles' entries into counts [C*T] and list the Gaussians that reach a flagged
    tile in sel[c] (index order); returns how many."""
    n = 0
    for k in range(active.shape[0]):
        if not active[k]:
            continue
        for i in range(slices[k], slices[k + 1]):
            x0 = rects[c, i, 0]
            x1 = rects[c, i, 1]
            if x1 < x0:
                continue
            hit = False
            for ty in range(rects[c, i, 2] >> _TILE_BITS, (rects[c, i, 3] >> _TILE_BITS) + 1):
                for tx in range(x0 >> _TILE_BITS, (x1 >> _TILE_BITS) + 1):
                    t = ty * tiles_x + tx
                    if dc[t]:
                        counts[c * T + t] += 1
                        hit = True
            if hit:
                sel[c, n] = i
                n += 1
    return n


@nb.njit(cache=True)
def _bin_fill(c, n, keys, rects, dc, tiles_x, T, sel, fill, gauss):
    """Camera c: write its selected Gaussians into the flagged tiles' lists in depth order."""
    sub_keys = np.empty((1, n), dtype=keys.dtype)
    sub_rects = np.empty((1, n, 4), dtype=rects.dtype)
    for k in range(n):
        sub_keys[0, k] = keys[c, sel[c, k]]
        for j in range(4):
            sub_rects[0, k, j] = rects[c, sel[c, k], j]
    order, _ = depth_order(sub_keys, sub_rects)
    for k in range(n):
        i = sel[c, order[0, k]]
        for ty in range(rects[c, i, 2] >> _TILE_BITS, (rects[c, i, 3] >> _TILE_BITS) + 1):
            for tx in range(rects[c, i, 0] >> _TILE_BITS, (rects[c, i, 1] >> _TILE_BITS) + 1):
                t = ty * tiles_x + tx
                if dc[t]:
                    gauss[fill[c * T + t]] = i
                    fill[c * T + t] += 1


@nb.njit(cache=True)
def _bin_offsets(counts):
    offsets = np.zeros(counts.shape[0] + 1, dtype=np.int64)
    for t in range(counts.shape[0]):
        offsets[t + 1] = offsets[t] + counts[t]
    return offsets


@nb.njit(cache=True)
def bin_tiles(keys, rects, dirty, tiles_x, tiles_y, slices, active):
    """Per-tile depth-ordered Gaussian lists of the tiles flagged in ``dirty`` [C, T] only.

    keys [C,N] unsigned ints that order like the depths, rects [C,N,4] (x1 < x0: culled); the N
    Gaussians are K objects' consecutive ranges ``slices`` [K+1], and only the objects flagged in
    ``active`` [K] are looked at (the others must reach no flagged tile). Returns ``tile_offsets
    [C*T+1]`` (CSR; tiles not flagged get empty lists) and ``tile_gauss`` int32. A flagged tile's list
    equals the one ``numba_bins.bin_gaussians`` builds from ``depth_order`` (depth order, ties in
    index order): the same stable sort, applied to the Gaussians that reach a flagged tile only (a
    stable sort of a subsequence is the subsequence of the stable sort).
    """
    C, N, T = rects.shape[0], rects.shape[1], tiles_x * tiles_y
    counts = np.zeros(C * T, dtype=np.int64)
    sel = np.empty((C, N), dtype=np.int64)
    nsel = np.zeros(C, dtype=np.int64)
    for c in range(C):
        nsel[c] = _bin_select(c, rects, dirty[c], tiles_x, T, slices, active, counts, sel)
    offsets = _bin_offsets(counts)
    gauss = np.empty(offsets[C * T], dtype=np.int32)
    fill = offsets[:-1].copy()
    for c in range(C):
        _bin_fill(c, nsel[c], keys, rects, dirty[c], tiles_x, T, sel, fill, gauss)
    return offsets, gauss


@nb.njit(parallel=True, cache=True)
def bin_tiles_parallel(keys, rects, dirty, tiles_x, tiles_y, slices, active):
    """:func:`bin_tiles` with the cameras on numba's threads (the same lists)."""
    C, N, T = rects.shape[0], rects.shape[1], tiles_x * tiles_y
    counts = np.zeros(C * T, dtype=np.int64)
    sel = np.empty((C, N), dtype=np.int64)
    nsel = np.zeros(C, dtype=np.int64)
    for c in nb.prange(C):
        nsel[c] = _bin_select(c, rects, dirty[c], tiles_x, T, slices, active, counts, sel)
    offsets = _bin_offsets(counts)
    gauss = np.empty(offsets[C * T], dtype=np.int32)
    fill = offsets[:-1].copy()
    for c in nb.prange(C):
        _bin_fill(c, nsel[c], keys, rects, dirty[c], tiles_x, T, sel, fill, gauss)
    return offsets, gauss


@nb.njit(cache=True)
def fill_colors(rgb, labels, depths, o_rgb, o_mask, o_depth, out):
    """Per-Gaussian channel values of one camera: out [n, D] = 0, then RGB (rgb [n,3]) at ``o_rgb``, a one-hot
    1 at ``o_mask + labels[i]`` and the depth at ``o_depth`` (each only where its offset is >= 0)."""
    for i in range(out.shape[0]):
        for d in range(out.shape[1]):
            out[i, d] = 0.0
        if o_rgb >= 0:
            for ch in range(3):
                out[i, o_rgb + ch] = rgb[i, ch]
        if o_mask >= 0:
            out[i, o_mask + labels[i]] = 1.0
        if o_depth >= 0:
            out[i, o_depth] = depths[i]
