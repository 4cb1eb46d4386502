"""Property-based tests (hypothesis, derandomised): the float64 pose algebra of ``dsg_gym.poses`` (with
``dsg_gym.geometry`` as a cross-check) and invariants of the splat renderer.

Quaternions are drawn unnormalised (norms 1e-3..1e3), including exact half turns (``w = 0``) and the
identity. Pose algebra tolerances are 1e-12 (relative to the translation size for translations). Renderer
invariants hold for any input: non-negative colours give a non-negative image that never exceeds the largest
colour (compositing is a convex combination), alphas lie in [0, 1], a single Gaussian adds exactly
``alpha * colour``; moving the camera and the scene by the same rigid transform changes the float64 image by
<= 1e-9 (float32 renders are compared with float64 in ``test_stress_render``; in float32 an alpha right at
the 1/255 cut-off may flip, so the exact invariant is checked in float64).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from _stress_ref import quat_error
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.splat_scenes import intrinsics
from dsg_gym import geometry as G
from dsg_gym import poses as P
from dsg_gym.splat import rasterize


def profile(n: int):
    """Deterministic hypothesis settings: ``n`` examples, fixed seed, no example database, no deadline."""
    return settings(max_examples=n, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])  # fmt: skip


unit = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
coord = st.floats(-100.0, 100.0, allow_nan=False, allow_infinity=False)


@st.composite
def quats(draw) -> np.ndarray:
    """An unnormalised quaternion ``[4]``: generic, a half turn (``w = 0``) or the identity, times 1e-3..1e3."""
    kind = draw(st.sampled_from(["generic", "generic", "half_turn", "identity"]))
    if kind == "identity":
        q = np.array([1.0, 0.0, 0.0, 0.0])
    else:
        q = np.array(draw(st.tuples(unit, unit, unit, unit)))
        if kind == "half_turn":
            q[0] = 0.0
        if np.linalg.norm(q) < 1e-3:
            q = np.array([0.0, 0.0, 0.0, 1.0]) if kind == "half_turn" else np.array([1.0, 0.0, 0.0, 0.0])
    return q * 10.0 ** draw(st.floats(-3.0, 3.0))


@st.composite
def poses7(draw) -> np.ndarray:
    """A pose ``(x, y, z, qw, qx, qy, qz)`` with an unnormalised quaternion."""
    return np.concatenate([np.array(draw(st.tuples(coord, coord, coord))), draw(quats())])


def compose7(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a o b`` (``b`` first) of 7-vector poses, from the ``poses`` primitives."""
    t = a[:3] + P.quat_to_rotmat(a[3:]) @ b[:3]
    return np.concatenate(
        [t, P.quat_normalize(P.quat_multiply(P.quat_normalize(a[3:]), P.quat_normalize(b[3:])))]
    )


def inverse7(a: np.ndarray) -> np.ndarray:
    """Inverse of a 7-vector pose: ``(-R^T t, conj(q))``."""
    q = P.quat_normalize(a[3:]) * np.array([1.0, -1.0, -1.0, -1.0])
    return np.concatenate([-(P.quat_to_rotmat(a[3:]).T @ a[:3]), P.quat_normalize(q)])


def assert_pose_close(a: np.ndarray, b: np.ndarray, tol: float = 1e-12) -> None:
    scale = 1.0 + max(np.abs(a[:3]).max(), np.abs(b[:3]).max())
    assert np.abs(a[:3] - b[:3]).max() <= tol * scale, (a, b)
    assert quat_error(a[3:], b[3:]) <= tol, (a, b)


IDENTITY = np.array([0.0, 0, 0, 1, 0, 0, 0])


# ----------------------------------------------------------------------------------------- transform algebra


@profile(300)
@given(quats())
def test_quaternion_matrix_round_trip(q):
    """quaternion -> rotation matrix (orthonormal, det 1) -> quaternion (unit, ``w >= 0``, same rotation);
    numpy and torch agree."""
    r = P.quat_to_rotmat(q)
    assert np.abs(r.T @ r - np.eye(3)).max() <= 1e-12 and abs(np.linalg.det(r) - 1) <= 1e-12
    back = P.rotmat_to_quat(r)
    assert abs(np.linalg.norm(back) - 1) <= 1e-14 and back[0] >= 0
    assert quat_error(back, q / np.linalg.norm(q)) <= 1e-12
    assert np.abs(P.quat_to_rotmat(back) - r).max() <= 1e-12
    # the torch helpers agree (sign free at w = 0)
    assert np.abs(G.quat_to_rotmat(torch.tensor(q)).numpy() - r).max() <= 1e-12
    assert quat_error(G.rotmat_to_quat(torch.tensor(r)).numpy(), back) <= 1e-12


@profile(200)
@given(poses7())
def test_pose7_matrix_round_trip(p):
    """pose -> 4x4 -> pose keeps the translation bit for bit and the rotation; ``as_poses7`` accepts it."""
    m = P.pose7_to_matrix(p)
    back = P.matrix_to_pose7(m)
    assert np.array_equal(back[:3], p[:3])
    assert_pose_close(back, np.concatenate([p[:3], p[3:] / np.linalg.norm(p[3:])]))
    assert_pose_close(P.as_poses7(m[None], 1)[0], back, 0.0)  # a rigid [1,4,4] passes validation unchanged
    assert np.abs(G.pose7_to_matrix(torch.tensor(p)).numpy() - m).max() <= 1e-12 * (1 + np.abs(p[:3]).max())


@profile(200)
@given(poses7())
def test_identity_and_inverse(p):
    """The identity is neutral on both sides, ``p o p^-1 = p^-1 o p = I``, ``(p^-1)^-1 = p``; the matrix forms
    (numpy and ``geometry.se3_inverse``) agree."""
    assert_pose_close(compose7(p, IDENTITY), compose7(IDENTITY, p))
    assert_pose_close(compose7(p, inverse7(p)), IDENTITY)
    assert_pose_close(compose7(inverse7(p), p), IDENTITY)
    assert_pose_close(inverse7(inverse7(p)), P.matrix_to_pose7(P.pose7_to_matrix(p)))
    m = P.pose7_to_matrix(p)
    scale = 1 + np.abs(p[:3]).max()
    assert np.abs(m @ P.pose7_to_matrix(inverse7(p)) - np.eye(4)).max() <= 1e-12 * scale
    assert (
        np.abs(G.se3_inverse(torch.tensor(m)).numpy() - P.pose7_to_matrix(inverse7(p))).max() <= 1e-12 * scale
    )


@profile(200)
@given(poses7(), poses7(), poses7())
def test_composition_is_associative_and_matches_matrices(a, b, c):
    """``(a o b) o c = a o (b o c)``, and both equal the product of the 4x4 matrices (numpy and torch)."""
    left, right = compose7(compose7(a, b), c), compose7(a, compose7(b, c))
    assert_pose_close(left, right)
    ma, mb, mc = (P.pose7_to_matrix(x) for x in (a, b, c))
    scale = 1 + sum(np.abs(x[:3]).max() for x in (a, b, c))
    assert np.abs(P.pose7_to_matrix(left) - ma @ mb @ mc).max() <= 1e-12 * scale
    got = G.se3_compose(torch.tensor(ma), G.se3_compose(torch.tensor(mb), torch.tensor(mc))).numpy()
    assert np.abs(got - ma @ mb @ mc).max() <= 1e-12 * scale


@profile(200)
@given(quats(), quats())
def test_relative_angle_matches_torch_and_is_symmetric(a, b):
    """``poses.quat_angle`` (arccos; ~3e-8 rad resolution near 0) agrees with ``geometry``'s atan2 form."""
    ang = P.quat_angle(a, b)
    assert 0.0 <= ang <= math.pi
    assert abs(ang - P.quat_angle(b, a)) <= 1e-12
    assert abs(ang - float(G.quat_angle_distance(torch.tensor(a), torch.tensor(b)))) <= 1e-7
    rel = P.quat_multiply(P.quat_normalize(b), P.quat_normalize(a) * np.array([1.0, -1, -1, -1]))
    assert (
        quat_error(P.quat_normalize(P.quat_multiply(rel, P.quat_normalize(a))), P.quat_normalize(b)) <= 1e-12
    )


# ----------------------------------------------------------------------------------------- renderer invariants

W, H = 24, 20
K64 = intrinsics(W, H, dtype=torch.float64)
scales_st = st.one_of(st.just(0.0), st.floats(-9.0, 3.0).map(lambda e: 10.0**e))
depth_st = st.one_of(
    st.floats(0.05, 30.0), st.floats(0.05, 30.0), st.floats(-1.0, 0.05)
)  # 1/3 near or behind


def _render(means, quats_, scales, opacities, colors, viewmat, dtype, backend="numba", backgrounds=None):
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=np.float64), dtype=dtype)
    out, alpha, _ = rasterize(t(means), t(quats_), t(scales), t(opacities), t(colors), t(viewmat)[None],
                              K64.to(dtype)[None], W, H, backend=backend,
                              backgrounds=None if backgrounds is None else t(backgrounds))  # fmt: skip
    return out[0].double(), alpha[0, ..., 0].double()


@profile(150)
@given(
    st.tuples(st.floats(-1.3, 1.3), st.floats(-1.3, 1.3), depth_st).map(
        lambda m: (0.6 * m[0] * abs(m[2]), 0.5 * m[1] * abs(m[2]), m[2])  # mostly in view, some beside/behind
    ),
    quats(),
    st.tuples(scales_st, scales_st, scales_st),
    st.one_of(st.floats(0.05, 1.0), st.floats(0.05, 1.0), st.sampled_from([0.0, 1.0 / 255.0, 1.0])),
    st.tuples(*[st.floats(0.0, 4.0)] * 3),
    st.sampled_from([("numba", torch.float32), ("numba", torch.float64), ("torch", torch.float64)]),
)
def test_single_gaussian_adds_alpha_times_colour(mean, q, scale, opacity, colour, backend):
    """One Gaussian with a non-negative colour on a black background: image = alpha * colour >= 0, and
    0 <= alpha <= 0.99 (the per-Gaussian cap)."""
    be, dt = backend
    out, alpha = _render([mean], [q], [scale], [opacity], [colour], np.eye(4), dt, be)
    tol = 1e-6 if dt == torch.float32 else 1e-12
    assert torch.isfinite(out).all() and (out >= 0).all()
    assert (alpha >= 0).all() and (alpha <= 0.99 + tol).all()
    want = alpha[..., None] * torch.tensor(colour, dtype=torch.float64)
    assert (out - want).abs().max() <= tol * (1 + max(colour))


@profile(100)
@given(st.integers(0, 2**31 - 1), st.integers(1, 12), st.tuples(*[st.floats(0.0, 1.0)] * 3),
       st.sampled_from(["numba", "torch"]))  # fmt: skip
def test_compositing_is_a_convex_combination(seed, n, background, backend):
    """Many Gaussians, non-negative colours and background: every pixel lies between 0 and the largest colour
    (per channel, background included); alphas in [0, 1]."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(-0.5, 8.0, n)
    means = np.stack([rng.uniform(-1, 1, n) * np.abs(z), rng.uniform(-1, 1, n) * np.abs(z), z], 1)
    scales = 10.0 ** rng.uniform(-4, 0.5, (n, 3))
    colors = rng.uniform(0, 3, (n, 3)) * (rng.random((n, 1)) < 0.8)
    out, alpha = _render(means, rng.normal(size=(n, 4)), scales, rng.uniform(0, 1, n), colors, np.eye(4),
                         torch.float32, backend, backgrounds=background)  # fmt: skip
    assert ((alpha >= 0) & (alpha <= 1)).all()
    top = torch.tensor(np.maximum(colors.max(0), background))
    assert (out >= 0).all() and (out <= top + 1e-5).all()


def _rigid(rotvec, t) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = P.quat_to_rotmat(P.axis_angle_to_quat(np.asarray(rotvec)))
    m[:3, 3] = t
    return m


@profile(100)
@given(
    st.integers(0, 2**31 - 1),
    st.tuples(*[st.floats(-4.0, 4.0)] * 3),
    st.tuples(*[st.floats(-10.0, 10.0)] * 3),
)
def test_moving_camera_and_scene_together_changes_nothing(seed, rotvec, shift):
    """Scene ``S`` seen by ``V`` equals ``T S`` seen by ``V T^-1`` (float64: <= 1e-9). The scene (1..23
    Gaussians from ``seed``) lies inside the view, so every example draws something."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 24))
    z = rng.uniform(1.0, 6.0, n)
    cam = np.stack([rng.uniform(-0.45, 0.45, n) * z, rng.uniform(-0.35, 0.35, n) * z, z], 1)  # all in view
    view = _rigid(rng.normal(size=3), rng.normal(size=3))
    inv = np.linalg.inv(view)
    means = cam @ inv[:3, :3].T + inv[:3, 3]  # world points seen at ``cam`` by ``view``
    quats_ = rng.normal(size=(n, 4))
    scales = 10.0 ** rng.uniform(-2.5, -0.5, (n, 3))
    opac, cols = rng.uniform(0.2, 1, n), rng.uniform(0, 1, (n, 3))
    tr = _rigid(rotvec, shift)
    q_tr = P.axis_angle_to_quat(np.asarray(rotvec))
    moved_means = means @ tr[:3, :3].T + tr[:3, 3]
    moved_quats = P.quat_multiply(q_tr, quats_)
    a = _render(means, quats_, scales, opac, cols, view, torch.float64)
    b = _render(moved_means, moved_quats, scales, opac, cols, view @ np.linalg.inv(tr), torch.float64)
    assert float(a[1].max()) > 0  # something is on screen
    assert (a[0] - b[0]).abs().max() <= 1e-9 and (a[1] - b[1]).abs().max() <= 1e-9
