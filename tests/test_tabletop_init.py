"""Initial points of a tabletop capture without depth but with object masks (train_world.single_state.init.
tabletop_points, what training on a dsg-capture capture starts from): points on the table top coloured from the
pixels that see it, points inside each object's visual hull with that object's id, and the trainer using them."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from _captures import tiny_capture

from dsg_gym.cameras import camera_centres
from train_world.single_state.data import load_training_data
from train_world.single_state.init import (
    ROOM_DEPTHS,
    ROOM_SHARE,
    TABLE_SHARE,
    _pixels,
    object_hull_points,
    points_from_depth,
    room_points,
    table_points,
    tabletop_points,
)
from train_world.single_state.presets import TrainConfig, get_preset
from train_world.single_state.trainer import Trainer


@pytest.fixture(scope="module")
def with_depth(tmp_path_factory):
    cap = tiny_capture(tmp_path_factory.mktemp("tabletop"), "four_mixed", size=64, views=16)
    cfg = TrainConfig(preset=get_preset("quick"), state="state1", holdout_every=0)
    d = load_training_data(cap, cfg)
    assert d.depths is not None and d.classes is not None and d.table_bounds is not None
    scene = json.loads((cap / "scene.json").read_text())
    centres = np.array([p["pose"] for p in scene["states"]["state1"]["object_poses"]])[:, :3, 3]
    return d, cfg, centres


@pytest.fixture(scope="module")
def data(with_depth):
    d, cfg, centres = with_depth
    return dataclasses.replace(d, depths=None), cfg, centres  # as a capture from photos: no depth


def test_points_from_depth_land_on_their_pixels(with_depth):
    d = with_depth[0]
    one = slice(0, 1)
    P, cols, ids = points_from_depth(
        d.images[one],
        d.depths[one],
        d.viewmats[one],
        d.Ks[one],
        d.classes[one],
        10**6,
        np.random.default_rng(0),
    )
    depth, image, classes = d.depths[0].numpy(), d.images[0].numpy(), d.classes[0].numpy()
    assert len(P) == int((depth > 0).sum())  # every pixel with depth, none without
    u, v, ok = _pixels(P, d.viewmats[0], d.Ks[0], d.width, d.height)
    assert ok.all()
    z = P @ d.viewmats[0, :3, :3].double().numpy().T + d.viewmats[0, :3, 3].double().numpy()
    np.testing.assert_allclose(z[:, 2], depth[v, u], rtol=1e-6)
    np.testing.assert_array_equal(cols, image[v, u].astype(np.float64))
    np.testing.assert_array_equal(ids, classes[v, u])
    assert len(np.unique(v * d.width + u)) == len(P)  # one point per pixel
    sub = points_from_depth(d.images, d.depths, d.viewmats, d.Ks, None, 500, np.random.default_rng(1))
    assert len(sub[0]) == 500 and not sub[2].any()  # the budget holds; no masks: id 0


def _box(d):
    lo, hi = d.table_bounds.copy()
    hi[2] = lo[2] + 0.5 * max(hi[0] - lo[0], hi[1] - lo[1])
    return np.stack([lo, hi])


def test_table_points_lie_on_the_top_and_take_the_colours_of_their_pixels(data):
    d, _, _ = data
    box = _box(d)
    P, cols, ids = table_points(box, 4000, d.images, d.classes, d.viewmats, d.Ks, np.random.default_rng(0))
    assert 0.5 * 4000 < len(P) <= 4000 and not ids.any()
    assert np.all(P[:, 2] == box[0, 2])
    assert np.all((P[:, :2] >= box[0, :2]) & (P[:, :2] <= box[1, :2]))
    assert np.all((cols >= 0) & (cols <= 1))
    # a point's colour follows the pixel it falls in (a mean over views, so not equal): strongly correlated
    u, v, ok = _pixels(P, d.viewmats[0], d.Ks[0], d.width, d.height)
    ok[ok] &= d.classes[0].numpy()[v[ok], u[ok]] == 0
    px = d.images[0].numpy()[v[ok], u[ok]]
    assert ok.sum() > 500
    for ch in range(3):
        assert np.corrcoef(px[:, ch], cols[ok, ch])[0, 1] > 0.6


def test_hull_points_sit_in_their_object(data):
    d, _, centres = data
    box = _box(d)
    P, cols, ids = object_hull_points(
        box, 60_000, d.images, d.classes, d.viewmats, d.Ks, np.random.default_rng(1)
    )
    assert set(np.unique(ids)) == set(range(1, len(centres) + 1))  # every object, never the background
    dist = np.linalg.norm(P[:, None, :] - centres[None], axis=-1)  # [P, K]
    assert np.all(dist.argmin(axis=1) + 1 == ids)  # nearest to its own object's origin
    assert np.all(dist[np.arange(len(P)), ids - 1] < 0.12)
    assert np.all((cols >= 0) & (cols <= 1)) and cols.std() > 0.05


def test_room_points_lie_on_background_rays_out_to_the_room(data):
    d, _, _ = data
    box = _box(d)
    one = (d.images[:1], d.classes[:1], d.viewmats[:1], d.Ks[:1])  # every point from view 0
    P, cols, ids = room_points(box, 4000, *one, np.random.default_rng(4))
    bg = float((d.classes[0] == 0).double().mean())
    assert 0.8 * bg * 4000 < len(P) <= 4000 and not ids.any()  # object pixels' draws dropped
    u, v, ok = _pixels(P, d.viewmats[0], d.Ks[0], d.width, d.height)
    assert ok.all() and np.all(d.classes[0].numpy()[v, u] == 0)
    assert np.allclose(cols, d.images[0].numpy()[v, u])  # coloured like the pixel it was drawn on
    vm = d.viewmats[0].double().numpy()
    z = (P @ vm[:3, :3].T + vm[:3, 3])[:, 2]
    centre = np.array([box[:, 0].mean(), box[:, 1].mean(), box[0, 2]])
    dist = np.linalg.norm(camera_centres(d.viewmats[:1].numpy())[0] - centre)
    near, far = ROOM_DEPTHS[0] * dist, ROOM_DEPTHS[1] * dist
    assert np.all((z >= near * (1 - 1e-9)) & (z <= far * (1 + 1e-9)))
    inv = (1 / z - 1 / far) / (1 / near - 1 / far)  # uniform in inverse depth: uniform on [0, 1]
    assert abs(inv.mean() - 0.5) < 0.03 and abs(np.median(inv) - 0.5) < 0.04
    inside = np.all((P >= box[0]) & (P <= box[1]), axis=1)
    assert (~inside).mean() > 0.3  # many lie beyond the table box (the room)
    again = room_points(box, 4000, *one, np.random.default_rng(4))
    assert all(np.array_equal(x, y) for x, y in zip((P, cols, ids), again))
    # without masks every draw is kept
    assert (
        len(room_points(box, 500, d.images[:1], None, d.viewmats[:1], d.Ks[:1], np.random.default_rng(5))[0])
        == 500
    )


def test_tabletop_points_are_deterministic_and_within_the_budget(data):
    d, _, _ = data
    a = tabletop_points(_box(d), 3000, d.images, d.classes, d.viewmats, d.Ks, np.random.default_rng(2))
    b = tabletop_points(_box(d), 3000, d.images, d.classes, d.viewmats, d.Ks, np.random.default_rng(2))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    P, _, ids = a
    assert len(P) == 3000 and 0.5 * TABLE_SHARE * 3000 < (P[:, 2] == 0).sum() <= TABLE_SHARE * 3000
    assert ids.max() >= 1
    lo, hi = _box(d)
    outside = ~np.all((P >= lo - 1e-9) & (P <= hi + 1e-9), axis=1)  # only room points leave the box
    assert 0.1 * ROOM_SHARE * 3000 < outside.sum() < ROOM_SHARE * 3000


def test_training_without_depth_starts_on_the_table_and_in_the_objects(data):
    d, cfg, _ = data
    t = Trainer(d, cfg)
    means = t.field.means.detach().double().numpy()
    assert len(means) == t.preset.num_init_points  # random points in the table box fill the budget
    assert (means[:, 2] == 0.0).mean() > 0.5 * TABLE_SHARE
    # without masks: random points in the table box, as before
    bare = Trainer(dataclasses.replace(d, classes=None), cfg)
    m2 = bare.field.means.detach().double().numpy()
    assert len(m2) == t.preset.num_init_points and (m2[:, 2] == 0.0).sum() == 0


def test_no_object_in_any_view_gives_no_hull_points(data):
    d, _, _ = data
    P, cols, ids = object_hull_points(
        _box(d), 1000, d.images, d.classes * 0, d.viewmats, d.Ks, np.random.default_rng(3)
    )
    assert P.shape == (0, 3) and cols.shape == (0, 3) and ids.shape == (0,)


def test_depth_with_holes_starts_with_points_in_proportion(tmp_path_factory):
    cap = tiny_capture(tmp_path_factory.mktemp("holes"), "four_mixed", size=64, views=16)
    cfg = TrainConfig(preset=get_preset("quick"), state="state1", holdout_every=0)
    d = load_training_data(cap, cfg)
    n = get_preset("quick").num_init_points
    full = Trainer(d, cfg).field.means.detach().double().numpy()
    assert len(full) == n  # a complete depth map: the whole budget, as always
    depths = d.depths.clone()
    depths[:, :, : depths.shape[2] // 2] = 0.0  # stereo-like holes: the left half of every view
    holes = dataclasses.replace(d, depths=depths)
    cover = float((depths > 0).double().mean())
    means = Trainer(holes, cfg).field.means.detach().double().numpy()
    assert len(means) == round(cover * n) < n
    # every point comes from a pixel that has depth: in its view's right half, on the surface seen there
    vm, K = holes.viewmats.double().numpy(), holes.Ks.double().numpy()
    seen_right = np.zeros(len(means), bool)
    for i in range(len(vm)):
        cam = means @ vm[i][:3, :3].T + vm[i][:3, 3]
        u = K[i][0, 0] * cam[:, 0] / cam[:, 2] + K[i][0, 2]
        v = K[i][1, 1] * cam[:, 1] / cam[:, 2] + K[i][1, 2]
        ok = (cam[:, 2] > 0) & (u >= 32) & (u < 64) & (v >= 0) & (v < 64)
        ui, vi = np.clip(u.astype(int), 0, 63), np.clip(v.astype(int), 0, 63)
        z = depths[i].numpy()[vi, ui]
        seen_right |= ok & (np.abs(z - cam[:, 2]) < 1e-3 + 0.01 * z)
    assert seen_right.mean() > 0.99
