"""Hostile inputs to ``DSGWorld-v0``: the workspace bounds every collision mode, checked reset poses, settling
without penetration, real-valued actions only, and bounded pose spaces."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
from _worlds import HALF, two_box_world
from gymnasium.utils.env_checker import check_env

import dsg_gym  # noqa: F401  registers DSGWorld-v0
from dsg_gym.envs.dsg_world import DSGWorldEnv
from dsg_gym.envs.dsg_world_vector import DSGWorldVectorEnv
from dsg_gym.physics import BOUNDS_TOL, SETTLE_TOLERANCE
from dsg_gym.poses import matrix_to_pose7

MODES = ("reject", "settle", "ignore")


@pytest.fixture(scope="module")
def boxes():
    return two_box_world()


def _env(world, mode="reject", **kw):
    return DSGWorldEnv(world=world, collision=mode, width=16, height=16, obs=("poses",), **kw)


def _state1(world):
    return matrix_to_pose7(world.states["state1"])  # red at x=-0.1, blue at x=+0.1, 8 cm cubes on the table


def _inside(env, poses) -> None:
    """Every origin in the workspace box, every hull within its x/y bounds and below its top."""
    lo, hi = np.array(env.physics.workspace.lo), np.array(env.physics.workspace.hi)
    assert np.all(poses[:, :3] >= lo) and np.all(poses[:, :3] <= hi), poses
    for k in range(env.K):
        h = env.physics.hull_world(k, poses[k])
        assert np.all(h[:, :2] >= lo[:2] - BOUNDS_TOL) and np.all(h[:, :2] <= hi[:2] + BOUNDS_TOL)
        assert h[:, 2].max() <= hi[2] + BOUNDS_TOL


# ------------------------------------------------------------------------------------------- workspace
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("push", [(0, 0, 1, 0), (1, 0, 0, 0), (0, -1, 0, 0), (0, 0, -1, 0)])
def test_no_object_leaves_the_workspace(boxes, mode, push):
    env = _env(boxes, mode)
    obs, _ = env.reset(seed=0, options={"start": "state1", "goal": "state2"})
    a = np.zeros(8, np.float32)
    a[:4] = push  # red: up, +x, -y or down, one max_translation a step, for 1.2 m
    for _ in range(60):
        obs, reward, _, _, info = env.step(a)
        _inside(env, obs["poses"])
        assert np.isfinite(reward) and obs in env.observation_space
    if not (mode == "settle" and push[2]):  # settling brings red back onto the table
        assert info["rejected"][0] and info["collision"]  # the last move would have left the workspace


def test_workspace_is_the_table_and_half_a_metre_above_it(boxes):
    ws = _env(boxes).physics.workspace
    t = boxes.table
    assert ws.lo == (t.xmin, t.ymin, t.z) and ws.hi == (t.xmax, t.ymax, t.z + 0.5)


# ------------------------------------------------------------------------------------------- reset poses
def _bad_poses(world):
    s = _state1(world)
    far, high, edge, nan = s.copy(), s.copy(), s.copy(), s.copy()
    far[0, 0] = 1e300
    high[1, 2] = 0.6
    edge[1, 0] = 0.29  # half of blue beyond the table's edge x = 0.3
    nan[0, 4] = np.nan
    return [
        (
            far,
            r"object 0 \('red'\): its position x = 1e\+300 is outside the workspace's x range \[-0.3, 0.3\]",
        ),
        (high, r"object 1 \('blue'\): its position z = 0.6 is outside the workspace's z range \[0, 0.5\]"),
        (edge, r"object 1 \('blue'\): its collision hull reaches x = 0.33.*x range \[-0.3, 0.3\]"),
        (nan, "NaN"),
        (s + 0j, "complex128"),
        (np.full((2, 7), None), "dtype object"),
    ]


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("key", ["start", "goal"])
def test_reset_refuses_poses_outside_the_workspace(boxes, mode, key):
    env = _env(boxes, mode)
    env.reset(seed=1)
    before, goal = env.poses, env.goal
    for bad, msg in _bad_poses(boxes):
        with pytest.raises(ValueError, match=msg) as err:
            env.reset(options={key: bad})
        assert f"options['{key}']" in str(err.value)
        assert np.array_equal(env.poses, before) and np.array_equal(env.goal, goal)
    obs, reward, *_ = env.step(np.zeros(8, np.float32))
    assert np.isfinite(reward) and np.array_equal(obs["poses"], before)


def _overlapping(world):
    s = _state1(world)
    s[0, 0] = s[1, 0] - 0.05  # red 3 cm inside blue
    return s


def test_overlapping_start_follows_the_collision_mode(boxes):
    s = _overlapping(boxes)
    env = _env(boxes, "reject")
    with pytest.raises(
        ValueError, match=r"object 0 \('red'\) and object 1 \('blue'\) interpenetrate by [23]\d"
    ):
        env.reset(options={"start": s})
    with pytest.raises(ValueError, match="and the table interpenetrate"):
        sunk = _state1(boxes)
        sunk[0, 2] = HALF - 0.02
        env.reset(options={"start": sunk})

    env = _env(boxes, "settle")
    obs, info = env.reset(options={"start": s, "goal": "state2"})
    assert info["settled"] and not info["penetrating_pairs"].size
    assert max(env.physics.check(obs["poses"], tol=0.0).depths, default=0.0) <= SETTLE_TOLERANCE
    assert obs["poses"][1, 0] - obs["poses"][0, 0] >= 2 * HALF - SETTLE_TOLERANCE  # pushed apart
    assert np.isfinite(env.step(np.zeros(8, np.float32))[1])

    env = _env(boxes, "ignore")
    obs, info = env.reset(options={"start": s, "goal": "state2"})
    assert np.array_equal(obs["poses"], s) and info["penetrating_pairs"].tolist() == [[0, 1]]
    assert not info["settled"] and np.isfinite(env.step(np.zeros(8, np.float32))[1])


@pytest.mark.parametrize("mode", MODES)
def test_overlapping_goal(boxes, mode):
    env = _env(boxes, mode)
    if mode == "ignore":
        obs, _ = env.reset(options={"start": "state1", "goal": _overlapping(boxes)})
        assert np.array_equal(obs["goal"], _overlapping(boxes))
    else:
        with pytest.raises(ValueError, match=f"interpenetrate by [23]\\d.*collision='{mode}' cannot reach"):
            env.reset(options={"start": "state1", "goal": _overlapping(boxes)})


# ------------------------------------------------------------------------------------------- settle
def _max_penetration(env, poses) -> float:
    """The deepest penetration among MuJoCo's contacts (their ``dist``) at ``poses``, metres."""
    return max(env.physics.check(poses, tol=0.0, distance=False).depths, default=0.0)


def test_settle_push_never_leaves_objects_inside_each_other(boxes):
    env = _env(boxes, "settle")
    obs, _ = env.reset(seed=0, options={"start": "state1", "goal": "state2"})
    start = obs["poses"]
    d = start[1, :2] - start[0, :2]
    a = np.zeros(8, np.float32)
    a[:2] = d / np.linalg.norm(d)  # red straight into blue, then on until blue would fall off the table
    rejected = 0
    for _ in range(100):
        obs, reward, _, _, info = env.step(a)
        assert _max_penetration(env, obs["poses"]) <= SETTLE_TOLERANCE
        assert np.isfinite(reward)
        _inside(env, obs["poses"])
        rejected += bool(info["rejected"].any())
    assert obs["poses"][1, 0] > start[1, 0] + 0.1  # blue was pushed along
    assert rejected > 0  # and the moves that would push it off the table were undone


# ------------------------------------------------------------------------------------------- actions
@pytest.mark.parametrize(
    "bad,dtype",
    [
        (np.zeros(8) + 1j, "complex128"),
        (np.zeros(8, np.complex64), "complex64"),
        (np.array([None] * 8), "object"),
        ([0.0] * 7 + [None], "object"),
        (np.array(["0.1"] * 8), "<U3"),
    ],
)
def test_non_real_actions_are_refused_by_dtype(boxes, bad, dtype):
    env = _env(boxes)
    env.reset(seed=0)
    before = env.poses
    with pytest.raises(ValueError, match=f"action must be a real numeric array, got dtype {dtype}"):
        env.step(bad)
    assert np.array_equal(env.poses, before)
    env.step(np.ones(8, dtype=bool))  # booleans and integers are real numbers
    env.step(np.zeros(8, dtype=np.int64))


def test_vector_env_refuses_a_complex_row(boxes):
    envs = DSGWorldVectorEnv(2, world=boxes, width=16, height=16, obs=("poses",))
    obs, _ = envs.reset(seed=0)
    a = np.zeros((2, 8), np.complex128)
    with pytest.raises(ValueError, match="env 0: action must be a real numeric array, got dtype complex128"):
        envs.step(a)
    assert np.array_equal(envs.step(np.zeros((2, 8), np.float32))[0]["poses"], obs["poses"])


# ------------------------------------------------------------------------------------------- spaces
def test_pose_spaces_are_bounded_and_check_env_is_clean(boxes):
    env = gym.make("DSGWorld-v0", world=boxes, width=32, height=32, render_mode="rgb_array").unwrapped
    ws = env.physics.workspace
    for key in ("poses", "goal"):
        space = env.observation_space[key]
        assert np.all(np.isfinite(space.low)) and np.all(np.isfinite(space.high))
        assert np.array_equal(space.low[:, :3], np.tile(ws.lo, (2, 1)))
        assert np.array_equal(space.high[:, :3], np.tile(ws.hi, (2, 1)))
        assert np.all(space.low[:, 3:] == -1) and np.all(space.high[:, 3:] == 1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(env, skip_render_check=False)
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=2)
    for _ in range(30):
        obs = env.step(rng.uniform(-1, 1, 8).astype(np.float32))[0]
        assert obs in env.observation_space


def test_look_at_cameras_take_real_numbers_only(boxes):
    for spec, msg in (
        ({"eye": [0, -1, 1j], "target": [0, 0, 0]}, "eye must be a real numeric array, got dtype complex128"),
        ({"eye": [0, -1, 1], "target": [0, 0, 0], "fovy_deg": [40]}, "fovy_deg a number"),
        (
            {"eye": [0, -1, 1], "target": [0, 0, 0], "fovy_deg": "wide"},
            "fovy_deg must be a real numeric array",
        ),
    ):
        with pytest.raises(ValueError, match=msg):
            DSGWorldEnv(world=boxes, cameras=spec)
