"""Shrinking a capture's views: images area-averaged, masks by majority, depth nearest, intrinsics scaled."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from train_world.capture.files import area_resize, label_resize
from train_world.capture.loader import load_capture
from train_world.capture.shrink import shrink_capture, shrunk_size
from train_world.synth.generate import GenerateConfig, generate_scene

STATES = ("state1", "state2")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("shrink") / "cap"
    cfg = GenerateConfig(
        width=32, height=24, views=2, test_views=1, test_states=1, supersample=1, progress=False
    )
    return generate_scene("two_blocks", out, cfg)


def test_shrunk_size_keeps_the_aspect_and_never_grows():
    assert shrunk_size(4032, 3024, 256) == (256, 192)
    assert shrunk_size(100, 50, 256) == (100, 50)
    assert shrunk_size(30, 20, 16) == (16, 11)
    assert shrunk_size(1000, 1, 10) == (10, 1)
    with pytest.raises(ValueError, match="at least one pixel"):
        shrunk_size(10, 10, 0)


def test_halving_matches_the_loaders_downscale(capture, tmp_path):
    small = tmp_path / "small"
    shutil.copytree(capture, small)
    assert shrink_capture(small, STATES, 16) == (16, 12)
    for s in STATES:
        half = load_capture(capture, downscale=2, states=[s])
        shrunk = load_capture(small, states=[s])
        a, b = half.states[s], shrunk.states[s]
        assert (b.width, b.height) == (a.width, a.height) == (16, 12)
        np.testing.assert_allclose(b.Ks.numpy(), a.Ks.numpy(), rtol=1e-6)
        assert (b.images - a.images).abs().max() <= 0.5 / 255 + 1e-6  # the same means, rounded to 8 bits
        np.testing.assert_array_equal(b.masks.numpy(), a.masks.numpy())
        np.testing.assert_array_equal(b.depths.numpy(), a.depths.numpy())
        np.testing.assert_array_equal(b.c2w_opengl, a.c2w_opengl)
    # the test states were not asked for: untouched
    t = json.loads((small / "test_0" / "transforms.json").read_text())
    assert (t["w"], t["h"]) == (32, 24)


def test_area_resize_is_the_block_mean_without_rounding():
    a = np.random.default_rng(0).integers(0, 256, (12, 16, 3), dtype=np.uint8)
    block = a.astype(np.float64).reshape(6, 2, 8, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(area_resize(a, (8, 6)), block, atol=1e-4)  # no half-level bias
    assert area_resize(a, (16, 12)).dtype == np.float32


def test_label_resize_takes_the_majority_of_each_block():
    ids = np.array(
        [
            [1, 1, 0, 0],
            [1, 0, 0, 2],
            [3, 3, 2, 2],
            [0, 3, 0, 2],
        ],
        dtype=np.uint8,
    )
    # the bottom-right pixel of each block, which Pillow's nearest pixel takes, would give [[0, 2], [3, 2]]
    np.testing.assert_array_equal(label_resize(ids, (2, 2)), [[1, 0], [3, 2]])
    tie = np.array([[2, 2, 2, 2], [1, 1, 1, 1]], np.uint8)  # two blocks split evenly between ids 1 and 2
    np.testing.assert_array_equal(label_resize(tie, (2, 1)), [[1, 2]])  # the lower at x + y even, else higher
    up = np.kron(ids, np.ones((3, 3), np.uint8))  # each id a 3x3 block: shrinking gives the ids back
    np.testing.assert_array_equal(label_resize(up, (4, 4)), ids)
    odd = label_resize(up, (5, 5))  # not an integer factor: the id under each pixel's centre
    assert odd.shape == (5, 5) and set(np.unique(odd)) <= {0, 1, 2, 3}


def test_label_resize_keeps_an_objects_area_where_outlines_split_blocks():
    # discs sampled at 2x the size, shrunk back, against the same discs sampled at the small size's pixel
    # centres (what a mask of that size is): with ties to the background they would come out ~3 % smaller
    rng = np.random.default_rng(0)
    got, want = 0, 0
    for _ in range(40):
        cx, cy, r = rng.uniform(20, 44, 2).tolist() + [rng.uniform(6, 14)]
        fine = np.indices((128, 128))[::-1] * 0.5 + 0.25  # fine pixel centres in small-image pixels
        small = np.indices((64, 64))[::-1] + 0.5
        disc = lambda p: ((p[0] - cx) ** 2 + (p[1] - cy) ** 2 < r * r).astype(np.uint8)  # noqa: E731
        got += int(label_resize(disc(fine), (64, 64)).sum())
        want += int(disc(small).sum())
    assert abs(got / want - 1) < 0.005


def test_the_loaders_downscale_is_the_block_mean(capture):
    full = load_capture(capture, states=["state1"]).states["state1"].images.numpy().astype(np.float64)
    half = load_capture(capture, states=["state1"], downscale=2).states["state1"].images.numpy()
    v, h, w, _ = full.shape
    np.testing.assert_allclose(half, full.reshape(v, h // 2, 2, w // 2, 2, 3).mean(axis=(2, 4)), atol=1e-6)


def test_odd_factors_scale_each_axis_by_its_own_ratio(capture, tmp_path):
    small = tmp_path / "small"
    shutil.copytree(capture, small)
    before = json.loads((capture / "state1" / "transforms.json").read_text())
    assert shrink_capture(small, STATES, 20) == (20, 15)
    after = json.loads((small / "state1" / "transforms.json").read_text())
    assert after["fl_x"] == pytest.approx(before["fl_x"] * 20 / 32) and after["cx"] == pytest.approx(10.0)
    assert after["fl_y"] == pytest.approx(before["fl_y"] * 15 / 24) and after["cy"] == pytest.approx(7.5)
    assert after["camera_angle_x"] == pytest.approx(before["camera_angle_x"], rel=1e-12)
    frame = after["frames"][1]
    with Image.open(small / "state1" / frame["file_path"]) as im:
        assert im.size == (20, 15) and im.mode == "RGB"
    with Image.open(small / "state1" / frame["mask_path"]) as im:
        ids = np.asarray(im)
    with Image.open(capture / "state1" / frame["mask_path"]) as im:
        truth_ids = np.asarray(im)
    assert ids.shape == (15, 20) and set(np.unique(ids)) <= set(np.unique(truth_ids))  # ids never blended
    with Image.open(small / "state1" / frame["depth_path"]) as im:
        depth = np.asarray(im)
    with Image.open(capture / "state1" / frame["depth_path"]) as im:
        truth_depth = np.asarray(im)
    assert depth.dtype == np.uint16 and set(np.unique(depth)) <= set(np.unique(truth_depth))


def test_small_views_and_mixed_sizes_are_left_alone(capture, tmp_path):
    small = tmp_path / "small"
    shutil.copytree(capture, small)
    before = {p: p.read_bytes() for p in small.rglob("*") if p.is_file()}
    assert shrink_capture(small, STATES, 32) is None
    assert {p: p.read_bytes() for p in small.rglob("*") if p.is_file()} == before
    doc = json.loads((small / "state2" / "transforms.json").read_text())
    doc["w"] = 30
    (small / "state2" / "transforms.json").write_text(json.dumps(doc))
    before = {p: p.read_bytes() for p in small.rglob("*") if p.is_file()}
    with pytest.raises(ValueError, match="differ in size"):
        shrink_capture(small, STATES, 16)
    assert {p: p.read_bytes() for p in small.rglob("*") if p.is_file()} == before


def test_photos_for_the_motions_are_area_averaged_and_keep_their_ids():
    pytest.importorskip("pycolmap")
    from train_world.capture.photo_capture import SILHOUETTE_SIZE, _photo_view

    n = 2 * SILHOUETTE_SIZE
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (n, n, 3), dtype=np.uint8)
    ids = np.zeros((n, n), np.uint8)
    ids[101:603, 200:901] = 2  # odd start: blocks on the outline are split between two ids
    K = np.array([[900.0, 0.0, n / 2], [0.0, 900.0, n / 2], [0.0, 0.0, 1.0]])
    v = _photo_view(rgb, ids, K, np.eye(4))
    means = rgb.reshape(SILHOUETTE_SIZE, 2, SILHOUETTE_SIZE, 2, 3).astype(np.float64).mean(axis=(1, 3))
    assert v.rgb.dtype == np.uint8 and v.rgb.shape == (SILHOUETTE_SIZE, SILHOUETTE_SIZE, 3)
    assert np.abs(v.rgb - means).max() <= 0.5 + 1e-6 and abs(np.mean(v.rgb - means)) < 0.01  # unbiased
    np.testing.assert_array_equal(v.ids, label_resize(ids, (SILHOUETTE_SIZE, SILHOUETTE_SIZE)))
    np.testing.assert_allclose(v.K[:2], K[:2] / 2)
