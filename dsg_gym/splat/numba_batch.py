"""Numba kernels for many scenes that share one background: the objects of every scene re-posed at once.

A batch of E scenes seen by the same V cameras is laid out as ``C = E * V`` cameras (scene ``e``'s camera ``v``
is ``e * V + v``); the per-Gaussian arrays of the objects hold every scene's copy. :func:`update_objects`
re-poses the (scene, object) pairs that moved, re-projects and re-colours them in parallel over (pair, camera,
run of Gaussians) items (:func:`chunk_for`), and marks the tiles each touched before and after its move. Every
Gaussian gets exactly the arithmetic of the one-scene projection and colouring (``project_forward``,
``sh_to_rgb``, ``fill_colors``), however the work is split, so the images are the same bit for bit. One scene
(E = 1) is :class:`dsg_gym.scene_renderer.SceneRenderer`'s object update.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .numba_incremental import fill_colors, mark_tiles, sh_to_rgb
from .numba_project import _FASTMATH, _antialias_one, _project_one
from .numba_rigid import rigid_transform

__all__ = ["CHUNK", "chunk_for", "update_objects", "update_objects_serial"]

CHUNK = 256  # Gaussians of one object in one camera per work item, when there are few (pair, camera) items
_WHOLE = 1 << 40  # one item per (pair, camera)


def chunk_for(pairs: int, cameras: int, threads: int) -> int:
    """The run length of :func:`update_objects`' items: :data:`CHUNK` while the (pair, camera) items are fewer
    than twice the threads (one env: one moved object), else whole objects (a batch: enough items already)."""
    return CHUNK if pairs * cameras < 2 * threads else _WHOLE


@nb.njit(cache=True)
def _items(pairs, slices, V, chunk):
    """Work items [I, 4]: (pair, camera, first Gaussian, end) over every pair's Gaussians in runs of ``chunk``."""
    n = 0
    for m in range(pairs.shape[0]):
        k = pairs[m, 1]
        n += V * ((slices[k + 1] - slices[k] + chunk - 1) // chunk)
    items = np.empty((n, 4), np.int64)
    j = 0
    for m in range(pairs.shape[0]):
        k = pairs[m, 1]
        for v in range(V):
            for i0 in range(slices[k], slices[k + 1], chunk):
                items[j, 0] = m
                items[j, 1] = v
                items[j, 2] = i0
                items[j, 3] = min(i0 + chunk, slices[k + 1])
                j += 1
    return items


@nb.njit(cache=True)
def _pose_pair(e, k, q, R, t, obj_means, obj_quats, slices, means, quats):
    s = slices[k]
    f = slices[k + 1]
    if f > s:
        rigid_transform(
            obj_means[s:f], obj_quats[s:f], R[e, k], t[e, k], q[e, k], means[e, s:f], quats[e, s:f]
        )


@nb.njit(cache=True, fastmath=_FASTMATH)
def _view_item(e, k, v, s, f, R, obj_scales, obj_opac, obj_sh, labels, viewmats, Ks, campos, width, height, near,
               far, alpha_min, eps2d, antialiased, sh_degree, o_rgb, o_mask, o_depth, means, quats, m2, conics,
               depths, radii, rects, opac, colors):  # fmt: skip
    """Project and colour Gaussians s..f of scene e's object k in camera v."""
    V = viewmats.shape[0]
    c0 = e * V
    cam_m2, cam_cn, cam_dp = m2[c0 : c0 + V], conics[c0 : c0 + V], depths[c0 : c0 + V]
    cam_rd, cam_rc = radii[c0 : c0 + V], rects[c0 : c0 + V]
    me, qe = means[e], quats[e]
    for i in range(s, f):
        _project_one(v, i, me, qe, obj_scales, obj_opac, viewmats, Ks, width, height, near, far, cam_m2, cam_cn,
                     cam_dp, cam_rd, cam_rc, alpha_min, eps2d)  # fmt: skip
    c = c0 + v
    if antialiased:
        for i in range(s, f):
            opac[c, i] = _antialias_one(np.float64(conics[c, i, 0]), np.float64(conics[c, i, 1]),
                                        np.float64(conics[c, i, 2]), np.float64(obj_opac[0, i]), eps2d)  # fmt: skip
    rgb = np.empty((f - s, 3), np.float32)
    if o_rgb >= 0:
        sh_to_rgb(me[s:f], R[e, k], campos[v], obj_sh[s:f], sh_degree, rgb)
    fill_colors(rgb, labels[s:f], depths[c, s:f], o_rgb, o_mask, o_depth, colors[c, s:f])


@nb.njit(cache=True)
def _mark_view(e, k, v, slices, tiles_x, rects, tile_masks):
    """Scene e's object k's tiles in camera v at its new pose."""
    V = tile_masks.shape[2]
    tm = tile_masks[e, k, v : v + 1]
    tm[:] = False
    mark_tiles(rects[e * V + v : e * V + v + 1, slices[k] : slices[k + 1]], tiles_x, tm)


@nb.njit(cache=True)
def _mark_dirty(pairs, tile_masks, dirty):
    V = tile_masks.shape[2]
    for m in range(pairs.shape[0]):
        e = pairs[m, 0]
        k = pairs[m, 1]
        for v in range(V):
            row = dirty[e * V + v]
            tm = tile_masks[e, k, v]
            for j in range(row.shape[0]):
                if tm[j]:
                    row[j] = True


@nb.njit(parallel=True, cache=True)
def update_objects(pairs, q, R, t, obj_means, obj_quats, obj_scales, obj_opac, obj_sh, labels, slices, viewmats, Ks,
                   campos, width, height, near, far, alpha_min, eps2d, antialiased, sh_degree, o_rgb, o_mask,
                   o_depth, tiles_x, means, quats, m2, conics, depths, radii, rects, opac, colors, tile_masks,
                   dirty, chunk=CHUNK):  # fmt: skip
    """Re-pose the moved (scene, object) ``pairs`` [M, 2] and flag the tiles they leave and reach.

    Poses per scene and object: unit quaternions q [E,K,4] (w >= 0), rotations R [E,K,3,3], translations
    t [E,K,3] (float64, :mod:`~dsg_gym.splat.numba_rigid`). Objects (object frame, all objects' Gaussians
    concatenated, object k owning ``slices[k]:slices[k+1]``): obj_means [N,3], obj_quats [N,4], obj_scales
    [N,3], obj_opac [1,N], obj_sh [N,B,3], labels [N] (1-based object ids). Cameras: viewmats [V,4,4],
    Ks [V,3,3], campos [V,3]; width, height, near, far, alpha_min and eps2d as ``project_forward``;
    ``antialiased``: write the Mip-filtered opacities into opac [C,N] (else opac is not touched);
    ``sh_degree`` and the channel offsets o_rgb, o_mask, o_depth as ``fill_colors``.

    Written per pair: means [E,N,3], quats [E,N,4] (world frame), means2d m2 [C,N,2], conics [C,N,3],
    depths [C,N], radii [C,N,2], rects [C,N,4], colors [C,N,D] and the pair's tiles tile_masks [E,K,V,T];
    dirty [C,T] is or-ed with the pair's tiles before and after the move. Three parallel loops: the poses over
    pairs, projection and colours over (pair, camera, run of ``chunk`` Gaussians) items, the new tiles over (pair,
    camera). ``chunk`` only splits the work (:func:`chunk_for`); every split writes the same bits.
    """
    V = viewmats.shape[0]
    M = pairs.shape[0]
    _mark_dirty(pairs, tile_masks, dirty)
    for m in nb.prange(M):
        _pose_pair(pairs[m, 0], pairs[m, 1], q, R, t, obj_means, obj_quats, slices, means, quats)
    items = _items(pairs, slices, V, chunk)
    for j in nb.prange(items.shape[0]):
        m = items[j, 0]
        _view_item(pairs[m, 0], pairs[m, 1], items[j, 1], items[j, 2], items[j, 3], R, obj_scales, obj_opac, obj_sh,
                   labels, viewmats, Ks, campos, width, height, near, far, alpha_min, eps2d, antialiased, sh_degree,
                   o_rgb, o_mask, o_depth, means, quats, m2, conics, depths, radii, rects, opac, colors)  # fmt: skip
    for mv in nb.prange(M * V):
        m = mv // V
        _mark_view(pairs[m, 0], pairs[m, 1], mv - m * V, slices, tiles_x, rects, tile_masks)
    _mark_dirty(pairs, tile_masks, dirty)


@nb.njit(cache=True)
def update_objects_serial(pairs, q, R, t, obj_means, obj_quats, obj_scales, obj_opac, obj_sh, labels, slices,
                          viewmats, Ks, campos, width, height, near, far, alpha_min, eps2d, antialiased, sh_degree,
                          o_rgb, o_mask, o_depth, tiles_x, means, quats, m2, conics, depths, radii, rects, opac,
                          colors, tile_masks, dirty, chunk=CHUNK):  # fmt: skip
    """:func:`update_objects` on the calling thread: the same arithmetic, the same bits."""
    V = viewmats.shape[0]
    M = pairs.shape[0]
    _mark_dirty(pairs, tile_masks, dirty)
    for m in range(M):
        _pose_pair(pairs[m, 0], pairs[m, 1], q, R, t, obj_means, obj_quats, slices, means, quats)
    items = _items(pairs, slices, V, chunk)
    for j in range(items.shape[0]):
        m = items[j, 0]
        _view_item(pairs[m, 0], pairs[m, 1], items[j, 1], items[j, 2], items[j, 3], R, obj_scales, obj_opac, obj_sh,
                   labels, viewmats, Ks, campos, width, height, near, far, alpha_min, eps2d, antialiased, sh_degree,
                   o_rgb, o_mask, o_depth, means, quats, m2, conics, depths, radii, rects, opac, colors)  # fmt: skip
    for mv in range(M * V):
        m = mv // V
        _mark_view(pairs[m, 0], pairs[m, 1], mv - m * V, slices, tiles_x, rects, tile_masks)
    _mark_dirty(pairs, tile_masks, dirty)
