"""Long pose compositions in float64 stay rigid and accurate (the CI-sized version).

The reference for every check composes the *same* float64 increments in extended precision
(``np.longdouble``, see ``_stress_ref``), so it measures only the rounding the float64 code adds. Bounds:
quaternion norm error and rotation-matrix orthonormality <= 1e-9; the float64 result within 1e-9 (rotation
entries; translations relative to their size) of the reference. ``benchmarks/stress.py`` runs the full counts
(1e6 increments, 1e5 env steps).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _stress_ref import EXTENDED, LD, env_reference, increment_blocks, ld_matrices, quat_error
from _worlds import two_box_world

from dsg_gym import geometry as G
from dsg_gym import poses as P
from dsg_gym.envs.dsg_world import DSGWorldEnv

CHAIN = 100_000  # increments per chain (the benchmark: 1e6)
CHAINS = 3  # independent chains composed in lockstep
BLOCK = 10_000  # increments generated at a time (bounded memory)
TOL = 1e-9

needs_extended = pytest.mark.skipif(not EXTENDED, reason="np.longdouble is float64 here: no reference")


@needs_extended
def test_composed_increments_stay_rigid_and_match_extended_precision():
    """1e5 world-frame increments ``T <- D_i T`` per chain through three routes: unrenormalised quaternion
    products (``poses.quat_multiply``), numpy 4x4 products of ``poses.pose7_to_matrix`` and the longdouble
    reference."""
    q = np.tile([1.0, 0.0, 0.0, 0.0], (CHAINS, 1))
    m_np = np.tile(np.eye(4), (CHAINS, 1, 1))
    m_ref = np.tile(np.eye(4, dtype=LD), (CHAINS, 1, 1))
    for dq, dt in increment_blocks(CHAIN, CHAINS, seed=0, block=BLOCK):
        d_np = P.pose7_to_matrix(np.concatenate([dt, dq], -1))
        d_ref = ld_matrices(dq, dt)
        for i in range(len(dq)):
            q = P.quat_multiply(dq[i], q)
            m_np = d_np[i] @ m_np
            m_ref = d_ref[i] @ m_ref
    assert np.abs(np.linalg.norm(q, axis=-1) - 1.0).max() <= TOL
    r = m_np[:, :3, :3]
    assert np.abs(r.transpose(0, 2, 1) @ r - np.eye(3)).max() <= TOL
    assert np.abs(np.linalg.det(r) - 1.0).max() <= TOL
    np.testing.assert_array_equal(m_np[:, 3], np.tile([0.0, 0, 0, 1], (CHAINS, 1)))
    ref = m_ref.astype(np.float64)
    scale = max(1.0, float(np.abs(ref[:, :3, 3]).max()))  # translations random-walk to ~10-30 m
    assert np.abs(P.quat_to_rotmat(q) - ref[:, :3, :3]).max() <= TOL
    assert np.abs(m_np[:, :3, :3] - ref[:, :3, :3]).max() <= TOL
    assert np.abs(m_np[:, :3, 3] - ref[:, :3, 3]).max() <= TOL * scale


@needs_extended
def test_torch_geometry_chains_stay_rigid():
    """The torch float64 helpers (``geometry.quat_multiply`` unrenormalised, ``geometry.se3_compose``) over
    1e4 increments (torch calls cost ~10x numpy's; ``test_geometry`` has a lockstep 1e5 drift test): unit
    norm, rigid, and equal to the longdouble reference to 1e-9."""
    ((dq, dt),) = increment_blocks(BLOCK, CHAINS, seed=1, block=BLOCK)
    qt = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * CHAINS, dtype=torch.float64)
    mt = torch.eye(4, dtype=torch.float64).repeat(CHAINS, 1, 1)
    m_ref = np.tile(np.eye(4, dtype=LD), (CHAINS, 1, 1))
    dqt = torch.from_numpy(dq)
    d_t = G.pose7_to_matrix(torch.from_numpy(np.concatenate([dt, dq], -1)))
    d_ref = ld_matrices(dq, dt)
    for i in range(len(dq)):
        qt = G.quat_multiply(dqt[i], qt)
        mt = G.se3_compose(d_t[i], mt)
        m_ref = d_ref[i] @ m_ref
    ref = m_ref.astype(np.float64)
    assert (torch.linalg.vector_norm(qt, dim=-1) - 1).abs().max() <= TOL
    assert G.is_rigid(mt, atol=TOL).all()
    assert np.abs(G.quat_to_rotmat(qt).numpy() - ref[:, :3, :3]).max() <= TOL
    assert np.abs(mt.numpy() - ref).max() <= TOL * max(1.0, float(np.abs(ref).max()))


@needs_extended
@pytest.mark.parametrize("mode,steps", [("se3", 2000), ("delta", 1000)])
def test_env_pose_after_many_small_steps_matches_exact_composition(mode, steps):
    """``DSGWorld-v0`` with ``collision="ignore"`` and only poses observed (no rendering): after ``steps``
    random actions the env's poses equal the longdouble composition of the same increments to 1e-11 (the
    benchmark runs 1e5 steps), the quaternions stay unit (1e-12) with ``qw >= 0``, and the observation
    agrees with ``env.poses``."""
    env = DSGWorldEnv(world=two_box_world(), obs=("poses",), collision="ignore", action_mode=mode)
    obs, _ = env.reset(seed=3)
    actions = np.random.default_rng(4).uniform(-1, 1, (steps,) + env.action_space.shape).astype(np.float32)
    want_t, want_q = env_reference(env, actions)
    start = env.poses
    for a in actions:
        obs, *_ = env.step(a)
    got = env.poses
    assert set(obs) == {"poses", "goal"} and env._renderer is None  # nothing was rendered
    np.testing.assert_array_equal(obs["poses"], got)
    assert np.abs(got[:, :3] - start[:, :3]).max() > 0.2  # the objects really travelled
    assert np.abs(got[:, :3] - want_t).max() <= 1e-11
    assert quat_error(got[:, 3:], want_q) <= 1e-11
    assert np.abs(np.linalg.norm(got[:, 3:], axis=1) - 1).max() <= 1e-12 and (got[:, 3] >= 0).all()
    env.close()
