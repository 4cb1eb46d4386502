"""Numba kernels: tile binning and front-to-back alpha compositing, forward and backward.

Work is split into 16x16 pixel tiles processed in parallel (one tile per task, no atomics).
Inside a tile, Gaussians are visited front to back and each one only touches the pixels of
its own rectangle (``rects`` from the projection), so the cost is proportional to the area the
Gaussians really cover, not to ``tiles x list length x 256``.

Compositing rule per pixel (identical in forward and backward, so the backward pass replays the
forward decisions bit for bit):

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy,   dx = x + 0.5 - u,   dy = y + 0.5 - v
    alpha = min(0.99, o exp(-sigma));  skipped if sigma < 0 or alpha < 1/255
    if T (1 - alpha) < 1e-4: the pixel is finished (this Gaussian does not contribute)
    C += alpha T color;  T *= 1 - alpha

Backward (per contributing pixel, in the same front-to-back order) uses
    dL/dalpha_i = T_i (c_i . v) - (P_total - P_i) / (1 - alpha_i)
with v = dL/dC, P_i the running sum of w_j (c_j . v) for j <= i, and P_total = C_out . v +
dL/dA * A_out (the output alpha behaves as a channel of ones over a zero background).
Per-(tile, Gaussian) gradients land in their own slots and are summed per Gaussian in a fixed
order afterwards: the result is deterministic bit for bit.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

TILE = 16
ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
# No reassociation or contraction: forward and backward must take identical decisions.
_FASTMATH = {"nsz", "arcp"}


@nb.njit(cache=True)
def bin_gaussians(rects, order, tiles_x, tiles_y):
    """Build per-tile lists of Gaussians in depth order.

    rects [C,N,4] int32 inclusive pixel rectangles (x1 < x0: culled); order [C,N] int64 with each
    camera's Gaussians sorted front to back. Returns ``tile_offsets [C*T+1]`` (CSR over tiles),
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
            x0 = rects[c, i, 0]
            x1 = rects[c, i, 1]
            if x1 < x0:
                continue
            tx0 = x0 // TILE
            tx1 = x1 // TILE
            ty0 = rects[c, i, 2] // TILE
            ty1 = rects[c, i, 3] // TILE
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
        for k in range(N):
            i = order[c, k]
            x0 = rects[c, i, 0]
            x1 = rects[c, i, 1]
            if x1 < x0:
                continue
            tx0 = x0 // TILE
            tx1 = x1 // TILE
            ty0 = rects[c, i, 2] // TILE
            ty1 = rects[c, i, 3] // TILE
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = c * T + ty * tiles_x + tx
                    slot = fill[t]
                    fill[t] += 1
                    tile_gauss[slot] = i
                    gauss_pairs[gfill[c * N + i]] = slot
                    gfill[c * N + i] += 1
    return tile_offsets, tile_gauss, gauss_offsets, gauss_pairs


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def composite_forward(means2d, conics, opacities, colors, rects, tile_offsets, tile_gauss,
                      tiles_x, tiles_y, width, height, out_colors, out_T):
    """Front-to-back compositing.

    means2d [C,N,2], conics [C,N,3], opacities [Co,N], colors [Cc,N,D] (Co, Cc in {1, C}),
    rects [C,N,4]; writes out_colors [C,H,W,D] (without background) and out_T [C,H,W]
    (final transmittance).
    """
    C = means2d.shape[0]
    D = colors.shape[2]
    Co = opacities.shape[0]
    Cc = colors.shape[0]
    T = tiles_x * tiles_y
    for ct in nb.prange(C * T):
        c = ct // T
        t = ct - c * T
        ty = t // tiles_x
        tx = t - ty * tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        pw = min(TILE, width - px0)
        ph = min(TILE, height - py0)
        npix = pw * ph
        acc = np.zeros((TILE * TILE, D), dtype=out_colors.dtype)
        trans = np.ones(TILE * TILE, dtype=out_colors.dtype)
        done = np.zeros(TILE * TILE, dtype=np.bool_)
        ndone = 0
        co = 0 if Co == 1 else c
        cc = 0 if Cc == 1 else c
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            if ndone == npix:
                break
            g = tile_gauss[s]
            u = means2d[c, g, 0]
            v = means2d[c, g, 1]
            ca = conics[c, g, 0]
            cb = conics[c, g, 1]
            cc_ = conics[c, g, 2]
            o = opacities[co, g]
            x0 = max(rects[c, g, 0], px0) - px0
            x1 = min(rects[c, g, 1], px0 + pw - 1) - px0
            y0 = max(rects[c, g, 2], py0) - py0
            y1 = min(rects[c, g, 3], py0 + ph - 1) - py0
            col = colors[cc, g]
            for ly in range(y0, y1 + 1):
                dy = (py0 + ly) + 0.5 - v
                for lx in range(x0, x1 + 1):
                    p = ly * TILE + lx
                    if done[p]:
                        continue
                    dx = (px0 + lx) + 0.5 - u
                    sigma = 0.5 * (ca * dx * dx + cc_ * dy * dy) + cb * dx * dy
                    if sigma < 0.0:
                        continue
                    alpha = min(ALPHA_MAX, o * math.exp(-sigma))
                    if alpha < ALPHA_MIN:
                        continue
                    tp = trans[p]
                    nt = tp * (1.0 - alpha)
                    if nt < T_MIN:
                        done[p] = True
                        ndone += 1
                        continue
                    w = alpha * tp
                    for d in range(D):
                        acc[p, d] += w * col[d]
                    trans[p] = nt
        for ly in range(ph):
            for lx in range(pw):
                p = ly * TILE + lx
                for d in range(D):
                    out_colors[c, py0 + ly, px0 + lx, d] = acc[p, d]
                out_T[c, py0 + ly, px0 + lx] = trans[p]


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def composite_backward(means2d, conics, opacities, colors, rects, tile_offsets, tile_gauss,
                       tiles_x, tiles_y, width, height, out_colors, out_T, v_colors, v_alphas,
                       pair_grads):
    """Per-(tile, Gaussian) gradients.

    out_colors [C,H,W,D] are the final colours including background, out_T [C,H,W] the final
    transmittance, v_colors [C,H,W,D] and v_alphas [C,H,W] the incoming gradients. Writes
    pair_grads [P, D + 6]: (d colour [D], d means2d [2], d conic [3], d opacity).
    """
    C = means2d.shape[0]
    D = colors.shape[2]
    Co = opacities.shape[0]
    Cc = colors.shape[0]
    T = tiles_x * tiles_y
    for ct in nb.prange(C * T):
        c = ct // T
        t = ct - c * T
        ty = t // tiles_x
        tx = t - ty * tiles_x
        px0 = tx * TILE
        py0 = ty * TILE
        pw = min(TILE, width - px0)
        ph = min(TILE, height - py0)
        npix = pw * ph
        if tile_offsets[ct] == tile_offsets[ct + 1]:
            continue
        trans = np.ones(TILE * TILE, dtype=out_T.dtype)
        done = np.zeros(TILE * TILE, dtype=np.bool_)
        vpix = np.zeros((TILE * TILE, D), dtype=v_colors.dtype)
        va = np.zeros(TILE * TILE, dtype=np.float64)
        ptot = np.zeros(TILE * TILE, dtype=np.float64)
        pacc = np.zeros(TILE * TILE, dtype=np.float64)
        gcol = np.zeros(D, dtype=np.float64)
        for ly in range(ph):
            for lx in range(pw):
                p = ly * TILE + lx
                tot = 0.0
                for d in range(D):
                    vv = v_colors[c, py0 + ly, px0 + lx, d]
                    vpix[p, d] = vv
                    tot += np.float64(vv) * np.float64(out_colors[c, py0 + ly, px0 + lx, d])
                a = np.float64(v_alphas[c, py0 + ly, px0 + lx])
                va[p] = a
                ptot[p] = tot + a * (1.0 - np.float64(out_T[c, py0 + ly, px0 + lx]))
        ndone = 0
        co = 0 if Co == 1 else c
        cc = 0 if Cc == 1 else c
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            if ndone == npix:
                break
            g = tile_gauss[s]
            u = means2d[c, g, 0]
            v = means2d[c, g, 1]
            ca = conics[c, g, 0]
            cb = conics[c, g, 1]
            cc_ = conics[c, g, 2]
            o = opacities[co, g]
            x0 = max(rects[c, g, 0], px0) - px0
            x1 = min(rects[c, g, 1], px0 + pw - 1) - px0
            y0 = max(rects[c, g, 2], py0) - py0
            y1 = min(rects[c, g, 3], py0 + ph - 1) - py0
            col = colors[cc, g]
            gcol[:] = 0.0
            gu = 0.0
            gv = 0.0
            ga = 0.0
            gb = 0.0
            gc = 0.0
            go = 0.0
            for ly in range(y0, y1 + 1):
                dy = (py0 + ly) + 0.5 - v
                for lx in range(x0, x1 + 1):
                    p = ly * TILE + lx
                    if done[p]:
                        continue
                    dx = (px0 + lx) + 0.5 - u
                    sigma = 0.5 * (ca * dx * dx + cc_ * dy * dy) + cb * dx * dy
                    if sigma < 0.0:
                        continue
                    gauss = math.exp(-sigma)
                    raw = o * gauss
                    alpha = min(ALPHA_MAX, raw)
                    if alpha < ALPHA_MIN:
                        continue
                    tp = trans[p]
                    nt = tp * (1.0 - alpha)
                    if nt < T_MIN:
                        done[p] = True
                        ndone += 1
                        continue
                    w = alpha * tp
                    trans[p] = nt
                    cv = va[p]
                    for d in range(D):
                        cv += np.float64(col[d]) * np.float64(vpix[p, d])
                        gcol[d] += w * vpix[p, d]
                    pp = pacc[p] + w * cv
                    pacc[p] = pp
                    if raw >= ALPHA_MAX:
                        continue  # clamped alpha: no gradient to sigma or opacity
                    valpha = tp * cv - (ptot[p] - pp) / (1.0 - alpha)
                    go += valpha * gauss
                    vsig = -valpha * alpha
                    ga += 0.5 * vsig * dx * dx
                    gb += vsig * dx * dy
                    gc += 0.5 * vsig * dy * dy
                    gu -= vsig * (ca * dx + cb * dy)
                    gv -= vsig * (cb * dx + cc_ * dy)
            for d in range(D):
                pair_grads[s, d] = gcol[d]
            pair_grads[s, D] = gu
            pair_grads[s, D + 1] = gv
            pair_grads[s, D + 2] = ga
            pair_grads[s, D + 3] = gb
            pair_grads[s, D + 4] = gc
            pair_grads[s, D + 5] = go


@nb.njit(parallel=True, cache=True)
def reduce_pairs(pair_grads, gauss_offsets, gauss_pairs, C, N, D, v_means2d, v_conics,
                 v_colors, v_opacities):
    """Sum pair slots per Gaussian in a fixed order.

    v_means2d [C,N,2], v_conics [C,N,3]; v_colors [Cc,N,D] and v_opacities [Co,N] are summed
    over cameras when they are shared (Cc == 1, Co == 1). All outputs are overwritten.
    """
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
            kc = 0 if Cc == 1 else c
            for j in range(gauss_offsets[c * N + i], gauss_offsets[c * N + i + 1]):
                s = gauss_pairs[j]
                for d in range(D):
                    v_colors[kc, i, d] += pair_grads[s, d]
                gu += pair_grads[s, D]
                gv += pair_grads[s, D + 1]
                ga += pair_grads[s, D + 2]
                gb += pair_grads[s, D + 3]
                gcn += pair_grads[s, D + 4]
                go += pair_grads[s, D + 5]
            v_means2d[c, i, 0] = gu
            v_means2d[c, i, 1] = gv
            v_conics[c, i, 0] = ga
            v_conics[c, i, 1] = gb
            v_conics[c, i, 2] = gcn
            v_opacities[0 if Co == 1 else c, i] += go
