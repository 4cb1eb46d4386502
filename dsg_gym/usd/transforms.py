"""Rigid poses for USD: validation and matrix <-> (translation, quaternion) in float64 numpy.

Conventions are those of ``dsg_gym.geometry`` (column vectors, ``[[R, t], [0, 1]]``, quaternions
``w, x, y, z``), but on numpy float64 arrays so the USD writer never needs torch.

USD itself uses row vectors: a ``Gf.Matrix4d`` equals the *transpose* of our matrix
(``to_gf_matrix`` / ``from_gf_matrix``). ``Vt.QuatfArray`` / ``Vt.QuatdArray`` numpy buffers are
laid out ``x, y, z, w`` (imaginary first, real last); ``wxyz_to_usd`` / ``usd_to_wxyz`` reorder.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf

__all__ = [
    "RIGID_TOL",
    "check_rigid",
    "rigid_inverse",
    "rotmat_to_quat",
    "quat_to_rotmat",
    "quat_hemisphere_continuous",
    "wxyz_to_usd",
    "usd_to_wxyz",
    "to_gf_matrix",
    "from_gf_matrix",
]

RIGID_TOL = 1e-5


def check_rigid(name: str, mat, tol: float = RIGID_TOL) -> np.ndarray:
    """``mat`` as float64 ``[..., 4, 4]`` after checking it is a finite rigid transform.

    Rigid: last row ``[0, 0, 0, 1]``, ``R^T R = I`` and ``det R = +1`` within ``tol``.
    Raises ``ValueError`` naming ``name`` (and the first bad index for batches).
    """
    arr = np.asarray(mat)
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    arr = np.asarray(arr, dtype=np.float64)
    if arr.ndim < 2 or arr.shape[-2:] != (4, 4):
        raise ValueError(f"{name}: expected shape [..., 4, 4], got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name}: contains non-finite values")
    r = arr[..., :3, :3]
    err_row = np.abs(arr[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    err_orth = np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max(axis=(-1, -2))
    det = np.linalg.det(r)
    bad = (err_row > tol) | (err_orth > tol) | (np.abs(det - 1.0) > tol)
    if bad.any():
        where = "" if arr.ndim == 2 else f" at index {tuple(int(i) for i in np.argwhere(bad)[0])}"
        raise ValueError(
            f"{name}: not a rigid transform{where} (last row must be [0, 0, 0, 1], rotation "
            f"orthonormal with det +1, tolerance {tol})"
        )
    return arr


def rigid_inverse(mat: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``[..., 4, 4]``: ``[[R^T, -R^T t], [0, 1]]`` (float64)."""
    mat = np.asarray(mat, dtype=np.float64)
    out = np.zeros_like(mat)
    rt = np.swapaxes(mat[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -(rt @ mat[..., :3, 3:4])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """Rotation matrices ``[..., 3, 3]`` -> unit quaternions ``[..., 4]`` (w, x, y, z), ``w >= 0``.

    Branch-free variant of Shepperd's method: each row uses the largest of the four
    candidate denominators, so it is accurate for every rotation (incl. 180 degrees).
    """
    r = np.asarray(r, dtype=np.float64)
    m00, m01, m02 = r[..., 0, 0], r[..., 0, 1], r[..., 0, 2]
    m10, m11, m12 = r[..., 1, 0], r[..., 1, 1], r[..., 1, 2]
    m20, m21, m22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    # 4 q_i^2 for i = w, x, y, z
    sq = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], axis=-1
    )
    # Candidate quaternions, each scaled by 4 q_i (row i is exact when q_i is the largest).
    cand = np.stack(
        [
            np.stack([sq[..., 0], m21 - m12, m02 - m20, m10 - m01], axis=-1),
            np.stack([m21 - m12, sq[..., 1], m10 + m01, m02 + m20], axis=-1),
            np.stack([m02 - m20, m10 + m01, sq[..., 2], m21 + m12], axis=-1),
            np.stack([m10 - m01, m20 + m02, m21 + m12, sq[..., 3]], axis=-1),
        ],
        axis=-2,
    )
    best = np.argmax(sq, axis=-1)
    q = np.take_along_axis(cand, best[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[..., 4]`` (w, x, y, z; renormalised) -> rotation matrices ``[..., 3, 3]``."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def quat_hemisphere_continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[T, ..., 4]`` with signs flipped along axis 0 so consecutive samples have a
    non-negative dot product (interpolation between samples then takes the short way)."""
    q = np.array(q, dtype=np.float64, copy=True)
    for t in range(1, q.shape[0]):
        flip = (q[t] * q[t - 1]).sum(axis=-1, keepdims=True) < 0
        q[t] = np.where(flip, -q[t], q[t])
    return q


def wxyz_to_usd(q: np.ndarray) -> np.ndarray:
    """``[..., 4]`` w, x, y, z -> the ``Vt.Quat*Array`` numpy layout x, y, z, w (contiguous copy)."""
    return np.ascontiguousarray(np.asarray(q)[..., [1, 2, 3, 0]])


def usd_to_wxyz(q: np.ndarray) -> np.ndarray:
    """``Vt.Quat*Array`` numpy layout x, y, z, w -> ``[..., 4]`` w, x, y, z (contiguous copy)."""
    return np.ascontiguousarray(np.asarray(q)[..., [3, 0, 1, 2]])


def to_gf_matrix(mat: np.ndarray) -> Gf.Matrix4d:
    """Column-vector 4x4 (ours) -> ``Gf.Matrix4d`` (USD row-vector convention: the transpose)."""
    return Gf.Matrix4d(np.asarray(mat, dtype=np.float64).T.tolist())


def from_gf_matrix(m: Gf.Matrix4d) -> np.ndarray:
    """``Gf.Matrix4d`` (row vectors) -> column-vector float64 ``[4, 4]``."""
    return np.array(m, dtype=np.float64).T.copy()
