"""Numba kernels for many scenes that share one background: the objects of every scene re-posed at once.

A batch of E scenes seen by the same V cameras is laid out as ``C = E * V`` cameras (scene ``e``'s camera ``v``
is ``e * V + v``); the per-Gaussian arrays of the objects hold every scene's copy. :func:`update_objects`
re-poses, re-projects and re-colours the (scene, object) pairs that moved, in parallel over the pairs, and
marks the tiles each touched before and after its move. Per pair it performs exactly the arithmetic of the
one-scene renderer (:class:`dsg_gym.scene_renderer.SceneRenderer`), so the images are the same bit for bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .numba_incremental import fill_colors, mark_tiles, sh_to_rgb
from .numba_project import _FASTMATH, _antialias_one, _project_one
from .numba_rigid import rigid_transform

__all__ = ["update_objects", "update_objects_serial"]


@nb.njit(cache=True, fastmath=_FASTMATH)
def _update_pair(
    e,
    k,
    q,
    R,
    t,
    obj_means,
    obj_quats,
    obj_scales,
    obj_opac,
    obj_sh,
    labels,
    slices,
    viewmats,
    Ks,
    campos,
    width,
    height,
    near,
    far,
    alpha_min,
    eps2d,
    antialiased,
    sh_degree,
    o_rgb,
    o_mask,
    o_depth,
    tiles_x,
    means,
    quats,
    m2,
    conics,
    depths,
    radii,
    rects,
    opac,
    colors,
    tile_masks,
):
    V = viewmats.shape[0]
    s = slices[k]
    f = slices[k + 1]
    if f == s:
        return
    c0 = e * V
    rigid_transform(obj_means[s:f], obj_quats[s:f], R[e, k], t[e, k], q[e, k], means[e, s:f], quats[e, s:f])
    cam_m2, cam_cn, cam_dp = m2[c0 : c0 + V], conics[c0 : c0 + V], depths[c0 : c0 + V]
    cam_rd, cam_rc = radii[c0 : c0 + V], rects[c0 : c0 + V]
    me, qe = means[e], quats[e]
    for v in range(V):
        for i in range(s, f):
            _project_one(
                v,
                i,
                me,
                qe,
                obj_scales,
                obj_opac,
                viewmats,
                Ks,
                width,
                height,
                near,
                far,
                cam_m2,
                cam_cn,
                cam_dp,
                cam_rd,
                cam_rc,
                alpha_min,
                eps2d,
            )
    if antialiased:
        for v in range(V):
            for i in range(s, f):
                opac[c0 + v, i] = _antialias_one(
                    np.float64(conics[c0 + v, i, 0]),
                    np.float64(conics[c0 + v, i, 1]),
                    np.float64(conics[c0 + v, i, 2]),
                    np.float64(obj_opac[0, i]),
                    eps2d,
                )
    rgb = np.empty((f - s, 3), np.float32)
    for v in range(V):
        if o_rgb >= 0:
            sh_to_rgb(means[e, s:f], R[e, k], campos[v], obj_sh[s:f], sh_degree, rgb)
        fill_colors(rgb, labels[s:f], depths[c0 + v, s:f], o_rgb, o_mask, o_depth, colors[c0 + v, s:f])
    tm = tile_masks[e, k]
    tm[:] = False
    mark_tiles(rects[c0 : c0 + V, s:f], tiles_x, tm)


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


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def update_objects(
    pairs,
    q,
    R,
    t,
    obj_means,
    obj_quats,
    obj_scales,
    obj_opac,
    obj_sh,
    labels,
    slices,
    viewmats,
    Ks,
    campos,
    width,
    height,
    near,
    far,
    alpha_min,
    eps2d,
    antialiased,
    sh_degree,
    o_rgb,
    o_mask,
    o_depth,
    tiles_x,
    means,
    quats,
    m2,
    conics,
    depths,
    radii,
    rects,
    opac,
    colors,
    tile_masks,
    dirty,
):
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
    dirty [C,T] is or-ed with the pair's tiles before and after the move.
    """
    _mark_dirty(pairs, tile_masks, dirty)
    for m in nb.prange(pairs.shape[0]):
        _update_pair(
            pairs[m, 0],
            pairs[m, 1],
            q,
            R,
            t,
            obj_means,
            obj_quats,
            obj_scales,
            obj_opac,
            obj_sh,
            labels,
            slices,
            viewmats,
            Ks,
            campos,
            width,
            height,
            near,
            far,
            alpha_min,
            eps2d,
            antialiased,
            sh_degree,
            o_rgb,
            o_mask,
            o_depth,
            tiles_x,
            means,
            quats,
            m2,
            conics,
            depths,
            radii,
            rects,
            opac,
            colors,
            tile_masks,
        )
    _mark_dirty(pairs, tile_masks, dirty)


@nb.njit(cache=True, fastmath=_FASTMATH)
def update_objects_serial(
    pairs,
    q,
    R,
    t,
    obj_means,
    obj_quats,
    obj_scales,
    obj_opac,
    obj_sh,
    labels,
    slices,
    viewmats,
    Ks,
    campos,
    width,
    height,
    near,
    far,
    alpha_min,
    eps2d,
    antialiased,
    sh_degree,
    o_rgb,
    o_mask,
    o_depth,
    tiles_x,
    means,
    quats,
    m2,
    conics,
    depths,
    radii,
    rects,
    opac,
    colors,
    tile_masks,
    dirty,
):
    """:func:`update_objects` on the calling thread: the same arithmetic, the same bits."""
    _mark_dirty(pairs, tile_masks, dirty)
    for m in range(pairs.shape[0]):
        _update_pair(
            pairs[m, 0],
            pairs[m, 1],
            q,
            R,
            t,
            obj_means,
            obj_quats,
            obj_scales,
            obj_opac,
            obj_sh,
            labels,
            slices,
            viewmats,
            Ks,
            campos,
            width,
            height,
            near,
            far,
            alpha_min,
            eps2d,
            antialiased,
            sh_degree,
            o_rgb,
            o_mask,
            o_depth,
            tiles_x,
            means,
            quats,
            m2,
            conics,
            depths,
            radii,
            rects,
            opac,
            colors,
            tile_masks,
        )
    _mark_dirty(pairs, tile_masks, dirty)
