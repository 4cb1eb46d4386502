"""Rigid-body geometry over batched torch tensors (pure functions, no state).

Conventions (stated once, used everywhere in dsg-gym):

* Quaternions are ``[..., 4]`` in **w, x, y, z** order (Hamilton convention,
  ``q * v * q^-1`` rotates ``v``; ``quat_multiply(a, b)`` applies ``b`` first).
  Functions that interpret a quaternion as a rotation renormalise it first; the
  zero quaternion is read as the identity. ``q`` and ``-q`` are the same rotation;
  functions that *return* a rotation quaternion give the sign with ``w >= 0``.
* Rotation matrices are ``[..., 3, 3]`` and act on column vectors (``R @ v``).
* Rigid transforms are ``[..., 4, 4]`` homogeneous matrices ``[[R, t], [0, 1]]``;
  ``se3_compose(a, b) = a @ b`` applies ``b`` first.
* Poses are 7-vectors ``[..., 7] = (x, y, z, qw, qx, qy, qz)``: the transform
  taking points from the object (child) frame to the world (parent) frame.
* Axis-angle ("rotation vector") is ``[..., 3]``: unit axis times angle (radians).
* Cameras are OpenCV: x right, y down, z forward. A ``viewmat`` is the
  world-to-camera transform ``[..., 4, 4]``. NeRF / nerfstudio ``transforms.json``
  camera-to-world matrices use OpenGL camera axes (x right, y up, z back).
* Intrinsics ``K`` are ``[..., 3, 3]``; pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)``,
  so the centre of a ``W x H`` image is at ``(W/2, H/2)``.
* Units are metres and radians.

All functions accept any leading batch dimensions (broadcast where two inputs are
given), keep the input dtype and device, and are differentiable away from the
documented singular points. float64 is what the environment uses for poses.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = [
    "quat_normalize",
    "quat_standardize",
    "quat_multiply",
    "quat_conjugate",
    "quat_inverse",
    "quat_apply",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "axis_angle_to_quat",
    "quat_to_axis_angle",
    "yaw_to_quat",
    "quat_angle_distance",
    "pose7_to_matrix",
    "matrix_to_pose7",
    "se3_from_rt",
    "se3_inverse",
    "se3_compose",
    "transform_points",
    "is_rigid",
    "opengl_c2w_to_viewmat",
    "viewmat_to_opengl_c2w",
    "look_at_viewmat",
    "intrinsics_from_fov",
]

# Below this angle (radians) closed forms like sin(t/2)/t switch to Taylor series.
_SMALL_ANGLE = 1e-2


def _identity_quat_like(q: Tensor) -> Tensor:
    ident = torch.zeros(4, dtype=q.dtype, device=q.device)
    ident[0] = 1
    return ident.expand_as(q)


# --------------------------------------------------------------------------- quaternions


def quat_normalize(q: Tensor, eps: float = 1e-12) -> Tensor:
    """Unit quaternion with the direction of ``q``.

    ``q``: ``[..., 4]`` (w, x, y, z) -> ``[..., 4]``. Quaternions with norm ``<= eps``
    (in particular the zero quaternion) become the identity ``(1, 0, 0, 0)``, never NaN.
    The sign is kept (``quat_standardize`` makes ``w >= 0``).
    """
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    ok = norm > eps
    safe = torch.where(ok, norm, torch.ones_like(norm))
    return torch.where(ok, q / safe, _identity_quat_like(q))


def quat_standardize(q: Tensor) -> Tensor:
    """Flip the sign of ``q`` where ``w < 0`` so that ``w >= 0``. ``[..., 4] -> [..., 4]``."""
    return torch.where(q[..., :1] < 0, -q, q)


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product ``a * b`` (rotation ``b`` then ``a``).

    ``a``: ``[..., 4]``, ``b``: ``[..., 4]`` (broadcast) -> ``[..., 4]``. No renormalisation.
    """
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ),
        dim=-1,
    )


def quat_conjugate(q: Tensor) -> Tensor:
    """Conjugate ``(w, -x, -y, -z)``. ``[..., 4] -> [..., 4]``."""
    sign = torch.tensor([1, -1, -1, -1], dtype=q.dtype, device=q.device)
    return q * sign


def quat_inverse(q: Tensor) -> Tensor:
    """Multiplicative inverse ``conj(q) / |q|^2`` (equals the conjugate for unit ``q``).

    ``[..., 4] -> [..., 4]``. The zero quaternion (no inverse) maps to the identity,
    consistent with ``quat_normalize``.
    """
    n2 = (q * q).sum(dim=-1, keepdim=True)
    ok = n2 > 0
    safe = torch.where(ok, n2, torch.ones_like(n2))
    return torch.where(ok, quat_conjugate(q) / safe, _identity_quat_like(q))


def quat_apply(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors ``v`` by the rotation ``q`` (renormalised).

    ``q``: ``[..., 4]``, ``v``: ``[..., 3]`` (broadcast) -> ``[..., 3]``.
    Equal to ``quat_to_rotmat(q) @ v``.
    """
    q = quat_normalize(q)
    shape = torch.broadcast_shapes(q.shape[:-1], v.shape[:-1])
    q = q.expand(*shape, 4)
    v = v.expand(*shape, 3)
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v, dim=-1)
    return v + w * t + torch.linalg.cross(u, t, dim=-1)


def quat_to_rotmat(q: Tensor) -> Tensor:
    """Rotation matrix of ``q`` (renormalised). ``[..., 4] -> [..., 3, 3]``.

    ``q`` and ``-q`` give bit-identical matrices.
    """
    q = quat_normalize(q)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = (
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    )  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit quaternion of a rotation matrix (Shepperd's method), ``w >= 0``.

    ``R``: ``[..., 3, 3]`` -> ``[..., 4]``. Picks, per matrix, the numerically largest of
    ``w, x, y, z`` to divide by, so it is accurate for all angles including pi. For a
    slightly non-orthonormal input the result is a close (not the nearest) rotation.
    """
    m00, m01, m02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    m10, m11, m12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    m20, m21, m22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    # Each candidate equals 4 * q_k * (w, x, y, z) for the component q_k named in the comment.
    cands = torch.stack(
        (
            torch.stack((1 + trace, m21 - m12, m02 - m20, m10 - m01), -1),  # k = w
            torch.stack((m21 - m12, 1 + m00 - m11 - m22, m01 + m10, m02 + m20), -1),  # k = x
            torch.stack((m02 - m20, m01 + m10, 1 - m00 + m11 - m22, m12 + m21), -1),  # k = y
            torch.stack((m10 - m01, m02 + m20, m12 + m21, 1 - m00 - m11 + m22), -1),  # k = z
        ),
        dim=-2,
    )  # [..., 4, 4]
    choice = torch.stack((trace, m00, m11, m22), dim=-1).argmax(dim=-1)  # [...]
    idx = choice[..., None, None].expand(*choice.shape, 1, 4)
    q = torch.gather(cands, -2, idx).squeeze(-2)
    return quat_standardize(quat_normalize(q))


def axis_angle_to_quat(rotvec: Tensor) -> Tensor:
    """Quaternion of a rotation vector (axis * angle). ``[..., 3] -> [..., 4]``.

    Stable at angle 0 (Taylor series) and at any angle (no division by a small angle).
    Angles beyond pi are fine; the result then has ``w < 0``.
    """
    theta = torch.linalg.vector_norm(rotvec, dim=-1, keepdim=True)
    small = theta < _SMALL_ANGLE
    t2 = theta * theta
    taylor = 0.5 - t2 / 48.0 + t2 * t2 / 3840.0  # sin(t/2)/t
    safe = torch.where(small, torch.ones_like(theta), theta)
    k = torch.where(small, taylor, torch.sin(0.5 * safe) / safe)
    return torch.cat((torch.cos(0.5 * theta), k * rotvec), dim=-1)


def quat_to_axis_angle(q: Tensor) -> Tensor:
    """Rotation vector of ``q`` (renormalised), angle in ``[0, pi]``. ``[..., 4] -> [..., 3]``.

    Stable near angle 0 (series for ``atan2(n, w) / n``) and near pi (``atan2``).
    At exactly pi the axis sign is that of the input's vector part.
    """
    q = quat_standardize(quat_normalize(q))
    w, v = q[..., :1], q[..., 1:]
    n = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    small = n < _SMALL_ANGLE
    # Small n means w ~ 1 (since w >= 0), so r = n / w is small and well defined.
    w_safe = torch.where(small, w, torch.ones_like(w))
    r2 = (n / w_safe) ** 2
    taylor = (2.0 / w_safe) * (1.0 - r2 / 3.0 + r2 * r2 / 5.0)  # 2 atan(n/w) / n
    n_safe = torch.where(small, torch.ones_like(n), n)
    k = torch.where(small, taylor, 2.0 * torch.atan2(n_safe, w) / n_safe)
    return k * v


def yaw_to_quat(yaw: Tensor) -> Tensor:
    """Rotation by ``yaw`` radians about +z (counter-clockwise seen from +z). ``[...] -> [..., 4]``."""
    half = 0.5 * yaw
    zero = torch.zeros_like(half)
    return torch.stack((torch.cos(half), zero, zero, torch.sin(half)), dim=-1)


def quat_angle_distance(a: Tensor, b: Tensor) -> Tensor:
    """Geodesic angle (radians, ``[0, pi]``) between rotations ``a`` and ``b``.

    ``[..., 4]``, ``[..., 4]`` (broadcast) -> ``[...]``. Sign-invariant (``q`` ~ ``-q``) and
    accurate for small angles (``atan2`` of the relative rotation, not ``acos``).
    """
    r = quat_multiply(quat_conjugate(quat_normalize(a)), quat_normalize(b))
    n = torch.linalg.vector_norm(r[..., 1:], dim=-1)
    return 2.0 * torch.atan2(n, r[..., 0].abs())


# --------------------------------------------------------------------------- rigid transforms


def se3_from_rt(R: Tensor, t: Tensor) -> Tensor:
    """Homogeneous ``[[R, t], [0, 0, 0, 1]]``.

    ``R``: ``[..., 3, 3]``, ``t``: ``[..., 3]`` (broadcast) -> ``[..., 4, 4]``.
    """
    shape = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    R = R.expand(*shape, 3, 3)
    t = t.expand(*shape, 3)
    top = torch.cat((R, t[..., None]), dim=-1)
    bottom = torch.zeros(*shape, 1, 4, dtype=R.dtype, device=R.device)
    bottom[..., 0, 3] = 1
    return torch.cat((top, bottom), dim=-2)


def pose7_to_matrix(pose: Tensor) -> Tensor:
    """``(x, y, z, qw, qx, qy, qz)`` -> rigid transform. ``[..., 7] -> [..., 4, 4]``.

    The quaternion is renormalised (zero -> identity).
    """
    return se3_from_rt(quat_to_rotmat(pose[..., 3:7]), pose[..., :3])


def matrix_to_pose7(mat: Tensor) -> Tensor:
    """Rigid transform -> ``(x, y, z, qw, qx, qy, qz)`` with ``qw >= 0``. ``[..., 4, 4] -> [..., 7]``."""
    return torch.cat((mat[..., :3, 3], rotmat_to_quat(mat[..., :3, :3])), dim=-1)


def se3_inverse(mat: Tensor) -> Tensor:
    """Inverse of a rigid transform, ``[[R^T, -R^T t], [0, 1]]``. ``[..., 4, 4] -> [..., 4, 4]``.

    Assumes ``mat`` is rigid (see ``is_rigid``); use ``torch.linalg.inv`` otherwise.
    """
    Rt = mat[..., :3, :3].transpose(-1, -2)
    t = mat[..., :3, 3:]
    return se3_from_rt(Rt, -(Rt @ t)[..., 0])


def se3_compose(a: Tensor, b: Tensor) -> Tensor:
    """``a @ b``: apply ``b`` first, then ``a``. ``[..., 4, 4]`` x ``[..., 4, 4]`` (broadcast)."""
    return a @ b


def transform_points(mat: Tensor, points: Tensor) -> Tensor:
    """Apply rigid (or affine) transforms to points.

    ``mat``: ``[..., 4, 4]``, ``points``: ``[..., N, 3]`` (batch dims broadcast) -> ``[..., N, 3]``.
    """
    R = mat[..., :3, :3]
    t = mat[..., None, :3, 3]
    return points @ R.transpose(-1, -2) + t


def is_rigid(mat: Tensor, atol: float = 1e-6) -> Tensor:
    """Whether each ``[4, 4]`` matrix is a finite proper rigid transform.

    ``mat``: ``[..., 4, 4]`` -> bool ``[...]``. Checks, all to ``atol``: ``R^T R = I``,
    ``det R = 1`` (so reflections fail), last row ``(0, 0, 0, 1)``; and all entries finite.
    """
    if mat.shape[-2:] != (4, 4):
        raise ValueError(f"is_rigid expects [..., 4, 4], got {tuple(mat.shape)}")
    m = mat if mat.dtype in (torch.float32, torch.float64) else mat.to(torch.float32)
    finite = torch.isfinite(m).flatten(-2).all(dim=-1)
    m = torch.where(finite[..., None, None], m, torch.zeros_like(m))  # keep det/matmul NaN-free
    R = m[..., :3, :3]
    eye = torch.eye(3, dtype=m.dtype, device=m.device)
    ortho = ((R.transpose(-1, -2) @ R - eye).abs() <= atol).flatten(-2).all(dim=-1)
    det = (torch.linalg.det(R) - 1).abs() <= atol
    last = torch.tensor([0, 0, 0, 1], dtype=m.dtype, device=m.device)
    bottom = ((m[..., 3, :] - last).abs() <= atol).all(dim=-1)
    return finite & ortho & det & bottom


# --------------------------------------------------------------------------- cameras


def _flip_yz(mat: Tensor) -> Tensor:
    """Negate the camera y and z axes (columns 1 and 2 of a camera-to-world matrix)."""
    sign = torch.tensor([1, -1, -1, 1], dtype=mat.dtype, device=mat.device)
    return mat * sign


def opengl_c2w_to_viewmat(c2w_gl: Tensor) -> Tensor:
    """OpenGL camera-to-world (NeRF ``transform_matrix``) -> OpenCV world-to-camera viewmat.

    ``[..., 4, 4] -> [..., 4, 4]``. Flips the camera's y and z axes, then inverts
    (rigid inverse: the input must be rigid).
    """
    return se3_inverse(_flip_yz(c2w_gl))


def viewmat_to_opengl_c2w(viewmat: Tensor) -> Tensor:
    """OpenCV world-to-camera viewmat -> OpenGL camera-to-world. ``[..., 4, 4] -> [..., 4, 4]``."""
    return _flip_yz(se3_inverse(viewmat))


def _normalize(v: Tensor) -> Tensor:
    n = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return v / torch.where(n > 0, n, torch.ones_like(n))


def look_at_viewmat(eye: Tensor, target: Tensor, up: Tensor | None = None) -> Tensor:
    """OpenCV world-to-camera viewmat of a camera at ``eye`` looking at ``target``.

    ``eye``, ``target``, ``up``: ``[..., 3]`` (broadcast; ``up`` defaults to world +z)
    -> ``[..., 4, 4]``. The camera's +z points at ``target`` (which lands on the optical
    axis at depth ``|target - eye|``), and world ``up`` projects upwards in the image
    (towards -y). If ``up`` is parallel to the viewing direction, the world axis least
    aligned with it is used instead. ``eye == target`` is undefined.
    """
    if up is None:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=eye.dtype, device=eye.device)
    shape = torch.broadcast_shapes(eye.shape, target.shape, up.shape)
    eye, target, up = eye.expand(shape), target.expand(shape), up.expand(shape)
    z = _normalize(target - eye)
    x = torch.linalg.cross(z, up, dim=-1)
    xn = torch.linalg.vector_norm(x, dim=-1, keepdim=True)
    up_n = torch.linalg.vector_norm(up, dim=-1, keepdim=True)
    degenerate = xn <= 1e-9 * up_n.clamp_min(torch.finfo(eye.dtype).tiny)
    # Fallback: the world axis least aligned with z.
    axis = torch.nn.functional.one_hot(z.abs().argmin(dim=-1), 3).to(z.dtype)
    x = torch.where(degenerate, torch.linalg.cross(z, axis, dim=-1), x)
    x = _normalize(x)
    y = torch.linalg.cross(z, x, dim=-1)
    c2w_R = torch.stack((x, y, z), dim=-1)  # columns are the camera axes in world
    R = c2w_R.transpose(-1, -2)
    t = -(R @ eye[..., None])[..., 0]
    return se3_from_rt(R, t)


def intrinsics_from_fov(
    fovy_rad: Tensor | float,
    width: int,
    height: int,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Pinhole ``K`` from a vertical field of view, square pixels.

    ``fovy_rad``: ``[...]`` or a float -> ``[..., 3, 3]`` with ``fx = fy = (H/2) / tan(fovy/2)``
    and principal point ``(W/2, H/2)`` (pixel centres are at ``+0.5``). dtype/device follow
    a tensor ``fovy_rad``; for a float they default to torch's default dtype and CPU.
    """
    if not isinstance(fovy_rad, Tensor):
        fovy_rad = torch.tensor(float(fovy_rad), dtype=dtype or torch.get_default_dtype(), device=device)
    elif dtype is not None or device is not None:
        fovy_rad = fovy_rad.to(dtype=dtype or fovy_rad.dtype, device=device or fovy_rad.device)
    if not bool(torch.all((fovy_rad > 0) & (fovy_rad < math.pi))):
        raise ValueError("fovy_rad must lie in (0, pi)")
    f = (0.5 * height) / torch.tan(0.5 * fovy_rad)
    zero, one = torch.zeros_like(f), torch.ones_like(f)
    rows = (f, zero, zero + 0.5 * width, zero, f, zero + 0.5 * height, zero, zero, one)
    return torch.stack(rows, dim=-1).reshape(*f.shape, 3, 3)
