import numpy as np
import pytest
from _worlds import HALF, two_box_world

from dsg_gym.physics import TABLE, PhysicsProxy
from dsg_gym.poses import matrix_to_pose7
from dsg_gym.world_model import WorldModel


@pytest.fixture(scope="module")
def proxy():
    return PhysicsProxy(two_box_world())


def test_captured_states_are_valid(proxy):
    for name, poses in proxy.world.states.items():
        r = proxy.check(poses, distance_range=0.5)
        assert r.ok, (name, r)
        assert r.min_distance == pytest.approx(0.12, abs=2e-3)  # centres 0.2 apart, 8 cm cubes


def test_bundled_world_states_are_valid():
    from dsg_gym.envs.dsg_world import load_default_world

    w = load_default_world()
    p = PhysicsProxy(w)
    for name, poses in w.states.items():
        assert p.check(poses).ok, name


def test_boxes_pushed_into_each_other(proxy):
    p = matrix_to_pose7(proxy.world.states["state1"])
    p[0, 0] = p[1, 0] - 0.05  # 3 cm overlap
    r = proxy.check(p)
    assert r.penetrating == ((0, 1),)
    assert r.depths[0] == pytest.approx(0.03, abs=2e-3)
    assert r.min_distance < -0.02 and not r.ok
    s = proxy.settle(p)
    assert proxy.check(s).ok
    assert abs(s[1, 0] - s[0, 0]) >= 2 * HALF - 2e-3  # pushed apart
    np.testing.assert_allclose(s[:, 2], HALF, atol=2e-3)  # still resting on the table
    np.testing.assert_allclose(np.linalg.norm(s[:, 3:], axis=1), 1.0, atol=1e-12)
    assert np.array_equal(s, proxy.settle(p))  # deterministic, bit for bit


def test_table_penetration_and_bounds(proxy):
    p = matrix_to_pose7(proxy.world.states["state1"])
    p[0, 2] = HALF - 0.02
    assert proxy.check(p).penetrating == ((0, TABLE),)
    p = matrix_to_pose7(proxy.world.states["state1"])
    p[1, 0] = 0.29  # half of it beyond xmax = 0.3
    r = proxy.check(p)
    assert r.out_of_bounds == (1,) and not r.penetrating


def test_settle_drops_to_rest(proxy):
    p = matrix_to_pose7(proxy.world.states["state2"])
    p[:, 2] += 0.15
    s = proxy.settle(p, max_time=2.0)
    np.testing.assert_allclose(s[:, 2], HALF, atol=2e-3)
    np.testing.assert_allclose(s[:, :2], p[:, :2], atol=5e-3)
    assert proxy.resting_z(0, s[0, 3:]) == pytest.approx(HALF, abs=1e-6)


def test_bad_input(proxy):
    p = matrix_to_pose7(proxy.world.states["state1"])
    with pytest.raises(ValueError, match="poses"):
        proxy.check(p[:1])
    bad = p.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        proxy.settle(bad)
    with pytest.raises(ValueError, match="max_time"):
        proxy.settle(p, max_time=-1)


def test_degenerate_object_is_a_clear_error():
    w = two_box_world()
    flat = w.objects[0].subset(np.abs(w.objects[0].means[:, 2] - HALF) < 1e-9)  # only the top face
    import dataclasses

    w2 = dataclasses.replace(w, objects=(flat, w.objects[1]))
    assert isinstance(w2, WorldModel)
    with pytest.raises(ValueError, match="collision model"):
        PhysicsProxy(w2)


def test_hulls_of_resting_objects_are_lifted_out_of_the_table():
    """Trained objects blur a few millimetres into the table they stood on; their hulls are lifted onto the
    top for the captured states, while an object floating above the table keeps its hull."""
    import dataclasses

    w = two_box_world()
    sunk = dataclasses.replace(w.objects[0], means=w.objects[0].means - np.float32([0, 0, 0.006]))
    w2 = dataclasses.replace(w, objects=(sunk, *w.objects[1:]))
    p = PhysicsProxy(w2)
    for name, poses in w2.states.items():
        assert p.check(poses).ok, name
    low = min(p.hull_world(0, matrix_to_pose7(P[0]))[:, 2].min() for P in w2.states.values())
    assert low == pytest.approx(w2.table.z, abs=1e-9)
    # without lifting (tolerance 0) the sunk box penetrates the table by about 6 mm
    r = PhysicsProxy(w2, rest_tolerance=0.0).check(w2.states["state1"])
    assert (0, TABLE) in r.penetrating and r.depths[r.penetrating.index((0, TABLE))] == pytest.approx(
        0.006, abs=1e-3
    )


def test_workspace_bounds_z_as_well_as_x_and_y(proxy):
    p = matrix_to_pose7(proxy.world.states["state1"])
    assert proxy.workspace.hi[2] == proxy.world.table.z + 0.5 and not proxy.workspace_problems(p)
    high = p.copy()
    high[0, 2] = 0.5 - HALF + 0.005  # origin inside, hull top 5 mm above the workspace
    r = proxy.check(high)
    assert r.out_of_bounds == (0,) and not r.penetrating
    assert "hull reaches z = 0.505" in proxy.workspace_problems(high)[0]
    sunk = p.copy()
    sunk[1, 2] = -0.01  # origin below the table top (the hull mostly inside the table)
    assert proxy.check(sunk).out_of_bounds == (1,)
    assert proxy.workspace_problems(sunk) == {
        1: "its position z = -0.01 is outside the workspace's z range [0, 0.5] (the table top to 0.5 m above it)"
    }
