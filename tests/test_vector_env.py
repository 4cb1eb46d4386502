"""DSGWorld-v0's own vector env, the batch renderer and the thread chooser."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import dsg_gym  # noqa: F401  registers DSGWorld-v0
from dsg_gym.batch_renderer import BatchSceneRenderer
from dsg_gym.envs.dsg_world_vector import DSGWorldVectorEnv
from dsg_gym.splat.threads import ThreadChooser

VARIABLE = ("penetrating_pairs", "out_of_bounds")


def _rollout(mode, n, steps, seed=3, vector_kwargs=None, **kw):
    env = gym.make_vec(
        "DSGWorld-v0", num_envs=n, vectorization_mode=mode, vector_kwargs=vector_kwargs or {}, **kw
    )
    hist = [env.reset(seed=seed)]
    rng = np.random.default_rng(1)
    for _ in range(steps):
        hist.append(env.step(rng.uniform(-1, 1, env.action_space.shape).astype(np.float32)))
    env.close()
    return hist


def _assert_same(x, y, path=""):
    if isinstance(x, dict):
        assert set(k for k in x if k not in VARIABLE) <= set(y), path
        for k in x:
            if k in VARIABLE or k.startswith("_"):
                continue
            _assert_same(x[k], y[k], f"{path}/{k}")
    elif isinstance(x, (tuple, list)):
        for i, (a, b) in enumerate(zip(x, y, strict=True)):
            _assert_same(a, b, f"{path}[{i}]")
    elif isinstance(x, np.ndarray) and x.dtype == object:
        for i, (a, b) in enumerate(zip(x, y, strict=True)):
            _assert_same(a, b, f"{path}[{i}]")
    else:
        a, b = np.asarray(x), np.asarray(y)
        assert a.shape == b.shape and a.dtype == b.dtype and np.array_equal(a, b), path


@pytest.mark.parametrize(
    "kw",
    [
        {"obs": ("rgb", "mask", "depth", "poses"), "max_episode_steps": 12},
        {"cameras": [0, 1], "obs": ("rgb", "mask"), "action_mode": "absolute", "max_episode_steps": 7},
    ],
    ids=["one-camera", "two-cameras-absolute"],
)
def test_same_as_sync_vector_env_bit_for_bit(kw):
    """Observations, rewards, flags and infos equal SyncVectorEnv's over episodes with autoresets."""
    ours = _rollout("vector_entry_point", 3, 30, **kw, width=48, height=40)
    sync = _rollout("sync", 3, 30, **kw, width=48, height=40)
    assert sum(int(np.sum(h[2] | h[3])) for h in ours[1:]) >= 3  # autoresets happened
    _assert_same(ours, sync)


def test_same_step_autoreset_matches_sync():
    kw = {"obs": ("rgb", "poses"), "max_episode_steps": 5, "width": 32, "height": 32}
    ours = _rollout("vector_entry_point", 2, 12, autoreset_mode=AutoresetMode.SAME_STEP, **kw)
    sync = _rollout("sync", 2, 12, vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}, **kw)
    ends = [h for h in ours[1:] if h[4].get("_final_obs", np.zeros(2, bool)).any()]
    assert ends
    _assert_same(ours, sync)


def test_a_bad_action_raises_and_leaves_the_vector_env_usable():
    env = gym.make_vec(
        "DSGWorld-v0", num_envs=3, vectorization_mode="vector_entry_point", width=32, height=32
    )
    obs, _ = env.reset(seed=0)
    a = np.zeros(env.action_space.shape, np.float32)
    a[0, 0] = 1.0
    bad = a.copy()
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="env 2"):
        env.step(bad)
    with pytest.raises(ValueError, match="shape"):
        env.step(a[:2])
    for e, p in zip(env.unwrapped.envs, obs["poses"], strict=True):
        np.testing.assert_array_equal(e.poses, p)  # nothing moved
    obs2, *_ = env.step(a)
    assert not np.array_equal(obs2["poses"][0], obs["poses"][0])
    np.testing.assert_array_equal(obs2["poses"][1:], obs["poses"][1:])


def test_vector_env_checks_its_arguments():
    with pytest.raises(ValueError, match="num_envs"):
        DSGWorldVectorEnv(0)
    with pytest.raises(ValueError, match="autoreset_mode"):
        DSGWorldVectorEnv(2, autoreset_mode="sometimes")
    env = DSGWorldVectorEnv(2, width=16, height=16)
    with pytest.raises(gym.error.ResetNeeded):
        env.step(np.zeros(env.action_space.shape, np.float32))
    with pytest.raises(ValueError, match="seeds"):
        env.reset(seed=[1, 2, 3])


def test_disabled_autoreset_and_reset_mask():
    env = DSGWorldVectorEnv(
        3, width=24, height=24, max_episode_steps=2, autoreset_mode=AutoresetMode.DISABLED
    )
    with pytest.raises(ValueError, match="first reset"):
        env.reset(seed=0, options={"reset_mask": np.array([True, False, False])})
    obs, _ = env.reset(seed=0)
    zero = np.zeros(env.action_space.shape, np.float32)
    for _ in range(2):
        obs, _, _, trunc, _ = env.step(zero)
    assert trunc.all()
    obs2, _, _, _, _ = env.step(zero)  # no autoreset: the ended envs step on
    np.testing.assert_array_equal(obs2["poses"], obs["poses"])
    mask = np.array([False, True, False])
    obs3, infos = env.reset(seed=[None, 7, None], options={"reset_mask": mask})
    single = gym.make("DSGWorld-v0", width=24, height=24)
    ref, _ = single.reset(seed=7)
    np.testing.assert_array_equal(obs3["poses"][1], ref["poses"])
    np.testing.assert_array_equal(obs3["rgb"][1], ref["rgb"])
    np.testing.assert_array_equal(obs3["poses"][[0, 2]], obs["poses"][[0, 2]])
    assert infos["_success"].tolist() == [False, True, False]
    with pytest.raises(ValueError, match="reset_mask"):
        env.reset(options={"reset_mask": [1, 0, 1]})


def test_batch_renderer_equals_one_renderer_per_scene():
    env = gym.make("DSGWorld-v0", cameras=[0, 2], width=40, height=36).unwrapped
    env.reset(seed=0)
    E = 4
    batch = BatchSceneRenderer(env.renderer, E)
    singles = [env._make_renderer(env.cameras) for _ in range(E)]
    rng = np.random.default_rng(0)
    poses = np.stack([env.poses] * E)
    for step in range(12):
        for e in range(E):
            for k in range(env.K):
                if rng.random() < 0.5:
                    poses[e, k, :3] += rng.normal(0, 0.01, 3)
                    poses[e, k, 3:] += rng.normal(0, 0.05, 4)
        fresh = rng.random(E) < 0.2 if step else None
        out = batch.render(poses, rgb=True, mask=True, depth=step % 2 == 0, fresh=fresh)
        for e in range(E):
            ref = singles[e].render(poses[e], rgb=True, mask=True, depth=step % 2 == 0)
            for key in ("rgb", "mask", "depth", "alpha"):
                a, b = getattr(out, key), getattr(ref, key)
                assert (a is None) == (b is None)
                if a is not None:
                    np.testing.assert_array_equal(a[e], b, err_msg=f"step {step} scene {e} {key}")
    with pytest.raises(ValueError, match="shape"):
        batch.render(poses[:2])
    bad = poses.copy()
    bad[1, 0, 3:] = 0.0
    with pytest.raises(ValueError, match="scene 1 object 0"):
        batch.render(bad)


def _drive(chooser, speed, calls):
    """Let ``chooser`` pick ``calls`` times, each call costing ``speed[path]`` per unit; the picks."""
    picks = []
    for _ in range(calls):
        p = chooser.choose()
        picks.append(p)
        chooser.record(p, speed[p], 1.0)
    return picks


def test_thread_chooser_follows_the_faster_path_and_backs_off():
    c = ThreadChooser(probe=4, max_probe=16)
    assert c.choose(allowed=False) is False
    speed = {True: 1.0, False: 3.0}  # seconds per unit: threads faster
    picks = _drive(c, speed, 200)
    assert c.best() is True and sum(picks[-100:]) >= 85  # probes of the slow path are rare
    speed = {True: 10.0, False: 3.0}  # another process takes a core: threads stall
    picks = _drive(c, speed, 200)
    assert c.best() is False and sum(picks[-100:]) <= 15


def test_automatic_threads_give_the_same_images():
    envs = [gym.make("DSGWorld-v0", width=48, height=48).unwrapped for _ in range(2)]
    envs[1].renderer.parallel = False
    for e in envs:
        e.reset(seed=5)
    rng = np.random.default_rng(2)
    for _ in range(40):
        a = rng.uniform(-1, 1, envs[0].action_space.shape).astype(np.float32)
        o = [e.step(a)[0] for e in envs]
        np.testing.assert_array_equal(o[0]["rgb"], o[1]["rgb"])
        np.testing.assert_array_equal(o[0]["mask"], o[1]["mask"])


def test_stable_baselines3_trains_on_the_vector_env():
    pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")
    from stable_baselines3 import PPO

    from dsg_gym.envs.sb3 import DSGWorldSB3VecEnv

    venv = DSGWorldSB3VecEnv(num_envs=4, width=64, height=64, obs=("rgb", "poses"), max_episode_steps=10)
    PPO("MultiInputPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, seed=0).learn(64)
    venv.reset()
    ended = None
    for _ in range(12):
        obs, rewards, dones, infos = venv.step(np.stack([venv.action_space.sample() for _ in range(4)]))
        assert rewards.shape == (4,) and obs["rgb"].shape == (4, 64, 64, 3)
        if dones.any():
            ended = infos[int(np.flatnonzero(dones)[0])]
            break
    assert ended is not None and ended["TimeLimit.truncated"] is True
    assert ended["terminal_observation"]["rgb"].shape == (64, 64, 3)


def test_thread_chooser_keeps_threads_within_its_margin():
    with pytest.raises(ValueError, match="margin"):
        ThreadChooser(margin=0.9)
    c = ThreadChooser(probe=4, max_probe=16, margin=1.25)
    speed = {True: 1.0, False: 0.85}  # one thread slightly faster per unit: noise-level, within the margin
    picks = _drive(c, speed, 200)
    assert c.best() is True and sum(picks[-100:]) >= 85
    speed = {True: 1.0, False: 0.7}  # a clear lead past the margin hands over
    picks = _drive(c, speed, 200)
    assert c.best() is False and sum(picks[-100:]) <= 15
    plain = ThreadChooser(probe=4, max_probe=16, margin=1.0)  # without a margin the slight lead wins
    _drive(plain, {True: 1.0, False: 0.85}, 60)
    assert plain.best() is False


@pytest.mark.parametrize("antialiased", [False, True])
def test_update_objects_in_gaussian_runs_equals_the_per_camera_kernels(antialiased):
    """The object update split into (pair, camera, run of Gaussians) items, threaded or not, in runs of any
    length, writes exactly what projecting, filtering and colouring each camera's Gaussians in one piece does."""
    from dsg_gym.splat import numba_batch as nbatch
    from dsg_gym.splat import numba_incremental as incr
    from dsg_gym.splat import numba_project as proj
    from dsg_gym.splat import numba_rigid as rigid

    rng = np.random.default_rng(4)
    # runs across a chunk edge, a small and an empty object
    sizes = [2 * nbatch.CHUNK + 37, 5, 0, nbatch.CHUNK]
    N, K, V, E, deg = sum(sizes), len(sizes), 3, 2, 2
    slices = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    obj_means = rng.normal(0, 0.05, (N, 3)).astype(np.float32)
    obj_quats = rng.normal(size=(N, 4)).astype(np.float32)
    obj_quats /= np.linalg.norm(obj_quats, axis=1, keepdims=True)
    obj_scales = rng.uniform(0.002, 0.02, (N, 3)).astype(np.float32)
    obj_opac = rng.uniform(0.1, 1.0, (1, N)).astype(np.float32)
    obj_sh = rng.normal(0, 0.3, (N, (deg + 1) ** 2, 3)).astype(np.float32)
    labels = np.concatenate([np.full(n, k + 1, np.int64) for k, n in enumerate(sizes)])
    W = H = 64
    viewmats = np.tile(np.eye(4), (V, 1, 1))
    viewmats[:, 0, 3] = [-0.03, 0.0, 0.04]
    viewmats[:, 2, 3] = [0.5, 0.6, 0.55]
    Ks = np.tile(np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]]), (V, 1, 1))
    campos = np.stack([-(m[:3, :3].T @ m[:3, 3]) for m in viewmats])
    q = rng.normal(size=(E, K, 4))
    q /= np.linalg.norm(q, axis=2, keepdims=True)
    q[q[..., 0] < 0] *= -1
    R = np.stack([[np.array(_rotmat(qq)) for qq in qe] for qe in q])
    t = rng.normal(0, 0.02, (E, K, 3))
    tiles_x = tiles_y = 4
    D, o_rgb, o_mask, o_depth = 3 + K + 1 + 1, 0, 3, 3 + K + 1
    pairs = np.array([[0, 0], [1, 0], [1, 1], [0, 2], [1, 3]], np.int64)
    C = E * V
    outs = []
    runs = [(nbatch.update_objects, nbatch.CHUNK), (nbatch.update_objects_serial, nbatch.CHUNK),
            (nbatch.update_objects, 7), (nbatch.update_objects, nbatch.chunk_for(len(pairs), V, 1))]  # fmt: skip
    assert nbatch.chunk_for(len(pairs), V, 1) > N and nbatch.chunk_for(1, 1, 2) == nbatch.CHUNK
    for kernel, chunk in runs:
        o = {"means": np.zeros((E, N, 3), np.float32), "quats": np.zeros((E, N, 4), np.float32),
             "m2": np.zeros((C, N, 2), np.float32), "conics": np.zeros((C, N, 3), np.float32),
             "depths": np.zeros((C, N), np.float32), "radii": np.zeros((C, N, 2), np.int32),
             "rects": np.zeros((C, N, 4), np.int32), "opac": np.zeros((C, N), np.float32),
             "colors": np.zeros((C, N, D), np.float32), "tiles": np.zeros((E, K, V, tiles_x * tiles_y), np.bool_),
             "dirty": np.zeros((C, tiles_x * tiles_y), np.bool_)}  # fmt: skip
        kernel(pairs, q, R, t, obj_means, obj_quats, obj_scales, obj_opac, obj_sh, labels, slices, viewmats, Ks,
               campos, float(W), float(H), 0.01, 1e10, 1 / 255, 0.3, antialiased, deg, o_rgb, o_mask, o_depth,
               tiles_x, o["means"], o["quats"], o["m2"], o["conics"], o["depths"], o["radii"], o["rects"],
               o["opac"], o["colors"], o["tiles"], o["dirty"], chunk)  # fmt: skip
        outs.append(o)
    for other in outs[1:]:
        for key in outs[0]:
            np.testing.assert_array_equal(outs[0][key], other[key], err_msg=key)
    o = outs[0]
    assert o["dirty"].any() and o["colors"][:, :, o_rgb].any()
    for e, k in pairs:
        s, f = slices[k], slices[k + 1]
        if f == s:
            assert not o["tiles"][e, k].any()
            continue
        m, qq = np.empty((f - s, 3), np.float32), np.empty((f - s, 4), np.float32)
        rigid.rigid_transform(obj_means[s:f], obj_quats[s:f], R[e, k], t[e, k], q[e, k], m, qq)
        np.testing.assert_array_equal(o["means"][e, s:f], m)
        ref = {"m2": np.empty((V, f - s, 2), np.float32), "conics": np.empty((V, f - s, 3), np.float32),
               "depths": np.empty((V, f - s), np.float32), "radii": np.empty((V, f - s, 2), np.int32),
               "rects": np.empty((V, f - s, 4), np.int32)}  # fmt: skip
        proj.project_forward_serial(m, qq, obj_scales[s:f], obj_opac[:, s:f], viewmats, Ks, float(W), float(H),
                                    0.01, 1e10, ref["m2"], ref["conics"], ref["depths"], ref["radii"], ref["rects"],
                                    1 / 255, 0.3)  # fmt: skip
        cams = slice(e * V, (e + 1) * V)
        for key, want in ref.items():
            np.testing.assert_array_equal(o[key][cams, s:f], want, err_msg=f"{key} pair {e},{k}")
        if antialiased:
            op = np.empty((V, f - s), np.float32)
            proj.antialias_opacities_serial(ref["conics"], obj_opac[:, s:f], op, 0.3)
            np.testing.assert_array_equal(o["opac"][cams, s:f], op)
        tiles = np.zeros((V, tiles_x * tiles_y), np.bool_)
        for v in range(V):
            rgb = np.empty((f - s, 3), np.float32)
            incr.sh_to_rgb(m, R[e, k], campos[v], obj_sh[s:f], deg, rgb)
            col = np.empty((f - s, D), np.float32)
            incr.fill_colors(rgb, labels[s:f], ref["depths"][v], o_rgb, o_mask, o_depth, col)
            np.testing.assert_array_equal(o["colors"][e * V + v, s:f], col)
        incr.mark_tiles(ref["rects"], tiles_x, tiles)
        np.testing.assert_array_equal(o["tiles"][e, k], tiles)
        assert (o["dirty"][cams] >= tiles).all()


def _rotmat(q):
    from dsg_gym.poses import quat_to_rotmat

    return quat_to_rotmat(np.asarray(q, np.float64))
