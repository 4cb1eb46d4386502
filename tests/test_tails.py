"""Background tail tables: the incremental renderer's shortcut behind a tile's last object Gaussian."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest

import dsg_gym  # noqa: F401  registers DSGWorld-v0
from dsg_gym.scene_renderer import RenderSettings, SceneRenderer
from dsg_gym.splat import numba_tails as ntails


@pytest.fixture(scope="module")
def world():
    env = gym.make("DSGWorld-v0", width=64, height=64, cameras=[0, 3]).unwrapped
    env.reset(seed=0)
    return env.renderer, env.poses.copy()


def _renderer(world, stride, t_min=1e-3, parallel=None):
    r, _ = world
    return SceneRenderer(r.background, r.objects, r.viewmats, r.Ks, r.width, r.height,
                         background_color=r.background_color, alpha_min=2 / 255, t_min=t_min,
                         tail_stride=stride, parallel=parallel)  # fmt: skip


def _moves(poses, n, seed=1):
    rng = np.random.default_rng(seed)
    p = poses.copy()
    for _ in range(n):
        k = rng.integers(len(p))
        p[k, :2] += rng.uniform(-0.04, 0.04, 2)
        p[k, 3:] += rng.normal(0, 0.05, 4)
        yield p.copy()


def test_tail_offsets():
    off = ntails.tail_offsets(np.array([0, 0, 5, 69, 70]), 32)
    np.testing.assert_array_equal(off, [0, 0, 1, 3, 4])  # lists of 0, 5, 64 and 1 entries
    with pytest.raises(ValueError, match="stride"):
        ntails.tail_offsets(np.array([0, 3]), 0)


def test_tails_equal_the_exact_merge_up_to_rounding_without_the_cutoff(world):
    """With t_min = 0 the cut-off cannot fall differently: the tables change the accumulators by float32
    rounding only."""
    exact, tails = _renderer(world, 0, t_min=0.0), _renderer(world, 16, t_min=0.0)
    _, poses = world
    for p in [poses, *_moves(poses, 12)]:
        a, b = exact.render(p, depth=True), tails.render(p, depth=True)
        (fa, ta), (fb, tb) = exact.buffers(), tails.buffers()
        np.testing.assert_allclose(fb, fa, atol=2e-5)
        np.testing.assert_allclose(tb, ta, atol=2e-6)
        assert np.abs(a.rgb.astype(int) - b.rgb.astype(int)).max() <= 1
        np.testing.assert_array_equal(a.mask, b.mask)
    assert tails._bg_tails[4].any()


def test_tails_are_as_close_to_the_uncut_composite_as_the_exact_merge(world):
    """The cut-off at t_min is itself an approximation: against t_min = 0, the tables' images are no further
    off than the exact merge's."""
    ref, exact, tails = _renderer(world, 0, t_min=0.0), _renderer(world, 0), _renderer(world, 64)
    _, poses = world
    err = {"exact": 0.0, "tails": 0.0}
    differ = False
    for p in [poses, *_moves(poses, 15, seed=2)]:
        r = ref.render(p).rgb.astype(float)
        e, t = exact.render(p).rgb.astype(float), tails.render(p).rgb.astype(float)
        err["exact"] += ((e - r) ** 2).mean()
        err["tails"] += ((t - r) ** 2).mean()
        differ |= not np.array_equal(e, t)
    assert differ
    assert err["tails"] <= 1.05 * err["exact"], err


def test_tails_threaded_and_serial_give_the_same_bits(world):
    a, b = _renderer(world, 32, parallel=True), _renderer(world, 32, parallel=False)
    _, poses = world
    for p in [poses, *_moves(poses, 8, seed=3)]:
        x, y = a.render(p, depth=True), b.render(p, depth=True)
        for key in ("rgb", "mask", "depth", "alpha"):
            np.testing.assert_array_equal(getattr(x, key), getattr(y, key), err_msg=key)
    np.testing.assert_array_equal(a._bg_tails[4], b._bg_tails[4])


def test_tables_are_built_as_objects_reach_tiles_and_rebuild_the_same(world):
    r = _renderer(world, 32)
    _, poses = world
    r.render(poses)
    _, off, col, T, built = r._bg_tails
    first = built.copy()
    assert 0 < first.sum() < built.size  # only the tiles the objects cover
    for p in _moves(poses, 6, seed=4):
        r.render(p)
        dirty = r.last_dirty_tiles
        assert dirty == 0 or built.sum() >= first.sum()
    assert built.sum() > first.sum()
    tiles = np.flatnonzero(built)
    col0, T0 = col.copy(), T.copy()
    rec, rect, rows = r._background_lists(r._bg_tails[0][0])
    grid = (r.tiles_x, r.tiles_y, r.width, r.height)
    ntails.build_tails_serial(tiles, (rec, rect, rows, r._bg_bins[0]), 32, (off, col, T), grid, r._consts, 1)
    for ct in tiles:
        k = slice(off[ct], off[ct + 1])
        np.testing.assert_array_equal(col[k], col0[k])
        np.testing.assert_array_equal(T[k], T0[k])
    # checkpoint 0 of a tile is the background alone, chained segment by segment: without the cut-off it is the
    # background render up to rounding; with it, it goes at least as deep (a cut-off applies within a segment)
    ct = tiles[0]
    v, t = divmod(ct, r.tiles_x * r.tiles_y)
    ty, tx = divmod(t, r.tiles_x)
    window = (v, slice(ty * 16, (ty + 1) * 16), slice(tx * 16, (tx + 1) * 16))
    bg_T = r.background_render(r._bg_tails[0][0])[1][window]
    T0 = T[off[ct]].reshape(16, 16)[: bg_T.shape[0], : bg_T.shape[1]]
    assert (T0 <= bg_T + 1e-6).all() and (T0 < bg_T).any()
    uncut = _renderer(world, 32, t_min=0.0)
    uncut.render(poses)
    _, off_u, _, T_u, built_u = uncut._bg_tails
    ct = np.flatnonzero(built_u)[0]
    v, t = divmod(ct, r.tiles_x * r.tiles_y)
    ty, tx = divmod(t, r.tiles_x)
    window = (v, slice(ty * 16, (ty + 1) * 16), slice(tx * 16, (tx + 1) * 16))
    bg_T = uncut.background_render(uncut._bg_tails[0][0])[1][window]
    np.testing.assert_allclose(
        T_u[off_u[ct]].reshape(16, 16)[: bg_T.shape[0], : bg_T.shape[1]], bg_T, atol=1e-6
    )


def test_tail_stride_is_checked_and_reaches_the_env():
    for bad in (-1, True, 1.5, "8"):
        with pytest.raises(ValueError, match="tail_stride"):
            RenderSettings(tail_stride=bad)
    assert RenderSettings().kwargs()["tail_stride"] == 64
    env = gym.make("DSGWorld-v0", width=32, height=32, render_settings={"tail_stride": 0}).unwrapped
    assert env.renderer.tail_stride == 0
    with pytest.raises(
        ValueError, match=r"unknown keys \['stride'\] \(alpha_min, t_min, sh_degree, tail_stride\)"
    ):
        gym.make("DSGWorld-v0", render_settings={"stride": 8})


def test_changing_the_stride_rebuilds_the_tables(world):
    """A renderer whose ``tail_stride`` changes renders as a new renderer with that stride."""
    _, poses = world
    moves = list(_moves(poses, 4, seed=5))
    r, fresh = _renderer(world, 32), _renderer(world, 16)
    for p in moves[:2]:
        r.render(p)
    r.tail_stride = 16
    fresh.render(moves[1])
    for p in moves[2:]:
        np.testing.assert_array_equal(r.render(p).rgb, fresh.render(p).rgb)
    assert r._bg_tails[0][1] == 16
