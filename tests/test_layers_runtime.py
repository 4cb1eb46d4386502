"""Two-layer compositing in the runtime renderers (SceneRenderer, BatchSceneRenderer, DSGWorld-v0)."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest
import torch

from dsg_gym.batch_renderer import BatchSceneRenderer
from dsg_gym.geometry import intrinsics_from_fov, look_at_viewmat
from dsg_gym.scene_renderer import SceneRenderer
from dsg_gym.splat.layers import rasterize_layers
from dsg_gym.world import WorldFormatError, compositing
from tests._worlds import two_box_world
from tests.test_scene_renderer import _gset, _pose


@pytest.fixture(scope="module")
def setup():
    rng = np.random.default_rng(3)
    # a table whose Gaussians reach up among the objects' lowest ones: one sorted list interleaves them
    bg = _gset(rng, 2500, (0.3, 0.3, 0.012), deg=1, s=0.012, centre=(0.0, 0.0, 0.0))
    objs = [_gset(rng, 250, 0.03, deg=1), _gset(rng, 200, 0.025, deg=0)]
    W, H = 64, 48
    eyes = torch.tensor([[0.7, 0.2, 0.45], [-0.5, 0.6, 0.4]], dtype=torch.float64)
    vm = look_at_viewmat(eyes, torch.zeros(2, 3, dtype=torch.float64)).float().double().numpy()
    K = intrinsics_from_fov(np.radians(55), W, H).float().double().numpy()[None].repeat(2, 0)
    return bg, objs, vm, K, W, H


def _poses():
    return np.stack([_pose(-0.1, 0.0, 0.0, z=0.03), _pose(0.12, 0.08, 0.7, z=0.03)])


def _reference(sr, bg, vm, K, W, H):
    """The torch two-layer render of the renderer's current scene (colour channels as it composites them)."""
    st = sr._state
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a))  # noqa: E731
    bg_colors = sr._colors(st["layout"], sr._bg_rgb, np.zeros(bg.num, np.int64), sr._bg.depths)
    front = torch.from_numpy(np.arange(bg.num + len(st["means"])) >= bg.num)
    out, alpha, _ = rasterize_layers(
        front,
        t(np.concatenate([bg.means, st["means"]])),
        t(np.concatenate([bg.quats, st["quats"]])),
        t(np.concatenate([bg.scales, sr._obj_scales])),
        t(np.concatenate([bg.opacities, sr._obj_opac])),
        t(np.concatenate([bg_colors, st["colors"]], axis=1)),
        t(vm.astype(np.float32)),
        t(K.astype(np.float32)),
        W,
        H,
    )
    return out.numpy(), alpha[..., 0].numpy()


def test_layered_incremental_render_equals_full_and_the_torch_layers(setup):
    bg, objs, vm, K, W, H = setup
    sr = SceneRenderer(bg, objs, vm, K, W, H, background_color=(0.1, 0.2, 0.3), compositing="layers")
    one_list = SceneRenderer(bg, objs, vm, K, W, H, background_color=(0.1, 0.2, 0.3))
    poses = _poses()
    first = sr.render(poses)
    assert first.depth is None and first.mask.max() == 2  # depth is composited, not returned unless asked
    rng = np.random.default_rng(1)
    dirty = []
    for step in range(10):
        k = step % 2
        poses[k] = poses[k] @ _pose(rng.normal(0, 0.02), rng.normal(0, 0.02), rng.normal(0, 0.3), z=0.0)
        inc = sr.render(poses, depth=True)
        dirty.append(sr.last_dirty_tiles)
        out_i, T_i = (x.copy() for x in sr.buffers())
        full = sr.render(poses, depth=True, incremental=False)
        assert np.array_equal(out_i, sr.buffers()[0]) and np.array_equal(T_i, sr.buffers()[1]), step
        for name in ("rgb", "mask", "depth", "alpha"):
            assert np.array_equal(getattr(inc, name), getattr(full, name)), (step, name)
    assert 0 < min(dirty) and max(dirty) < 2 * 4 * 3  # only part of the image was recomposited
    out_r, alpha_r = _reference(sr, bg, vm, K, W, H)
    np.testing.assert_allclose(sr.buffers()[0], out_r, atol=2e-5)
    np.testing.assert_allclose(1.0 - sr.buffers()[1], alpha_r, atol=2e-6)
    sorted_img = one_list.render(poses, depth=True)
    assert np.abs(sorted_img.rgb.astype(int) - full.rgb.astype(int)).max() > 10  # the layers changed pixels


def test_layered_threads_and_batch_render_the_same_bits(setup):
    bg, objs, vm, K, W, H = setup
    threaded, serial = (
        SceneRenderer(bg, objs, vm, K, W, H, compositing="layers", parallel=p) for p in (True, False)
    )
    E = 3
    batch = BatchSceneRenderer(threaded, E)
    singles = [SceneRenderer(bg, objs, vm, K, W, H, compositing="layers") for _ in range(E)]
    rng = np.random.default_rng(7)
    poses = np.stack([_poses()] * E)
    for step in range(6):
        for e in range(E):
            poses[e, step % 2] = poses[e, step % 2] @ _pose(
                rng.normal(0, 0.03), rng.normal(0, 0.03), 0.2, z=0.0
            )
        p7 = np.concatenate([poses[..., :3, 3], _quats(poses)], axis=-1)
        out = batch.render(p7, depth=True)
        a, b = threaded.render(poses[0], depth=True), serial.render(poses[0], depth=True)
        for e in range(E):
            ref = singles[e].render(poses[e], depth=True)
            for name in ("rgb", "mask", "depth", "alpha"):
                assert np.array_equal(getattr(out, name)[e], getattr(ref, name)), (step, e, name)
        for name in ("rgb", "mask", "depth", "alpha"):
            assert np.array_equal(getattr(a, name), getattr(b, name)), (step, name)


def _quats(P):
    from dsg_gym.geometry import rotmat_to_quat

    return rotmat_to_quat(torch.from_numpy(P[..., :3, :3])).numpy()


def test_compositing_is_checked_and_read_from_the_world(setup):
    bg, objs, vm, K, W, H = setup
    with pytest.raises(ValueError, match="compositing must be one of"):
        SceneRenderer(bg, objs, vm, K, W, H, compositing="depth")
    assert compositing({}) == "sorted" and compositing({"compositing": "layers"}) == "layers"
    with pytest.raises(WorldFormatError, match="compositing"):
        compositing({"compositing": 1})
    world = two_box_world()
    layered = dataclasses.replace(world, metadata={**world.metadata, "compositing": "layers"})
    assert world.compositing == "sorted" and layered.compositing == "layers"
    env = gym.make("DSGWorld-v0", world=layered, width=48, height=40).unwrapped
    obs, _ = env.reset(seed=0)
    assert env.renderer.layers
    cams = env.cameras
    ref = SceneRenderer(
        layered.background, list(layered.objects), cams.viewmats, cams.Ks, cams.width, cams.height,
        background_color=env.background_color, compositing="layers", **env.render_settings.kwargs(),
    ).render(env.poses)  # fmt: skip
    np.testing.assert_array_equal(obs["rgb"], ref.rgb[0])
    env.close()
