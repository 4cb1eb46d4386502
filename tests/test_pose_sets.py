"""A capture state in estimated camera poses (undistorted), or restricted to named views; and the benchmark
that trains a world on each pose set of a real capture."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import json  # noqa: E402
import math  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

from dsg_gym.cameras import look_at  # noqa: E402
from train_world.capture import CaptureError, load_capture  # noqa: E402
from train_world.capture.cameras import GL_TO_CV  # noqa: E402
from train_world.capture.format import (  # noqa: E402
    FORMAT_NAME,
    FORMAT_VERSION,
    atomic_write_json,
    encode_png,
    matrix_to_list,
    write_state_views,
)
from train_world.capture.points import read_points_ply, write_points_ply  # noqa: E402
from train_world.capture.pose_sets import subset_capture, write_estimated_capture  # noqa: E402

LLFF = Path(__file__).resolve().parents[2] / "shared" / "external" / "ethiopian_head_llff"
W, H, F, N = 40, 30, 36.0, 8


def _cameras(n: int, z: float) -> list[np.ndarray]:
    """OpenGL camera-to-world ``[4,4]`` of ``n`` cameras on a circle at height ``z`` looking at the origin."""
    out = []
    for a in np.linspace(0, 2 * np.pi, n, endpoint=False):
        eye = np.array([3 * np.cos(a), 3 * np.sin(a), z])
        out.append(np.linalg.inv(look_at(eye, np.zeros(3))) @ GL_TO_CV)
    return out


def _pose(angle: float, t) -> np.ndarray:
    p = np.eye(4)
    p[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    p[:3, 3] = t
    return p


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """Two states of ``N`` ``W x H`` views (smooth colour ramps, two objects in the masks) and sparse points,
    made by hand."""
    root = tmp_path_factory.mktemp("posesets") / "cap"
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:H, 0:W]
    poses = {"state1": [_pose(0.3, [0.2, -0.1, 0.1]), _pose(-1.0, [-0.3, 0.2, 0.05])],
             "state2": [_pose(0.5, [0.1, -0.1, 0.1]), _pose(-1.0, [-0.3, 0.2, 0.05])]}  # fmt: skip
    for s, z in (("state1", 1.0), ("state2", 1.5)):
        images, masks = [], []
        for _ in range(N):
            a, b, c = rng.uniform(0.5, 4.0, 3)
            rgb = np.stack([xx * a, yy * b, (xx + yy) * c], -1) % 256
            images.append(encode_png(rgb.astype(np.uint8)))
            ids = np.zeros((H, W), np.uint8)
            ids[5:15, 4 + rng.integers(0, 10) : 20] = 1
            ids[18:27, 22:35] = 2
            masks.append(encode_png(ids))
        write_state_views(root / s, _cameras(N, z), W, H, F, F, W / 2, H / 2, images, masks)
    atomic_write_json(
        root / "scene.json",
        {"format": FORMAT_NAME, "format_version": FORMAT_VERSION, "name": "posesets", "units": "metres",
         "objects": [{"id": 1, "name": "box"}, {"id": 2, "name": "ball"}],
         "table": {"bounds": [[-1, -1, 0], [1, 1, 0.1]]},
         "states": {s: {"split": "train", "num_views": N,
                        "object_poses": [{"id": i + 1, "pose": matrix_to_list(p)} for i, p in enumerate(ps)]}
                    for s, ps in poses.items()},
         "relative_transforms": [], "points": {"path": "points3d.ply"}},
    )  # fmt: skip
    write_points_ply(
        root / "points3d.ply", rng.uniform(-1, 1, (20, 3)), rng.integers(0, 256, (20, 3), np.uint8)
    )
    return root


def _similarity(c2w_gl: list[np.ndarray], s: float) -> dict[str, np.ndarray]:
    """The cameras in another frame: ``x' = s R x + t``; OpenCV world-to-camera per stem."""
    rot, t = _pose(0.7, [0.0, 0.0, 0.0])[:3, :3], np.array([1.0, -2.0, 0.5])
    out = {}
    for i, m in enumerate(c2w_gl):
        c = m @ GL_TO_CV
        e = np.eye(4)
        e[:3, :3] = rot @ c[:3, :3]
        e[:3, 3] = s * rot @ c[:3, 3] + t
        out[f"{i:04d}"] = np.linalg.inv(e)
    return out


def test_subset_keeps_the_named_views_in_their_order(capture, tmp_path):
    src = load_capture(capture, ["state1"]).states["state1"]
    stems = ["0005", "0001", "0003"]
    out = subset_capture(capture, tmp_path / "sub", stems)
    cap = load_capture(out)
    assert list(cap.states) == ["state1"] and cap.object_names == ("box", "ball")
    v = cap.states["state1"]
    assert [p.stem for p in v.image_paths] == stems
    idx = [5, 1, 3]
    assert np.array_equal(v.images.numpy(), src.images[idx].numpy())
    assert np.array_equal(v.masks.numpy(), src.masks[idx].numpy())
    assert np.array_equal(v.c2w_opengl, src.c2w_opengl[idx])
    assert np.array_equal(cap.poses["state1"], load_capture(capture, []).poses["state1"])
    assert (out / "state1" / "images" / "0005.png").read_bytes() == (
        capture / "state1" / "images" / "0005.png"
    ).read_bytes()
    with pytest.raises(CaptureError, match="no view '0042'"):
        subset_capture(capture, tmp_path / "bad", ["0001", "0042"])
    with pytest.raises(FileExistsError):
        subset_capture(capture, out, ["0001"])
    assert (out / "points3d.ply").read_bytes() == (capture / "points3d.ply").read_bytes()
    assert not (tmp_path / "bad").exists()


def test_estimated_poses_without_distortion_keep_the_pixels(capture, tmp_path):
    src_cap = load_capture(capture, ["state1"])
    src = src_cap.states["state1"]
    s = 0.5
    w2c = _similarity(list(src.c2w_opengl), s)
    for unregistered in ("0002", "0006"):
        del w2c[unregistered]
    out = write_estimated_capture(
        capture, "state1", tmp_path / "est", w2c, "SIMPLE_RADIAL", (F, W / 2, H / 2, 0.0)
    )
    cap = load_capture(out)
    v = cap.states["state1"]
    keep = [0, 1, 3, 4, 5, 7]
    assert [p.stem for p in v.image_paths] == [f"{i:04d}" for i in keep]
    assert np.array_equal(v.images.numpy(), src.images[keep].numpy())  # pinhole camera: no resampling
    assert np.array_equal(v.masks.numpy(), src.masks[keep].numpy())
    assert np.allclose(v.Ks.numpy(), src.Ks[keep].numpy())
    assert np.allclose(v.viewmats.numpy(), np.stack([w2c[f"{i:04d}"] for i in keep]), atol=1e-5)
    # each object sits where the new cameras see it: same direction, distance scaled by s
    for j, i in enumerate(keep):
        for k in range(2):
            old = src.viewmats[i].double().numpy() @ src_cap.poses["state1"][k]
            new = v.viewmats[j].double().numpy() @ cap.poses["state1"][k]
            assert np.allclose(new[:3, :3], old[:3, :3], atol=1e-5)
            assert np.allclose(new[:3, 3], s * old[:3, 3], atol=1e-5)
    scene = json.loads((out / "scene.json").read_text())
    assert list(scene["states"]) == ["state1"] and scene["states"]["state1"]["num_views"] == 6
    # so do the sparse points: in every new camera at s times their distance, same direction, same colours
    (old_xyz, old_rgb), (new_xyz, new_rgb) = (
        read_points_ply(capture / "points3d.ply"),
        read_points_ply(out / scene["points"]["path"]),
    )
    assert np.array_equal(new_rgb, old_rgb)
    for j, i in enumerate(keep):
        old = old_xyz @ src.viewmats[i, :3, :3].double().numpy().T + src.viewmats[i, :3, 3].double().numpy()
        new = new_xyz @ v.viewmats[j, :3, :3].double().numpy().T + v.viewmats[j, :3, 3].double().numpy()
        assert np.allclose(new, s * old, atol=1e-5)
    assert "table" not in scene and scene["camera_poses"]["similarity_from_capture"][
        "scale"
    ] == pytest.approx(s)


def test_estimated_poses_with_distortion_are_undistorted(capture, tmp_path):
    from train_world.capture.undistort import Undistorter

    src = load_capture(capture, ["state2"]).states["state2"]
    params = (F, W / 2 + 0.7, H / 2 - 0.4, -0.2)
    w2c = _similarity(list(src.c2w_opengl), 2.0)
    out = write_estimated_capture(capture, "state2", tmp_path / "est", w2c, "SIMPLE_RADIAL", params)
    v = load_capture(out).states["state2"]
    und = Undistorter.for_camera("SIMPLE_RADIAL", params, W, H)
    assert (v.width, v.height) == (W, H) and np.allclose(v.Ks[0].numpy(), und.K, atol=1e-4)
    assert v.Ks[0, 0, 0] < F  # barrel distortion: the widest pinhole view without blank pixels is wider
    with Image.open(capture / "state2" / "images" / "0003.png") as im:
        want = und.rgb(np.asarray(im.convert("RGB")))
    with Image.open(out / "state2" / "images" / "0003.png") as im:
        assert np.array_equal(np.asarray(im), want)
        assert not np.array_equal(want, np.asarray(Image.open(capture / "state2" / "images" / "0003.png")))
    assert np.array_equal(v.masks[3].numpy(), und.ids(src.masks[3].numpy()))
    assert set(np.unique(v.masks.numpy())) == {0, 1, 2}


def test_estimated_poses_refuse_unknown_or_too_few_views(capture, tmp_path):
    w2c = _similarity(list(load_capture(capture, ["state1"]).states["state1"].c2w_opengl), 1.0)
    cam = ("SIMPLE_RADIAL", (F, W / 2, H / 2, 0.0))
    with pytest.raises(ValueError, match="no view 'DSC_1'"):
        write_estimated_capture(capture, "state1", tmp_path / "a", {**w2c, "DSC_1": np.eye(4)}, *cam)
    with pytest.raises(ValueError, match="need 3"):
        write_estimated_capture(capture, "state1", tmp_path / "b", dict(list(w2c.items())[:2]), *cam)
    with pytest.raises(CaptureError, match="no state 'state9'"):
        write_estimated_capture(capture, "state9", tmp_path / "c", w2c, *cam)
    assert not any((tmp_path / n).exists() for n in "abc")


def test_real_pose_worlds_refuses_a_folder_without_poses(tmp_path, capsys):
    from benchmarks.real_pose_worlds import main

    with pytest.raises(SystemExit) as e:
        main(["--llff", str(tmp_path), "--out", str(tmp_path / "r.json")])
    assert e.value.code == 2 and "no poses_bounds.npy" in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


@pytest.mark.slow
@pytest.mark.skipif(
    not (LLFF / "poses_bounds.npy").is_file(), reason="shared/external/ethiopian_head_llff absent"
)
def test_real_pose_worlds_on_the_ethiopian_head(tmp_path):
    pytest.importorskip("pycolmap", reason="needs the capture extra")
    from benchmarks.real_pose_worlds import main

    out = tmp_path / "r.json"
    args = ["--llff", str(LLFF), "--preset", "quick", "--iterations", "40", "--downscale", "4"]
    assert main([*args, "--work", str(tmp_path / "work"), "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    n = r["registered"]
    assert r["views"] == 66 and 0.5 * r["views"] <= n == r["pose_comparison"]["registered"]
    assert len(r["held_out_stems"]) == math.ceil(n / 8)
    for k in ("shipped", "estimated"):
        assert 5 < r[k]["psnr"] < 60 and 0 < r[k]["ssim"] <= 1 and 0 <= r[k]["mask_iou"] <= 1
        assert r[k]["train_s"] > 0 and r[k]["peak_rss_gib"] > 0.05
    assert r["gap_db"] == pytest.approx(r["shipped"]["psnr"] - r["estimated"]["psnr"], abs=1e-3)
    work = tmp_path / "work"
    for k in ("shipped", "estimated"):
        report = json.loads((work / f"eval_{k}" / "report.json").read_text())
        assert [v["view"] for v in report["per_view"]] == [f"state1/{s}" for s in r["held_out_stems"]]
        assert report["image_size"] == [125, 125]
    shipped, est = load_capture(work / "shipped"), load_capture(work / "estimated")
    stems = [p.stem for p in shipped.states["state1"].image_paths]
    assert stems == [p.stem for p in est.states["state1"].image_paths] and len(stems) == n
    assert r["held_out_stems"] == stems[::8] and stems == sorted(stems)
