"""Numba kernels: front-to-back alpha compositing of 16x16 tiles (the tile lists come from
:mod:`.numba_bins`; the gradients of this pass are :mod:`.numba_raster_backward`).

Work is split into 16x16 pixel tiles processed in parallel (one tile per task, no atomics).
Inside a tile, Gaussians are visited front to back and each one only touches, row by row, the
pixel span where its alpha can reach 1/255 (plus one pixel of margin), so the cost follows the
area the Gaussians really cover, not ``tiles x list length x 256``. Float32 inputs are
composited in float32 (constants come in the working dtype from ``make_consts``).

Compositing rule per pixel (identical in forward and backward, so the backward pass replays the
forward decisions bit for bit):

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,   dx = x + 0.5 - u,   dy = y + 0.5 - v
    alpha = min(0.99, o exp(-sigma));  skipped if sigma < 0 or alpha < 1/255
    if T (1 - alpha) < 1e-4: the pixel is finished (this Gaussian does not contribute)
    C += alpha T color;  T *= 1 - alpha

Memory layout: ``gather_pairs`` first copies each pair's Gaussian data (position, conic, opacity, rectangle,
colour) into pair order, so both passes stream through it instead of missing the cache once per pair.
The row helpers (``row_pixel_range``, ``column_bits``, ``pop_lowest_bit``, ``rows_finished``,
``pixel_step``) are shared with the backward pass and with training-side kernels that replay the same
per-pixel decisions.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .numba_intrinsics import lowest_bit

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# No reassociation or contraction: forward and backward must take identical decisions.
FASTMATH = {"nsz", "arcp"}


def make_consts(dtype, alpha_min: float = ALPHA_MIN, t_min: float = T_MIN) -> np.ndarray:
    """Constants of the compositing kernels in the working dtype (float32 kernels stay float32):
    (alpha max, alpha min, T min, 0.5, 1, 0). ``alpha_min`` (a Gaussian is skipped at a pixel where its
    alpha is below it; the projection's footprint must use the same value) and ``t_min`` (a pixel is
    finished once its transmittance would drop below it) trade accuracy for speed; the defaults are
    3DGS's 1/255 and 1e-4."""
    check_thresholds(alpha_min, t_min)
    return np.array([ALPHA_MAX, alpha_min, t_min, 0.5, 1.0, 0.0], dtype=dtype)


def check_thresholds(alpha_min: float, t_min: float) -> None:
    """ValueError unless 0 < alpha_min < ALPHA_MAX and 0 <= t_min < 1 (both finite)."""
    if not (math.isfinite(alpha_min) and 0.0 < alpha_min < ALPHA_MAX):
        raise ValueError(f"alpha_min must lie in (0, {ALPHA_MAX}), got {alpha_min!r}")
    if not (math.isfinite(t_min) and 0.0 <= t_min < 1.0):
        raise ValueError(f"t_min must lie in [0, 1), got {t_min!r}")


@nb.njit(cache=True, inline="always")
def log_opacity_ratio(consts, o):
    """log(o / alpha_min) in float64: the Gaussian's reach, shared by the row spans and the sigma cut-off."""
    return math.log(np.float64(o) / np.float64(consts[1]))


@nb.njit(cache=True, inline="always")
def sigma_cutoff_from_log(consts, logo):
    """Beyond this sigma, alpha < alpha_min for sure, so the exp is skipped; in the working dtype (no conversion
    per pixel), with a margin that covers rounding. ``logo``: :func:`log_opacity_ratio`."""
    return consts[5] + np.float32(logo * 1.0001 + 1e-4)


@nb.njit(cache=True, inline="always")
def row_pixel_range(ca, cb, cc, u, dy, logo, x0, x1, px0):
    """Tile-local x range of a row's pixels where alpha can reach 1/255 (1 px margin).

    Solves a dx^2 + 2 b dy dx + c dy^2 <= 2 ln(255 o) for dx in float64 and clips it to the
    absolute pixel range [x0, x1]; returns lo > hi when the row misses the footprint.
    """
    a = np.float64(ca)
    bdy = np.float64(cb) * dy
    disc = bdy * bdy - a * (np.float64(cc) * dy * dy - 2.0 * logo)
    if not (disc >= 0.0) or not (a > 0.0):
        return 1, 0
    r = math.sqrt(disc)
    lo = math.ceil(np.float64(u) - 0.5 + (-bdy - r) / a) - 1.0
    hi = math.floor(np.float64(u) - 0.5 + (-bdy + r) / a) + 1.0
    lo = max(lo, np.float64(x0)) - px0
    hi = min(hi, np.float64(x1)) - px0
    if hi < lo:
        return 1, 0
    return int(lo), int(hi)


@nb.njit(cache=True, inline="always")
def column_bits(x0, x1):
    """Bit mask of tile columns x0..x1."""
    return ((np.int64(1) << (x1 + 1)) - 1) ^ ((np.int64(1) << x0) - 1)


@nb.njit(cache=True, inline="always")
def pop_lowest_bit(bits):
    """(index of the lowest set bit of ``bits`` (not 0), ``bits`` without it)."""
    return lowest_bit(bits), bits & (bits - 1)


@nb.njit(cache=True, inline="always")
def rows_finished(row_done, y0, y1, x0, x1):
    """True when every pixel of columns x0..x1 in rows y0..y1 has finished."""
    bits = column_bits(x0, x1)
    for ly in range(y0, y1 + 1):
        if row_done[ly] & bits != bits:
            return False
    return True


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def pixel_step(consts, ca, bdy, cdy, dx, o, smax, tp, row_done, ly, lx):
    """The compositing rule at tile pixel (lx, ly) (module docstring) for a Gaussian with halved conic terms
    ca, cdy (row part bdy = b dy) at x offset dx, opacity o, sigma cut-off smax, over transmittance tp.
    Returns ``(code, alpha, gauss, nt)``: code 0 = no contribution, 1 = the pixel finishes here (marked in
    row_done; the Gaussian does not contribute), 2 = blend with weight alpha tp, leaving transmittance nt;
    gauss = exp(-sigma). Every forward, backward and replaying kernel decides through this function, so they
    agree bit for bit."""
    zero = consts[5]
    sigma = (ca * dx + bdy) * dx + cdy
    if sigma < zero or sigma > smax:
        return 0, zero, zero, tp
    gauss = math.exp(-sigma)
    alpha = min(consts[0], o * gauss)
    if alpha < consts[1]:
        return 0, alpha, gauss, tp
    nt = tp * (consts[4] - alpha)
    if nt < consts[2]:
        row_done[ly] |= np.int64(1) << lx
        return 1, alpha, gauss, nt
    return 2, alpha, gauss, nt


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def _blend_row(consts, todo, ly, dy, u, ca, cb, cc_, o, smax, col, xc, acc, trans, row_done):
    """Blend one Gaussian into the pixels ``todo`` (bits) of tile row ``ly`` (dy = row centre - v, ca and
    cc_ the halved conic terms), in increasing x; returns how many pixels it finished. The per-pixel
    arithmetic of every forward kernel (the backward pass replays it)."""
    D = col.shape[0]
    finished = 0
    bdy = cb * dy
    cdy = cc_ * dy * dy
    while todo != 0:
        lx, todo = pop_lowest_bit(todo)
        p = ly * TILE + lx
        tp = trans[p]
        code, alpha, _, nt = pixel_step(consts, ca, bdy, cdy, xc[lx] - u, o, smax, tp, row_done, ly, lx)
        if code < 2:
            finished += code
            continue
        w = alpha * tp
        for d in range(D):
            acc[p, d] += w * col[d]
        trans[p] = nt
    return finished


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def splat_forward(
    consts,
    u,
    v,
    conic_a,
    conic_b,
    conic_c,
    o,
    rx0,
    rx1,
    ry0,
    ry1,
    col,
    px0,
    py0,
    pw,
    ph,
    xc,
    yc,
    acc,
    trans,
    row_done,
):
    """Composite one Gaussian into a tile's accumulators; returns how many pixels it finished.

    Every forward kernel calls it (or :func:`splat_rows`, the same with precomputed spans), so that
    full and incremental renders agree bit for bit. (rx0, rx1, ry0, ry1) is the Gaussian's
    absolute pixel rectangle; acc [256, D], trans [256], row_done [16] the tile state (bit lx of row
    ly set: that pixel has finished). A row's unfinished pixels in the span are visited in increasing x
    (:func:`_blend_row`).
    """
    half = consts[3]
    ca = conic_a * half
    cc_ = conic_c * half
    logo = log_opacity_ratio(consts, o)
    smax = sigma_cutoff_from_log(consts, logo)
    y0 = max(ry0, py0) - py0
    y1 = min(ry1, py0 + ph - 1) - py0
    xr0 = max(rx0, px0)
    xr1 = min(rx1, px0 + pw - 1)
    finished = 0
    if xr1 < xr0 or rows_finished(row_done, y0, y1, xr0 - px0, xr1 - px0):
        return 0  # hidden behind finished pixels: nothing to do
    rect_bits = column_bits(xr0 - px0, xr1 - px0)
    for ly in range(y0, y1 + 1):
        if row_done[ly] & rect_bits == rect_bits:
            continue
        dy = yc[ly] - v
        x0, x1 = row_pixel_range(conic_a, conic_b, conic_c, u, np.float64(dy), logo, xr0, xr1, px0)
        if x1 < x0:
            continue
        todo = column_bits(x0, x1) & ~row_done[ly]  # the span's unfinished pixels
        if todo == 0:
            continue
        finished += _blend_row(
            consts, todo, ly, dy, u, ca, conic_b, cc_, o, smax, col, xc, acc, trans, row_done
        )
    return finished


@nb.njit(cache=True, inline="always")
def span_rows(consts, u, v, conic_a, conic_b, conic_c, o, rx0, rx1, ry0, ry1, px0, py0, pw, ph, yc, rows):
    """rows [16] = per tile row, the bits of the pixels :func:`splat_forward` would visit for this Gaussian
    (its row span clipped to the rectangle and the tile; 0 for rows it does not reach). Same inputs, same
    arithmetic: a span computed here equals the one ``splat_forward`` computes."""
    for ly in range(TILE):
        rows[ly] = 0
    y0 = max(ry0, py0) - py0
    y1 = min(ry1, py0 + ph - 1) - py0
    xr0 = max(rx0, px0)
    xr1 = min(rx1, px0 + pw - 1)
    if xr1 < xr0:
        return
    logo = log_opacity_ratio(consts, o)
    for ly in range(y0, y1 + 1):
        dy = yc[ly] - v
        x0, x1 = row_pixel_range(conic_a, conic_b, conic_c, u, np.float64(dy), logo, xr0, xr1, px0)
        if x0 <= x1:
            rows[ly] = column_bits(x0, x1)


@nb.njit(cache=True, inline="always")
def sigma_cutoff(consts, o):
    """The sigma beyond which a Gaussian of opacity ``o`` has alpha < alpha_min for sure, in the working dtype:
    what :func:`splat_forward` computes, the same bits."""
    return sigma_cutoff_from_log(consts, log_opacity_ratio(consts, o))


@nb.njit(cache=True, inline="always", fastmath=FASTMATH)
def splat_rows(
    consts,
    u,
    v,
    conic_a,
    conic_b,
    conic_c,
    o,
    ry0,
    ry1,
    rows,
    col,
    py0,
    ph,
    xc,
    yc,
    acc,
    trans,
    row_done,
    smax=np.nan,
):
    """:func:`splat_forward` with the row spans given (``rows`` from :func:`span_rows`): visits the same
    pixels in the same order with the same arithmetic, so the result is the same bit for bit; returns how
    many pixels it finished. ``smax``: the Gaussian's :func:`sigma_cutoff` when the caller has it (NaN:
    computed here, on the first row with work)."""
    half = consts[3]
    zero = consts[5]
    y0 = max(ry0, py0) - py0
    y1 = min(ry1, py0 + ph - 1) - py0
    finished = 0
    ready = False
    ca = cc_ = zero
    for ly in range(y0, y1 + 1):
        todo = np.int64(rows[ly]) & ~row_done[ly]
        if todo == 0:
            continue
        if (
            not ready
        ):  # set up on the first row with work: Gaussians hidden behind finished pixels cost no log
            ready = True
            ca = conic_a * half
            cc_ = conic_c * half
            if smax != smax:
                smax = sigma_cutoff(consts, o)
        dy = yc[ly] - v
        finished += _blend_row(
            consts, todo, ly, dy, u, ca, conic_b, cc_, o, smax, col, xc, acc, trans, row_done
        )
    return finished


@nb.njit(cache=True, inline="always")
def reset_tile(tile, tiles_x, width, height, acc, trans, row_done, xc, yc):
    """Start tile ``tile`` in given accumulators (acc [256, D] = 0, trans [256] = 1, row_done [16] = 0: bit lx
    set when pixel (lx, ly) has finished; xc, yc [16] the pixel centres); returns (px0, py0, pw, ph)."""
    ty = tile // tiles_x
    tx = tile - ty * tiles_x
    px0 = tx * TILE
    py0 = ty * TILE
    pw = min(TILE, width - px0)
    ph = min(TILE, height - py0)
    for p in range(TILE * TILE):
        for d in range(acc.shape[1]):
            acc[p, d] = 0
        trans[p] = 1
    for j in range(TILE):
        row_done[j] = 0
        xc[j] = (px0 + j) + 0.5
        yc[j] = (py0 + j) + 0.5
    return px0, py0, pw, ph


@nb.njit(cache=True, inline="always")
def tile_state(tile, tiles_x, width, height, D, dtype):
    """Fresh accumulators of one tile: (px0, py0, pw, ph, acc, trans, row_done, xc, yc) (:func:`reset_tile`)."""
    acc = np.empty((TILE * TILE, D), dtype=dtype)
    trans = np.empty(TILE * TILE, dtype=dtype)
    row_done = np.empty(TILE, dtype=np.int64)
    xc = np.empty(TILE, dtype=dtype)
    yc = np.empty(TILE, dtype=dtype)
    px0, py0, pw, ph = reset_tile(tile, tiles_x, width, height, acc, trans, row_done, xc, yc)
    return px0, py0, pw, ph, acc, trans, row_done, xc, yc


@nb.njit(cache=True, inline="always")
def store_tile(c, px0, py0, pw, ph, acc, trans, out_colors, out_T):
    D = acc.shape[1]
    for ly in range(ph):
        for lx in range(pw):
            p = ly * TILE + lx
            for d in range(D):
                out_colors[c, py0 + ly, px0 + lx, d] = acc[p, d]
            out_T[c, py0 + ly, px0 + lx] = trans[p]


@nb.njit(parallel=True, cache=True)
def gather_pairs(
    means2d,
    conics,
    opacities,
    colors,
    rects,
    tile_offsets,
    tile_gauss,
    tiles_x,
    tiles_y,
    pair_f,
    pair_r,
    pair_col,
):
    """Copy each (tile, Gaussian) pair's inputs into pair order, so that the compositing kernels read them
    sequentially: looked up per pair inside the compositing loop, they cost a cache miss each (a third of the
    forward time on a 60k-Gaussian field at 128x128).

    means2d [C,N,2], conics [C,N,3], opacities [Co,N], colors [Cc,N,D] (Co, Cc in {1, C}), rects [C,N,4],
    tile_offsets [C*T+1] and tile_gauss [P] from ``bin_gaussians``; writes pair_f [P,6] (u, v, conic a, b, c,
    opacity), pair_r [P,4] (the pixel rectangle) and pair_col [P,D]. The autograd backend keeps them from the
    forward to the backward pass: (10 + D) x 4 bytes per pair (8.7 MB for a 128x128 render of 60k Gaussians).
    """
    C = means2d.shape[0]
    D = colors.shape[2]
    Co = opacities.shape[0]
    Cc = colors.shape[0]
    T = tiles_x * tiles_y
    for ct in nb.prange(C * T):
        c = ct // T
        co = 0 if Co == 1 else c
        cc = 0 if Cc == 1 else c
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            g = tile_gauss[s]
            pair_f[s, 0] = means2d[c, g, 0]
            pair_f[s, 1] = means2d[c, g, 1]
            pair_f[s, 2] = conics[c, g, 0]
            pair_f[s, 3] = conics[c, g, 1]
            pair_f[s, 4] = conics[c, g, 2]
            pair_f[s, 5] = opacities[co, g]
            for k in range(4):
                pair_r[s, k] = rects[c, g, k]
            for d in range(D):
                pair_col[s, d] = colors[cc, g, d]


@nb.njit(parallel=True, cache=True, fastmath=FASTMATH)
def composite_forward(
    pair_f,
    pair_r,
    pair_col,
    tile_offsets,
    tiles_x,
    tiles_y,
    width,
    height,
    consts,
    tile_order,
    out_colors,
    out_T,
):
    """Front-to-back compositing of C cameras' tiles.

    pair_f [P,6], pair_r [P,4], pair_col [P,D] from ``gather_pairs`` (each tile's pairs front to back),
    tile_offsets [C*T+1], consts from ``make_consts``, tile_order from ``balanced_order``; writes
    out_colors [C,H,W,D] (without background) and out_T [C,H,W] (final transmittance).
    """
    D = pair_col.shape[1]
    T = tiles_x * tiles_y
    C = out_T.shape[0]
    for m in nb.prange(C * T):
        ct = tile_order[m]
        c = ct // T
        px0, py0, pw, ph, acc, trans, row_done, xc, yc = tile_state(
            ct - c * T, tiles_x, width, height, D, out_colors.dtype
        )
        npix = pw * ph
        ndone = 0
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            if ndone == npix:
                break
            ndone += splat_forward(
                consts,
                pair_f[s, 0],
                pair_f[s, 1],
                pair_f[s, 2],
                pair_f[s, 3],
                pair_f[s, 4],
                pair_f[s, 5],
                pair_r[s, 0],
                pair_r[s, 1],
                pair_r[s, 2],
                pair_r[s, 3],
                pair_col[s],
                px0,
                py0,
                pw,
                ph,
                xc,
                yc,
                acc,
                trans,
                row_done,
            )
        store_tile(c, px0, py0, pw, ph, acc, trans, out_colors, out_T)
