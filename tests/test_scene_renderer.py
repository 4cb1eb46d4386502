"""Incremental scene rendering equals a full render bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from dsg_gym.gaussians import GaussianSet
from dsg_gym.geometry import intrinsics_from_fov, look_at_viewmat
from dsg_gym.scene_renderer import SceneRenderer
from dsg_gym.splat import rasterize


def _gset(rng, n, spread, deg=1, s=0.01, centre=(0.0, 0.0, 0.0)):
    return GaussianSet(
        means=(np.asarray(centre) + rng.normal(0, 1, (n, 3)) * np.asarray(spread)).astype(np.float32),
        quats=rng.normal(size=(n, 4)).astype(np.float32),
        scales=np.exp(rng.uniform(np.log(s), np.log(3 * s), (n, 3))).astype(np.float32),
        opacities=rng.uniform(0.2, 0.95, n).astype(np.float32),
        sh=rng.normal(0, 0.3, (n, (deg + 1) ** 2, 3)).astype(np.float32),
    )


def _pose(x, y, yaw, z=0.05):
    P = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    P[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    P[:3, 3] = [x, y, z]
    return P


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(0)
    bg = _gset(rng, 3000, (0.3, 0.3, 0.01), deg=2, centre=(0.0, 0.0, -0.03))  # a table
    objs = [_gset(rng, 300, 0.03, deg=1), _gset(rng, 200, 0.04, deg=0), _gset(rng, 250, 0.02, deg=3)]
    W, H = 72, 56
    eyes = torch.tensor([[0.8, 0.2, 0.6], [-0.6, 0.7, 0.5]], dtype=torch.float64)
    vm = look_at_viewmat(eyes, torch.zeros(2, 3, dtype=torch.float64)).float().double().numpy()
    K = intrinsics_from_fov(np.radians(55), W, H).float().double().numpy()[None].repeat(2, 0)
    return bg, objs, vm, K, W, H


def _compose_and_rasterize(sr, bg, vm, K, W, H, mode="classic", eps2d=0.3):
    st = sr._state
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    means = np.concatenate([bg.means, st["means"]])
    quats = np.concatenate([bg.quats, st["quats"]])
    scales = np.concatenate([bg.scales, sr._obj_scales])
    op = np.concatenate([bg.opacities, sr._obj_opac])
    bg_colors = sr._colors(st["layout"], sr._bg_rgb, np.zeros(bg.num, np.int64), sr._bg.depths)
    cols = np.concatenate([bg_colors, st["colors"]], axis=1)
    out, alpha, _ = rasterize(
        t(means),
        t(quats),
        t(scales),
        t(op),
        t(cols),
        t(vm.astype(np.float32)),
        t(K.astype(np.float32)),
        W,
        H,
        rasterize_mode=mode,
        eps2d=eps2d,
    )
    return out.numpy(), alpha[..., 0].numpy()


@pytest.mark.parametrize("mode,eps2d", [("classic", 0.3), ("antialiased", 0.3), ("antialiased", 0.1)])
def test_incremental_equals_full_and_rasterize(setup, mode, eps2d):
    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(
        bg, objs, vm, K, W, H, background_color=(0.1, 0.2, 0.3), rasterize_mode=mode, eps2d=eps2d
    )
    rng = np.random.default_rng(1)
    poses = np.stack([_pose(-0.2, 0.0, 0.0), _pose(0.1, 0.15, 0.5), _pose(0.15, -0.2, 1.0)])
    sr.render(poses, depth=True)
    dirty = []
    for step in range(12):
        k = step % 3
        poses[k] = poses[k] @ _pose(rng.normal(0, 0.02), rng.normal(0, 0.02), rng.normal(0, 0.3), z=0.0)
        inc = sr.render(poses, depth=True)
        out_i, T_i = (x.copy() for x in sr.buffers())
        dirty.append(sr.last_dirty_tiles)
        full = sr.render(poses, depth=True, incremental=False)
        out_f, T_f = sr.buffers()
        assert np.array_equal(out_i, out_f) and np.array_equal(T_i, T_f), f"step {step}"
        for name in ("rgb", "mask", "depth", "alpha"):
            assert np.array_equal(getattr(inc, name), getattr(full, name)), name
    total = 2 * ((W + 15) // 16) * ((H + 15) // 16)
    assert 0 < min(dirty) and max(dirty) < total  # only part of the image was recomposited
    out_r, alpha_r = _compose_and_rasterize(sr, bg, vm, K, W, H, mode, eps2d)
    assert np.array_equal(out_r, sr.buffers()[0])
    assert np.array_equal(alpha_r, 1.0 - sr.buffers()[1])
    if mode == "antialiased":  # the filter really acted: not the classic image
        classic = SceneRenderer(bg, objs, vm, K, W, H, background_color=(0.1, 0.2, 0.3)).render(
            poses, depth=True
        )
        assert np.abs(classic.alpha - inc.alpha).max() > 0.01


def test_unknown_rasterize_mode_rejected(setup):
    bg, objs, vm, K, W, H = setup
    with pytest.raises(ValueError, match="rasterize_mode"):
        SceneRenderer(bg, objs, vm, K, W, H, rasterize_mode="mip")
    with pytest.raises(ValueError, match="eps2d"):
        SceneRenderer(bg, objs, vm, K, W, H, eps2d=0.0)


def test_single_threaded_kernels_render_the_same_bits(setup):
    """``parallel=False`` (vector-env workers) and the threaded kernels give identical images, step by step."""
    bg, objs, vm, K, W, H = setup
    rs = [
        SceneRenderer(bg, objs, vm, K, W, H, rasterize_mode="antialiased", parallel=p) for p in (True, False)
    ]
    poses = np.stack([_pose(-0.2, 0.0, 0.0), _pose(0.1, 0.15, 0.5), _pose(0.15, -0.2, 1.0)])
    rng = np.random.default_rng(5)
    for step in range(6):
        poses[step % 3] = poses[step % 3] @ _pose(
            rng.normal(0, 0.03), rng.normal(0, 0.03), rng.normal(0, 0.3)
        )
        a, b = (r.render(poses, depth=True) for r in rs)
        for name in ("rgb", "mask", "depth", "alpha"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (step, name)
    with pytest.raises(ValueError, match="parallel"):
        SceneRenderer(bg, objs, vm, K, W, H, parallel="auto")


def test_borrow_is_the_same_memory_without_an_owner():
    import numba as nb

    from dsg_gym.splat.numba_intrinsics import borrow

    @nb.njit
    def touch(a):
        b = borrow(a)
        row = b[1]  # a view of the borrowed array
        row[2] += 10.0
        return b.shape, b.strides, row.sum()

    a = np.arange(12, dtype=np.float32).reshape(3, 4)
    shape, strides, total = touch(a)
    assert shape == a.shape and strides == a.strides  # same layout, same data: the write reached ``a``
    assert a[1, 2] == 16.0 and total == a[1].sum()
    with pytest.raises(nb.core.errors.TypingError):
        nb.njit(lambda x: borrow(x))(1.0)


def test_plan_tiles_gives_every_tile_to_one_thread_longest_first():
    from dsg_gym.splat import numba_incremental as incr

    rng = np.random.default_rng(0)
    tiles = rng.permutation(40)[:13].astype(np.int64)
    b_off = np.concatenate([[0], np.cumsum(rng.integers(0, 300, 40))]).astype(np.int64)
    a_off = np.concatenate([[0], np.cumsum(rng.integers(0, 900, 40))]).astype(np.int64)
    for use_cache, P in ((True, 2), (False, 3), (True, 1), (True, 20)):
        order, starts = incr.plan_tiles(tiles, a_off, b_off, use_cache, P)
        assert sorted(order) == sorted(tiles) and starts[0] == 0 and starts[-1] == tiles.size
        assert len(starts) == min(P, tiles.size) + 1
        cost = {
            int(t): b_off[t + 1] - b_off[t] + (40 if use_cache else a_off[t + 1] - a_off[t]) for t in tiles
        }
        loads = [sum(cost[int(t)] for t in order[starts[k] : starts[k + 1]]) for k in range(len(starts) - 1)]
        # longest-processing-time: no thread ends more than one tile's cost after the least loaded one
        assert max(loads) - min(loads) <= max(cost.values())


def test_unmoved_render_touches_nothing_and_outputs(setup):
    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(bg, objs, vm, K, W, H)
    poses = np.stack([_pose(-0.2, 0.0, 0.0), _pose(0.1, 0.15, 0.5), _pose(0.15, -0.2, 1.0)])
    a = sr.render(poses)
    b = sr.render(poses.copy())
    assert sr.last_dirty_tiles == 0
    assert np.array_equal(a.rgb, b.rgb) and np.array_equal(a.mask, b.mask)
    assert a.rgb.shape == (2, H, W, 3) and a.rgb.dtype == np.uint8
    assert a.mask.dtype == np.uint8 and set(np.unique(a.mask)) <= {0, 1, 2, 3}
    assert {1, 2, 3} & set(np.unique(a.mask))  # objects are visible
    assert a.depth is None
    only_mask = sr.render(poses, rgb=False, mask=True)
    assert only_mask.rgb is None and np.array_equal(only_mask.mask, a.mask)


def test_object_moved_out_of_view_reveals_background(setup):
    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(GaussianSet.empty(sh_degree=0), objs[:1], vm, K, W, H)
    out = sr.render(_pose(0.0, 0.0, 0.0)[None])
    assert (out.mask == 1).any()
    gone = sr.render(_pose(50.0, 0.0, 0.0)[None])
    assert not (gone.mask == 1).any() and gone.alpha.max() == 0.0


def test_bad_poses_rejected(setup):
    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(bg, objs, vm, K, W, H)
    poses = np.stack([_pose(0, 0, 0)] * 3)
    with pytest.raises(ValueError, match="shape"):
        sr.render(poses[:2])
    bad = poses.copy()
    bad[1, 0, 3] = np.nan
    with pytest.raises(ValueError, match="object 1"):
        sr.render(bad)
    mirror = poses.copy()
    mirror[2, :3, :3] = np.diag([1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match="reflection"):
        sr.render(mirror)


def test_scene_renderer_colours_match_moved_gaussians_with_rotated_sh(setup):
    """The env evaluates object SH with view directions taken into the object frame; moving the Gaussians
    with :func:`dsg_gym.world_model.transform_gaussians` (which rotates SH) and evaluating in the world frame
    gives the same colours, so training/evaluation and the env agree for turned objects."""
    from dsg_gym.poses import matrix_to_pose7
    from dsg_gym.splat import spherical_harmonics
    from dsg_gym.world_model import transform_gaussians

    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(bg, objs, vm, K, W, H)
    poses = np.stack([_pose(-0.2, 0.0, 2.0), _pose(0.1, 0.15, -1.2), _pose(0.15, -0.2, 2.8)])
    sr.render(poses)
    st = sr._state
    campos = np.linalg.inv(vm[0])[:3, 3]
    start = 0
    for k, g in enumerate(objs):
        moved = transform_gaussians(g, matrix_to_pose7(poses[k]))
        deg = int(np.sqrt(g.sh.shape[1])) - 1
        want = torch.clamp_min(
            spherical_harmonics(
                deg,
                torch.from_numpy(moved.means.astype(np.float64) - campos),
                torch.from_numpy(moved.sh.astype(np.float64)),
            )
            + 0.5,
            0.0,
        ).numpy()
        got = st["colors"][0, start : start + g.num, :3]
        assert np.allclose(got, want, atol=2e-5), (k, np.abs(got - want).max())
        if deg > 0:  # without the SH rotation the colours would differ
            plain = torch.clamp_min(
                spherical_harmonics(
                    deg,
                    torch.from_numpy(moved.means.astype(np.float64) - campos),
                    torch.from_numpy(g.sh.astype(np.float64)),
                )
                + 0.5,
                0.0,
            ).numpy()
            assert np.abs(got - plain).max() > 1e-2
        start += g.num


def test_render_settings_defaults_and_incremental_exactness(setup):
    """Settings at the 3DGS values with the exact merge render exactly like no settings; the env's default
    settings change the image only a little; other thresholds keep incremental == full."""
    from dsg_gym.scene_renderer import RenderSettings
    from dsg_gym.splat import numba_raster as raster

    bg, objs, vm, K, W, H = setup
    poses = np.stack([_pose(-0.2, 0.0, 0.0), _pose(0.1, 0.15, 0.5), _pose(0.15, -0.2, 1.0)])
    ref = SceneRenderer(bg, objs, vm, K, W, H).render(poses, depth=True)
    same = SceneRenderer(
        bg, objs, vm, K, W, H, **RenderSettings(raster.ALPHA_MIN, raster.T_MIN, tail_stride=0).kwargs()
    ).render(poses, depth=True)
    assert np.array_equal(ref.rgb, same.rgb) and np.array_equal(ref.alpha, same.alpha)
    env_default = SceneRenderer(bg, objs, vm, K, W, H, **RenderSettings().kwargs()).render(poses, depth=True)
    d = np.abs(env_default.rgb.astype(int) - ref.rgb.astype(int))
    assert 0 < d.max() and d.mean() < 2.0
    fast = SceneRenderer(bg, objs, vm, K, W, H, alpha_min=0.02, t_min=0.01)
    fast.render(poses, depth=True)
    moved = poses.copy()
    moved[1] = moved[1] @ _pose(0.03, -0.02, 0.4, z=0.0)
    inc = fast.render(moved, depth=True)
    full = fast.render(moved, depth=True, incremental=False)
    for name in ("rgb", "mask", "depth", "alpha"):
        assert np.array_equal(getattr(inc, name), getattr(full, name)), name
    ref2 = SceneRenderer(bg, objs, vm, K, W, H).render(moved, depth=True)
    diff = np.abs(inc.rgb.astype(int) - ref2.rgb.astype(int))
    assert 0 < diff.max() and diff.mean() < 8.0


def test_alpha_min_and_t_min_take_effect():
    """One Gaussian: no pixel gets an alpha below alpha_min; a stack of opaque ones stops at t_min."""
    W = H = 32
    vm = np.eye(4)[None]
    K = np.array([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    one = GaussianSet(
        means=np.array([[0.0, 0.0, 1.0]], np.float32),
        quats=np.array([[1.0, 0, 0, 0]], np.float32),
        scales=np.full((1, 3), 0.1, np.float32),
        opacities=np.array([0.9], np.float32),
        sh=np.zeros((1, 1, 3), np.float32),
    )
    a_def = SceneRenderer(one, [], vm, K, W, H).render(np.zeros((0, 4, 4))).alpha
    a_cut = SceneRenderer(one, [], vm, K, W, H, alpha_min=0.1).render(np.zeros((0, 4, 4))).alpha
    assert 0 < a_def[a_def > 0].min() < 0.05
    assert a_cut[a_cut > 0].min() >= 0.1 - 1e-6
    assert (a_cut > 0).sum() < (a_def > 0).sum()
    n = 6
    stack = GaussianSet(
        means=np.array([[0.0, 0.0, 1.0 + 0.1 * i] for i in range(n)], np.float32),
        quats=np.tile(np.array([[1.0, 0, 0, 0]], np.float32), (n, 1)),
        scales=np.full((n, 3), 1.0, np.float32),
        opacities=np.full(n, 0.6, np.float32),
        sh=np.zeros((n, 1, 3), np.float32),
    )
    for t_min in (1e-4, 0.05, 0.3):
        a = SceneRenderer(stack, [], vm, K, W, H, t_min=t_min).render(np.zeros((0, 4, 4))).alpha
        assert a.max() <= 1.0 - t_min + 1e-6 and a.max() > 1.0 - 2.5 * t_min - 0.4**n


def test_sh_degree_cap_equals_truncated_world(setup):
    bg, objs, vm, K, W, H = setup
    poses = np.stack([_pose(-0.2, 0.0, 0.0), _pose(0.1, 0.15, 0.5), _pose(0.15, -0.2, 1.0)])
    capped = SceneRenderer(bg, objs, vm, K, W, H, sh_degree=0).render(poses)

    def dc(g):
        return GaussianSet(
            means=g.means, quats=g.quats, scales=g.scales, opacities=g.opacities, sh=g.sh[:, :1]
        )

    trunc = SceneRenderer(dc(bg), [dc(o) for o in objs], vm, K, W, H).render(poses)
    full = SceneRenderer(bg, objs, vm, K, W, H).render(poses)
    assert np.array_equal(capped.rgb, trunc.rgb)
    assert not np.array_equal(capped.rgb, full.rgb)


@pytest.mark.parametrize(
    "kw, msg",
    [
        ({"alpha_min": 0.0}, "alpha_min"),
        ({"alpha_min": 1.0}, "alpha_min"),
        ({"t_min": -0.1}, "t_min"),
        ({"t_min": float("nan")}, "t_min"),
        ({"sh_degree": 4}, "sh_degree"),
        ({"sh_degree": 1.5}, "sh_degree"),
    ],
)
def test_bad_render_settings_rejected(setup, kw, msg):
    from dsg_gym.scene_renderer import RenderSettings

    bg, objs, vm, K, W, H = setup
    with pytest.raises(ValueError, match=msg):
        SceneRenderer(bg, objs, vm, K, W, H, **kw)
    with pytest.raises(ValueError, match=msg):
        RenderSettings(**kw)


def test_pose7_and_matrix_poses_render_alike(setup):
    """``render`` takes [K,7] or [K,4,4]; both give the same image (quaternions renormalised, drifted
    rotation blocks re-orthonormalised); bad poses name the object."""
    from dsg_gym.poses import matrix_to_pose7, quat_to_rotmat

    bg, objs, vm, K, W, H = setup
    mats = np.stack([_pose(-0.2, 0.0, 0.3), _pose(0.1, 0.15, 2.5), _pose(0.15, -0.2, -1.0)])
    p7 = matrix_to_pose7(mats)
    a = SceneRenderer(bg, objs, vm, K, W, H).render(mats)
    scaled = p7.copy()
    scaled[:, 3:] *= np.array([[1e200], [-3.0], [1e-3]])  # huge, negative, small: same rotations
    b = SceneRenderer(bg, objs, vm, K, W, H).render(scaled)
    drift = mats.copy()
    drift[:, :3, :3] *= 1.0 + 1e-9  # a slightly non-orthonormal block
    c = SceneRenderer(bg, objs, vm, K, W, H).render(drift)
    assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1 and np.array_equal(a.mask, b.mask)
    assert np.abs(a.rgb.astype(int) - c.rgb.astype(int)).max() <= 1
    sr = SceneRenderer(bg, objs, vm, K, W, H)
    for bad, msg in (
        (np.where(np.arange(7) == 4, np.nan, p7), "object 0"),
        (np.concatenate([p7[:2], [[0, 0, 0, 0, 0, 0, 0]]]), "object 2"),
        (p7[:, :6], "shape"),
    ):
        with pytest.raises(ValueError, match=msg):
            sr.render(bad)
    assert np.allclose(quat_to_rotmat(scaled[:, 3:]), mats[:, :3, :3], atol=1e-12)
