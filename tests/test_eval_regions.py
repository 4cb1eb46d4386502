"""train_world.eval.regions: the squared error of a rendering split into outline, object and background pixels."""

from __future__ import annotations

import numpy as np
import pytest

from train_world.eval.metrics import psnr_from_mse
from train_world.eval.regions import REGIONS, RegionErrors, combine, region_masks, seen_by


def _scene(h=20, w=24):
    cls = np.zeros((h, w), np.int64)
    cls[5:12, 4:10] = 1  # a 7x6 object
    cls[5:12, 10:14] = 2  # touching a second one
    return cls


def test_regions_partition_the_image_and_the_outline_is_the_band_around_id_changes():
    cls = _scene()
    m = region_masks(cls, radius=1)
    stack = np.stack([m[r] for r in REGIONS])
    assert (stack.sum(0) == 1).all()  # a partition
    # a pixel is outline iff some pixel of its 3x3 neighbourhood has another id
    pad = np.pad(cls, 1, mode="edge")
    want = np.zeros_like(m["outline"])
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            want |= pad[1 + dy : 1 + dy + cls.shape[0], 1 + dx : 1 + dx + cls.shape[1]] != cls
    assert np.array_equal(m["outline"], want)
    assert m["outline"][5:12, 9:11].all()  # the boundary between the touching objects
    assert np.array_equal(m["objects"], (cls > 0) & ~want)
    assert not region_masks(cls, radius=0)["outline"].any()
    wide = region_masks(cls, radius=2)["outline"]
    assert (wide >= m["outline"]).all() and wide.sum() > m["outline"].sum()


def test_region_errors_put_the_error_where_it_is():
    cls = _scene()
    truth = np.full(cls.shape + (3,), 0.5)
    ours = truth.copy()
    outline = region_masks(cls)["outline"]
    ours[outline] += 0.1  # error on the outline only
    acc = RegionErrors(["box", "can"])
    acc.add(ours, truth, cls)
    r = acc.report()
    assert r["regions"]["outline"]["error_share"] == pytest.approx(1.0)
    assert r["regions"]["objects"]["error_share"] == 0.0 and r["regions"]["objects"]["psnr"] == float("inf")
    assert r["regions"]["outline"]["psnr"] == pytest.approx(psnr_from_mse(0.01))
    assert sum(e["pixel_share"] for e in r["regions"].values()) == pytest.approx(1.0)
    assert r["regions"]["outline"]["pixel_share"] == pytest.approx(outline.mean())
    inner = region_masks(cls)["objects"]
    assert r["per_object"]["box"]["pixels"] == int((inner & (cls == 1)).sum())


def test_combined_reports_equal_one_accumulation():
    rng = np.random.default_rng(0)
    cls = _scene()
    views = [(rng.random(cls.shape + (3,)), rng.random(cls.shape + (3,))) for _ in range(3)]
    one = RegionErrors(["box", "can"])
    parts = []
    for ours, truth in views:
        one.add(ours, truth, cls)
        part = RegionErrors(["box", "can"])
        part.add(ours, truth, cls)
        parts.append(part.report())
    a, b = one.report(), combine(parts)
    for r in REGIONS:
        assert a["regions"][r]["pixels"] == b["regions"][r]["pixels"]
        if r == "unseen":  # no coverage given: empty
            assert a["regions"][r]["psnr"] is None is b["regions"][r]["psnr"]
        else:
            assert a["regions"][r]["psnr"] == pytest.approx(b["regions"][r]["psnr"], rel=1e-12)
    assert a["views"] == b["views"] == 3
    with pytest.raises(ValueError, match="cannot be combined"):
        combine([parts[0], RegionErrors(["box"]).report()])


def test_bad_inputs_are_refused():
    acc = RegionErrors(["box"])
    with pytest.raises(ValueError, match="shapes differ"):
        acc.add(np.zeros((4, 4, 3)), np.zeros((4, 4, 3)), np.zeros((4, 5), int))
    with pytest.raises(ValueError, match=r"id mask \[H, W\]"):
        region_masks(np.zeros((4, 4, 1), int))
    with pytest.raises(ValueError, match="radius"):
        region_masks(np.zeros((4, 4), int), radius=-1)


def _plane_view(R, t, K, H=24, W=32, z0=0.0):
    """World-to-camera [4, 4] and the depth map of the plane z = z0 seen by that camera (0 where missed)."""
    vm = np.eye(4)
    vm[:3, :3], vm[:3, 3] = R, t
    y, x = np.mgrid[0:H, 0:W] + 0.5
    rays = np.stack(
        [(x - K[0, 2]) / K[0, 0], (y - K[1, 2]) / K[1, 1], np.ones_like(x)], -1
    )  # camera frame, z = 1
    centre = -R.T @ t
    dirs = rays @ R  # world directions (R^T r)
    s = (z0 - centre[2]) / dirs[..., 2]
    return vm, np.where(s > 0, s, 0.0)  # depth along the optical axis = s for z-normalised rays


def _look_down(x, y, h):
    R = np.diag([1.0, -1.0, -1.0])  # camera looks along -z, image y along -world y
    return R, -R @ np.array([x, y, h])


def test_seen_by_follows_the_training_views():
    K = np.array([[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]])
    vm, depth = _plane_view(*_look_down(0.0, 0.0, 1.0), K)
    # the same camera sees every pixel of its own view
    same = seen_by(depth, vm, K, depth[None], vm[None], K[None])
    assert same.all()
    # a training camera shifted along x by half the view's footprint sees about half of it
    vm2, depth2 = _plane_view(*_look_down(0.55, 0.0, 1.0), K)
    half = seen_by(depth, vm, K, depth2[None], vm2[None], K[None])
    assert 0.3 < half.mean() < 0.7
    assert half[:, -1].all() and not half[:, 0].any()  # its right side is seen, its left side not
    # something in front of the plane in the training view (its depth much smaller): occluded, not seen
    assert not seen_by(depth, vm, K, 0.5 * depth[None], vm[None], K[None]).any()
    # pixels without depth are never seen, nor are points behind a training camera
    assert not seen_by(np.zeros_like(depth), vm, K, depth[None], vm[None], K[None]).any()
    vm_up, _ = _plane_view(
        np.eye(3), -np.array([0.0, 0.0, 2.0]), K
    )  # at z = 2 looking up, away from the plane
    assert not seen_by(depth, vm, K, np.ones((1, 24, 32)), vm_up[None], K[None]).any()


def test_unseen_background_is_its_own_region():
    cls = _scene()
    seen = np.ones(cls.shape, bool)
    seen[:3] = False  # the top rows: background nobody saw
    m = region_masks(cls, seen=seen)
    assert (np.stack([m[r] for r in REGIONS]).sum(0) == 1).all()
    assert m["unseen"][:3].all() and not m["unseen"][3:].any()
    truth = np.zeros(cls.shape + (3,))
    ours = truth.copy()
    ours[:3] = 0.5
    acc = RegionErrors(["box", "can"])
    acc.add(ours, truth, cls, seen)
    acc.add(truth, truth, cls)  # a view without coverage: its background all counts as seen
    r = acc.report()
    assert r["regions"]["unseen"]["error_share"] == pytest.approx(1.0)
    assert r["views"] == 2 and r["coverage_views"] == 1
    assert r["mean_psnr_seen"] == float("inf")  # the covered view is perfect but for its unseen rows
    acc2 = RegionErrors(["box", "can"])
    ours[5:7] = 0.1  # error on seen pixels too
    acc2.add(ours, truth, cls, seen)
    want = psnr_from_mse(float(np.mean(((ours - truth) ** 2).mean(-1)[~m["unseen"]])))
    assert acc2.report()["mean_psnr_seen"] == pytest.approx(want)
    assert combine([acc2.report(), acc2.report()])["mean_psnr_seen"] == pytest.approx(want)
    assert r["regions"]["unseen"]["pixels"] == 3 * cls.shape[1]
