"""Numba kernels for rigid poses: poses to unit quaternions and rotations, and a pose applied to Gaussians.

Quaternions are ``wxyz`` (Hamilton), normalised with ``w >= 0``; all arithmetic is float64.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np


@nb.njit(cache=True, inline="always")
def _unit_quat_to_rot(q, R):
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1.0 - 2.0 * (y * y + z * z)
    R[0, 1] = 2.0 * (x * y - w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[1, 1] = 1.0 - 2.0 * (x * x + z * z)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[2, 1] = 2.0 * (y * z + w * x)
    R[2, 2] = 1.0 - 2.0 * (x * x + y * y)


@nb.njit(cache=True, inline="always")
def _unit(q):
    """Normalise q [4] in place with w >= 0; False for a zero or non-finite quaternion."""
    m = 0.0
    for i in range(4):
        if not math.isfinite(q[i]):
            return False
        m = max(m, abs(q[i]))
    if not (m > 0.0):
        return False
    n = 0.0
    for i in range(4):
        q[i] /= m  # scale first: no overflow for huge finite quaternions
        n += q[i] * q[i]
    n = math.sqrt(n)
    if m * n <= 1e-12:  # as dsg_gym.poses.quat_normalize: a near-zero quaternion is an error
        return False
    sgn = -1.0 if q[0] < 0.0 else 1.0
    for i in range(4):
        q[i] = sgn * q[i] / n
    return True


@nb.njit(cache=True)
def rigid_from_pose7(p7, q_out, R_out, t_out):
    """Poses [K,7] (x y z qw qx qy qz) -> unit quaternions (w >= 0) [K,4], rotations [K,3,3],
    translations [K,3]; returns the index of the first pose with a zero/non-finite quaternion or a
    non-finite position, else -1."""
    for k in range(p7.shape[0]):
        for i in range(3):
            t_out[k, i] = p7[k, i]
            if not math.isfinite(p7[k, i]):
                return k
        for i in range(4):
            q_out[k, i] = p7[k, 3 + i]
        if not _unit(q_out[k]):
            return k
        _unit_quat_to_rot(q_out[k], R_out[k])
    return -1


@nb.njit(cache=True)
def rigid_from_matrices(M, q_out, R_out, t_out):
    """Rigid transforms [K,4,4] -> (as ``rigid_from_pose7``); the quaternion comes from the rotation block
    by Shepperd's method and the rotation is rebuilt from it (consistent and orthonormal even if the
    block drifted). Returns the index of the first non-finite matrix or rotation with det <= 0, else -1."""
    for k in range(M.shape[0]):
        r = M[k]
        for i in range(4):
            for j in range(4):
                if not math.isfinite(r[i, j]):
                    return k
        det = (
            r[0, 0] * (r[1, 1] * r[2, 2] - r[1, 2] * r[2, 1])
            - r[0, 1] * (r[1, 0] * r[2, 2] - r[1, 2] * r[2, 0])
            + r[0, 2] * (r[1, 0] * r[2, 1] - r[1, 1] * r[2, 0])
        )
        if not (det > 0.0):
            return k
        tr = r[0, 0] + r[1, 1] + r[2, 2]
        q = q_out[k]
        if tr >= r[0, 0] and tr >= r[1, 1] and tr >= r[2, 2]:
            q[0], q[1], q[2], q[3] = 1.0 + tr, r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
        elif r[0, 0] >= r[1, 1] and r[0, 0] >= r[2, 2]:
            q[0], q[1], q[2], q[3] = (
                r[2, 1] - r[1, 2],
                1.0 + r[0, 0] - r[1, 1] - r[2, 2],
                r[0, 1] + r[1, 0],
                r[0, 2] + r[2, 0],
            )
        elif r[1, 1] >= r[2, 2]:
            q[0], q[1], q[2], q[3] = (
                r[0, 2] - r[2, 0],
                r[0, 1] + r[1, 0],
                1.0 + r[1, 1] - r[0, 0] - r[2, 2],
                r[1, 2] + r[2, 1],
            )
        else:
            q[0], q[1], q[2], q[3] = (
                r[1, 0] - r[0, 1],
                r[0, 2] + r[2, 0],
                r[1, 2] + r[2, 1],
                1.0 + r[2, 2] - r[0, 0] - r[1, 1],
            )
        if not _unit(q):
            return k
        _unit_quat_to_rot(q, R_out[k])
        for i in range(3):
            t_out[k, i] = r[i, 3]
    return -1


@nb.njit(cache=True)
def rigid_transform(means, quats, R, t, q, out_means, out_quats):
    """out = pose applied to Gaussians: means R m + t (float64 math), quats q * quat (Hamilton).

    means [n,3], quats [n,4] wxyz (float32); R [3,3], t [3], q [4] float64.
    """
    for i in range(means.shape[0]):
        mx = np.float64(means[i, 0])
        my = np.float64(means[i, 1])
        mz = np.float64(means[i, 2])
        out_means[i, 0] = R[0, 0] * mx + R[0, 1] * my + R[0, 2] * mz + t[0]
        out_means[i, 1] = R[1, 0] * mx + R[1, 1] * my + R[1, 2] * mz + t[1]
        out_means[i, 2] = R[2, 0] * mx + R[2, 1] * my + R[2, 2] * mz + t[2]
        bw = np.float64(quats[i, 0])
        bx = np.float64(quats[i, 1])
        by = np.float64(quats[i, 2])
        bz = np.float64(quats[i, 3])
        out_quats[i, 0] = q[0] * bw - q[1] * bx - q[2] * by - q[3] * bz
        out_quats[i, 1] = q[0] * bx + q[1] * bw + q[2] * bz - q[3] * by
        out_quats[i, 2] = q[0] * by - q[1] * bz + q[2] * bw + q[3] * bx
        out_quats[i, 3] = q[0] * bz + q[1] * by - q[2] * bx + q[3] * bw
