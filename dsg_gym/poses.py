"""Rigid poses and quaternions in float64 numpy: the one numpy implementation (the environment's hot path,
world files and USD export avoid torch).

Same conventions as :mod:`dsg_gym.geometry` (which is the batched torch version used in training): quaternions
``w, x, y, z`` (Hamilton, ``quat_multiply(a, b)`` applies ``b`` first), poses are 7-vectors
``(x, y, z, qw, qx, qy, qz)`` taking object-frame points to the world, 4x4 matrices ``[[R, t], [0, 1]]``.
Every function that reads a quaternion renormalises it; returned quaternions have ``w >= 0``. All functions
accept any leading batch dimensions. :func:`check_rigid` validates ``[..., 4, 4]`` transforms and
:func:`rigid_inverse` inverts them.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "RIGID_TOL",
    "as_poses7",
    "axis_angle_to_quat",
    "check_rigid",
    "matrix_to_pose7",
    "pose7_to_matrix",
    "quat_angle",
    "quat_hemisphere_continuous",
    "quat_multiply",
    "quat_normalize",
    "quat_to_rotmat",
    "rigid_inverse",
    "rotmat_to_quat",
    "yaw_to_quat",
]


#: tolerance of :func:`check_rigid` (last row, orthonormality and determinant of the rotation)
RIGID_TOL = 1e-5

#: batches of at most this many quaternions (``[n, 4]``) take a scalar path: Python floats, the same IEEE
#: operations in the same order as the numpy code (identical results, without numpy's per-call overhead)
_SMALL = 8


def _sum_order_is_sequential() -> bool:
    """Whether ``np.add.reduce(x, axis=-1)`` over ``[n, 4]`` rows adds ``((a + b) + c) + d`` (the scalar
    path's order); checked once at import on values where the orders differ, else the scalar path is off."""
    rng = np.random.default_rng(12345)
    for n in range(1, _SMALL + 1):
        s = rng.uniform(0.0, 1.0, (64, n, 4)) * np.exp2(rng.integers(-30, 30, (64, n, 1)))
        ref = np.stack([np.add.reduce(x, axis=-1) for x in s])
        if not np.array_equal(ref, ((s[..., 0] + s[..., 1]) + s[..., 2]) + s[..., 3]):
            return False
    return True


_SCALAR_OK = _sum_order_is_sequential()


def _small(q: np.ndarray) -> bool:
    return _SCALAR_OK and q.ndim == 2 and q.shape[1] == 4 and 0 < q.shape[0] <= _SMALL


def _unit_rows(q: np.ndarray, eps: float) -> list[tuple[float, float, float, float]] | None:
    """Scalar path of :func:`quat_normalize` on ``[n, 4]`` rows; None where the numpy path must decide
    (non-finite or huge components)."""
    out = []
    for w, x, y, z in q.tolist():
        if not max(abs(w), abs(x), abs(y), abs(z)) <= 1e150:
            return None
        n = math.sqrt(((w * w + x * x) + y * y) + z * z)
        if n <= eps:
            raise ValueError("quaternion is zero or not finite")
        w, x, y, z = w / n, x / n, y / n, z / n
        out.append((-w, -x, -y, -z) if w < 0 else (w, x, y, z))
    return out


def quat_normalize(q: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    """Unit quaternions with ``w >= 0`` (float64); ValueError for a (near-)zero or non-finite one."""
    q = np.asarray(q, dtype=np.float64)
    if _small(q):
        rows = _unit_rows(q, eps)
        if rows is not None:
            return np.array(rows)
    a = np.abs(q)
    if not np.isfinite(a).all():
        raise ValueError("quaternion is zero or not finite")
    if a.size and a.max() > 1e150:  # rescale those first so that the squared norm cannot overflow
        big = a.max(axis=-1, keepdims=True) > 1e150
        q = np.where(big, q / np.where(big, a.max(axis=-1, keepdims=True), 1.0), q)
    # np.linalg.norm(q, axis=-1, keepdims=True) without its Python overhead (the same reduction)
    n = np.sqrt(np.add.reduce(q * q, axis=-1, keepdims=True))
    if (n <= eps).any():
        raise ValueError("quaternion is zero or not finite")
    q = q / n
    return np.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (rotation ``b`` first), not renormalised."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    if a.shape == b.shape and _small(a):
        return np.array([
            (aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
             aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw)
            for (aw, ax, ay, az), (bw, bx, by, bz) in zip(a.tolist(), b.tolist())
        ])  # fmt: skip
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = aw * bw - ax * bx - ay * by - az * bz
    out[..., 1] = aw * bx + ax * bw + ay * bz - az * by
    out[..., 2] = aw * by - ax * bz + ay * bw + az * bx
    out[..., 3] = aw * bz + ax * by - ay * bx + az * bw
    return out


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """``[..., 4] -> [..., 3, 3]`` (renormalises)."""
    q = quat_normalize(q)
    if _small(q):
        return np.array([
            ((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
             (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
             (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)))
            for w, x, y, z in q.tolist()
        ])  # fmt: skip
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - w * z)
    r[..., 0, 2] = 2 * (x * z + w * y)
    r[..., 1, 0] = 2 * (x * y + w * z)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - w * x)
    r[..., 2, 0] = 2 * (x * z - w * y)
    r[..., 2, 1] = 2 * (y * z + w * x)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def rotmat_to_quat(r: np.ndarray) -> np.ndarray:
    """``[..., 3, 3] -> [..., 4]`` unit quaternion with ``w >= 0`` (Shepperd's method, stable everywhere)."""
    r = np.asarray(r, dtype=np.float64)
    shape = r.shape[:-2]
    m = r.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    tr = m00 + m11 + m22
    # four candidate (unnormalised) quaternions, each well conditioned when its diagonal term is largest
    cands = np.stack(
        [
            np.stack([1.0 + tr, m21 - m12, m02 - m20, m10 - m01], axis=1),
            np.stack([m21 - m12, 1.0 + m00 - m11 - m22, m01 + m10, m02 + m20], axis=1),
            np.stack([m02 - m20, m01 + m10, 1.0 + m11 - m00 - m22, m12 + m21], axis=1),
            np.stack([m10 - m01, m02 + m20, m12 + m21, 1.0 + m22 - m00 - m11], axis=1),
        ],
        axis=1,
    )
    pick = np.argmax(np.stack([tr, m00, m11, m22], axis=1), axis=1)
    q = cands[np.arange(m.shape[0]), pick]
    return quat_normalize(q).reshape(*shape, 4)


def axis_angle_to_quat(v: np.ndarray) -> np.ndarray:
    """Rotation vectors ``[..., 3]`` (axis times angle, radians) -> unit quaternions ``[..., 4]``."""
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle with its Taylor series near 0
    k = np.where(angle > 1e-8, np.sin(half) / np.where(angle > 1e-8, angle, 1.0), 0.5 - angle**2 / 48.0)
    return quat_normalize(np.concatenate([np.cos(half), v * k], axis=-1))


def yaw_to_quat(yaw: np.ndarray) -> np.ndarray:
    """Rotations by ``yaw`` radians about +z, ``[...] -> [..., 4]``."""
    yaw = np.asarray(yaw, dtype=np.float64)
    q = np.zeros(yaw.shape + (4,))
    q[..., 0] = np.cos(0.5 * yaw)
    q[..., 3] = np.sin(0.5 * yaw)
    return quat_normalize(q)


def quat_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (radians, in [0, pi]) of the rotation taking ``b`` to ``a``."""
    d = np.abs(np.sum(quat_normalize(a) * quat_normalize(b), axis=-1))
    return 2.0 * np.arccos(np.clip(d, 0.0, 1.0))


def pose7_to_matrix(p: np.ndarray) -> np.ndarray:
    """``[..., 7] -> [..., 4, 4]`` float64 (the quaternion is renormalised)."""
    p = np.asarray(p, dtype=np.float64)
    m = np.zeros(p.shape[:-1] + (4, 4))
    m[..., :3, :3] = quat_to_rotmat(p[..., 3:7])
    m[..., :3, 3] = p[..., :3]
    m[..., 3, 3] = 1.0
    return m


def matrix_to_pose7(m: np.ndarray) -> np.ndarray:
    """``[..., 4, 4] -> [..., 7]`` float64 with a unit quaternion, ``w >= 0``."""
    m = np.asarray(m, dtype=np.float64)
    return np.concatenate([m[..., :3, 3], rotmat_to_quat(m[..., :3, :3])], axis=-1)


def as_poses7(value, k: int, name: str = "poses") -> np.ndarray:
    """Validate ``[k, 7]`` poses or ``[k, 4, 4]`` rigid transforms -> ``[k, 7]`` float64, renormalised.

    ValueError naming ``name`` for a wrong shape, non-finite values, a zero quaternion or a non-rigid matrix.
    """
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape == (k, 4, 4):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}: contains NaN or Inf")
        r = arr[:, :3, :3]
        if np.abs(r.transpose(0, 2, 1) @ r - np.eye(3)).max() > 1e-5 or np.any(np.linalg.det(r) < 0):
            raise ValueError(f"{name}: matrices are not rigid transforms")
        if np.abs(arr[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
            raise ValueError(f"{name}: last row of a transform must be (0, 0, 0, 1)")
        return matrix_to_pose7(arr)
    if arr.shape != (k, 7):
        raise ValueError(f"{name}: expected shape ({k}, 7) or ({k}, 4, 4), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: contains NaN or Inf")
    try:
        q = quat_normalize(arr[:, 3:7])
    except ValueError:
        raise ValueError(f"{name}: a quaternion is zero") from None
    return np.concatenate([arr[:, :3], q], axis=1)


def quat_hemisphere_continuous(q: np.ndarray) -> np.ndarray:
    """Quaternions ``[T, ..., 4]`` with signs flipped along axis 0 so consecutive samples have a
    non-negative dot product (interpolation between samples then takes the short way)."""
    q = np.array(q, dtype=np.float64, copy=True)
    for t in range(1, q.shape[0]):
        flip = (q[t] * q[t - 1]).sum(axis=-1, keepdims=True) < 0
        q[t] = np.where(flip, -q[t], q[t])
    return q


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
