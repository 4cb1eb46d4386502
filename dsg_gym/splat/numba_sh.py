"""Numba kernels for real SH colours (degree 0..3) and their gradients, one pass per Gaussian.

The same basis as :func:`dsg_gym.sh_basis.basis_columns` (3DGS order and signs) at the normalised view
direction; the torch path of :func:`dsg_gym.splat.sh.spherical_harmonics` builds it from ~25 tensor ops
and a batched ``[1, K] x [K, 3]`` product per Gaussian, whose backward passes dominate SH cost in training.
Here forward and backward are one loop each, in float64 internally.

Shapes: dirs ``[C, N, 3]`` (C views of the same N Gaussians), coeffs ``[N, K, 3]`` (K >= (degree+1)^2).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ..sh_basis import C0, C1, C2, C3

_CHUNK = 1024  # Gaussians per parallel task


@nb.njit(cache=True, inline="always")
def _unit(dirs, c, i):
    """(x, y, z, norm) of dirs[c, i] normalised (a zero vector stays zero, norm then reported as 0)."""
    dx = np.float64(dirs[c, i, 0])
    dy = np.float64(dirs[c, i, 1])
    dz = np.float64(dirs[c, i, 2])
    n = math.sqrt(dx * dx + dy * dy + dz * dz)
    s = 1.0 / n if n > 0 else 1.0
    return dx * s, dy * s, dz * s, n


@nb.njit(cache=True, inline="always")
def sh_basis(degree, x, y, z, b):
    """b[:(degree+1)^2] = the basis at the unit direction (x, y, z) (3DGS order and signs)."""
    b[0] = C0
    if degree >= 1:
        b[1] = -C1 * y
        b[2] = C1 * z
        b[3] = -C1 * x
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        b[4] = C2[0] * x * y
        b[5] = C2[1] * y * z
        b[6] = C2[2] * (2.0 * zz - xx - yy)
        b[7] = C2[3] * x * z
        b[8] = C2[4] * (xx - yy)
        if degree >= 3:
            b[9] = C3[0] * y * (3.0 * xx - yy)
            b[10] = C3[1] * x * y * z
            b[11] = C3[2] * y * (4.0 * zz - xx - yy)
            b[12] = C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)
            b[13] = C3[4] * x * (4.0 * zz - xx - yy)
            b[14] = C3[5] * z * (xx - yy)
            b[15] = C3[6] * x * (xx - 3.0 * yy)


@nb.njit(cache=True, inline="always")
def _basis_grad(degree, x, y, z, g):
    """d(sum_k g_k B_k)/d(x, y, z) for the unit components (not yet projected on the sphere)."""
    gx = gy = gz = 0.0
    if degree >= 1:
        gx -= C1 * g[3]
        gy -= C1 * g[1]
        gz += C1 * g[2]
    if degree >= 2:
        gx += C2[0] * y * g[4] - 2.0 * C2[2] * x * g[6] + C2[3] * z * g[7] + 2.0 * C2[4] * x * g[8]
        gy += C2[0] * x * g[4] + C2[1] * z * g[5] - 2.0 * C2[2] * y * g[6] - 2.0 * C2[4] * y * g[8]
        gz += C2[1] * y * g[5] + 4.0 * C2[2] * z * g[6] + C2[3] * x * g[7]
        if degree >= 3:
            xx, yy, zz = x * x, y * y, z * z
            gx += (
                6.0 * C3[0] * x * y * g[9]
                + C3[1] * y * z * g[10]
                - 2.0 * C3[2] * x * y * g[11]
                - 6.0 * C3[3] * x * z * g[12]
                + C3[4] * (4.0 * zz - 3.0 * xx - yy) * g[13]
                + 2.0 * C3[5] * x * z * g[14]
                + 3.0 * C3[6] * (xx - yy) * g[15]
            )
            gy += (
                3.0 * C3[0] * (xx - yy) * g[9]
                + C3[1] * x * z * g[10]
                + C3[2] * (4.0 * zz - xx - 3.0 * yy) * g[11]
                - 6.0 * C3[3] * y * z * g[12]
                - 2.0 * C3[4] * x * y * g[13]
                - 2.0 * C3[5] * y * z * g[14]
                - 6.0 * C3[6] * x * y * g[15]
            )
            gz += (
                C3[1] * x * y * g[10]
                + 8.0 * C3[2] * y * z * g[11]
                + 3.0 * C3[3] * (2.0 * zz - xx - yy) * g[12]
                + 8.0 * C3[4] * x * z * g[13]
                + C3[5] * (xx - yy) * g[14]
            )
    return gx, gy, gz


@nb.njit(parallel=True, cache=True)
def sh_forward(degree, dirs, coeffs, out):
    """out [C, N, 3] = sum_k B_k(dirs / |dirs|) coeffs[:, k] (no +0.5 offset)."""
    C, N = dirs.shape[0], dirs.shape[1]
    K = (degree + 1) * (degree + 1)
    for chunk in nb.prange((N + _CHUNK - 1) // _CHUNK):
        b = np.empty(16)  # scratch once per chunk: an allocation per Gaussian would dominate
        for i in range(chunk * _CHUNK, min(N, (chunk + 1) * _CHUNK)):
            for c in range(C):
                x, y, z, _ = _unit(dirs, c, i)
                sh_basis(degree, x, y, z, b)
                for ch in range(3):
                    v = 0.0
                    for k in range(K):
                        v += b[k] * np.float64(coeffs[i, k, ch])
                    out[c, i, ch] = v


@nb.njit(parallel=True, cache=True)
def sh_backward(degree, dirs, coeffs, v_out, v_dirs, v_coeffs):
    """Gradients of :func:`sh_forward`: v_dirs [C, N, 3] (through the normalisation) and v_coeffs [N, K, 3]
    (summed over the C views; bases beyond the degree get 0)."""
    C, N = dirs.shape[0], dirs.shape[1]
    K = (degree + 1) * (degree + 1)
    for chunk in nb.prange((N + _CHUNK - 1) // _CHUNK):
        b = np.empty(16)
        g = np.empty(16)
        acc = np.empty((16, 3))
        for i in range(chunk * _CHUNK, min(N, (chunk + 1) * _CHUNK)):
            acc[:] = 0.0
            for c in range(C):
                x, y, z, n = _unit(dirs, c, i)
                sh_basis(degree, x, y, z, b)
                v0 = np.float64(v_out[c, i, 0])
                v1 = np.float64(v_out[c, i, 1])
                v2 = np.float64(v_out[c, i, 2])
                for k in range(K):
                    acc[k, 0] += b[k] * v0
                    acc[k, 1] += b[k] * v1
                    acc[k, 2] += b[k] * v2
                    g[k] = v0 * coeffs[i, k, 0] + v1 * coeffs[i, k, 1] + v2 * coeffs[i, k, 2]
                gx, gy, gz = _basis_grad(degree, x, y, z, g)
                if n > 0:  # through d / |d|: (g - (g . u) u) / |d|
                    dot = gx * x + gy * y + gz * z
                    gx, gy, gz = (gx - dot * x) / n, (gy - dot * y) / n, (gz - dot * z) / n
                v_dirs[c, i, 0] = gx
                v_dirs[c, i, 1] = gy
                v_dirs[c, i, 2] = gz
            for k in range(coeffs.shape[1]):
                for ch in range(3):
                    v_coeffs[i, k, ch] = acc[k, ch] if k < K else 0.0
