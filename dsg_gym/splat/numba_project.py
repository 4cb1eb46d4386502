"""Numba kernels: EWA projection of 3D Gaussians to screen space, forward and backward.

All per-Gaussian arithmetic runs in float64 (inputs may be float32) so that huge or degenerate
covariances neither overflow nor lose their positive definiteness; outputs are written in the
dtype of the output arrays. See ``dsg_gym.splat.rasterize`` for the conventions.

Per camera ``c`` and Gaussian ``i`` the forward pass writes

* ``means2d[c, i]``: pixel coordinates of the projected centre (pixel centres at +0.5),
* ``conics[c, i]``: the inverse 2D covariance (a, b, c) of ``[[a, b], [b, c]]``,
* ``depths[c, i]``: camera-space z,
* ``radii[c, i]``: half extents (x, y) in whole pixels of the region where alpha >= 1/255
  (0 for culled Gaussians),
* ``rects[c, i]``: the inclusive pixel rectangle (x0, x1, y0, y1) a kernel must visit (one pixel of
  margin beyond the exact extent, clipped to the image; x1 < x0 when culled).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..splat_options import DEFAULT_EPS2D

BLUR = DEFAULT_EPS2D  # px^2 added to the 2D covariance diagonal by default (EWA low-pass; gsplat's eps2d)
ALPHA_MIN = 1.0 / 255.0
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}
_QNORM_EPS = 1e-12


@nb.njit(cache=True, inline="always")
def _quat_to_rot(qw, qx, qy, qz):
    n2 = qw * qw + qx * qx + qy * qy + qz * qz
    if n2 < _QNORM_EPS * _QNORM_EPS:
        return 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0
    inv = 1.0 / math.sqrt(n2)
    w = qw * inv
    x = qx * inv
    y = qy * inv
    z = qz * inv
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
        inv,
    )


@nb.njit(cache=True, inline="always")
def _clamp(v, lo, hi):
    return lo if v < lo else (hi if v > hi else v)


@nb.njit(cache=True, inline="always")
def _cam_rotation(V, r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """W = Rw R: the Gaussian's rotation seen in camera axes (row-major, 9 values)."""
    return (V[0, 0] * r00 + V[0, 1] * r10 + V[0, 2] * r20, V[0, 0] * r01 + V[0, 1] * r11 + V[0, 2] * r21,
            V[0, 0] * r02 + V[0, 1] * r12 + V[0, 2] * r22, V[1, 0] * r00 + V[1, 1] * r10 + V[1, 2] * r20,
            V[1, 0] * r01 + V[1, 1] * r11 + V[1, 2] * r21, V[1, 0] * r02 + V[1, 1] * r12 + V[1, 2] * r22,
            V[2, 0] * r00 + V[2, 1] * r10 + V[2, 2] * r20, V[2, 0] * r01 + V[2, 1] * r11 + V[2, 2] * r21,
            V[2, 0] * r02 + V[2, 1] * r12 + V[2, 2] * r22)


@nb.njit(cache=True, inline="always")
def _jacobian(px, py, rz, fx, fy, cx, cy, width, height):
    """Perspective Jacobian entries (j00, j02, j11, j12) with 3DGS's clamp of x/z and y/z to
    1.3x the half field of view, the clamped ratios (ux, uy) and whether each was clamped."""
    tanx = 0.5 * width / fx
    tany = 0.5 * height / fy
    xr = px * rz
    yr = py * rz
    lox = -(cx / fx + 0.3 * tanx)
    hix = (width - cx) / fx + 0.3 * tanx
    loy = -(cy / fy + 0.3 * tany)
    hiy = (height - cy) / fy + 0.3 * tany
    ux = _clamp(xr, lox, hix)
    uy = _clamp(yr, loy, hiy)
    return fx * rz, -fx * ux * rz, fy * rz, -fy * uy * rz, ux, uy, xr < lox or xr > hix, yr < loy or yr > hiy


@nb.njit(cache=True, inline="always")
def _cov2d(j00, j02, j11, j12, m00, m01, m02, m10, m11, m12, m20, m21, m22, blur):
    """A = J Mc (2x3) and the 2D covariance A A^T + blur I as (a00..a12, sa, sb, sc)."""
    a00 = j00 * m00 + j02 * m20
    a01 = j00 * m01 + j02 * m21
    a02 = j00 * m02 + j02 * m22
    a10 = j11 * m10 + j12 * m20
    a11 = j11 * m11 + j12 * m21
    a12 = j11 * m12 + j12 * m22
    sa = a00 * a00 + a01 * a01 + a02 * a02 + blur
    sb = a00 * a10 + a01 * a11 + a02 * a12
    sc = a10 * a10 + a11 * a11 + a12 * a12 + blur
    return a00, a01, a02, a10, a11, a12, sa, sb, sc


@nb.njit(cache=True, inline="always", fastmath=_FASTMATH)
def _project_one(c, i, means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                 means2d, conics, depths, radii, rects, alpha_min, blur):
    """Project Gaussian i into camera c (the body of ``project_forward``)."""
    Co = opacities.shape[0]
    radii[c, i, 0] = 0
    radii[c, i, 1] = 0
    rects[c, i, 0] = 0
    rects[c, i, 1] = -1
    rects[c, i, 2] = 0
    rects[c, i, 3] = -1
    V = viewmats[c]
    mx = np.float64(means[i, 0])
    my = np.float64(means[i, 1])
    mz = np.float64(means[i, 2])
    px = V[0, 0] * mx + V[0, 1] * my + V[0, 2] * mz + V[0, 3]
    py = V[1, 0] * mx + V[1, 1] * my + V[1, 2] * mz + V[1, 3]
    pz = V[2, 0] * mx + V[2, 1] * my + V[2, 2] * mz + V[2, 3]
    depths[c, i] = pz
    fx = np.float64(Ks[c, 0, 0])
    fy = np.float64(Ks[c, 1, 1])
    cx = np.float64(Ks[c, 0, 2])
    cy = np.float64(Ks[c, 1, 2])
    if not (pz >= near and pz <= far):
        means2d[c, i, 0] = 0.0
        means2d[c, i, 1] = 0.0
        conics[c, i, 0] = 0.0
        conics[c, i, 1] = 0.0
        conics[c, i, 2] = 0.0
        return
    rz = 1.0 / pz
    u = fx * px * rz + cx
    v = fy * py * rz + cy
    means2d[c, i, 0] = u
    means2d[c, i, 1] = v
    o = np.float64(opacities[0 if Co == 1 else c, i])
    # 3D covariance: M = R S, Sigma = M M^T.
    r00, r01, r02, r10, r11, r12, r20, r21, r22, _ = _quat_to_rot(
        np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]),
        np.float64(quats[i, 3]))
    sx = np.float64(scales[i, 0])
    sy = np.float64(scales[i, 1])
    sz = np.float64(scales[i, 2])
    # Rotate into the camera first: Mc = Rw R S; then Sigma2d = J Mc Mc^T J^T + blur.
    w00, w01, w02, w10, w11, w12, w20, w21, w22 = _cam_rotation(V, r00, r01, r02, r10, r11, r12, r20, r21, r22)
    j00, j02, j11, j12, _, _, _, _ = _jacobian(px, py, rz, fx, fy, cx, cy, width, height)
    _, _, _, _, _, _, sa, sb, sc = _cov2d(j00, j02, j11, j12, w00 * sx, w01 * sy, w02 * sz, w10 * sx, w11 * sy,
                                          w12 * sz, w20 * sx, w21 * sy, w22 * sz, blur)
    det = sa * sc - sb * sb
    if not (det > 0.0) or not math.isfinite(det):
        conics[c, i, 0] = 0.0
        conics[c, i, 1] = 0.0
        conics[c, i, 2] = 0.0
        return
    idet = 1.0 / det
    conics[c, i, 0] = sc * idet
    conics[c, i, 1] = -sb * idet
    conics[c, i, 2] = sa * idet
    # Opacity-aware extent: alpha >= alpha_min  <=>  d^T conic d <= 2 ln(o / alpha_min).
    if o <= alpha_min:
        return
    t = 2.0 * math.log(o / alpha_min)
    ex = math.sqrt(t * sa)
    ey = math.sqrt(t * sc)
    # Pixel p is visited when its centre p + 0.5 lies within [u - ex, u + ex] (+1 px margin).
    fx0 = math.ceil(u - ex - 0.5) - 1.0
    fx1 = math.floor(u + ex - 0.5) + 1.0
    fy0 = math.ceil(v - ey - 0.5) - 1.0
    fy1 = math.floor(v + ey - 0.5) + 1.0
    if fx1 < 0.0 or fy1 < 0.0 or fx0 > width - 1.0 or fy0 > height - 1.0:
        return
    radii[c, i, 0] = np.int32(min(math.ceil(ex), 1e9))
    radii[c, i, 1] = np.int32(min(math.ceil(ey), 1e9))
    rects[c, i, 0] = np.int32(max(fx0, 0.0))
    rects[c, i, 1] = np.int32(min(fx1, width - 1.0))
    rects[c, i, 2] = np.int32(max(fy0, 0.0))
    rects[c, i, 3] = np.int32(min(fy1, height - 1.0))


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def project_forward(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                    means2d, conics, depths, radii, rects, alpha_min=ALPHA_MIN, blur=BLUR):
    """Project N Gaussians into C cameras; see the module docstring for the outputs.

    means [N,3], quats [N,4] wxyz, scales [N,3], opacities [Co,N] (Co in {1, C}),
    viewmats [C,4,4], Ks [C,3,3]; outputs means2d [C,N,2], conics [C,N,3], depths [C,N],
    radii [C,N,2] int32, rects [C,N,4] int32; ``blur``: px^2 added to the 2D covariance's diagonal.
    """
    N = means.shape[0]
    for ci in nb.prange(viewmats.shape[0] * N):
        c = ci // N
        _project_one(c, ci - c * N, means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                     means2d, conics, depths, radii, rects, alpha_min, blur)


@nb.njit(cache=True, fastmath=_FASTMATH)
def project_forward_serial(means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                           means2d, conics, depths, radii, rects, alpha_min=ALPHA_MIN, blur=BLUR):
    """``project_forward`` on one thread: cheaper for a few thousand Gaussians (no thread start)."""
    N = means.shape[0]
    for ci in range(viewmats.shape[0] * N):
        c = ci // N
        _project_one(c, ci - c * N, means, quats, scales, opacities, viewmats, Ks, width, height, near, far,
                     means2d, conics, depths, radii, rects, alpha_min, blur)


@nb.njit(parallel=True, cache=True, fastmath=_FASTMATH)
def project_backward(means, quats, scales, viewmats, Ks, width, height, radii,
                     v_means2d, v_conics, v_depths, v_means, v_quats, v_scales, blur=BLUR):
    """Gradients of the projection w.r.t. means, quats and scales (summed over cameras).

    v_means2d [C,N,2], v_conics [C,N,3], v_depths [C,N]; outputs v_means [N,3], v_quats [N,4],
    v_scales [N,3] are overwritten. Culled Gaussians (radii == 0) pass no gradient through
    means2d/conics; depths always pass theirs (depth is linear in the mean).
    """
    C = viewmats.shape[0]
    N = means.shape[0]
    for i in nb.prange(N):
        gm0 = 0.0
        gm1 = 0.0
        gm2 = 0.0
        gq0 = 0.0
        gq1 = 0.0
        gq2 = 0.0
        gq3 = 0.0
        gs0 = 0.0
        gs1 = 0.0
        gs2 = 0.0
        qw = np.float64(quats[i, 0])
        qx = np.float64(quats[i, 1])
        qy = np.float64(quats[i, 2])
        qz = np.float64(quats[i, 3])
        r00, r01, r02, r10, r11, r12, r20, r21, r22, qinv = _quat_to_rot(qw, qx, qy, qz)
        sx = np.float64(scales[i, 0])
        sy = np.float64(scales[i, 1])
        sz = np.float64(scales[i, 2])
        mx = np.float64(means[i, 0])
        my = np.float64(means[i, 1])
        mz = np.float64(means[i, 2])
        for c in range(C):
            V = viewmats[c]
            vd = np.float64(v_depths[c, i])
            # depth = pz: d pz / d mean = V[2, :3]
            vpx = 0.0
            vpy = 0.0
            vpz = vd
            if radii[c, i, 0] > 0 or radii[c, i, 1] > 0:
                px = V[0, 0] * mx + V[0, 1] * my + V[0, 2] * mz + V[0, 3]
                py = V[1, 0] * mx + V[1, 1] * my + V[1, 2] * mz + V[1, 3]
                pz = V[2, 0] * mx + V[2, 1] * my + V[2, 2] * mz + V[2, 3]
                fx = np.float64(Ks[c, 0, 0])
                fy = np.float64(Ks[c, 1, 1])
                cx = np.float64(Ks[c, 0, 2])
                cy = np.float64(Ks[c, 1, 2])
                rz = 1.0 / pz
                rz2 = rz * rz
                # means2d
                vu = np.float64(v_means2d[c, i, 0])
                vv = np.float64(v_means2d[c, i, 1])
                vpx += vu * fx * rz
                vpy += vv * fy * rz
                vpz -= (vu * fx * px + vv * fy * py) * rz2
                # Recompute the forward quantities.
                w00, w01, w02, w10, w11, w12, w20, w21, w22 = _cam_rotation(V, r00, r01, r02, r10, r11, r12,
                                                                            r20, r21, r22)
                m00 = w00 * sx
                m01 = w01 * sy
                m02 = w02 * sz
                m10 = w10 * sx
                m11 = w11 * sy
                m12 = w12 * sz
                m20 = w20 * sx
                m21 = w21 * sy
                m22 = w22 * sz
                j00, j02, j11, j12, ux, uy, clx, cly = _jacobian(px, py, rz, fx, fy, cx, cy, width, height)
                a00, a01, a02, a10, a11, a12, sa, sb, sc = _cov2d(j00, j02, j11, j12, m00, m01, m02, m10, m11, m12,
                                                                  m20, m21, m22, blur)
                idet = 1.0 / (sa * sc - sb * sb)
                ca = sc * idet
                cb = -sb * idet
                cc = sa * idet
                # d conic: G = [[ga, gb/2], [gb/2, gc]]; dL/dSigma = -Conic G Conic.
                ga = np.float64(v_conics[c, i, 0])
                gb = 0.5 * np.float64(v_conics[c, i, 1])
                gc = np.float64(v_conics[c, i, 2])
                # T = G Conic
                t00 = ga * ca + gb * cb
                t01 = ga * cb + gb * cc
                t10 = gb * ca + gc * cb
                t11 = gb * cb + gc * cc
                s00 = -(ca * t00 + cb * t10)
                s01 = -(ca * t01 + cb * t11)
                s11 = -(cb * t01 + cc * t11)
                # Sigma2d = A A^T -> dA = (S + S^T) A = 2 S A (S symmetric).
                d00 = 2.0 * (s00 * a00 + s01 * a10)
                d01 = 2.0 * (s00 * a01 + s01 * a11)
                d02 = 2.0 * (s00 * a02 + s01 * a12)
                d10 = 2.0 * (s01 * a00 + s11 * a10)
                d11 = 2.0 * (s01 * a01 + s11 * a11)
                d12 = 2.0 * (s01 * a02 + s11 * a12)
                # A = J Mc -> dJ = dA Mc^T, dMc = J^T dA.
                vj00 = d00 * m00 + d01 * m01 + d02 * m02
                vj02 = d00 * m20 + d01 * m21 + d02 * m22
                vj11 = d10 * m10 + d11 * m11 + d12 * m12
                vj12 = d10 * m20 + d11 * m21 + d12 * m22
                vm00 = j00 * d00
                vm01 = j00 * d01
                vm02 = j00 * d02
                vm10 = j11 * d10
                vm11 = j11 * d11
                vm12 = j11 * d12
                vm20 = j02 * d00 + j12 * d10
                vm21 = j02 * d01 + j12 * d11
                vm22 = j02 * d02 + j12 * d12
                # J's dependence on the camera-space point.
                vpz -= (vj00 * fx + vj11 * fy) * rz2
                if clx:
                    vpz += vj02 * fx * ux * rz2
                else:
                    vpx -= vj02 * fx * rz2
                    vpz += 2.0 * vj02 * fx * px * rz2 * rz
                if cly:
                    vpz += vj12 * fy * uy * rz2
                else:
                    vpy -= vj12 * fy * rz2
                    vpz += 2.0 * vj12 * fy * py * rz2 * rz
                # Mc = Rw R S: dS_j = sum_k (Rw R)_kj dMc_kj; d(R) = Rw^T dMc S.
                gs0 += w00 * vm00 + w10 * vm10 + w20 * vm20
                gs1 += w01 * vm01 + w11 * vm11 + w21 * vm21
                gs2 += w02 * vm02 + w12 * vm12 + w22 * vm22
                e00 = vm00 * sx
                e01 = vm01 * sy
                e02 = vm02 * sz
                e10 = vm10 * sx
                e11 = vm11 * sy
                e12 = vm12 * sz
                e20 = vm20 * sx
                e21 = vm21 * sy
                e22 = vm22 * sz
                vr00 = V[0, 0] * e00 + V[1, 0] * e10 + V[2, 0] * e20
                vr01 = V[0, 0] * e01 + V[1, 0] * e11 + V[2, 0] * e21
                vr02 = V[0, 0] * e02 + V[1, 0] * e12 + V[2, 0] * e22
                vr10 = V[0, 1] * e00 + V[1, 1] * e10 + V[2, 1] * e20
                vr11 = V[0, 1] * e01 + V[1, 1] * e11 + V[2, 1] * e21
                vr12 = V[0, 1] * e02 + V[1, 1] * e12 + V[2, 1] * e22
                vr20 = V[0, 2] * e00 + V[1, 2] * e10 + V[2, 2] * e20
                vr21 = V[0, 2] * e01 + V[1, 2] * e11 + V[2, 2] * e21
                vr22 = V[0, 2] * e02 + V[1, 2] * e12 + V[2, 2] * e22
                if qinv > 0.0:
                    w = qw * qinv
                    x = qx * qinv
                    y = qy * qinv
                    z = qz * qinv
                    # d R / d (w, x, y, z) for R(q) of a unit quaternion (formula above).
                    vw = 2.0 * (-z * vr01 + y * vr02 + z * vr10 - x * vr12 - y * vr20 + x * vr21)
                    vx = 2.0 * (y * vr01 + z * vr02 + y * vr10 - w * vr12 + z * vr20 + w * vr21
                                - 2.0 * x * (vr11 + vr22))
                    vy = 2.0 * (x * vr01 + w * vr02 + x * vr10 + z * vr12 - w * vr20 + z * vr21
                                - 2.0 * y * (vr00 + vr22))
                    vz = 2.0 * (-w * vr01 + x * vr02 + w * vr10 + y * vr12 + x * vr20 + y * vr21
                                - 2.0 * z * (vr00 + vr11))
                    # Through the normalisation q / |q|.
                    dot = vw * w + vx * x + vy * y + vz * z
                    gq0 += (vw - w * dot) * qinv
                    gq1 += (vx - x * dot) * qinv
                    gq2 += (vy - y * dot) * qinv
                    gq3 += (vz - z * dot) * qinv
            # Camera point p = Rw mean + t -> d mean = Rw^T dp.
            gm0 += V[0, 0] * vpx + V[1, 0] * vpy + V[2, 0] * vpz
            gm1 += V[0, 1] * vpx + V[1, 1] * vpy + V[2, 1] * vpz
            gm2 += V[0, 2] * vpx + V[1, 2] * vpy + V[2, 2] * vpz
        v_means[i, 0] = gm0
        v_means[i, 1] = gm1
        v_means[i, 2] = gm2
        v_quats[i, 0] = gq0
        v_quats[i, 1] = gq1
        v_quats[i, 2] = gq2
        v_quats[i, 3] = gq3
        v_scales[i, 0] = gs0
        v_scales[i, 1] = gs1
        v_scales[i, 2] = gs2


@nb.njit(cache=True)
def _antialias_one(ca, cb, cc, o, blur):
    # det(Sigma) / det(Sigma + blur I) = det(I - blur * conic), conic = (Sigma + blur I)^-1.
    x = 1.0 - blur * (ca + cc) + blur * blur * (ca * cc - cb * cb)
    return o * math.sqrt(x) if x > 0.0 else 0.0


@nb.njit(parallel=True, cache=True)
def antialias_opacities(conics, opacities, out, blur=BLUR):
    """Mip-Splatting's 2D Mip filter as gsplat's ``rasterize_mode="antialiased"``: each Gaussian's opacity
    times ``sqrt(det Sigma / det(Sigma + blur I))``, which keeps a Gaussian's integrated weight when the
    low-pass widens it (a sub-pixel Gaussian fades instead of growing to a pixel).

    conics [C,N,3] (of the blurred covariance, as ``project_forward`` writes them with the same ``blur``),
    opacities [Co,N]
    (Co in {1, C}); out [C,N] is overwritten. Culled Gaussians (conic 0) keep their opacity. float64
    arithmetic without fast-math, so every caller gets the same bits.
    """
    C, N = conics.shape[0], conics.shape[1]
    Co = opacities.shape[0]
    for ci in nb.prange(C * N):
        c = ci // N
        i = ci - c * N
        o = np.float64(opacities[0 if Co == 1 else c, i])
        out[c, i] = _antialias_one(np.float64(conics[c, i, 0]), np.float64(conics[c, i, 1]),
                                   np.float64(conics[c, i, 2]), o, blur)


@nb.njit(cache=True)
def antialias_opacities_serial(conics, opacities, out, blur=BLUR):
    """``antialias_opacities`` on one thread (a few thousand Gaussians)."""
    C, N = conics.shape[0], conics.shape[1]
    Co = opacities.shape[0]
    for c in range(C):
        for i in range(N):
            o = np.float64(opacities[0 if Co == 1 else c, i])
            out[c, i] = _antialias_one(np.float64(conics[c, i, 0]), np.float64(conics[c, i, 1]),
                                       np.float64(conics[c, i, 2]), o, blur)
