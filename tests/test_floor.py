"""The floor below a tabletop (train_world.capture.floor): found in structure-from-motion points, and depth maps
put on it only where they should be."""

from __future__ import annotations

import numpy as np
import pytest

from dsg_gym.cameras import look_at
from train_world.capture.floor import MIN_FLOOR_POINTS, fit_floor, floor_depth

BOUNDS = np.array([[-0.4, -0.3, 0.0], [0.4, 0.3, 0.0]])
FLOOR_Z = -0.74
K = np.array([[60.0, 0.0, 32.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]])


def _points(rng, n_floor=300, n_other=150):
    """Table-top points, floor points beyond the table (1 mm noise) and scattered room points."""
    table = np.c_[
        rng.uniform(-0.4, 0.4, (400, 1)), rng.uniform(-0.3, 0.3, (400, 1)), rng.normal(0, 1e-3, 400)
    ]
    xy = rng.uniform(-1.5, 1.5, (n_floor * 3, 2))
    xy = xy[(np.abs(xy[:, 0]) > 0.5) | (np.abs(xy[:, 1]) > 0.4)][:n_floor]
    floor = np.c_[xy, FLOOR_Z + rng.normal(0, 1e-3, len(xy))]
    other = np.c_[rng.uniform(-1.5, 1.5, (n_other, 2)), rng.uniform(-0.7, 0.5, n_other)]
    return np.concatenate([table, floor, other])


def test_the_floor_is_found_below_the_table_and_only_when_the_points_show_one():
    rng = np.random.default_rng(0)
    fl = fit_floor(_points(rng), BOUNDS, ref=1.0)
    assert fl is not None and fl.z == pytest.approx(FLOOR_Z, abs=1e-3)
    assert fl.points >= 250 and fl.candidates > fl.points  # the scattered points are not in its band
    assert np.all(fl.lo < -1.3) and np.all(fl.hi > 1.3)  # the extent of its points
    assert fl.to_dict()["z"] == pytest.approx(fl.z, abs=1e-6)
    # the same scene in other units: the bands scale with the reference length
    scaled = fit_floor(_points(np.random.default_rng(0)) * 3.0, BOUNDS * 3.0, ref=3.0)
    assert (
        scaled is not None and scaled.z == pytest.approx(3 * FLOOR_Z, abs=3e-3) and scaled.points == fl.points
    )
    # too few floor points, or scattered points only: no floor
    assert fit_floor(_points(rng, n_floor=MIN_FLOOR_POINTS - 5, n_other=0), BOUNDS, 1.0) is None
    assert fit_floor(_points(rng, n_floor=0, n_other=500), BOUNDS, 1.0) is None
    # points on the table top never make a floor, however many
    assert fit_floor(_points(rng, n_floor=0, n_other=0), BOUNDS, 1.0) is None
    with pytest.raises(ValueError, match="reference length"):
        fit_floor(_points(rng), BOUNDS, ref=0.0)


def _true_depth(viewmat, H=64, W=64):
    """Camera-z depth of the table top (z = 0 inside BOUNDS) and the floor below, seen by ``viewmat``."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    c = -R.T @ t
    v, u = np.mgrid[0:H, 0:W] + 0.5
    ray = np.stack([(u - 32) / 60, (v - 32) / 60, np.ones_like(u)], -1) @ R
    z_table = -c[2] / ray[..., 2]
    p = c[:2] + ray[..., :2] * z_table[..., None]
    on_table = (z_table > 0) & (np.abs(p[..., 0]) <= 0.4) & (np.abs(p[..., 1]) <= 0.3)
    z_floor = (FLOOR_Z - c[2]) / ray[..., 2]
    q = c[:2] + ray[..., :2] * z_floor[..., None]
    depth = np.where(on_table, z_table, np.where(z_floor > 0, z_floor, 0.0))  # 0: above the horizon
    return depth, on_table, q


def test_floor_depth_moves_only_background_beyond_the_table_that_roughly_agrees():
    fl = fit_floor(_points(np.random.default_rng(0)), BOUNDS, ref=1.0)
    vm = look_at([0.9, -0.7, 0.5], [0.0, 0.0, -0.2])
    true, on_table, hit = _true_depth(vm)
    floor_px = ~on_table & (true > 0) & ((hit >= fl.lo) & (hit <= fl.hi)).all(-1)  # inside the floor's extent
    assert floor_px.mean() > 0.2 and on_table.mean() > 0.1  # the view sees both
    rng = np.random.default_rng(1)
    # a depth fit's error: a few per cent on the table top, up to 15 % beyond it, and a band of floor 2x too far
    est = true * (
        1 + np.where(on_table, rng.uniform(-0.03, 0.03, true.shape), rng.uniform(-0.15, 0.15, true.shape))
    )
    est[20:24] = np.where(on_table[20:24], est[20:24], 2.0 * true[20:24])
    background = np.ones_like(true, bool)
    background[40:44, 40:44] = False  # an object's pixels: never moved
    out, moved = floor_depth(est, background, vm, K, fl, tolerance=0.3)
    assert not moved[on_table].any() and np.array_equal(out[on_table], est[on_table])
    assert not moved[~background].any() and not moved[20:24].any()
    want = floor_px & background
    want[20:24] = False
    assert moved[want].mean() > 0.97
    assert np.allclose(out[moved], true[moved], rtol=3e-3)  # on the fitted floor (1 mm from the truth)
    # off means off; the input is not modified
    same, none = floor_depth(est, background, vm, K, fl, tolerance=0.0)
    assert not none.any() and np.array_equal(same, est)
    # no depth stays no depth
    est[:5] = 0.0
    out, moved = floor_depth(est, background, vm, K, fl, tolerance=0.3)
    assert not moved[:5].any() and np.all(out[:5] == 0)
