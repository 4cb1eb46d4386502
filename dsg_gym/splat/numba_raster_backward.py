"""Numba kernels: gradients of the tile compositing of :mod:`.numba_raster`.

Backward (per contributing pixel, in the same front-to-back order as the forward pass, whose decisions it
replays bit for bit with the same row helpers) uses
    dL/dalpha_i = T_i (c_i . v) - (P_total - P_i) / (1 - alpha_i)
with v = dL/dC, P_i the running sum of w_j (c_j . v) for j <= i, and P_total = C_out . v +
dL/dA * A_out (the output alpha behaves as a channel of ones over a zero background).
Per-(tile, Gaussian) gradients land in their own slots, Gaussian-major rows (``pair_slots``), and
``reduce_pairs`` sums them per Gaussian in a fixed order in one sweep: the result is deterministic bit for
bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .numba_raster import (
    FASTMATH,
    TILE,
    column_bits,
    log_opacity_ratio,
    pixel_step,
    pop_lowest_bit,
    row_pixel_range,
    rows_finished,
    sigma_cutoff_from_log,
)

__all__ = ["composite_backward", "pair_slots", "reduce_pairs"]


@nb.njit(cache=True, fastmath=True)
def _dot(a, b, n):
    """Dot product of two length-n vectors (fast math: vectorised; used on gradients only)."""
    acc = a[0] * b[0]
    for d in range(1, n):
        acc += a[d] * b[d]
    return acc


@nb.njit(parallel=True, cache=True, fastmath=FASTMATH)
def composite_backward(
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
    v_colors,
    v_alphas,
    pair_slot,
    pair_grads,
):
    """Per-(tile, Gaussian) gradients.

    pair_f, pair_r, pair_col, tile_offsets as for ``composite_forward``; out_colors [C,H,W,D] are the final
    colours including background, out_T [C,H,W] the final transmittance, v_colors [C,H,W,D] and
    v_alphas [C,H,W] the incoming gradients. Writes row ``pair_slot[s]`` of pair_grads [P, D + 6] for pair s:
    (d colour [D], d means2d [2], d conic [3], d opacity); with [P, D + 8], also the sums over the pixels of
    the absolute per-pixel means2d gradients (AbsGS's densification statistic). Rows of pairs never reached
    stay as they were (zero-initialise the array). With ``pair_slot`` from ``pair_slots``, each Gaussian's rows
    are contiguous for ``reduce_pairs``.
    """
    D = pair_col.shape[1]
    with_abs = pair_grads.shape[1] >= D + 8
    C = out_T.shape[0]
    T = tiles_x * tiles_y
    amax = consts[0]
    half = consts[3]
    for m in nb.prange(C * T):
        ct = tile_order[m]
        if tile_offsets[ct] == tile_offsets[ct + 1]:
            continue
        c = ct // T
        t = ct - c * T
        ty = t // tiles_x
        tx = t - ty * tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        pw = min(TILE, width - px0)
        ph = min(TILE, height - py0)
        npix = pw * ph
        trans = np.ones(TILE * TILE, dtype=out_T.dtype)
        row_done = np.zeros(TILE, dtype=np.int64)  # bit lx set: pixel (lx, ly) has finished
        vpix = np.zeros((TILE * TILE, D), dtype=v_colors.dtype)
        va = np.zeros(TILE * TILE, dtype=v_colors.dtype)
        ptot = np.zeros(TILE * TILE, dtype=np.float64)
        pacc = np.zeros(TILE * TILE, dtype=np.float64)
        gcol = np.zeros(D, dtype=v_colors.dtype)
        xc = np.empty(TILE, dtype=out_T.dtype)
        yc = np.empty(TILE, dtype=out_T.dtype)
        for j in range(TILE):
            xc[j] = (px0 + j) + 0.5
            yc[j] = (py0 + j) + 0.5
        for ly in range(ph):
            for lx in range(pw):
                p = ly * TILE + lx
                tot = 0.0
                for d in range(D):
                    vv = v_colors[c, py0 + ly, px0 + lx, d]
                    vpix[p, d] = vv
                    tot += np.float64(vv) * np.float64(out_colors[c, py0 + ly, px0 + lx, d])
                a = v_alphas[c, py0 + ly, px0 + lx]
                va[p] = a
                ptot[p] = tot + np.float64(a) * (1.0 - np.float64(out_T[c, py0 + ly, px0 + lx]))
        ndone = 0
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            if ndone == npix:
                break
            u = pair_f[s, 0]
            v = pair_f[s, 1]
            ca = pair_f[s, 2] * half
            cb = pair_f[s, 3]
            cc_ = pair_f[s, 4] * half
            ca64 = np.float64(pair_f[s, 2])
            cb64 = np.float64(cb)
            cc64 = np.float64(pair_f[s, 4])
            o = pair_f[s, 5]
            logo = log_opacity_ratio(consts, o)
            smax = sigma_cutoff_from_log(consts, logo)
            y0 = max(pair_r[s, 2], py0) - py0
            y1 = min(pair_r[s, 3], py0 + ph - 1) - py0
            xr0 = max(pair_r[s, 0], px0)
            xr1 = min(pair_r[s, 1], px0 + pw - 1)
            col = pair_col[s]
            gcol[:] = 0.0
            gu = 0.0
            gv = 0.0
            ga = 0.0
            gb = 0.0
            gc = 0.0
            go = 0.0
            agu = 0.0
            agv = 0.0
            if xr1 < xr0 or rows_finished(row_done, y0, y1, xr0 - px0, xr1 - px0):
                continue  # the forward pass skipped it too; its slot stays zero
            rect_bits = column_bits(xr0 - px0, xr1 - px0)
            for ly in range(y0, y1 + 1):
                if row_done[ly] & rect_bits == rect_bits:
                    continue
                dy = yc[ly] - v
                dyd = np.float64(dy)
                x0, x1 = row_pixel_range(pair_f[s, 2], cb, pair_f[s, 4], u, dyd, logo, xr0, xr1, px0)
                if x1 < x0:
                    continue
                todo = (
                    column_bits(x0, x1) & ~row_done[ly]
                )  # the span's unfinished pixels, as in the forward pass
                if todo == 0:
                    continue
                bdy = cb * dy
                cdy = cc_ * dy * dy
                while todo != 0:
                    lx, todo = pop_lowest_bit(todo)
                    p = ly * TILE + lx
                    dx = xc[lx] - u
                    tp = trans[p]
                    code, alpha, gauss, nt = pixel_step(
                        consts, ca, bdy, cdy, dx, o, smax, tp, row_done, ly, lx
                    )
                    if code < 2:
                        ndone += code
                        continue
                    raw = o * gauss
                    w = alpha * tp
                    trans[p] = nt
                    vp = vpix[p]
                    cv = np.float64(_dot(col, vp, D) + va[p])
                    for d in range(D):
                        gcol[d] += w * vp[d]
                    pp = pacc[p] + np.float64(w) * cv
                    pacc[p] = pp
                    if raw >= amax:
                        continue  # clamped alpha: no gradient to sigma or opacity
                    alpha64 = np.float64(alpha)
                    valpha = np.float64(tp) * cv - (ptot[p] - pp) / (1.0 - alpha64)
                    go += valpha * np.float64(gauss)
                    vsig = -valpha * alpha64
                    dxd = np.float64(dx)
                    ga += 0.5 * vsig * dxd * dxd
                    gb += vsig * dxd * dyd
                    gc += 0.5 * vsig * dyd * dyd
                    du = vsig * (ca64 * dxd + cb64 * dyd)
                    dv = vsig * (cb64 * dxd + cc64 * dyd)
                    gu -= du
                    gv -= dv
                    if with_abs:
                        agu += abs(du)
                        agv += abs(dv)
            j = pair_slot[s]
            for d in range(D):
                pair_grads[j, d] = gcol[d]
            pair_grads[j, D] = gu
            pair_grads[j, D + 1] = gv
            pair_grads[j, D + 2] = ga
            pair_grads[j, D + 3] = gb
            pair_grads[j, D + 4] = gc
            pair_grads[j, D + 5] = go
            if with_abs:
                pair_grads[j, D + 6] = agu
                pair_grads[j, D + 7] = agv


@nb.njit(cache=True)
def pair_slots(gauss_pairs):
    """``pair_slot [P]``: the row of pair s in Gaussian-major order (the inverse of ``gauss_pairs`` from
    ``bin_gaussians``), so that ``composite_backward`` writes each Gaussian's pair gradients next to each other
    and ``reduce_pairs`` reads them in one sweep (reading them scattered cost it a cache miss per pair)."""
    slot = np.empty(gauss_pairs.shape[0], dtype=np.int64)
    for j in range(gauss_pairs.shape[0]):
        slot[gauss_pairs[j]] = j
    return slot


@nb.njit(parallel=True, cache=True)
def reduce_pairs(pair_grads, gauss_offsets, C, N, D, v_means2d, v_conics, v_colors, v_opacities, abs_means2d):
    """Sum the pair gradients of each Gaussian in a fixed order (ascending tile).

    pair_grads [P, D + 6] (or [P, D + 8]) in Gaussian-major order (``composite_backward`` with ``pair_slots``),
    gauss_offsets [C*N+1] from ``bin_gaussians``; v_means2d [C,N,2], v_conics [C,N,3]; v_colors [Cc,N,D] and
    v_opacities [Co,N] are summed over cameras when they are shared (Cc == 1, Co == 1); abs_means2d [C,N,2]
    gets the absolute gradient sums of [P, D + 8] pairs (pass [0,N,2] without them). All outputs are
    overwritten.
    """
    with_abs = abs_means2d.shape[0] == C
    Cc = v_colors.shape[0]
    Co = v_opacities.shape[0]
    for i in nb.prange(N):
        for d in range(D):
            for k in range(Cc):
                v_colors[k, i, d] = 0.0
        for k in range(Co):
            v_opacities[k, i] = 0.0
        for c in range(C):
            gu = 0.0
            gv = 0.0
            ga = 0.0
            gb = 0.0
            gcn = 0.0
            go = 0.0
            au = 0.0
            av = 0.0
            kc = 0 if Cc == 1 else c
            for s in range(gauss_offsets[c * N + i], gauss_offsets[c * N + i + 1]):
                for d in range(D):
                    v_colors[kc, i, d] += pair_grads[s, d]
                gu += pair_grads[s, D]
                gv += pair_grads[s, D + 1]
                ga += pair_grads[s, D + 2]
                gb += pair_grads[s, D + 3]
                gcn += pair_grads[s, D + 4]
                go += pair_grads[s, D + 5]
                if with_abs:
                    au += pair_grads[s, D + 6]
                    av += pair_grads[s, D + 7]
            v_means2d[c, i, 0] = gu
            v_means2d[c, i, 1] = gv
            v_conics[c, i, 0] = ga
            v_conics[c, i, 1] = gb
            v_conics[c, i, 2] = gcn
            v_opacities[0 if Co == 1 else c, i] += go
            if with_abs:
                abs_means2d[c, i, 0] = au
                abs_means2d[c, i, 1] = av
