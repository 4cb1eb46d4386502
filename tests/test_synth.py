"""dsg-synth, the written capture: its files on disk, determinism, refusals and the CLI, and the geometry of
cameras, depth maps and masks."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from _synth_scenes import SCENE, TINY, make_tiny_capture  # noqa: E402
from PIL import Image  # noqa: E402

from train_world.capture import load_capture  # noqa: E402
from train_world.capture.format import depth_to_png_units  # noqa: E402
from train_world.cli import synth as cli  # noqa: E402
from train_world.synth.build import build_scene, set_object_poses  # noqa: E402
from train_world.synth.cameras import look_at_opengl  # noqa: E402
from train_world.synth.generate import GenerateConfig, generate_scene, rng_for  # noqa: E402
from train_world.synth.render import SceneRenderer  # noqa: E402
from train_world.synth.spec import default_scene_names, resolve_scene  # noqa: E402
from train_world.synth.states import sample_states  # noqa: E402


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    return make_tiny_capture(tmp_path_factory.mktemp("synth"))


@pytest.fixture(scope="session")
def spec():
    return resolve_scene(SCENE)


def _dilate(m: np.ndarray) -> np.ndarray:
    """3x3 binary dilation."""
    p = np.pad(m, 1)
    h, w = m.shape
    return np.any([p[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)], axis=0)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------- on disk
def test_layout_and_scene_json(tiny_capture, spec):
    meta = json.loads((tiny_capture / "scene.json").read_text())
    assert meta["units"] == "metres"
    assert meta["generator"]["seed"] == TINY.seed and meta["generator"]["version"]
    assert [o["id"] for o in meta["objects"]] == list(range(1, len(spec.objects) + 1))
    assert [o["name"] for o in meta["objects"]] == [o.name for o in spec.objects]
    assert set(meta["states"]) == {"state1", "state2", "test_0"}
    (x0, y0, _), (x1, y1, _) = meta["table"]["bounds"]
    assert (x1 - x0, y1 - y0) == pytest.approx(spec.surface.size)
    for name, st in meta["states"].items():
        tj = json.loads((tiny_capture / name / "transforms.json").read_text())
        assert (
            len(tj["frames"])
            == st["num_views"]
            == (TINY.views if st["split"] == "train" else TINY.test_views)
        )
        assert (tj["w"], tj["h"]) == (TINY.width, TINY.height)
        assert tj["fl_x"] == pytest.approx(0.5 * TINY.height / np.tan(np.deg2rad(spec.cameras.fovy_deg) / 2))
        assert tj["camera_angle_x"] == pytest.approx(2 * np.arctan(0.5 * TINY.width / tj["fl_x"]))
        for fr in tj["frames"]:
            img = Image.open(tiny_capture / name / fr["file_path"])
            assert img.mode == "RGB" and img.size == (TINY.width, TINY.height)
            assert Image.open(tiny_capture / name / fr["mask_path"]).mode == "L"
            assert Image.open(tiny_capture / name / fr["depth_path"]).mode == "I;16"
    assert not [p for p in tiny_capture.parent.iterdir() if p.name.startswith(".")], (
        "staging folder left behind"
    )


def test_same_seed_same_bytes_other_seed_differs(tiny_capture, tmp_path):
    again = generate_scene(SCENE, tmp_path / "again", TINY)
    assert _files(again) == _files(tiny_capture)
    other = generate_scene(SCENE, tmp_path / "other", GenerateConfig(**{**TINY.__dict__, "seed": 4}))
    a, b = (
        json.loads((tiny_capture / "scene.json").read_text()),
        json.loads((other / "scene.json").read_text()),
    )
    assert a["states"]["state1"]["object_poses"] != b["states"]["state1"]["object_poses"]


def test_refuses_existing_folder_unless_overwrite(tiny_capture, tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(FileExistsError, match="overwrite"):
        generate_scene(SCENE, out, TINY)
    assert (out / "keep.txt").read_text() == "mine"
    assert (
        cli.main(
            [
                "--scene",
                SCENE,
                "--out",
                str(out),
                "--width",
                "32",
                "--height",
                "32",
                "--views",
                "2",
                "--test-views",
                "1",
                "--test-states",
                "1",
                "--quiet",
            ]
        )
        == 2
    )
    generate_scene(SCENE, out, TINY, overwrite=True)
    assert not (out / "keep.txt").exists() and _files(out) == _files(tiny_capture)


def test_crash_leaves_no_partial_capture(tmp_path, monkeypatch):
    def boom(*a, **k):
        raise RuntimeError("renderer died")

    monkeypatch.setattr(SceneRenderer, "render", boom)
    with pytest.raises(RuntimeError, match="renderer died"):
        generate_scene(SCENE, tmp_path / "cap", TINY)
    assert list(tmp_path.iterdir()) == []


def test_cli_list_and_generate(tmp_path, capsys):
    assert cli.main(["--list"]) == 0
    listed = capsys.readouterr().out
    assert all(n in listed for n in default_scene_names())
    out = tmp_path / "c"
    assert (
        cli.main(
            [
                "--scene",
                "two_blocks",
                "--out",
                str(out),
                "--width",
                "24",
                "--height",
                "16",
                "--views",
                "3",
                "--test-views",
                "2",
                "--test-states",
                "2",
                "--seed",
                "5",
                "--quiet",
            ]
        )
        == 0
    )
    meta = json.loads((out / "scene.json").read_text())
    assert sorted(meta["states"]) == ["state1", "state2", "test_0", "test_1"]
    assert Image.open(out / "state2" / "images" / "0002.png").size == (24, 16)
    with pytest.raises(SystemExit):
        cli.main(["--scene", "two_blocks"])  # --out missing


# ------------------------------------------------------------------------------------------- geometry
def test_depth_reprojects_onto_the_table_and_known_points(tiny_capture):
    """Cameras + depth round trip: pixel centres (u+.5, v+.5) back-projected with depth land on the table
    plane z = 0, and known 3D points (box top centres, table points) project onto pixels whose depth
    matches."""
    cap = load_capture(tiny_capture)
    meta = json.loads((tiny_capture / "scene.json").read_text())
    (x0, y0, _), (x1, y1, _) = meta["table"]["bounds"]
    n_table = 0
    for name, views in cap.states.items():
        for i in range(len(views)):
            vm = views.viewmats[i].double().numpy()
            K = views.Ks[i].double().numpy()
            depth = views.depths[i].numpy().astype(np.float64)
            mask = views.masks[i].numpy()
            v, u = np.mgrid[0 : views.height, 0 : views.width]
            rays = np.stack(
                [(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones_like(depth)], -1
            )
            pc = rays * depth[..., None]
            pw = (pc - vm[:3, 3]) @ vm[:3, :3]  # R^T (pc - t)
            # not next to an object (antialiased edges) and inside the table top
            table = (
                ~_dilate(mask > 0)
                & (depth > 0)
                & (pw[..., 0] > x0 + 0.02)
                & (pw[..., 0] < x1 - 0.02)
                & (pw[..., 1] > y0 + 0.02)
                & (pw[..., 1] < y1 - 0.02)
                & (np.abs(pw[..., 2]) < 0.1)
            )
            n_table += int(table.sum())
            assert np.abs(pw[..., 2][table]).max() < 2.5e-3, (name, i)
            # known table point at the centre of a pixel seen as table: project it back onto that pixel
            if table.any():
                jj, ii = np.argwhere(table)[0]
                p = pw[jj, ii]
                q = vm[:3, :3] @ np.array([p[0], p[1], 0.0]) + vm[:3, 3]
                uv = (K @ q)[:2] / q[2]
                assert (int(np.floor(uv[0])), int(np.floor(uv[1]))) == (ii, jj)
            # the top-face centre of the box (object 1) projects onto a pixel of the box with matching depth
            pose = cap.poses[name][0]
            top = pose @ np.array([0.0, 0.0, 0.05, 1.0])
            q = vm[:3, :3] @ top[:3] + vm[:3, 3]
            uv = (K @ q)[:2] / q[2]
            ui, vi = int(np.floor(uv[0])), int(np.floor(uv[1]))
            if 0 <= ui < views.width and 0 <= vi < views.height and mask[vi, ui] == 1:
                assert depth[vi, ui] == pytest.approx(q[2], abs=0.02)
    assert n_table > 500


def test_renderer_pixel_centre_convention_is_exact():
    """At higher resolution the table plane is recovered to sub-millimetre only with centres at +0.5."""
    spec = resolve_scene("two_blocks")
    built = build_scene(spec, 96, 64)
    data = mujoco.MjData(built.model)
    set_object_poses(built, data, sample_states(spec, rng_for(0, "states"), 0)["state1"])
    with SceneRenderer(built, 96, 64) as r:
        c2w = look_at_opengl([0.1, -0.55, 0.45], [0.02, 0.01, 0.0])
        _, ids, depth = r.render(data, c2w, rgb=False)
        fx, fy, cx, cy = r.intrinsics()
    assert (cx, cy) == (48.0, 32.0) and fx == fy
    v, u = np.mgrid[0:64, 0:96]
    clear = ~_dilate(ids > 0)
    errs = {}
    for off in (0.0, 0.5):
        pc = (
            np.stack([(u + off - cx) / fx, -(v + off - cy) / fy, -np.ones_like(u, dtype=float)], -1)
            * depth[..., None]
        )
        pw = pc @ c2w[:3, :3].T + c2w[:3, 3]
        # table top pixels (the floor under the table is visible too: drop it by height)
        sel = clear & (np.abs(pw[..., 0]) < 0.3) & (np.abs(pw[..., 1]) < 0.2) & (np.abs(pw[..., 2]) < 0.1)
        assert sel.sum() > 1000
        errs[off] = np.abs(pw[..., 2][sel]).max()
    assert errs[0.5] < 1e-4 < 1e-3 < errs[0.0]


def test_masks_agree_with_mujoco_segmentation(tiny_capture, spec):
    """Re-render MuJoCo's own segmentation from scene.json poses and transforms.json cameras, map geoms to
    bodies by name, and compare with the mask PNGs."""
    meta = json.loads((tiny_capture / "scene.json").read_text())
    model = build_scene(spec, TINY.width, TINY.height).model
    data = mujoco.MjData(model)
    body_to_id = {model.body(f"object:{o['name']}").id: o["id"] for o in meta["objects"]}
    cam = model.camera("render_cam").id
    renderer = mujoco.Renderer(model, TINY.height, TINY.width)
    renderer.enable_segmentation_rendering()
    checked = 0
    for name, st in meta["states"].items():
        for entry in st["object_poses"]:
            body = model.body(f"object:{meta['objects'][entry['id'] - 1]['name']}")
            adr = model.jnt_qposadr[model.body_jntadr[body.id]]
            pose = np.asarray(entry["pose"])
            q = np.zeros(4)
            mujoco.mju_mat2Quat(q, pose[:3, :3].ravel())
            data.qpos[adr : adr + 7] = np.concatenate([pose[:3, 3], q])
        mujoco.mj_forward(model, data)
        tj = json.loads((tiny_capture / name / "transforms.json").read_text())
        for fr in tj["frames"]:
            c2w = np.asarray(fr["transform_matrix"])
            model.cam_pos[cam] = c2w[:3, 3]
            mujoco.mju_mat2Quat(q, c2w[:3, :3].ravel())
            model.cam_quat[cam] = q
            mujoco.mj_camlight(model, data)
            renderer.update_scene(data, camera=cam)
            seg = renderer.render()
            expect = np.zeros(seg.shape[:2], dtype=np.uint8)
            geom = (seg[..., 1] == mujoco.mjtObj.mjOBJ_GEOM) & (seg[..., 0] >= 0)
            bodies = model.geom_bodyid[seg[..., 0][geom]]
            expect[geom] = [body_to_id.get(int(b), 0) for b in bodies]
            mask = np.asarray(Image.open(tiny_capture / name / fr["mask_path"]))
            np.testing.assert_array_equal(mask, expect)
            checked += int((mask > 0).sum())
    renderer.close()
    assert checked > 0  # objects were actually visible


def test_depth_png_units():
    mm = depth_to_png_units(np.array([[0.0, 0.0004, 0.0006, 1.2345], [np.nan, np.inf, 65.535, 70.0]]))
    assert mm.dtype == np.uint16
    assert mm.tolist() == [[0, 0, 1, 1234], [0, 0, 65535, 0]] or mm.tolist() == [
        [0, 0, 1, 1235],
        [0, 0, 65535, 0],
    ]
