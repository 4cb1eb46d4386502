import warnings

import gymnasium as gym
import numpy as np
import pytest
from _worlds import HALF, two_box_world
from gymnasium.utils.env_checker import check_env

import dsg_gym  # noqa: F401  registers DSGWorld-v0
from dsg_gym.envs.dsg_world import DSGWorldEnv
from dsg_gym.poses import matrix_to_pose7


@pytest.fixture(scope="module")
def boxes():
    return two_box_world()


def _one_object_action(env, rng):
    a = np.zeros(env.action_space.shape, np.float32)
    n = a.size // env.unwrapped.K
    k = rng.integers(env.unwrapped.K)
    a[k * n : (k + 1) * n] = rng.uniform(-1, 1, n)
    return a


def test_check_env_without_our_warnings():
    env = gym.make(
        "DSGWorld-v0", render_mode="rgb_array", width=64, height=64, render_width=96, render_height=80
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped, skip_render_check=False)
    ours = [str(w.message) for w in caught if "dsg_gym" in str(w.filename) or "DSG" in str(w.message)]
    assert not ours, ours
    env.reset(seed=0)
    img = env.render()
    assert img.shape == (80, 96, 3) and img.dtype == np.uint8
    env.close()
    env.close()


def test_spaces_and_observation_contents():
    env = gym.make("DSGWorld-v0")
    obs, info = env.reset(seed=1)
    assert set(obs) == {"rgb", "mask", "poses", "goal"}
    assert obs["rgb"].shape == (128, 128, 3) and obs["rgb"].dtype == np.uint8
    assert obs["mask"].shape == (128, 128) and set(np.unique(obs["mask"])) <= {0, 1, 2}
    assert obs["poses"].dtype == np.float64 and obs["poses"].shape == (2, 7)
    np.testing.assert_allclose(np.linalg.norm(obs["poses"][:, 3:], axis=1), 1.0, atol=1e-12)
    assert env.action_space.shape == (8,) and env.action_space.low.min() == -1
    assert obs in env.observation_space
    assert not info["success"] and info["position_errors"].shape == (2,)
    env.close()


def test_seed_reproduces_and_steps_are_deterministic():
    rng_actions = np.random.default_rng(5).uniform(-1, 1, (6, 8)).astype(np.float32)
    runs = []
    for _ in range(2):
        env = gym.make("DSGWorld-v0", obs=("rgb", "mask", "depth", "poses"))
        obs, _ = env.reset(seed=123)
        trace = [obs]
        for a in rng_actions:
            trace.append(env.step(a)[0])
        runs.append(trace)
    for a, b in zip(*runs):
        for k in a:
            assert np.array_equal(a[k], b[k]), k
    env = gym.make("DSGWorld-v0")
    other, _ = env.reset(seed=124)
    assert not np.array_equal(other["goal"], runs[0][0]["goal"])


@pytest.mark.parametrize("tail_stride", [0, 64])
def test_incremental_equals_full_over_random_episode(tail_stride):
    """Exact merge (tail_stride 0): the same images as full renders, bit for bit. Background tail tables (the
    default): within the transmittance cut-off's reach: a few uint8 levels on a few percent of the pixels."""
    rng = np.random.default_rng(0)
    settings = {"tail_stride": tail_stride}
    inc = gym.make("DSGWorld-v0", obs=("rgb", "mask", "depth"), incremental=True, render_settings=settings)
    full = gym.make("DSGWorld-v0", obs=("rgb", "mask", "depth"), incremental=False, render_settings=settings)
    a, _ = inc.reset(seed=7)
    b, _ = full.reset(seed=7)
    differ = 0
    for _ in range(25):
        act = _one_object_action(inc, rng)
        a = inc.step(act)[0]
        b = full.step(act)[0]
        if tail_stride == 0:
            for k in ("rgb", "mask", "depth"):
                assert np.array_equal(a[k], b[k]), k
        else:
            d = np.abs(a["rgb"].astype(int) - b["rgb"].astype(int))
            assert d.max() <= 8 and (d > 0).any(-1).mean() < 0.05
            assert (a["mask"] != b["mask"]).mean() < 0.01
            differ += int((d > 0).any())
    assert tail_stride == 0 or differ > 0  # the tables are in use
    assert inc.unwrapped.renderer.last_dirty_tiles < full.unwrapped.renderer.last_dirty_tiles


def test_only_requested_observations_and_multiview():
    cams = [0, 10, {"eye": [0.0, -0.9, 0.6], "target": [0.0, 0.0, 0.0], "fovy_deg": 45}]
    env = gym.make("DSGWorld-v0", cameras=cams, obs=("depth",), width=48, height=40)
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"depth", "goal"}
    d = obs["depth"]
    assert d.shape == (3, 40, 48) and d.dtype == np.float32
    assert 0.3 < np.median(d[2]) < 3.0  # metres
    assert obs in env.observation_space
    with pytest.raises(ValueError, match="obs"):
        DSGWorldEnv(obs=("rgb", "normals"))
    with pytest.raises(ValueError, match="out of range"):
        DSGWorldEnv(cameras=[10_000])


def test_reject_settle_ignore(boxes):
    start = matrix_to_pose7(boxes.states["state1"])  # red at x=-0.1, blue at x=+0.1, 8 cm cubes
    push = np.zeros(8, np.float32)
    push[0] = 1.0  # red +x by max_translation
    for mode in ("reject", "settle", "ignore"):
        env = DSGWorldEnv(world=boxes, collision=mode, max_translation=0.15, width=32, height=32)
        env.reset(seed=0, options={"start": start, "goal": "state2"})
        obs, r, term, trunc, info = env.step(push)
        assert info["collision"]
        p = obs["poses"]
        if mode == "reject":
            assert info["rejected"].tolist() == [True, False]
            np.testing.assert_array_equal(p, start)
        elif mode == "settle":
            assert info["settled"] and not info["rejected"].any()
            assert env.physics.check(p).ok
            assert p[1, 0] - p[0, 0] >= 2 * HALF - 2e-3 and p[0, 0] > start[0, 0] + 0.05
        else:
            assert p[0, 0] == pytest.approx(start[0, 0] + 0.15)
            assert info["penetrating_pairs"].tolist() == [[0, 1]]
        assert r < -0.05


def test_success_terminates_and_time_limit_truncates(boxes):
    env = gym.make("DSGWorld-v0", world=boxes, width=32, height=32, max_episode_steps=3)
    _, info = env.reset(seed=0, options={"start": "state1", "goal": "state1"})
    assert info["success"]
    _, r, term, trunc, info = env.step(np.zeros(8, np.float32))
    assert term and not trunc and r == pytest.approx(1.0)
    env.reset(seed=0, options={"start": "state1", "goal": "state2"})
    flags = [env.step(np.zeros(8, np.float32))[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]


def test_action_modes(boxes):
    env = DSGWorldEnv(world=boxes, action_mode="absolute", width=32, height=32, collision="ignore")
    env.reset(seed=0)
    a = np.zeros(14, np.float32)
    a[:7] = (0.0, 0.0, -1.0, 1.0, 0.0, 0.0, 0.0)
    a[7:] = (0.5, 0.5, 1.0, 0.0, 0.0, 0.0, 1.0)
    p = env.step(a)[0]["poses"]
    np.testing.assert_allclose(p[0], [0.0, 0.0, 0.0, 1, 0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(p[1], [0.15, 0.1, 0.3, 0, 0, 0, 1], atol=1e-12)
    a[7:] = (1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 1.0)  # the table's corner: half the box beyond its edges
    obs, _, _, _, info = env.step(a)
    assert info["rejected"].tolist() == [False, True] and info["collision"]
    np.testing.assert_array_equal(obs["poses"][1], p[1])
    with pytest.raises(ValueError, match="quaternion"):
        env.step(np.zeros(14, np.float32))
    env = DSGWorldEnv(world=boxes, action_mode="se3", width=32, height=32, collision="ignore")
    obs, _ = env.reset(seed=0, options={"start": "state1"})
    a = np.zeros(12, np.float32)
    a[3] = 1.0  # roll red by max_rotation about world x
    p = env.step(a)[0]["poses"]
    assert p[0, 4] == pytest.approx(np.sin(0.1), abs=1e-12) and np.array_equal(p[1], obs["poses"][1])


def test_bad_input_is_a_value_error_and_changes_nothing(tmp_path):
    env = gym.make("DSGWorld-v0", width=32, height=32)
    obs, _ = env.reset(seed=3)
    before = env.unwrapped._poses.copy()
    for bad, msg in (
        (np.full(8, np.nan, np.float32), "NaN"),
        (np.array([0, 0, np.inf, 0, 0, 0, 0, 0], np.float32), "NaN or Inf"),
        (np.zeros(7, np.float32), "shape"),
        (np.zeros((2, 4), np.float32), "shape"),
        ("left", "numeric|shape"),
    ):
        with pytest.raises(ValueError, match=msg):
            env.step(bad)
        assert np.array_equal(env.unwrapped._poses, before)
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"teleport": 1})
    with pytest.raises(ValueError, match="unknown state"):
        env.reset(options={"goal": "state9"})
    with pytest.raises(ValueError, match="NaN"):
        env.reset(options={"start": np.full((2, 7), np.nan)})
    assert np.array_equal(env.unwrapped._poses, before)
    assert np.array_equal(env.step(np.zeros(8, np.float32))[0]["rgb"], obs["rgb"])
    garbage = tmp_path / "w.dsgworld"
    garbage.write_bytes(b"not a world")
    for path in (garbage, tmp_path / "missing.dsgworld"):
        with pytest.raises(ValueError, match=str(path.name)):
            gym.make("DSGWorld-v0", world=str(path))
    for kw in (
        {"width": 0},
        {"collision": "bounce"},
        {"action_mode": "joint"},
        {"render_mode": "human"},
        {"max_translation": float("nan")},
        {"cameras": [{"eye": [0, 0, 1]}]},
        {"task": {"gap": -1}},
        {"render_settings": {"alpha_min": 2.0}},
        {"render_settings": {"tile": 8}},
        {"render_settings": "fast"},
    ):
        with pytest.raises(ValueError):
            DSGWorldEnv(**kw)


def test_render_settings_reach_the_renderer(boxes):
    base = DSGWorldEnv(world=boxes, width=32, height=32)
    fast = DSGWorldEnv(world=boxes, width=32, height=32, render_settings={"t_min": 0.2, "sh_degree": 0})
    assert fast.renderer.t_min == 0.2 and fast.renderer._sh_degree == 0
    a, _ = base.reset(seed=1)
    b, _ = fast.reset(seed=1)
    assert np.array_equal(a["poses"], b["poses"]) and not np.array_equal(a["rgb"], b["rgb"])


@pytest.mark.parametrize("mode", ["sync", "async"])
def test_vector_envs(mode):
    kw = {"vectorization_mode": mode}
    if mode == "async":
        kw["vector_kwargs"] = {"shared_memory": True}
    envs = gym.make_vec("DSGWorld-v0", num_envs=2, width=32, height=32, **kw)
    obs, _ = envs.reset(seed=[1, 2])
    assert obs["rgb"].shape == (2, 32, 32, 3)
    assert not np.array_equal(obs["goal"][0], obs["goal"][1])
    for _ in range(3):
        obs, r, term, trunc, info = envs.step(envs.action_space.sample())
    assert obs["mask"].shape == (2, 32, 32) and r.shape == (2,)
    envs.close()


def test_stable_baselines3_check_env_and_ppo():
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = gym.make("DSGWorld-v0", width=40, height=40, max_episode_steps=50)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sb3_check(env.unwrapped, warn=True)
    ours = [str(w.message) for w in caught if "DSG" in str(w.message) or "dsg_gym" in str(w.filename)]
    assert not ours, ours
    model = sb3.PPO("MultiInputPolicy", env, n_steps=64, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(total_timesteps=256)
    assert model.num_timesteps >= 256


def test_small_quaternion_path_matches_numpy(monkeypatch):
    """The scalar path of dsg_gym.poses (small batches, the env's hot path) gives the numpy path's bits."""
    from dsg_gym import poses

    rng = np.random.default_rng(0)
    qs = [rng.normal(size=(n, 4)) * s for n in (1, 2, 5, 8) for s in (1e-6, 1.0, 1e4) for _ in range(20)]
    qs += [np.array([[-0.0, 1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0]]), np.array([[1e160, 1.0, 0.0, 0.0]])]
    funcs = (poses.quat_normalize, poses.quat_to_rotmat, lambda q: poses.quat_multiply(q, q[::-1]))
    with np.errstate(over="ignore"):  # the 1e160 quaternion's product overflows (to inf) on both paths alike
        fast = [[f(q) for f in funcs] for q in qs]
        monkeypatch.setattr(poses, "_SCALAR_OK", False)
        slow = [[f(q) for f in funcs] for q in qs]
    for a, b in zip(fast, slow):
        for x, y in zip(a, b):
            assert x.shape == y.shape and x.tobytes() == y.tobytes()
    for bad in (np.zeros((2, 4)), np.array([[np.nan, 1.0, 0.0, 0.0]])):
        with pytest.raises(ValueError):
            poses.quat_normalize(bad)
