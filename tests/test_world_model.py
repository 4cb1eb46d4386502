import dataclasses

import numpy as np
import pytest
import torch
from _worlds import two_box_world

from dsg_gym import geometry as G
from dsg_gym import poses as P
from dsg_gym.cameras import Cameras
from dsg_gym.world_model import WorldModel, WorldModelError, derive_table_bounds


def test_pose_helpers_agree_with_torch_geometry():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(64, 4)) * rng.uniform(0.1, 10, (64, 1))  # unnormalised on purpose
    r = P.quat_to_rotmat(q)
    np.testing.assert_allclose(r, G.quat_to_rotmat(torch.tensor(q)).numpy(), atol=1e-12)
    qn = P.rotmat_to_quat(r)
    assert np.all(qn[:, 0] >= 0)
    np.testing.assert_allclose(np.abs(np.sum(qn * P.quat_normalize(q), 1)), 1.0, atol=1e-12)
    v = rng.normal(size=(64, 3))
    dot = np.sum(P.axis_angle_to_quat(v) * G.axis_angle_to_quat(torch.tensor(v)).numpy(), 1)
    np.testing.assert_allclose(np.abs(dot), 1.0, atol=1e-12)  # same rotation (ours has w >= 0)
    p7 = np.concatenate([rng.normal(size=(64, 3)), q], 1)
    back = P.matrix_to_pose7(P.pose7_to_matrix(p7))
    np.testing.assert_allclose(back[:, :3], p7[:, :3], atol=1e-12)
    assert P.quat_angle(back[:, 3:], q).max() < 1e-7
    with pytest.raises(ValueError, match="zero"):
        P.as_poses7(np.zeros((1, 7)), 1)
    with pytest.raises(ValueError, match="rigid"):
        P.as_poses7(np.diag([2.0, 1, 1, 1])[None], 1)


def test_quat_normalize_huge_tiny_and_bad():
    q = np.array([[1e300, -2e300, 0.0, 5e299], [1.0, -2.0, 0.0, 0.5], [-1e-6, 0.0, 3e-6, 0.0]])
    n = P.quat_normalize(q)
    assert np.all(np.isfinite(n)) and np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-15)
    assert np.allclose(n[0], n[1], atol=1e-15) and n[2, 0] >= 0.0
    for bad in (
        [0.0, 0.0, 0.0, 0.0],
        [np.nan, 1.0, 0.0, 0.0],
        [np.inf, 0.0, 0.0, 0.0],
        [1e-13, 0.0, 0.0, 0.0],
    ):
        with pytest.raises(ValueError, match="zero or not finite"):
            P.quat_normalize(np.array(bad))


def test_compose_moves_objects_rigidly():
    w = two_box_world()
    rng = np.random.default_rng(1)
    p7 = np.concatenate([rng.normal(size=(2, 3)), rng.normal(size=(2, 4)) * 3.0], 1)
    gs = w.compose(p7)
    nb = w.background.num
    assert gs.num == w.num_gaussians
    assert gs.labels[:nb].max() == 0 and set(np.unique(gs.labels[nb:])) == {1, 2}
    m = P.pose7_to_matrix(p7)
    o0 = w.objects[0]
    want = o0.means.astype(np.float64) @ m[0, :3, :3].T + m[0, :3, 3]
    np.testing.assert_allclose(gs.means[nb : nb + o0.num], want, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(gs.quats[nb:], axis=1), 1.0, atol=1e-6)
    # rotations compose: Gaussian frames rotate with the object
    rq = P.quat_to_rotmat(gs.quats[nb : nb + 3].astype(np.float64))
    np.testing.assert_allclose(
        rq, m[0, :3, :3][None] @ P.quat_to_rotmat(o0.quats[:3].astype(np.float64)), atol=1e-6
    )
    # [K,4,4] input and a rescaled quaternion give the same scene
    p7b = p7.copy()
    p7b[:, 3:] *= -7.0
    assert np.array_equal(w.compose(m).means, gs.means)
    np.testing.assert_allclose(w.compose(p7b).means, gs.means, atol=1e-6)
    for bad in (p7[:1], np.full((2, 7), np.nan)):
        with pytest.raises(ValueError, match="poses"):
            w.compose(bad)


def test_validation_and_table_bounds():
    w = two_box_world()
    with pytest.raises(WorldModelError, match="names"):
        dataclasses.replace(w, object_names=("a",))
    with pytest.raises(WorldModelError, match="state1"):
        dataclasses.replace(w, states={"state1": np.zeros((2, 4, 4))})
    with pytest.raises(ValueError, match="unknown state"):
        w.state_poses("nope")
    t = derive_table_bounds(w.background, w.objects, w.states)
    assert t.z == pytest.approx(0.0, abs=1e-6)
    assert t.xmin == pytest.approx(-0.3, abs=0.03) and t.ymax == pytest.approx(0.2, abs=0.03)
    c = w.cameras.resized(128, 96)
    assert c.Ks[0, 0, 2] == pytest.approx(64) and c.Ks[0, 1, 2] == pytest.approx(48)
    with pytest.raises(ValueError, match="bad image size"):
        Cameras(np.eye(4)[None], np.eye(3)[None], 0, 10)


def test_load_bundled_world_and_errors(tmp_path):
    from dsg_gym.envs.dsg_world import DEFAULT_WORLD

    w = WorldModel.load(DEFAULT_WORLD)
    assert w.object_names == ("red_box", "blue_cylinder") and w.object_ids == (1, 2)
    assert {"state1", "state2"} <= set(w.states)
    assert (w.table.xmin, w.table.xmax, w.table.ymin, w.table.ymax) == (-0.4, 0.4, -0.3, 0.3)
    assert len(w.cameras) >= 1 and w.cameras.width == 128
    bad = tmp_path / "bad.dsgworld"
    bad.write_bytes(DEFAULT_WORLD.read_bytes()[:1000])
    with pytest.raises(ValueError, match="bad.dsgworld"):
        WorldModel.load(bad)
    with pytest.raises(ValueError, match="does not exist"):
        WorldModel.load(tmp_path / "none.dsgworld")
