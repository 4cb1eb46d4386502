"""train_world.eval.background_parts: background pixels told apart by the surface the truth's depth shows."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from train_world.eval.background_parts import PARTS, background_parts, capture_background_parts
from train_world.eval.regions import RegionErrors, combine, region_masks

H = W = 60
K = np.array([[40.0, 0, 30], [0, 40.0, 30], [0, 0, 1]])
EYE = np.array([0.0, 0.0, 1.0])
# looking straight down: camera x = world x, camera y = -world y, camera z = -world z
R = np.diag([1.0, -1.0, -1.0])
VIEWMAT = np.eye(4)
VIEWMAT[:3, :3], VIEWMAT[:3, 3] = R, -R @ EYE
BOUNDS = np.array([[-0.3, -1.0, 0.0], [0.25, 1.0, 0.0]])


def _plane_depth(normal, offset):
    """Depth [H, W] at which each pixel's ray meets the plane normal . x = offset."""
    y, x = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack([(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], np.ones_like(x)], -1) @ R  # world, z=1
    n = np.asarray(normal, float)
    return (offset - n @ EYE) / (rays @ n)


def _scene():
    """Columns 0-19 see a floor 0.7 below the table top, 20-39 the table top, 40-59 a shelf above the top
    (rows 0-29) and a floor tilted 45 degrees (rows 30-59) with no depth at its last rows."""
    d = _plane_depth([0, 0, 1], -0.7)
    d[:, 20:40] = _plane_depth([0, 0, 1], 0.0)[:, 20:40]
    d[:30, 40:] = _plane_depth([0, 0, 1], 0.2)[:30, 40:]
    d[30:, 40:] = _plane_depth([1, 0, 1], 0.5 - 0.7)[30:, 40:]
    d[55:, 40:] = 0.0
    return d


def test_the_parts_follow_the_surfaces_and_partition_the_view():
    parts = background_parts(_scene(), VIEWMAT, K, BOUNDS, 0.0, 1.0)
    assert set(parts) == set(PARTS)
    assert (np.stack([parts[p] for p in PARTS]).sum(0) == 1).all()
    # the table top: its column, exactly (the bounds reach past it)
    assert parts["table_top"][:, 20:40].all() and not parts["table_top"][:, :20].any()
    assert not parts["table_top"][:, 40:].any()
    # the floor inside its column (a normal at the seam mixes two surfaces)
    assert parts["floor"][:, :19].all()
    # above the top, tilted or without depth: other
    assert parts["other"][:, 41:].all()


def test_the_table_needs_its_bounds_and_the_floor_its_depth_below():
    narrow = BOUNDS.copy()
    narrow[1, 0] = 0.0  # the table ends at x = 0, the middle of its column
    parts = background_parts(_scene(), VIEWMAT, K, narrow, 0.0, 1.0)
    assert parts["table_top"][:, 20:29].all() and parts["other"][:, 32:40].all()
    # the same floor counts as table top when the table is said to lie at its height, not below it
    low = background_parts(_scene(), VIEWMAT, K, np.array([[-5, -5, -0.7], [5, 5, -0.7]]), -0.7, 1.0)
    assert low["table_top"][:, :19].all() and not low["floor"].any()
    with pytest.raises(ValueError, match="scale"):
        background_parts(_scene(), VIEWMAT, K, BOUNDS, 0.0, 0.0)
    with pytest.raises(ValueError, match="depth"):
        background_parts(_scene()[None], VIEWMAT, K, BOUNDS, 0.0, 1.0)


def test_region_errors_split_the_background_by_part():
    rng = np.random.default_rng(0)
    cls = np.zeros((H, W), np.int64)
    cls[10:20, 25:35] = 1  # an object on the table
    parts = background_parts(_scene(), VIEWMAT, K, BOUNDS, 0.0, 1.0)
    views = [(rng.random((H, W, 3)), rng.random((H, W, 3))) for _ in range(2)]
    acc, halves = RegionErrors(["box"]), []
    for ours, truth in views:
        acc.add(ours, truth, cls, parts=parts)
        one = RegionErrors(["box"])
        one.add(ours, truth, cls, parts=parts)
        halves.append(one.report())
    r = acc.report()
    bp = r["background_parts"]
    background = r["regions"]["background"]
    assert sum(bp[p]["pixels"] for p in PARTS) == background["pixels"]
    assert sum(bp[p]["squared_error"] for p in PARTS) == pytest.approx(background["squared_error"])
    m = region_masks(cls)["background"] & parts["table_top"]
    assert bp["table_top"]["pixels"] == 2 * int(m.sum())
    err = np.mean([np.mean((o - t) ** 2, -1)[m].mean() for o, t in views])
    assert bp["table_top"]["squared_error"] / bp["table_top"]["pixels"] == pytest.approx(err)
    merged = combine(halves)["background_parts"]
    for part in PARTS:
        assert merged[part] == pytest.approx(bp[part])
    # without parts for every view there is no split
    acc.add(*views[0], cls)
    assert acc.report()["background_parts"] is None


def _capture(up="+z", table=True, depth=True):
    """A loaded capture's fields that the split reads: one state of two views of :func:`_scene`, the eye 2
    above the table top in the second, with two strips 0.0125 and 0.0175 above the top: on it only with the
    tolerance of the median camera distance (about 1.5), not with that of the nearest (1) or farthest (2)."""
    vm2 = VIEWMAT.copy()
    vm2[:3, 3] = -R @ (2 * EYE)
    d = _scene()
    d[:, 22:26], d[:, 30:34] = 1 - 0.0125, 1 - 0.0175  # the eye 1 above the top, looking straight down
    views = SimpleNamespace(
        viewmats=torch.from_numpy(np.stack([VIEWMAT, vm2])).double(),
        Ks=torch.from_numpy(np.stack([K, K])).double(),
        depths=torch.from_numpy(np.stack([d, d + 1])).double() if depth else None,
    )
    meta = {"up_axis": up, **({"table": {"bounds": BOUNDS.tolist(), "top_z": 0.0}} if table else {})}
    return SimpleNamespace(metadata=meta, table_bounds=BOUNDS if table else None, states={"state1": views})


def test_a_loaded_capture_is_split_with_its_cameras_distance():
    cap = _capture()
    parts = capture_background_parts(cap, "state1", [1, 0])
    v = cap.states["state1"]
    # the scale: the median distance of the two eyes (1 and 2 above the origin) to the table top's centre
    scale = (np.hypot(0.025, 1.0) + np.hypot(0.025, 2.0)) / 2
    for got, i in zip(parts, [1, 0], strict=True):
        want = background_parts(v.depths[i].double().numpy(), v.viewmats[i].double().numpy(),
                                v.Ks[i].double().numpy(), BOUNDS, 0.0, scale)  # fmt: skip
        for part in PARTS:
            np.testing.assert_array_equal(got[part], want[part])
    near = parts[1]  # view 0, whose strips lie inside the table's bounds
    assert near["floor"].any() and near["table_top"][:, 22:26].all() and not near["table_top"][:, 30:34].any()


def test_a_capture_without_depth_a_table_or_up_axis_z_has_no_parts():
    assert capture_background_parts(_capture(table=False), "state1", [0]) is None
    assert capture_background_parts(_capture(up="+y"), "state1", [0]) is None
    assert capture_background_parts(_capture(depth=False), "state1", [0]) is None
    assert capture_background_parts(_capture(), "state2", [0]) is None  # a state it does not hold
