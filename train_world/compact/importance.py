"""Per-Gaussian importance over a set of cameras: accumulated blending weight and removal error.

For Gaussian ``i`` and pixel ``p`` of one view, the renderer composites front to back with weight
``w_ip = T_ip alpha_ip`` (:mod:`dsg_gym.splat`). Two numbers per Gaussian and camera come out of one pass:

* **accumulated weight** ``W_i = sum_p w_ip`` (pixels): how much of the image the Gaussian paints. It is
  also the gradient of the image sum with respect to a colour channel of ones (``tests/test_compact.py``
  checks the two against each other). ``W_i < 1/255`` in every view means no pixel of any of them moves by
  more than 1/255 when the Gaussian is removed (a pixel changes by ``w_ip (c_i - B_ip)``, both colours in
  [0, 1]).
* **removal error** ``E_i = sum_p ||C_p - C'_p||^2`` (colour^2 x pixels), ``C'`` being the image without
  Gaussian ``i``. With ``F`` the colour composited in front of ``i`` (inclusive) and ``C`` the final colour
  (background included), everything behind ``i`` is ``C - F`` and would be seen through ``1 / (1 - alpha)``
  more transmittance, so ``C_p - C'_p = w_ip c_i - alpha_ip / (1 - alpha_ip) (C_p - F_p)``: the weight
  times how much the Gaussian's colour differs from what is behind it. A Gaussian on a surface covered by
  similar neighbours has a small ``E_i`` even when its weight is large; one that alone covers a thin leg
  or a floor seam has a large one. Exact except where removing ``i`` would let a pixel composite Gaussians
  it skipped after its transmittance fell below 1e-4 (early termination); those are ignored.

The kernel replays the forward kernel's per-pixel decisions (same arithmetic, float32) inside 16x16
tiles: a first pass gives each pixel's final colour, a second the per-(tile, Gaussian) sums, which are
then reduced per Gaussian in a fixed order (deterministic, no atomics).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from dsg_gym.cameras import look_at
from dsg_gym.gaussians import GaussianSet
from dsg_gym.splat import numba_bins as binning
from dsg_gym.splat import numba_incremental as incr
from dsg_gym.splat import numba_project as projection
from dsg_gym.splat import numba_raster as raster

__all__ = [
    "Importance",
    "SceneCameras",
    "gaussian_importance",
    "scene_cameras",
    "sphere_cameras",
    "view_colors",
]

TILE = raster.TILE


@dataclass(frozen=True)
class Importance:
    """Per-Gaussian scores over ``num_cameras`` views (all ``[N]`` float64).

    ``weight_max`` / ``weight_sum``: max / sum over the views of the accumulated weight (pixels);
    ``error_sum``: sum over the views of the removal error (colour^2 x pixels)."""

    weight_max: np.ndarray
    weight_sum: np.ndarray
    error_sum: np.ndarray
    num_cameras: int


@nb.njit(parallel=True, cache=True, fastmath=raster.FASTMATH)
def _tile_scores(
    means2d,
    conics,
    opacities,
    colors,
    rects,
    tile_offsets,
    tile_gauss,
    tiles_x,
    tiles_y,
    width,
    height,
    consts,
    tile_order,
    bg,
    pair_out,
):
    """Per-(tile, Gaussian) slots: ``pair_out[s] = (sum w, sum ||dC||^2)`` over the tile's pixels.

    means2d [C,N,2], conics [C,N,3], opacities [Co,N] (Co in {1, C}), colors [C,N,3] float32; bg [3] float64;
    pair_out [P,2] float64 zero-initialised (slots of Gaussians never reached stay zero).
    """
    C = means2d.shape[0]
    T = tiles_x * tiles_y
    amin = consts[1]
    half = consts[3]
    one = consts[4]
    zero = consts[5]
    for m in nb.prange(C * T):
        ct = tile_order[m]
        if tile_offsets[ct] == tile_offsets[ct + 1]:
            continue
        c = ct // T
        co = 0 if opacities.shape[0] == 1 else c
        px0, py0, pw, ph, acc, trans, row_done, xc, yc = raster.tile_state(
            ct - c * T, tiles_x, width, height, 3, np.float32
        )
        npix = pw * ph
        ndone = 0
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):  # pass 1: final colours
            if ndone == npix:
                break
            g = tile_gauss[s]
            ndone += raster.splat_forward(
                consts,
                means2d[c, g, 0],
                means2d[c, g, 1],
                conics[c, g, 0],
                conics[c, g, 1],
                conics[c, g, 2],
                opacities[co, g],
                rects[c, g, 0],
                rects[c, g, 1],
                rects[c, g, 2],
                rects[c, g, 3],
                colors[c, g],
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
        final = np.empty((TILE * TILE, 3), dtype=np.float64)
        for p in range(TILE * TILE):
            for d in range(3):
                final[p, d] = np.float64(acc[p, d]) + np.float64(trans[p]) * bg[d]
        # pass 2: the same decisions again, now with the per-Gaussian sums
        trans[:] = one
        row_done[:] = 0
        run = np.zeros((TILE * TILE, 3), dtype=np.float64)
        ndone = 0
        for s in range(tile_offsets[ct], tile_offsets[ct + 1]):
            if ndone == npix:
                break
            g = tile_gauss[s]
            u = means2d[c, g, 0]
            v = means2d[c, g, 1]
            ca = conics[c, g, 0] * half
            cb = conics[c, g, 1]
            cc_ = conics[c, g, 2] * half
            o = opacities[co, g]
            logo = math.log(np.float64(o) / np.float64(amin))
            smax = zero + np.float32(logo * 1.0001 + 1e-4)
            y0 = max(rects[c, g, 2], py0) - py0
            y1 = min(rects[c, g, 3], py0 + ph - 1) - py0
            xr0 = max(rects[c, g, 0], px0)
            xr1 = min(rects[c, g, 1], px0 + pw - 1)
            if xr1 < xr0 or raster.rows_finished(row_done, y0, y1, xr0 - px0, xr1 - px0):
                continue
            col = colors[c, g]
            ws = 0.0
            es = 0.0
            rect_bits = raster.column_bits(xr0 - px0, xr1 - px0)
            for ly in range(y0, y1 + 1):
                if row_done[ly] & rect_bits == rect_bits:
                    continue
                dy = yc[ly] - v
                x0, x1 = raster.row_pixel_range(
                    conics[c, g, 0], cb, conics[c, g, 2], u, np.float64(dy), logo, xr0, xr1, px0
                )
                if x1 < x0:
                    continue
                todo = (
                    raster.column_bits(x0, x1) & ~row_done[ly]
                )  # unfinished pixels, as splat_forward visits them
                if todo == 0:
                    continue
                bdy = cb * dy
                cdy = cc_ * dy * dy
                while todo != 0:
                    lx, todo = raster.pop_lowest_bit(todo)
                    p = ly * TILE + lx
                    tp = trans[p]
                    code, alpha, _, nt = raster.pixel_step(
                        consts, ca, bdy, cdy, xc[lx] - u, o, smax, tp, row_done, ly, lx
                    )
                    if code < 2:
                        ndone += code
                        continue
                    w = alpha * tp
                    trans[p] = nt
                    w64 = np.float64(w)
                    k = np.float64(alpha) / (1.0 - np.float64(alpha))
                    e = 0.0
                    for d in range(3):
                        run[p, d] += w64 * col[d]
                        dc = w64 * col[d] - k * (final[p, d] - run[p, d])
                        e += dc * dc
                    ws += w64
                    es += e
            pair_out[s, 0] = ws
            pair_out[s, 1] = es


@nb.njit(parallel=True, cache=True)
def _reduce(pair_out, gauss_offsets, gauss_pairs, C, N, weight, error):
    """``weight[c, i]``, ``error[c, i]`` [C,N] float64: sums of the Gaussian's slots in a fixed order."""
    for i in nb.prange(N):
        for c in range(C):
            w = 0.0
            e = 0.0
            for j in range(gauss_offsets[c * N + i], gauss_offsets[c * N + i + 1]):
                w += pair_out[gauss_pairs[j], 0]
                e += pair_out[gauss_pairs[j], 1]
            weight[c, i] = w
            error[c, i] = e


def _campos(viewmats: np.ndarray) -> np.ndarray:
    """Camera centres ``[C,3]`` float64 of world-to-camera ``viewmats [C,4,4]``."""
    vm = np.asarray(viewmats, np.float64)
    return -np.einsum("cji,cj->ci", vm[:, :3, :3], vm[:, :3, 3])


def view_colors(g: GaussianSet, viewmats: np.ndarray) -> np.ndarray:
    """RGB ``[C,N,3]`` float32 of ``g`` seen from each camera: ``max(0, SH(dir) + 0.5)`` (the env's rule)."""
    out = np.empty((len(viewmats), g.num, 3), np.float32)
    sh = np.ascontiguousarray(g.sh, np.float32)
    means = np.ascontiguousarray(g.means, np.float32)
    for c, pos in enumerate(_campos(viewmats)):
        incr.sh_to_rgb(means, np.eye(3), pos, sh, g.sh_degree, out[c])
    return out


def gaussian_importance(
    g: GaussianSet,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    *,
    background=(0.0, 0.0, 0.0),
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    chunk: int = 8,
    rasterize_mode: str = "classic",
    eps2d: float = projection.BLUR,
) -> Importance:
    """Scores of every Gaussian of ``g`` (rendered alone, over ``background``) in the cameras
    ``viewmats [C,4,4]`` (OpenCV world-to-camera), ``Ks [C,3,3]``; ``chunk`` cameras per kernel call;
    ``rasterize_mode`` and ``eps2d`` as the world is rendered (``World.splat_options``)."""
    viewmats = np.ascontiguousarray(viewmats, np.float64)
    Ks = np.ascontiguousarray(Ks, np.float64)
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (len(viewmats), 3, 3):
        raise ValueError(f"viewmats must be [C,4,4] and Ks [C,3,3], got {viewmats.shape}, {Ks.shape}")
    if int(width) < 1 or int(height) < 1:
        raise ValueError(f"width and height must be positive, got {width}, {height}")
    n = g.num
    wmax, wsum, esum = np.zeros(n), np.zeros(n), np.zeros(n)
    if n == 0 or len(viewmats) == 0:
        return Importance(wmax, wsum, esum, len(viewmats))
    means = np.ascontiguousarray(g.means, np.float32)
    quats = np.ascontiguousarray(g.quats, np.float32)
    scales = np.ascontiguousarray(g.scales, np.float32)
    opac = np.ascontiguousarray(g.opacities, np.float32)[None]
    bg = np.asarray(background, np.float64).reshape(3)
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    consts = raster.make_consts(np.float32)
    for a in range(0, len(viewmats), max(1, int(chunk))):
        vm, K = viewmats[a : a + chunk], Ks[a : a + chunk]
        C = len(vm)
        m2, cn = np.empty((C, n, 2), np.float32), np.empty((C, n, 3), np.float32)
        dp, radii, rects = (
            np.empty((C, n), np.float32),
            np.empty((C, n, 2), np.int32),
            np.empty((C, n, 4), np.int32),
        )
        projection.project_forward(
            means,
            quats,
            scales,
            opac,
            vm,
            K,
            float(width),
            float(height),
            float(near_plane),
            float(far_plane),
            m2,
            cn,
            dp,
            radii,
            rects,
            raster.ALPHA_MIN,
            float(eps2d),
        )
        op = opac
        if rasterize_mode == "antialiased":  # per-camera opacities after the 2D Mip filter
            op = np.empty((C, n), np.float32)
            projection.antialias_opacities(cn, opac, op, float(eps2d))
        order, counts = binning.depth_order(dp.view(np.uint32), rects)
        t_off, t_gauss, g_off, g_pairs = binning.bin_gaussians(rects, order, counts, tiles_x, tiles_y)
        pair_out = np.zeros((len(t_gauss), 2), np.float64)
        _tile_scores(
            m2,
            cn,
            op,
            view_colors(g, vm),
            rects,
            t_off,
            t_gauss,
            tiles_x,
            tiles_y,
            int(width),
            int(height),
            consts,
            binning.balanced_order(C * tiles_x * tiles_y),
            bg,
            pair_out,
        )
        weight, error = np.empty((C, n)), np.empty((C, n))
        _reduce(pair_out, g_off, g_pairs, C, n, weight, error)
        np.maximum(wmax, weight.max(0), out=wmax)
        wsum += weight.sum(0)
        esum += error.sum(0)
    return Importance(wmax, wsum, esum, len(viewmats))


# --------------------------------------------------------------------------------------------- cameras
@dataclass(frozen=True, eq=False)
class SceneCameras:
    """Plausible cameras of a scene: ``viewmats [V,4,4]`` (OpenCV world-to-camera), ``Ks [V,3,3]`` (float64),
    the image size, how many of them are the capture cameras (the first ``num_capture``), and the geometry
    the orbit was derived from: ``target [3]``, ``up [3]``, ``radius`` and the ``elevations_deg`` of the
    rings."""

    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int
    num_capture: int
    target: np.ndarray
    up: np.ndarray
    radius: float
    elevations_deg: tuple[float, ...]

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """:func:`dsg_gym.cameras.look_at`, also when looking along ``up``: then any perpendicular is the image up."""
    z = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    z /= np.linalg.norm(z)
    if np.linalg.norm(np.cross(z, up)) < 1e-6:
        up = [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0]
    return look_at(eye, target, up)


def _axes_target(campos: np.ndarray, fwd: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """The point closest (least squares) to every camera's optical axis; ``fallback`` when the axes are
    (nearly) parallel."""
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for o, f in zip(campos, fwd):
        M = np.eye(3) - np.outer(f, f)
        A += M
        b += M @ o
    if np.linalg.cond(A) > 1e6:
        return fallback
    return np.linalg.solve(A, b)


def scene_cameras(
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    *,
    rings: int = 4,
    per_ring: int = 24,
    below_deg: float = 10.0,
    above_deg: float = 20.0,
    fallback_target=None,
) -> SceneCameras:
    """The capture cameras ``viewmats [V,4,4]``, ``Ks [V,3,3]`` plus an orbit around what they look at.

    The orbit's centre is the point closest to all optical axes (``fallback_target`` when they are nearly
    parallel, e.g. one camera), its up axis the direction most perpendicular to the cameras' x axes (exact
    for look-at cameras without roll), its radius their median distance from the centre; ``rings`` rings of
    ``per_ring`` look-at cameras (azimuths staggered between rings) span the capture elevations widened by
    ``below_deg`` / ``above_deg`` (clipped to 0..80 degrees), so views from above and below the captured
    band (e.g. a test orbit) are covered. Intrinsics are those of the first capture camera. Shapes: returns
    ``V + rings * per_ring`` cameras, capture cameras first.
    """
    vm = np.asarray(viewmats, np.float64)
    Ks = np.asarray(Ks, np.float64)
    if vm.ndim != 3 or vm.shape[1:] != (4, 4) or len(vm) < 1 or Ks.shape != (len(vm), 3, 3):
        raise ValueError(
            f"scene_cameras: need capture cameras [V,4,4] and Ks [V,3,3], got {vm.shape}, {Ks.shape}"
        )
    campos = _campos(vm)
    fwd = vm[:, 2, :3] / np.linalg.norm(vm[:, 2, :3], axis=1, keepdims=True)
    # Look-at cameras without roll have their x axis perpendicular to the world's up: take the direction
    # most perpendicular to all x axes, signed like the mean image-up direction (-y in OpenCV).
    up = np.linalg.eigh(vm[:, 0, :3].T @ vm[:, 0, :3])[1][:, 0]
    up = up if up @ -vm[:, 1, :3].mean(0) >= 0 else -up
    fb = campos.mean(0) + fwd.mean(0) if fallback_target is None else np.asarray(fallback_target, np.float64)
    target = _axes_target(campos, fwd, fb)
    rel = campos - target
    dist = np.linalg.norm(rel, axis=1)
    radius = float(np.median(dist))
    elev = np.degrees(np.arcsin(np.clip(rel @ up / np.maximum(dist, 1e-12), -1, 1)))
    lo = float(np.clip(elev.min() - below_deg, 0.0, 80.0))
    hi = float(np.clip(elev.max() + above_deg, lo, 80.0))
    els = np.linspace(lo, hi, rings) if rings > 1 else np.array([0.5 * (lo + hi)])
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    extra = []
    for r, el in enumerate(np.radians(els) if rings > 0 else []):
        for j in range(per_ring):
            az = 2 * np.pi * (j + 0.5 * (r % 2)) / per_ring
            d = np.cos(el) * (np.cos(az) * e1 + np.sin(az) * e2) + np.sin(el) * up
            extra.append(_look_at(target + radius * d, target, up))
    all_vm = np.concatenate([vm, np.array(extra).reshape(-1, 4, 4)])
    all_K = np.concatenate([Ks, np.repeat(Ks[:1], len(extra), 0)])
    return SceneCameras(
        all_vm,
        all_K,
        int(width),
        int(height),
        len(vm),
        target,
        up,
        radius,
        tuple(float(e) for e in els) if rings > 0 else (),
    )


def sphere_cameras(center: np.ndarray, radius: float, n: int, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """``n`` look-at cameras ``[n,4,4]`` (world-to-camera) on a sphere (Fibonacci lattice) of ``radius``
    around ``center``: every direction an object could be seen from, whatever its orientation."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = np.pi * (1.0 + 5.0**0.5) * i
    r = np.sqrt(1.0 - z * z)
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    up = np.asarray(up, np.float64)
    c = np.asarray(center, np.float64)
    return np.stack([_look_at(c + radius * d, c, up) for d in dirs]) if n else np.zeros((0, 4, 4))
