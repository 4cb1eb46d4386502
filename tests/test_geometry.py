"""Tests for dsg_gym.geometry: property tests (hypothesis) plus explicit cases."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dsg_gym import geometry as G

F64 = torch.float64
SETTINGS = settings(max_examples=150, deadline=None)

unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
coord = st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False)


@st.composite
def quats(draw, min_norm=1e-3):
    """Arbitrary (unnormalised) quaternion, float64 [4], norm >= min_norm."""
    q = torch.tensor(draw(st.tuples(unit, unit, unit, unit)), dtype=F64)
    assume(torch.linalg.vector_norm(q) >= min_norm)
    scale = draw(st.floats(1e-3, 1e3))
    return q * scale


@st.composite
def unit_axes(draw):
    a = torch.tensor(draw(st.tuples(unit, unit, unit)), dtype=F64)
    n = torch.linalg.vector_norm(a)
    assume(n > 1e-3)
    return a / n


angles = st.one_of(
    st.floats(0.0, math.pi),
    st.sampled_from([0.0, 1e-300, 1e-12, 1e-8, 1e-4, 9e-3, 1.1e-2, math.pi - 1e-9, math.pi - 1e-12, math.pi]),
)


@st.composite
def poses(draw):
    t = torch.tensor(draw(st.tuples(coord, coord, coord)), dtype=F64)
    return torch.cat((t, draw(quats())))


def assert_close(a, b, atol=1e-12, rtol=0.0):
    torch.testing.assert_close(a, b, atol=atol, rtol=rtol)


def random_quats(n, gen, dtype=F64):
    return G.quat_normalize(torch.randn(n, 4, generator=gen, dtype=dtype))


# --------------------------------------------------------------------------- properties


@SETTINGS
@given(quats())
def test_quat_rotmat_round_trip(q):
    R = G.quat_to_rotmat(q)
    q2 = G.rotmat_to_quat(R)
    qn = G.quat_standardize(G.quat_normalize(q))
    assert q2[0] >= 0
    # Same rotation (sign-insensitive) and, away from w == 0, the same standardized numbers.
    assert G.quat_angle_distance(q, q2) < 1e-7
    assert_close(G.quat_to_rotmat(q2), R, atol=1e-14)
    if qn[0] > 1e-6:
        assert_close(q2, qn, atol=1e-14)


@SETTINGS
@given(quats())
def test_rotmat_is_orthonormal(q):
    R = G.quat_to_rotmat(q)
    assert_close(R.T @ R, torch.eye(3, dtype=F64), atol=1e-14)
    assert abs(torch.linalg.det(R) - 1) < 1e-14


@SETTINGS
@given(quats())
def test_q_and_minus_q_same_matrix(q):
    assert torch.equal(G.quat_to_rotmat(q), G.quat_to_rotmat(-q))
    assert G.quat_angle_distance(q, -q) < 1e-7


@SETTINGS
@given(unit_axes(), angles)
def test_axis_angle_round_trip(axis, angle):
    rv = axis * angle
    q = G.axis_angle_to_quat(rv)
    assert abs(torch.linalg.vector_norm(q) - 1) < 1e-15
    assert torch.isfinite(q).all()
    rv2 = G.quat_to_axis_angle(q)
    assert torch.isfinite(rv2).all()
    assert abs(torch.linalg.vector_norm(rv2) - angle) < 1e-12
    if angle < math.pi - 1e-6:
        assert_close(rv2, rv, atol=1e-12)
    else:  # at pi the axis sign is ambiguous: compare rotations
        assert_close(G.quat_to_rotmat(G.axis_angle_to_quat(rv2)), G.quat_to_rotmat(q), atol=1e-12)


@SETTINGS
@given(quats())
def test_quat_axis_angle_quat(q):
    q2 = G.axis_angle_to_quat(G.quat_to_axis_angle(q))
    assert G.quat_angle_distance(q, q2) < 1e-7
    assert_close(G.quat_to_rotmat(q2), G.quat_to_rotmat(q), atol=1e-13)


@SETTINGS
@given(poses())
def test_pose7_matrix_round_trip(p):
    M = G.pose7_to_matrix(p)
    assert G.is_rigid(M, atol=1e-12)
    p2 = G.matrix_to_pose7(M)
    assert_close(p2[:3], p[:3])
    assert p2[3] >= 0
    assert G.quat_angle_distance(p2[3:], p[3:]) < 1e-7
    assert_close(G.pose7_to_matrix(p2), M, atol=1e-12)


@SETTINGS
@given(poses(), poses())
def test_compose_with_inverse_is_identity(p, p_other):
    M, N = G.pose7_to_matrix(p), G.pose7_to_matrix(p_other)
    eye = torch.eye(4, dtype=F64)
    assert_close(G.se3_compose(M, G.se3_inverse(M)), eye, atol=1e-12)
    assert_close(G.se3_compose(G.se3_inverse(M), M), eye, atol=1e-12)
    inv_mn = G.se3_compose(G.se3_inverse(N), G.se3_inverse(M))
    assert_close(G.se3_inverse(G.se3_compose(M, N)), inv_mn, atol=1e-10)
    assert_close(G.se3_inverse(M), torch.linalg.inv(M), atol=1e-10)


@SETTINGS
@given(quats(), st.tuples(coord, coord, coord))
def test_quat_apply_matches_rotmat(q, v):
    v = torch.tensor(v, dtype=F64)
    assert_close(G.quat_apply(q, v), G.quat_to_rotmat(q) @ v, atol=1e-11)


@SETTINGS
@given(quats(), quats())
def test_quat_multiply_is_matrix_product(a, b):
    ab = G.quat_multiply(G.quat_normalize(a), G.quat_normalize(b))
    assert_close(G.quat_to_rotmat(ab), G.quat_to_rotmat(a) @ G.quat_to_rotmat(b), atol=1e-13)
    inv = G.quat_inverse(a)
    assert_close(G.quat_multiply(a, inv), torch.tensor([1.0, 0, 0, 0], dtype=F64), atol=1e-13)
    assert_close(G.quat_inverse(G.quat_normalize(a)), G.quat_conjugate(G.quat_normalize(a)), atol=1e-15)


@SETTINGS
@given(quats(min_norm=1e-6))
def test_normalize_unnormalised(q):
    qn = G.quat_normalize(q)
    assert abs(torch.linalg.vector_norm(qn) - 1) < 1e-15
    assert_close(qn * torch.linalg.vector_norm(q), q, atol=1e-9 * float(torch.linalg.vector_norm(q)))


@SETTINGS
@given(quats(), quats())
def test_angle_distance_is_rotation_angle(a, b):
    d = G.quat_angle_distance(a, b)
    Ra, Rb = G.quat_to_rotmat(a), G.quat_to_rotmat(b)
    rel = Ra.T @ Rb
    cos = ((torch.trace(rel) - 1) / 2).clamp(-1, 1)
    assert 0 <= d <= math.pi + 1e-12
    assert abs(torch.cos(d) - cos) < 1e-10
    assert abs(d - G.quat_angle_distance(b, a)) < 1e-12


# --------------------------------------------------------------------------- explicit cases


def test_zero_quaternion_is_identity():
    z = torch.zeros(2, 3, 4, dtype=F64)
    ident = torch.tensor([1.0, 0, 0, 0], dtype=F64).expand(2, 3, 4)
    assert torch.equal(G.quat_normalize(z), ident)
    assert torch.equal(G.quat_inverse(z), ident)
    assert torch.equal(G.quat_to_rotmat(z), torch.eye(3, dtype=F64).expand(2, 3, 3, 3))
    assert torch.equal(G.quat_to_axis_angle(z), torch.zeros(2, 3, 3, dtype=F64))
    v = torch.tensor([1.0, 2.0, 3.0], dtype=F64)
    assert torch.equal(G.quat_apply(z, v), v.expand(2, 3, 3))
    for dt in (torch.float32, torch.float16):
        assert torch.isfinite(G.quat_normalize(torch.zeros(4, dtype=dt))).all()


def test_rotate_90_about_z():
    q = G.yaw_to_quat(torch.tensor(math.pi / 2, dtype=F64))
    ex, ey = torch.tensor([1.0, 0, 0], dtype=F64), torch.tensor([0, 1.0, 0], dtype=F64)
    assert_close(G.quat_apply(q, ex), ey, atol=1e-15)
    assert_close(G.quat_to_rotmat(q) @ ex, ey, atol=1e-15)
    assert_close(G.axis_angle_to_quat(torch.tensor([0, 0, math.pi / 2], dtype=F64)), q, atol=1e-15)
    M = G.pose7_to_matrix(torch.cat((torch.tensor([1.0, 2.0, 3.0], dtype=F64), q)))
    pts = torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=F64)
    assert_close(G.transform_points(M, pts), torch.tensor([[1.0, 3.0, 3.0], [1.0, 2.0, 4.0]], dtype=F64))


def test_rotmat_to_quat_half_turns_and_batches():
    gen = torch.Generator().manual_seed(0)
    axes = torch.randn(64, 3, generator=gen, dtype=F64)
    axes = axes / torch.linalg.vector_norm(axes, dim=-1, keepdim=True)
    rv = torch.cat((axes * math.pi, torch.eye(3, dtype=F64) * math.pi, -torch.eye(3, dtype=F64) * math.pi))
    R = G.quat_to_rotmat(G.axis_angle_to_quat(rv)).reshape(5, 14, 3, 3)
    q = G.rotmat_to_quat(R)
    assert q.shape == (5, 14, 4)
    assert (q[..., 0] >= 0).all()
    assert_close(G.quat_to_rotmat(q), R, atol=1e-14)


def test_transform_points_batched_and_float32():
    gen = torch.Generator().manual_seed(1)
    p = torch.cat((torch.randn(3, 3, generator=gen), torch.randn(3, 4, generator=gen)), -1)  # float32
    M = G.pose7_to_matrix(p)
    assert M.dtype == torch.float32 and M.shape == (3, 4, 4)
    pts = torch.randn(3, 10, 3, generator=gen)
    out = G.transform_points(M, pts)
    ref = G.quat_apply(p[:, None, 3:], pts) + p[:, None, :3]
    assert_close(out, ref, atol=1e-5)
    assert G.is_rigid(M, atol=1e-5).all()


def test_is_rigid_rejects():
    eye = torch.eye(4, dtype=F64)
    bad = torch.stack([eye.clone() for _ in range(5)])
    bad[0, 0, 0] = -1  # reflection
    bad[1, :3, :3] *= 1.01  # scaled
    bad[2, 3, 0] = 0.5  # projective row
    bad[3, 1, 3] = float("nan")
    bad[4, 0, 3] = float("inf")
    assert not G.is_rigid(bad).any()
    assert G.is_rigid(eye)
    assert G.is_rigid(eye).dtype == torch.bool


def test_look_at():
    eye = torch.tensor([2.0, -1.0, 1.5], dtype=F64)
    target = torch.tensor([0.1, 0.2, 0.3], dtype=F64)
    up = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    V = G.look_at_viewmat(eye, target, up)
    assert G.is_rigid(V, atol=1e-12)
    tc = G.transform_points(V, target[None])[0]
    assert_close(tc[:2], torch.zeros(2, dtype=F64), atol=1e-12)
    assert abs(tc[2] - torch.linalg.vector_norm(target - eye)) < 1e-12
    assert_close(G.transform_points(V, eye[None])[0], torch.zeros(3, dtype=F64), atol=1e-12)
    # A point above the target projects above the image centre (smaller v, i.e. -y).
    above = G.transform_points(V, (target + 0.1 * up)[None])[0]
    assert above[1] < 0 and abs(above[0]) < 1e-12
    # World up, expressed in camera axes, has a negative y component.
    assert (V[:3, :3] @ up)[1] < 0
    # Degenerate: looking straight down along -up still gives a valid camera.
    Vd = G.look_at_viewmat(torch.tensor([0.0, 0, 2], dtype=F64), torch.zeros(3, dtype=F64), up)
    assert G.is_rigid(Vd, atol=1e-12)
    origin_cam = G.transform_points(Vd, torch.zeros(1, 3, dtype=F64))[0]
    assert_close(origin_cam, torch.tensor([0, 0, 2.0], dtype=F64))
    # Batched with a default up.
    Vb = G.look_at_viewmat(torch.randn(6, 3, dtype=F64) + 3.0, torch.zeros(3, dtype=F64))
    assert Vb.shape == (6, 4, 4) and G.is_rigid(Vb, atol=1e-12).all()


def test_look_at_and_intrinsics_agree_with_the_numpy_runtime_ones():
    """The torch look-at / intrinsics (training) and :mod:`dsg_gym.cameras` (runtime) are one convention."""
    import numpy as np

    from dsg_gym.cameras import intrinsics_from_fov, look_at

    rng = np.random.default_rng(5)
    eye, target = rng.normal(size=(200, 3)) * 3.0, rng.normal(size=(200, 3))
    up = rng.normal(size=(200, 3))
    up[:100] = (0.0, 0.0, 1.0)
    batched = G.look_at_viewmat(torch.tensor(eye), torch.tensor(target), torch.tensor(up)).numpy()
    one_by_one = np.stack([look_at(e, t, u) for e, t, u in zip(eye, target, up)])
    np.testing.assert_allclose(batched, one_by_one, rtol=0, atol=1e-12)
    for fovy, w, h in ((50.0, 64, 64), (60.0, 320, 240), (12.5, 33, 17)):
        K = G.intrinsics_from_fov(math.radians(fovy), w, h, dtype=F64).numpy()
        np.testing.assert_allclose(K, intrinsics_from_fov(fovy, w, h), rtol=1e-15, atol=0)


def test_opengl_opencv_conversion():
    gen = torch.Generator().manual_seed(2)
    p = torch.randn(4, 7, generator=gen, dtype=F64)
    c2w_gl = G.pose7_to_matrix(p)
    V = G.opengl_c2w_to_viewmat(c2w_gl)
    assert G.is_rigid(V, atol=1e-12).all()
    c2w_cv = G.se3_inverse(V)
    # Same camera centre; OpenCV x = GL x, y = -GL y, z = -GL z.
    assert_close(c2w_cv[:, :3, 3], c2w_gl[:, :3, 3])
    assert_close(c2w_cv[:, :3, 0], c2w_gl[:, :3, 0])
    assert_close(c2w_cv[:, :3, 1], -c2w_gl[:, :3, 1])
    assert_close(c2w_cv[:, :3, 2], -c2w_gl[:, :3, 2])
    assert_close(G.viewmat_to_opengl_c2w(V), c2w_gl)
    # A point in front of a GL camera (negative GL z) has positive OpenCV depth.
    front = c2w_gl[:, :3, 3] - 2.0 * c2w_gl[:, :3, 2]
    depth = G.transform_points(V, front[:, None])[:, 0, 2]
    assert_close(depth, torch.full((4,), 2.0, dtype=F64))


def test_intrinsics_from_fov():
    K = G.intrinsics_from_fov(math.pi / 2, 640, 480, dtype=F64)
    expected = torch.tensor([[240.0, 0, 320.0], [0, 240.0, 240.0], [0, 0, 1.0]], dtype=F64)
    assert_close(K, expected, atol=1e-12)
    Kb = G.intrinsics_from_fov(torch.tensor([0.5, 1.0]), 64, 32)
    assert Kb.shape == (2, 3, 3) and Kb.dtype == torch.float32
    assert torch.allclose(Kb[:, 0, 0], Kb[:, 1, 1])
    # Pixel-centre convention: a point on the optical axis projects to (W/2, H/2).
    uvw = K @ torch.tensor([0.0, 0.0, 3.0], dtype=F64)
    assert_close(uvw[:2] / uvw[2], torch.tensor([320.0, 240.0], dtype=F64))
    with pytest.raises(ValueError):
        G.intrinsics_from_fov(0.0, 10, 10)


def test_small_angle_gradients_finite():
    rv = torch.zeros(3, dtype=F64, requires_grad=True)
    G.axis_angle_to_quat(rv).sum().backward()
    assert torch.isfinite(rv.grad).all()
    q = torch.tensor([1.0, 0, 0, 0], dtype=F64, requires_grad=True)
    G.quat_to_axis_angle(q).sum().backward()
    assert torch.isfinite(q.grad).all()


def test_float64_drift_1e5_compositions():
    """Compose 1e5 random small rotations with renormalisation after every product.

    Laid out as 100 chains of 1000 steps composed in lockstep, then the 100 chain
    results composed one after another: 1e5 sequential-style products in ~1100 torch calls.
    """
    gen = torch.Generator().manual_seed(3)
    steps = G.axis_angle_to_quat(0.05 * torch.randn(1000, 100, 3, generator=gen, dtype=F64))
    acc = torch.zeros(100, 4, dtype=F64)
    acc[:, 0] = 1
    Racc = torch.eye(3, dtype=F64).expand(100, 3, 3)
    for i in range(steps.shape[0]):
        acc = G.quat_normalize(G.quat_multiply(acc, steps[i]))
        Racc = Racc @ G.quat_to_rotmat(steps[i])  # unrenormalised matrix reference
    total = acc[0]
    Rtot = Racc[0]
    for j in range(1, acc.shape[0]):
        total = G.quat_normalize(G.quat_multiply(total, acc[j]))
        Rtot = Rtot @ Racc[j]
    assert abs(torch.linalg.vector_norm(total) - 1) <= 1e-9
    R = G.quat_to_rotmat(total)
    assert_close(R.T @ R, torch.eye(3, dtype=F64), atol=1e-9)
    assert abs(torch.linalg.det(R) - 1) <= 1e-9
    # And it still is the right rotation.
    assert_close(R, Rtot, atol=1e-9)
