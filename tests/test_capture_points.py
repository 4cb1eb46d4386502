"""A capture's sparse points (train_world.capture.points): the PLY written and read back, other PLY layouts,
bad files and entries as one-line errors, colours from the views."""

from __future__ import annotations

import numpy as np
import pytest

from train_world.capture.files import CaptureError
from train_world.capture.points import capture_points, point_colours, read_points_ply, write_points_ply


def test_written_points_read_back(tmp_path):
    rng = np.random.default_rng(0)
    xyz = rng.normal(size=(50, 3))
    rgb = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    write_points_ply(tmp_path / "p.ply", xyz, rgb)
    got, col = read_points_ply(tmp_path / "p.ply")
    np.testing.assert_allclose(got, xyz.astype(np.float32), rtol=0, atol=0)
    np.testing.assert_allclose(col, rgb / 255.0, atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["p.ply"]  # no temporary left
    with pytest.raises(ValueError, match="finite xyz"):
        write_points_ply(tmp_path / "q.ply", [[0, 0, np.nan]], np.zeros((1, 3), np.uint8))


def test_other_layouts_read(tmp_path):
    ascii_ply = "\n".join(
        ["ply", "format ascii 1.0", "element vertex 2", "property double x", "property double y",
         "property double z", "property float nx", "end_header", "1 2 3 0", "4 5 6 1", ""]
    )  # fmt: skip
    (tmp_path / "a.ply").write_text(ascii_ply)
    xyz, rgb = read_points_ply(tmp_path / "a.ply")
    np.testing.assert_array_equal(xyz, [[1, 2, 3], [4, 5, 6]])
    assert np.all(rgb == 0.5)  # no colours: grey
    rec = np.array([(1.0, 2.0, 3.0, 255, 0, 0, 7)], dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"),
                   ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("i", ">i4")])  # fmt: skip
    head = "\n".join(
        ["ply", "format binary_big_endian 1.0", "element vertex 1", "property double x", "property double y",
         "property double z", "property uchar red", "property uchar green", "property uchar blue",
         "property int i", "element face 0", "property list uchar int vertex_indices", "end_header", ""]
    )  # fmt: skip
    (tmp_path / "b.ply").write_bytes(head.encode() + rec.tobytes())
    xyz, rgb = read_points_ply(tmp_path / "b.ply")
    np.testing.assert_array_equal(xyz, [[1, 2, 3]])
    np.testing.assert_allclose(rgb, [[1, 0, 0]])


@pytest.mark.parametrize(
    "content, needle",
    [
        (b"hello", "not a PLY file"),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n",
            "x, y, z",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n\x00\x00",
            "the file is shorter",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n1 nan 2\n",
            "non-finite",
        ),  # fmt: skip
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nend_header\n",
            "not a scalar",
        ),
    ],
)
def test_bad_files_are_one_line_errors(tmp_path, content, needle):
    (tmp_path / "p.ply").write_bytes(content)
    with pytest.raises(CaptureError) as e:
        read_points_ply(tmp_path / "p.ply")
    assert needle in str(e.value) and "\n" not in str(e.value) and "p.ply" in str(e.value)


def test_scene_entries(tmp_path):
    assert capture_points(tmp_path, {}) is None
    write_points_ply(tmp_path / "pts.ply", np.zeros((3, 3)), np.zeros((3, 3), np.uint8))
    assert len(capture_points(tmp_path, {"points": {"path": "pts.ply"}})[0]) == 3
    with pytest.raises(CaptureError, match="leaves the capture folder"):
        capture_points(tmp_path / "sub", {"points": {"path": "../pts.ply"}})
    with pytest.raises(CaptureError, match="'points' must be an object"):
        capture_points(tmp_path, {"points": "pts.ply"})
    with pytest.raises(CaptureError, match="cannot read the point cloud"):
        capture_points(tmp_path, {"points": {"path": "missing.ply"}})


def test_colours_are_the_median_over_the_views_that_see_a_point():
    K = np.array([[10.0, 0, 5], [0, 10.0, 5], [0, 0, 1]])
    w2c = np.eye(4)
    imgs = [np.full((10, 10, 3), v, np.uint8) for v in (10, 200, 30)]
    pts = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [10.0, 0.0, 1.0]])  # seen, behind, outside
    col = point_colours(pts, imgs, [w2c] * 3, K)
    np.testing.assert_array_equal(col, [[30, 30, 30], [128, 128, 128], [128, 128, 128]])
