"""train_world.capture: loading captures (ours and NeRF-Blender), camera conventions, errors naming the file."""

from __future__ import annotations

import json
import os
import shutil

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from PIL import Image  # noqa: E402

from train_world.capture import CaptureError, load_blender, load_capture, load_views  # noqa: E402
from train_world.capture.cameras import (  # noqa: E402
    check_rigid,
    opengl_c2w_to_viewmat,
    viewmat_to_opengl_c2w,
)
from train_world.capture.loader import frame_poses, view_size  # noqa: E402
from train_world.single_state.data import eval_view_size  # noqa: E402
from train_world.synth.generate import GenerateConfig, generate_scene  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "external"
LEGO = SHARED / "nerf_synthetic_lego"
CFG = GenerateConfig(seed=1, width=32, height=24, views=3, test_views=2, test_states=1, progress=False)


@pytest.fixture(scope="session")
def capture_dir(tmp_path_factory) -> Path:
    return generate_scene("three_primitives", tmp_path_factory.mktemp("data") / "cap", CFG)


@pytest.fixture
def broken(capture_dir, tmp_path) -> Path:
    """A private copy of the capture to damage."""
    return Path(shutil.copytree(capture_dir, tmp_path / "cap"))


def _edit_json(path: Path, fn) -> None:
    d = json.loads(path.read_text())
    fn(d)
    path.write_text(json.dumps(d))


# ------------------------------------------------------------------------------------------- loading
def test_load_capture_tensors(capture_dir):
    cap = load_capture(capture_dir)
    meta = json.loads((capture_dir / "scene.json").read_text())
    assert cap.object_ids == (1, 2, 3) and cap.object_names == tuple(o["name"] for o in meta["objects"])
    assert (
        cap.units == "metres" and cap.train_states == ("state1", "state2") and cap.test_states == ("test_0",)
    )
    v = cap.states["state1"]
    assert len(v) == 3 and (v.width, v.height) == (32, 24)
    assert v.images.dtype == torch.float32 and v.images.shape == (3, 24, 32, 3)
    assert 0.0 <= float(v.images.min()) and float(v.images.max()) <= 1.0
    assert v.masks.dtype == torch.uint8 and v.masks.shape == (3, 24, 32)
    assert set(torch.unique(v.masks).tolist()) <= {0, 1, 2, 3} and int(v.masks.max()) > 0
    assert v.depths.dtype == torch.float32 and v.depths.shape == (3, 24, 32) and float(v.depths.max()) > 0.3
    assert v.viewmats.dtype == torch.float32 and v.viewmats.shape == (3, 4, 4)
    assert v.Ks.shape == (3, 3, 3) and float(v.Ks[0, 0, 2]) == 16.0 and float(v.Ks[0, 1, 2]) == 12.0
    assert cap.poses["state1"].dtype == np.float64 and cap.poses["state1"].shape == (3, 4, 4)
    assert len(cap.states["test_0"]) == 2
    img0 = np.asarray(Image.open(capture_dir / "state1" / "images" / "0000.png"), dtype=np.float32) / 255
    np.testing.assert_array_equal(v.images[0].numpy(), img0)
    np.testing.assert_allclose(cap.table_bounds[1, :2] - cap.table_bounds[0, :2], [0.8, 0.6])


def test_load_subset_and_downscale(capture_dir):
    cap = load_capture(capture_dir, states=["state2"], downscale=2, load_depth=False)
    full = load_capture(capture_dir, states=["state2"])
    assert list(cap.states) == ["state2"] and set(cap.poses) == set(full.poses)  # poses of all states
    v, f = cap.states["state2"], full.states["state2"]
    assert v.images.shape == (3, 12, 16, 3) and v.masks.shape == (3, 12, 16) and v.depths is None
    np.testing.assert_allclose(v.Ks[:, :2].numpy(), f.Ks[:, :2].numpy() / 2)
    np.testing.assert_allclose(
        v.images[0].numpy(), f.images[0].numpy().reshape(12, 2, 16, 2, 3).mean((1, 3)), atol=1.01 / 255
    )  # Pillow rounds the box average to uint8


def test_view_size_is_the_size_loaded_at_downscale_one(capture_dir):
    full = load_capture(capture_dir, states=["state2"]).states["state2"]
    assert view_size(capture_dir / "state2" / "transforms.json") == (full.width, full.height) == (32, 24)
    assert eval_view_size(capture_dir, "state2") == (32, 24)
    with pytest.raises(ValueError, match="no state 'state9'"):
        eval_view_size(capture_dir, "state9")


def test_frame_poses_are_the_loaded_poses_without_the_images(capture_dir, tmp_path):
    tj = capture_dir / "state2" / "transforms.json"
    full = load_capture(capture_dir, states=["state2"]).states["state2"]
    np.testing.assert_array_equal(frame_poses(tj), full.c2w_opengl)
    # images are not read: the poses of a copy of transforms.json without its images are the same
    lone = tmp_path / "transforms.json"
    lone.write_text(tj.read_text())
    np.testing.assert_array_equal(frame_poses(lone), full.c2w_opengl)


def test_cameras_are_opencv_world_to_camera(capture_dir):
    cap = load_capture(capture_dir, states=["state1"])
    v = cap.states["state1"]
    c2w = v.c2w_opengl
    vm = v.viewmats.double().numpy()
    np.testing.assert_allclose(
        vm @ c2w @ np.diag([1, -1, -1, 1]), np.broadcast_to(np.eye(4), vm.shape), atol=1e-6
    )
    np.testing.assert_allclose(viewmat_to_opengl_c2w(opengl_c2w_to_viewmat(c2w)), c2w, atol=1e-12)
    # a point 1 m in front of an OpenGL camera (-z) and one above it (+y) in OpenCV camera coordinates
    for i in range(len(v)):
        ahead = c2w[i] @ [0, 0, -1, 1]
        up = c2w[i] @ [0, 0.1, -1, 1]
        pa, pu = vm[i] @ ahead, vm[i] @ up
        np.testing.assert_allclose(pa[:3], [0, 0, 1], atol=1e-6)
        assert pu[1] < 0  # OpenCV y points down
    # the table centre is in front of every camera and projects inside the image
    for i in range(len(v)):
        p = vm[i] @ [0, 0, 0, 1]
        uv = (v.Ks[i].double().numpy() @ p[:3])[:2] / p[2]
        assert p[2] > 0 and 0 <= uv[0] < v.width and 0 <= uv[1] < v.height


def test_relative_transforms(capture_dir):
    cap = load_capture(capture_dir, states=["state1"])
    t = cap.relative_transform("state1", "state2")
    assert t.shape == (3, 4, 4) and t.dtype == np.float64
    p1, p2 = cap.poses["state1"], cap.poses["state2"]
    pt = np.array([0.01, -0.02, 0.03, 1.0])  # a point on each object, in object coordinates
    for k in range(3):
        np.testing.assert_allclose(t[k] @ (p1[k] @ pt), p2[k] @ pt, atol=1e-12)
    np.testing.assert_allclose(
        cap.relative_transform("state2", "state1") @ t, np.broadcast_to(np.eye(4), t.shape), atol=1e-12
    )
    assert not np.allclose(t, np.eye(4))


def test_user_supplied_relative_transforms(broken):
    """Real captures: no absolute object poses, a user-given T_1->2 in scene.json."""
    move = np.eye(4)
    move[:3, 3] = [0.1, 0.0, 0.0]

    def edit(d):
        for state in d["states"].values():
            state.pop("object_poses")
        d["relative_transforms"] = [
            {
                "src": "state1",
                "dst": "state2",
                "transforms": [{"id": i, "transform": move.tolist()} for i in (1, 2, 3)],
            }
        ]

    _edit_json(broken / "scene.json", edit)
    cap = load_capture(broken, states=["state1"])
    assert not cap.poses
    np.testing.assert_allclose(cap.relative_transform("state1", "state2")[2], move)
    np.testing.assert_allclose(cap.relative_transform("state2", "state1")[0], np.linalg.inv(move))
    with pytest.raises(KeyError, match="test_0"):
        cap.relative_transform("state1", "test_0")


@settings(max_examples=50, deadline=None)
@given(
    q=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    t=st.lists(st.floats(-5, 5), min_size=3, max_size=3),
)
def test_camera_conversion_round_trip(q, t):
    w, x, y, z = np.asarray(q) / np.linalg.norm(q)  # quaternion w, x, y, z
    rot = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot, t
    vm = opengl_c2w_to_viewmat(c2w)
    np.testing.assert_allclose(viewmat_to_opengl_c2w(vm), c2w, atol=1e-9)
    # the camera centre maps to the origin; a point ahead (OpenGL -z) gets positive OpenCV depth
    np.testing.assert_allclose(vm @ np.append(t, 1), [0, 0, 0, 1], atol=1e-9)
    assert (vm @ c2w @ [0.0, 0.0, -2.0, 1.0])[2] == pytest.approx(2.0)


def test_check_rigid():
    r = np.eye(4)
    assert check_rigid(r, "x") is not None
    for bad in (np.diag([1.1, 1, 1, 1]), np.diag([1, 1, -1, 1]), np.full((4, 4), np.nan)):
        with pytest.raises(ValueError, match="where"):
            check_rigid(bad, "where")


# ------------------------------------------------------------------------------------------- bad input
def test_missing_image(broken):
    (broken / "state2" / "images" / "0001.png").unlink()
    with pytest.raises(CaptureError, match=r"state2[/\\]images[/\\]0001\.png: image file not found"):
        load_capture(broken)


def test_unreadable_image(broken):
    (broken / "state1" / "images" / "0002.png").write_bytes(b"not a png at all")
    with pytest.raises(CaptureError, match=r"0002\.png: cannot read image"):
        load_capture(broken)
    (broken / "state1" / "images" / "0000.png").write_bytes(b"not a png at all")
    with pytest.raises(CaptureError, match=r"0000\.png: cannot read image"):
        view_size(broken / "state1" / "transforms.json")


def test_image_mask_size_mismatch(broken):
    Image.fromarray(np.zeros((24, 30), np.uint8)).save(broken / "state1" / "masks" / "0000.png")
    with pytest.raises(
        CaptureError, match=r"masks[/\\]0000\.png: mask is 30x24 but its image 0000\.png is 32x24"
    ):
        load_capture(broken)


def test_mask_ids_absent_from_scene_json(broken):
    m = np.zeros((24, 32), np.uint8)
    m[3:6, 4:9] = 7
    Image.fromarray(m).save(broken / "test_0" / "masks" / "0001.png")
    with pytest.raises(CaptureError, match=r"test_0[/\\]masks[/\\]0001\.png: mask contains ids \[7\]"):
        load_capture(broken)


@pytest.mark.parametrize("bad", ["nan", "scale", "shear", "row"])
def test_non_finite_or_non_rigid_camera_pose(broken, bad):
    def edit(d):
        m = np.asarray(d["frames"][1]["transform_matrix"])
        if bad == "nan":
            m[0, 3] = np.nan
        elif bad == "scale":
            m[:3, :3] *= 1.1
        elif bad == "shear":
            m[0, 1] += 0.2
        else:
            m[3] = [0, 0, 1, 1]
        d["frames"][1]["transform_matrix"] = [[float(x) for x in r] for r in m]

    tj = broken / "state1" / "transforms.json"
    d = json.loads(tj.read_text())
    edit(d)
    tj.write_text(json.dumps(d))  # NaN is written as the bare token NaN, which json reads back
    with pytest.raises(
        CaptureError, match=r"state1[/\\]transforms\.json: frames\[1\]\.transform_matrix"
    ) as e:
        load_capture(broken)
    assert ("non-finite" in str(e.value)) == (bad == "nan")
    with pytest.raises(CaptureError) as e2:
        frame_poses(tj)
    assert str(e2.value) == str(e.value)


def test_non_rigid_object_pose(broken):
    def edit(d):
        d["states"]["state2"]["object_poses"][1]["pose"][0][0] = 2.0

    _edit_json(broken / "scene.json", edit)
    with pytest.raises(CaptureError, match=r"scene\.json: states\.state2\.object_poses\[1\].*not a rigid"):
        load_capture(broken)


def test_camera_count_mismatch(broken):
    _edit_json(broken / "scene.json", lambda d: d["states"]["state1"].update(num_views=4))
    with pytest.raises(
        CaptureError, match=r"state1[/\\]transforms\.json: camera count mismatch: 3 frames.*4"
    ):
        load_capture(broken)


def test_missing_mask_in_one_frame(broken):
    _edit_json(broken / "state2" / "transforms.json", lambda d: d["frames"][2].pop("mask_path"))
    with pytest.raises(CaptureError, match=r"frames\[2\]: has no mask_path"):
        load_capture(broken)


def test_missing_or_broken_json(broken):
    (broken / "test_0" / "transforms.json").unlink()
    with pytest.raises(CaptureError, match=r"test_0[/\\]transforms\.json: file not found"):
        load_capture(broken)
    (broken / "scene.json").write_text("{oops")
    with pytest.raises(CaptureError, match=r"scene\.json: invalid JSON"):
        load_capture(broken)


def test_bad_objects_in_scene_json(broken):
    _edit_json(broken / "scene.json", lambda d: d["objects"].append({"id": 2, "name": "dup"}))
    with pytest.raises(CaptureError, match="unique"):
        load_capture(broken)


@pytest.mark.parametrize("version", [99, 0, "1", 1.5, True])
def test_scene_json_of_unknown_format_version_is_refused(broken, version):
    _edit_json(broken / "scene.json", lambda d: d.update(format_version=version))
    with pytest.raises(CaptureError, match="format_version") as e:
        load_capture(broken)
    assert "scene.json" in str(e.value)
    if version == 99:
        assert "upgrade dsg-gym" in str(e.value)


def test_scene_json_of_another_format_is_refused(broken):
    _edit_json(broken / "scene.json", lambda d: d.update(format="something-else"))
    with pytest.raises(CaptureError, match="not a 'dsg-capture' capture"):
        load_capture(broken)


@pytest.mark.parametrize("key", ["file_path", "mask_path", "depth_path"])
@pytest.mark.parametrize("where", ["../../../etc/passwd", "/etc/passwd", "../../outside.png"])
def test_frame_paths_never_leave_the_capture(broken, tmp_path, key, where):
    outside = tmp_path / "outside.png"
    Image.new("RGB", (32, 24)).save(outside)  # a readable file outside the capture must be refused too
    _edit_json(broken / "state1" / "transforms.json", lambda d: d["frames"][0].update({key: where}))
    with pytest.raises(CaptureError, match="leaves the capture folder") as e:
        load_capture(broken)
    assert key in str(e.value) and "frames[0]" in str(e.value)


def test_frame_path_of_the_wrong_type_is_refused(broken):
    _edit_json(broken / "state1" / "transforms.json", lambda d: d["frames"][1].update(file_path=["a.png"]))
    with pytest.raises(CaptureError, match="'file_path' must be a non-empty relative path"):
        load_capture(broken)


def test_distortion_and_size_are_checked(broken):
    _edit_json(broken / "state1" / "transforms.json", lambda d: d.update(k1=0.1))
    with pytest.raises(CaptureError, match="distortion k1"):
        load_views(broken / "state1" / "transforms.json")
    _edit_json(broken / "state1" / "transforms.json", lambda d: d.update(k1=0.0, w=64))
    with pytest.raises(CaptureError, match="w x h = 64 x 24"):
        load_views(broken / "state1" / "transforms.json")


# ------------------------------------------------------------------------------------------- NeRF-Blender
@pytest.fixture(scope="session")
def small_lego(tmp_path_factory) -> Path:
    """Three lego training views downscaled 800 -> 50 px (RGBA kept), with their transforms."""
    if not (LEGO / "transforms_train.json").is_file():
        pytest.skip("shared/external/nerf_synthetic_lego is not available")
    out = tmp_path_factory.mktemp("lego")
    meta = json.loads((LEGO / "transforms_train.json").read_text())
    frames = meta["frames"][:3]
    (out / "train").mkdir()
    for fr in frames:
        name = Path(fr["file_path"]).name
        Image.open(LEGO / "train" / f"{name}.png").resize((50, 50), Image.Resampling.BOX).save(
            out / "train" / f"{name}.png"
        )
    (out / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": meta["camera_angle_x"], "frames": frames})
    )
    return out


def test_load_blender(small_lego):
    tj = small_lego / "transforms_train.json"
    meta = json.loads(tj.read_text())
    white = load_blender(tj)
    black = load_blender(tj, background=(0.0, 0.0, 0.0))
    assert white.images.shape == (3, 50, 50, 3) and white.masks is None and white.depths is None
    assert view_size(tj) == (50, 50)  # file_path without its extension
    f = 0.5 * 50 / np.tan(0.5 * meta["camera_angle_x"])
    np.testing.assert_allclose(white.Ks[0].numpy(), [[f, 0, 25], [0, f, 25], [0, 0, 1]], rtol=1e-6)
    rgba = np.asarray(Image.open(small_lego / "train" / "r_0.png"), dtype=np.float32) / 255
    alpha = rgba[..., 3:]
    np.testing.assert_allclose(white.images[0].numpy(), rgba[..., :3] * alpha + (1 - alpha), atol=1e-6)
    np.testing.assert_allclose(black.images[0].numpy(), rgba[..., :3] * alpha, atol=1e-6)
    assert (white.images[0].numpy()[alpha[..., 0] == 0] == 1.0).all()
    # the lego sits at the world origin: it projects near the image centre, in front, onto opaque pixels
    for i in range(3):
        p = white.viewmats[i].double().numpy() @ [0, 0, 0, 1]
        uv = (white.Ks[i].double().numpy() @ p[:3])[:2] / p[2]
        assert p[2] > 0 and np.all(np.abs(uv - 25) < 8)
        a = np.asarray(Image.open(white.image_paths[i]))[..., 3]
        assert a[int(uv[1]), int(uv[0])] > 0
    half = load_blender(tj, downscale=2, max_views=2)
    assert half.images.shape == (2, 25, 25, 3)
    np.testing.assert_allclose(half.Ks[0, :2].numpy(), white.Ks[0, :2].numpy() / 2, rtol=1e-6)


def test_load_blender_test_subset_as_is():
    tj = LEGO / "transforms_test_subset.json"
    if not tj.is_file():
        pytest.skip("shared/external/nerf_synthetic_lego is not available")
    v = load_blender(tj, downscale=16, max_views=2)
    assert v.images.shape == (2, 50, 50, 3) and v.image_paths[0].name == "r_0.png"
