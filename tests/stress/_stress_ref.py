"""Shared pieces of the stress tests and of ``benchmarks/stress.py`` (not a test module; no pytest here).

* Reference pose maths in extended precision (``np.longdouble``: 64-bit mantissa on x86-64, eps ~1.1e-19),
  so float64 results are compared with a composition of the *same* float64 increments whose own rounding is
  ~2000x smaller: :func:`increment_blocks`, :func:`ld_matrices`, :func:`env_reference`.
* Environment helpers: :func:`random_action`, :func:`non_finite_entries`, :func:`rss_bytes`
  (``/proc/self/statm``).
* Extreme renderer configurations: :data:`CASES`, :func:`extreme_scene`, :func:`render_case`,
  :func:`render_errors` and the float32-vs-float64 tolerances.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping

import numpy as np
import torch

from benchmarks.splat_scenes import intrinsics
from dsg_gym import poses as P
from dsg_gym.splat import rasterize

LD = np.longdouble
#: whether ``np.longdouble`` really is more precise than float64 here (it is not on e.g. macOS arm64)
EXTENDED = bool(np.finfo(LD).eps < 1e-18)

# ------------------------------------------------------------------------------------------------ poses


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` (``w, x, y, z``; rotation ``b`` first) in the inputs' dtype, no renormalising."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def qnormalize(q: np.ndarray) -> np.ndarray:
    """``q / |q|`` in the input's dtype (no sign convention)."""
    return q / np.sqrt(np.sum(q * q, axis=-1, keepdims=True))


def quat_error(a: np.ndarray, b: np.ndarray) -> float:
    """Largest component difference of two quaternion arrays, up to the sign of each quaternion."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return float(np.minimum(np.abs(a - b).max(-1), np.abs(a + b).max(-1)).max())


def increment_blocks(
    n: int, chains: int, seed: int, block: int = 10_000
) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """Yield ``(dq [m,chains,4], dt [m,chains,3])`` blocks (``m <= block``, ``n`` in all) of random small rigid
    increments in float64: rotation vectors with 0.1 rad per component, translations with 5 cm."""
    rng = np.random.default_rng(seed)
    for start in range(0, n, block):
        m = min(block, n - start)
        dq = P.axis_angle_to_quat(rng.normal(scale=0.1, size=(m, chains, 3)))
        yield dq, rng.normal(scale=0.05, size=(m, chains, 3))


def ld_matrices(dq: np.ndarray, dt: np.ndarray) -> np.ndarray:
    """``[..., 4, 4]`` longdouble rigid transforms of float64 increments (quaternions normalised in longdouble)."""
    w, x, y, z = np.moveaxis(qnormalize(dq.astype(LD)), -1, 0)
    m = np.zeros(dq.shape[:-1] + (4, 4), dtype=LD)
    m[..., 0, :3] = np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1)
    m[..., 1, :3] = np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1)
    m[..., 2, :3] = np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)
    m[..., :3, 3] = dt
    m[..., 3, 3] = 1
    return m


def env_reference(env, actions: np.ndarray, start: tuple[np.ndarray, np.ndarray] | None = None):
    """Positions ``[K,3]`` and quaternions ``[K,4]`` (longdouble) after ``actions`` under the update rule of a
    ``DSGWorldEnv`` in ``delta``/``se3`` mode with ``collision="ignore"``, applied exactly: translations summed
    and rotations composed (``dq * q``, renormalised) in longdouble; an object's move that would take it out of
    the workspace is skipped, as the env undoes it (``env.physics.workspace_problems``). The per-step increments
    are the float64 numbers the env itself forms from each action, so the difference is the env's own rounding.
    ``start``: a previous result to continue from (default: the env's current poses)."""
    if start is None:
        p = env.poses
        t, q = p[:, :3].astype(LD), p[:, 3:].astype(LD)
    else:
        t, q = start[0].copy(), start[1].copy()
    n = env.action_space.shape[0] // env.K
    for a in actions:
        a = np.clip(np.asarray(a, dtype=np.float64), -1, 1).reshape(env.K, n)
        moved = np.any(a != 0.0, axis=1)
        nt, nq = t.copy(), q.copy()
        nt[moved] += env.max_translation * a[moved, :3]
        if env.action_mode == "delta":
            dq = P.yaw_to_quat(env.max_rotation * a[:, 3])
        else:
            dq = P.axis_angle_to_quat(env.max_rotation * a[:, 3:6])
        nq[moved] = qnormalize(qmul(dq.astype(LD), q))[moved]
        p7 = np.concatenate([nt.astype(np.float64), nq.astype(np.float64)], axis=1)
        keep = [k for k in env.physics.workspace_problems(p7) if moved[k]]
        nt[keep], nq[keep] = t[keep], q[keep]
        t, q = nt, nq
    return t, q


# ------------------------------------------------------------------------------------------------ env


def random_action(env, rng: np.random.Generator) -> np.ndarray:
    """A valid action: all objects (60%), one object (30%) or none (10%) move by uniform amounts; in
    ``absolute`` mode uniform targets (every object always gets one, with a quaternion of norm >= 0.1)."""
    a = rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)
    if env.action_mode == "absolute":
        q = a.reshape(env.K, 7)[:, 3:]
        q[np.linalg.norm(q, axis=1) < 0.1] = (1, 0, 0, 0)
        return a
    u = rng.random()
    if u < 0.3:
        n = a.size // env.K
        keep = int(rng.integers(env.K))
        a[: keep * n] = 0
        a[(keep + 1) * n :] = 0
    elif u < 0.4:
        a[:] = 0
    return a


def non_finite_entries(obs: Mapping, reward, info: Mapping) -> list[str]:
    """Names of the entries of one step's result that are not finite (or, for poses, not unit quaternions;
    for depth, negative): ``[]`` when everything is fine."""
    bad = [f"obs[{k!r}]" for k, v in obs.items() if not np.all(np.isfinite(v))]
    if not np.isfinite(reward):
        bad.append("reward")
    for k, v in info.items():
        arr = np.asarray(v)
        if arr.dtype == object or not np.all(np.isfinite(arr)):
            bad.append(f"info[{k!r}]")
    for k in ("poses", "goal"):
        if k in obs and np.abs(np.linalg.norm(obs[k][:, 3:], axis=1) - 1).max() > 1e-12:
            bad.append(f"obs[{k!r}] quaternion norm")
    if "depth" in obs and obs["depth"].min() < 0:
        bad.append("obs['depth'] < 0")
    return bad


def rss_bytes() -> int:
    """Resident set size of this process from ``/proc/self/statm`` (Linux), in bytes."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


# ------------------------------------------------------------------------------------------------ renderer

W, H = 40, 32
NEAR = 0.01
#: numba float32 vs torch float64: absolute, on colours and alphas (both in [0, 1])
COLOR_TOL = ALPHA_TOL = 1e-5
#: numba float32 vs torch float64: relative error of the expected depth where the reference alpha > 0.05
DEPTH_REL_TOL = 1e-4
#: numba float64 vs torch float64, every figure
F64_TOL = 1e-10
CASES = (
    "far",
    "far_from_origin",
    "behind",
    "near_plane",
    "half_turns",
    "tiny_and_huge",
    "degenerate",
    "mixed",
)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _in_view(rng: np.random.Generator, z: np.ndarray, frac: float = 0.4) -> np.ndarray:
    """Camera-space points at depths ``z`` inside ``frac`` of the 60-degree view."""
    half = np.tan(np.radians(30.0)) * frac
    x, y = rng.uniform(-half, half, z.shape), rng.uniform(-half, half, z.shape)
    return np.stack([x * np.abs(z), y * np.abs(z), z], -1)


def extreme_scene(case: str, seed: int = 0) -> dict:
    """One extreme configuration of :data:`CASES` as float64 arrays whose values are float32-representable
    (so float32 and float64 renders see the same scene): ``means [N,3]``, ``quats [N,4]``, ``scales [N,3]``,
    ``opacities [N]``, ``colors [N,3]`` (non-negative), ``viewmat [4,4]`` (world-to-camera)."""
    rng = np.random.default_rng(seed)
    vm = np.eye(4)
    if case == "far":  # depths 1e2..5e9 m, sizes to match
        z = np.repeat([1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 5e9], 2)
        means = _in_view(rng, z)
        scales = 0.03 * z[:, None] * rng.uniform(0.5, 2.0, (len(z), 3))
        quats = _unit(rng.normal(size=(len(z), 4)))
    elif case == "far_from_origin":  # an ordinary scene, with its camera, 1e4 m from the world origin
        z = rng.uniform(2.0, 5.0, 24)
        cam = _in_view(rng, z)
        offset = np.array([1e4, -1e4, 1e4])
        r = P.quat_to_rotmat(_unit(rng.normal(size=4)))
        means = cam @ r + offset  # world = R^T cam + offset
        vm[:3, :3], vm[:3, 3] = r, -r @ offset
        scales = rng.uniform(0.02, 0.3, (len(z), 3))
        quats = _unit(rng.normal(size=(len(z), 4)))
    elif case == "behind":  # all behind the camera, some by 1e-7 m
        z = -np.geomspace(1e-7, 10.0, 12)
        means = np.concatenate([rng.uniform(-1, 1, (12, 2)), z[:, None]], 1)
        scales = rng.uniform(0.01, 3.0, (12, 3))
        quats = _unit(rng.normal(size=(12, 4)))
    elif case == "near_plane":  # centres on both sides of the near plane, footprints far larger than it
        z = np.array([1e-3, 5e-3, 0.0099, 0.0100001, 0.0101, 0.011, 0.015, 0.02, 0.05, 0.1, 0.3, 0.5])
        means = np.concatenate([rng.uniform(-0.02, 0.02, (12, 2)), z[:, None]], 1)
        scales = np.geomspace(1e-3, 5.0, 12)[:, None] * rng.uniform(0.5, 1.0, (12, 3))
        quats = _unit(rng.normal(size=(12, 4)))
    elif case == "half_turns":  # w = 0: rotations by pi about +-x, +-y, +-z and random axes
        quats = np.zeros((12, 4))
        quats[:, 1:] = _unit(rng.normal(size=(12, 3)))
        quats[:3, 1:] = np.eye(3)
        quats[3:6, 1:] = -np.eye(3)
        means = _in_view(rng, rng.uniform(2.0, 5.0, 12))
        scales = rng.uniform(0.05, 0.4, (12, 3)) * np.array([1.0, 0.2, 0.05])
    elif case == "tiny_and_huge":  # scales 1e-9..1e6 m
        scales = np.geomspace(1e-9, 1e6, 16)[:, None] * rng.uniform(0.5, 1.0, (16, 3))
        means = _in_view(rng, rng.uniform(2.0, 5.0, 16))
        quats = _unit(rng.normal(size=(16, 4)))
    elif case == "degenerate":  # flat discs (one scale 1e-8), two of them exactly edge-on
        n = 16
        scales = rng.uniform(0.05, 0.3, (n, 3))
        scales[np.arange(n), rng.integers(0, 3, n)] = 1e-8
        quats = _unit(rng.normal(size=(n, 4)))
        h = np.sqrt(0.5)
        quats[:4] = [[1, 0, 0, 0], [h, h, 0, 0], [h, 0, h, 0], [0, 0, 0, 1]]
        scales[:4] = [0.2, 0.1, 1e-8]  # disc normals along z (face-on), y, x (edge-on), z (face-on)
        means = _in_view(rng, rng.uniform(2.0, 5.0, n))
    elif case == "mixed":  # all of the above with the identity camera, in one render
        parts = [extreme_scene(c, seed) for c in CASES if c not in ("mixed", "far_from_origin")]
        return {k: np.concatenate([p[k] for p in parts]) if k != "viewmat" else vm for k in parts[0]}
    else:
        raise ValueError(f"unknown case {case!r}; expected one of {CASES}")
    n = len(means)
    out = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": rng.uniform(0.3, 1.0, n),
        "colors": rng.uniform(0.0, 1.0, (n, 3)),
        "viewmat": vm,
    }
    return {k: v.astype(np.float32).astype(np.float64) for k, v in out.items()}


def render_case(scene: dict, backend: str, dtype: torch.dtype, grad: bool = False):
    """Render ``scene`` (``RGB+ED``, one camera, ``W x H``): ``(colours + expected depth [H,W,4] float64,
    alphas [H,W] float64, meta, grads)``; with ``grad``, ``grads`` maps means, quats, scales, opacities and
    colors to the gradients of a fixed random linear loss (else None)."""
    names = ("means", "quats", "scales", "opacities", "colors")
    leaves = [torch.tensor(scene[k], dtype=dtype, requires_grad=grad) for k in names]
    vm = torch.tensor(scene["viewmat"], dtype=dtype)[None]
    out, alpha, meta = rasterize(*leaves, vm, intrinsics(W, H, dtype=dtype)[None], W, H, near_plane=NEAR,
                                 render_mode="RGB+ED", backend=backend)  # fmt: skip
    grads = None
    if grad:
        g = torch.Generator().manual_seed(0)
        w_out = torch.randn(out.shape, generator=g, dtype=dtype)
        w_alpha = torch.randn(alpha.shape, generator=g, dtype=dtype)
        ((out * w_out).sum() + (alpha * w_alpha).sum()).backward()
        grads = {k: t.grad for k, t in zip(names, leaves)}
    return out.detach()[0].double(), alpha.detach()[0, ..., 0].double(), meta, grads


def render_errors(a, b) -> dict[str, float]:
    """Max errors of render ``a`` against the reference ``b`` (both from :func:`render_case`): ``color`` and
    ``alpha`` absolute, ``depth_rel`` relative error of the expected depth where the reference alpha > 0.05."""
    hit = b[1] > 0.05
    rel = ((a[0][..., 3] - b[0][..., 3]).abs() / b[0][..., 3].abs().clamp_min(1e-30))[hit]
    return {
        "color": float((a[0][..., :3] - b[0][..., :3]).abs().max()),
        "alpha": float((a[1] - b[1]).abs().max()),
        "depth_rel": float(rel.max()) if bool(hit.any()) else 0.0,
    }
