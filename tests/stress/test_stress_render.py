"""``dsg_gym.splat.rasterize`` at extreme configurations.

The cases (``_stress_ref.extreme_scene``; float32-representable inputs, so every precision renders the very
same scene): far away (depths 1e2..5e9 m), a scene and its camera 1e4 m from the origin, behind the camera,
straddling the near plane, half turns (quaternions with ``w = 0``), tiny and huge scales (1e-9..1e6 m),
nearly degenerate Gaussians (one scale 1e-8) and all of these in one render.

Checked: outputs, meta and gradients finite; alphas in [0, 1]; colours non-negative; the **numba float32**
render agrees with the **torch float64** reference within ``COLOR_TOL = ALPHA_TOL = 1e-5`` (absolute; colours
and alphas lie in [0, 1]) and ``DEPTH_REL_TOL = 1e-4`` (relative error of the expected depth where the
reference alpha exceeds 0.05); the numba backend also takes float64 inputs and then agrees with torch
float64 to ``F64_TOL = 1e-10``. Numba's projection runs in float64 whatever the input dtype, which is why
float32 holds 1e4 m from the origin. ``benchmarks/stress.py`` runs every case over many seeds.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _stress_ref import (
    ALPHA_TOL,
    CASES,
    COLOR_TOL,
    DEPTH_REL_TOL,
    F64_TOL,
    NEAR,
    extreme_scene,
    render_case,
    render_errors,
)


@pytest.mark.parametrize("case", CASES)
def test_extreme_render_is_finite_and_float32_matches_float64(case):
    scene = extreme_scene(case)
    got = render_case(scene, "numba", torch.float32, grad=True)
    ref = render_case(scene, "torch", torch.float64)
    out, alpha, meta, grads = got
    assert torch.isfinite(out).all() and torch.isfinite(alpha).all()
    assert ((alpha >= 0) & (alpha <= 1)).all() and (out[..., :3] >= 0).all()
    for key in ("means2d", "conics", "depths"):
        assert torch.isfinite(meta[key]).all(), key
    for key, g in grads.items():
        assert torch.isfinite(g).all(), f"gradient of {key}"
    err = render_errors(got, ref)
    assert err["color"] <= COLOR_TOL and err["alpha"] <= ALPHA_TOL and err["depth_rel"] <= DEPTH_REL_TOL, err
    err64 = render_errors(render_case(scene, "numba", torch.float64), ref)
    assert max(err64.values()) <= F64_TOL, err64
    visible = meta["radii"][0].amax(-1) > 0
    if case == "behind":
        assert not visible.any() and float(alpha.max()) == 0.0
    else:
        assert float(alpha.max()) > 0.3  # the case really draws something
    if case == "near_plane":  # culled exactly where the centre is in front of the near plane
        z = torch.tensor(scene["means"][:, 2])
        assert not visible[z < NEAR].any() and visible[z > 1.01 * NEAR].all()
    if case in ("tiny_and_huge", "degenerate"):  # the 0.3 px^2 low-pass keeps every conic positive definite
        c = meta["conics"][0][visible].double()
        assert visible.sum() >= 8
        assert (c[:, 0] > 0).all() and (c[:, 2] > 0).all() and (c[:, 0] * c[:, 2] - c[:, 1] ** 2 > 0).all()


def test_half_turn_sign_and_zero_quaternion():
    """``q`` and ``-q`` (here with ``w = 0``) render bit-identically; a zero quaternion renders exactly like
    the identity; a half turn about the viewing axis of Gaussians with equal x and y scales changes nothing."""
    s = extreme_scene("half_turns")
    a = render_case(s, "numba", torch.float32)
    b = render_case({**s, "quats": -s["quats"]}, "numba", torch.float32)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
    n = len(s["quats"])
    ident = {**s, "quats": np.tile([1.0, 0, 0, 0], (n, 1)), "scales": np.tile([0.2, 0.2, 0.05], (n, 1))}
    c = render_case(ident, "numba", torch.float32)
    assert float(c[1].max()) > 0.3
    assert torch.equal(c[0], render_case({**ident, "quats": np.zeros((n, 4))}, "numba", torch.float32)[0])
    zturn = {**ident, "quats": np.tile([0.0, 0, 0, 1], (n, 1))}
    assert (c[0] - render_case(zturn, "numba", torch.float32)[0]).abs().max() <= 1e-6


def test_behind_camera_gaussians_change_nothing():
    """Adding every Gaussian of the ``behind`` case to an ordinary scene leaves its render bit-identical."""
    base = extreme_scene("half_turns", seed=1)
    behind = extreme_scene("behind", seed=1)
    both = {k: np.concatenate([base[k], behind[k]]) if k != "viewmat" else base[k] for k in base}
    a = render_case(base, "numba", torch.float32)
    b = render_case(both, "numba", torch.float32)
    assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1])
