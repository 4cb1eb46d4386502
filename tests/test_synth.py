"""dsg-synth: scene descriptions, state sampling and checks, cameras, rendering, the written capture."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

from train_world.capture import load_capture  # noqa: E402
from train_world.cli import synth as cli  # noqa: E402
from train_world.synth.build import build_scene, set_object_poses  # noqa: E402
from train_world.synth.cameras import look_at_opengl, orbit_c2w  # noqa: E402
from train_world.synth.generate import GENERATOR_VERSION, GenerateConfig, generate_scene, rng_for  # noqa: E402
from train_world.synth.render import SceneRenderer, depth_to_png_units  # noqa: E402
from train_world.synth.shapes import resting_height, support  # noqa: E402
from train_world.synth.spec import (  # noqa: E402
    SpecError,
    default_scene_names,
    resolve_scene,
    scene_from_dict,
)
from train_world.synth.states import (  # noqa: E402
    StateError,
    check_complementary_visibility,
    check_state,
    sample_states,
    verify_with_mujoco,
)
from train_world.synth.textures import surface_texture  # noqa: E402

SCENE = "four_mixed"  # box, cylinder, sphere and a mesh; no props on the table
TINY = GenerateConfig(seed=3, width=32, height=32, views=4, test_views=2, test_states=1, progress=False)


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth") / "tiny"
    generate_scene(SCENE, out, TINY)
    return out


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


# ------------------------------------------------------------------------------------------- states
def test_generated_states_are_valid_and_complementary(tiny_capture, spec):
    cap = load_capture(tiny_capture, states=["state1"])
    built = build_scene(spec, 32, 32)
    data = mujoco.MjData(built.model)
    for name, poses in cap.poses.items():
        check_state(spec, poses, name)
        verify_with_mujoco(built, data, poses, name)
        lows = [
            poses[k, 2, 3] - resting_height(o.shape, poses[k, :3, :3]) for k, o in enumerate(spec.objects)
        ]
        np.testing.assert_allclose(lows, 0.0, atol=1e-9)
    check_complementary_visibility(spec, cap.poses["state1"], cap.poses["state2"])
    moved = np.linalg.norm(cap.poses["state1"][:, :2, 3] - cap.poses["state2"][:, :2, 3], axis=1)
    assert (moved > 0.03).all()
    assert not np.allclose(cap.poses["test_0"], cap.poses["state1"])


def test_complementary_check_rejects_hand_made_violations(tiny_capture, spec):
    cap = load_capture(tiny_capture, states=["state1"])
    p1 = cap.poses["state1"]
    # every object moves 1 cm: collision-free states, but their footprints overlap their old ones
    nudged = p1.copy()
    nudged[:, 0, 3] += 0.01
    with pytest.raises(StateError, match="complementary"):
        check_complementary_visibility(spec, p1, nudged)
    # objects swap places: everything moved, yet each region stays covered (by another object)
    swapped = p1.copy()
    for a, b in ((0, 1), (1, 0)):
        swapped[a, :2, 3] = p1[b, :2, 3]
    with pytest.raises(StateError, match=spec.objects[0].name):
        check_complementary_visibility(spec, p1, swapped)
    check_complementary_visibility(spec, p1, cap.poses["state2"])  # the generated pair passes


def test_check_state_rejects_bad_states(tiny_capture, spec):
    p = load_capture(tiny_capture, states=["state1"]).poses["state1"]
    built = build_scene(spec, 32, 32)
    data = mujoco.MjData(built.model)
    clash = p.copy()
    clash[1, :2, 3] = clash[0, :2, 3] + 0.02
    with pytest.raises(StateError, match="overlap"):
        check_state(spec, clash)
    with pytest.raises(StateError, match="collision"):
        verify_with_mujoco(built, data, clash)
    floating = p.copy()
    floating[2, 2, 3] += 0.01
    with pytest.raises(StateError, match="rest"):
        check_state(spec, floating)
    with pytest.raises(StateError, match="rest on the surface"):
        verify_with_mujoco(built, data, floating)
    outside = p.copy()
    outside[0, 0, 3] = spec.surface.size[0] / 2
    with pytest.raises(StateError, match="bounds"):
        check_state(spec, outside)


@pytest.mark.parametrize("name", default_scene_names())
def test_default_scenes(name):
    spec = resolve_scene(name)
    assert 2 <= len(spec.objects) <= 6
    for o in spec.objects:  # 4-15 cm
        size = 2 * support(o.shape, np.eye(3)).max()
        assert 0.04 <= size <= 0.15 + 1e-9, (o.name, size)
    cols = np.array([o.appearance.rgba[:3] for o in spec.objects])
    d = np.linalg.norm(cols[:, None] - cols[None], axis=-1) + np.eye(len(cols))
    assert d.min() > 0.15, "object colours must be distinct"
    states = sample_states(spec, rng_for(0, "states"), 2)
    check_complementary_visibility(spec, states["state1"], states["state2"])
    built = build_scene(spec, 32, 32)
    data = mujoco.MjData(built.model)
    for name, poses in states.items():
        verify_with_mujoco(built, data, poses, name)
    assert 0.6 <= spec.surface.size[0] * spec.surface.size[1] / 0.48 <= 1.5


def test_default_scene_set():
    names = default_scene_names()
    assert len(names) == 7
    counts = {len(resolve_scene(n).objects) for n in names}
    assert len(counts) >= 4  # object count varies
    kinds = {o.shape.type for n in names for o in resolve_scene(n).objects}
    assert kinds == {"box", "cylinder", "sphere", "capsule", "mesh"}


def test_surface_texture_is_high_frequency_and_deterministic():
    a = surface_texture(7, 128, 96, 32, 24, (0.8, 0.7, 0.5), (0.4, 0.3, 0.2)).astype(float)
    assert np.array_equal(a, surface_texture(7, 128, 96, 32, 24, (0.8, 0.7, 0.5), (0.4, 0.3, 0.2)))
    assert np.abs(np.diff(a, axis=1)).mean() > 10  # strong texel-to-texel variation


def test_spec_errors_name_the_file_and_field(tmp_path):
    good = json.loads((Path(resolve_scene(SCENE).source)).read_text())
    bad = json.loads(json.dumps(good))
    bad["objects"][1]["shape"]["type"] = "torus"
    with pytest.raises(SpecError, match=r"objects\[1\]\.shape\.type"):
        scene_from_dict(bad, "mine.json")
    bad = json.loads(json.dumps(good))
    bad["objects"][0]["colour"] = [1, 0, 0]
    with pytest.raises(SpecError, match=r"mine\.json: objects\[0\]: unknown keys \['colour'\]"):
        scene_from_dict(bad, "mine.json")
    p = tmp_path / "broken.json"
    p.write_text("{not json")
    with pytest.raises(SpecError, match="broken.json"):
        resolve_scene(str(p))
    with pytest.raises(SpecError, match="unknown scene"):
        resolve_scene("no_such_scene")


def test_impossible_scene_is_reported():
    spec = resolve_scene("two_blocks")
    crowded = scene_from_dict(
        {
            "name": "crowded",
            "surface": {"size": [0.2, 0.2]},
            "objects": [
                {"name": f"b{i}", "shape": {"type": "box", "extents": [0.1, 0.1, 0.1]}} for i in range(3)
            ],
            "placement": {"max_tries": 20},
        },
        "crowded.json",
    )
    assert spec.objects
    with pytest.raises(StateError, match="crowded"):
        sample_states(crowded, rng_for(0, "states"), 0, max_restarts=3)


# ------------------------------------------------------------------------------------------- cameras, lights
def test_orbits_look_at_the_table_and_test_cameras_are_held_out(tiny_capture, spec):
    cap = load_capture(tiny_capture)
    train = np.concatenate([cap.states[s].c2w_opengl for s in ("state1", "state2")])
    test = cap.states["test_0"].c2w_opengl
    for c2w in np.concatenate([train, test]):
        dist = np.linalg.norm(c2w[:3, 3])
        assert 0.6 <= dist <= 1.0
        forward = -c2w[:3, 2]
        to_centre = -c2w[:3, 3] / dist
        assert np.degrees(np.arccos(np.clip(forward @ to_centre, -1, 1))) < 6
    gap = np.linalg.norm(test[:, None, :3, 3] - train[None, :, :3, 3], axis=-1)
    assert gap.min() > 0.005  # held out: no test camera sits on a training camera
    elev = lambda c: np.degrees(np.arcsin(c[:, 2, 3] / np.linalg.norm(c[:, :3, 3], axis=1)))  # noqa: E731
    assert abs(elev(test).mean() - elev(train).mean()) < 5  # from the capture's own elevation band


def test_orbit_is_smooth():
    c = orbit_c2w(resolve_scene(SCENE).cameras.train, 48, np.random.default_rng(0))
    steps = np.linalg.norm(np.diff(c[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 2.0 * np.median(steps)  # no jumps
    np.testing.assert_allclose(
        c[:, :3, :3].transpose(0, 2, 1) @ c[:, :3, :3], np.broadcast_to(np.eye(3), (48, 3, 3)), atol=1e-12
    )


def test_shadows_flag(spec):
    from train_world.synth.build import CAMERA_LIGHT

    assert not build_scene(spec).model.light_castshadow.any()
    m = build_scene(spec, shadows=True).model
    cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, CAMERA_LIGHT)
    # the world-fixed lights cast shadows; the camera's own light would only cast them out of its sight
    assert cam >= 0 and np.delete(m.light_castshadow, cam).all() and not m.light_castshadow[cam]


def test_lighting_presets(spec):
    from train_world.synth.build import CAMERA_LIGHT, LIGHTING

    models = {n: build_scene(spec, lighting=n).model for n in ("soft", "spot", "headlight")}
    fixed = {}
    for name, m in models.items():
        cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, CAMERA_LIGHT)
        fixed[name] = np.delete(m.light_diffuse, cam, axis=0) if cam >= 0 else m.light_diffuse
        if name == "headlight":  # generator 1.2's soft: MuJoCo's directional headlight, no camera point light
            assert cam < 0 and m.vis.headlight.diffuse[0] == LIGHTING[name][1]
            continue
        # a positional light of the preset's strength, no shadows, no cone; the headlight only adds ambient
        assert (
            cam >= 0 and m.light_type[cam] == mujoco.mjtLightType.mjLIGHT_SPOT and not m.light_castshadow[cam]
        )
        np.testing.assert_allclose(m.light_diffuse[cam], LIGHTING[name][1])
        assert m.vis.headlight.diffuse[0] == 0.0 and m.vis.headlight.ambient[0] > 0
    np.testing.assert_allclose(fixed["soft"], LIGHTING["soft"][0] * fixed["spot"], rtol=1e-6)
    np.testing.assert_allclose(fixed["headlight"], fixed["soft"])
    with pytest.raises(ValueError, match="lighting"):
        build_scene(spec, lighting="disco")
    with pytest.raises(ValueError, match="lighting"):
        GenerateConfig(lighting="disco")


def test_camera_light_shades_by_camera_position_not_axis():
    """The camera light sits at the camera centre: panning the camera (same centre, the object off the image
    centre) keeps an object's colour, which a view-direction model can represent; MuJoCo's directional
    headlight shines along the camera axis, so panning changes the shading (what generator 1.3 removed)."""
    from train_world.synth.build import CAMERA_LIGHT

    spec = resolve_scene("two_blocks")  # its box is large and matte: shading shows
    shift = {}
    for lighting in ("soft", "headlight"):
        built = build_scene(spec, 64, 64, lighting=lighting)
        m = built.model
        cam = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_LIGHT, CAMERA_LIGHT)
        for j in range(m.nlight):  # only the camera-carried light (and ambient) stays on
            if j != cam:
                m.light_diffuse[j] = 0.0
                m.light_specular[j] = 0.0
        data = mujoco.MjData(m)
        poses = sample_states(spec, rng_for(0, "states"), 0)["state1"]
        set_object_poses(built, data, poses)
        target = np.asarray(poses)[0, :3, 3]
        eye = target + np.array([0.0, -0.45, 0.35])
        means = []
        with SceneRenderer(built, 64, 64) as r:
            for off in ([0.0, 0.0, 0.0], [0.12, 0.0, 0.0], [0.0, 0.0, 0.1]):
                c2w = look_at_opengl(eye, target + np.array(off))
                rgb, ids, _ = r.render(data, c2w)
                assert (ids == 1).sum() > 50
                means.append(rgb[ids == 1].astype(float).mean(0))
                if cam >= 0:
                    np.testing.assert_allclose(data.light_xpos[cam], c2w[:3, 3], atol=1e-9)
                    np.testing.assert_allclose(data.light_xdir[cam], -c2w[:3, 2], atol=1e-9)
        shift[lighting] = max(np.abs(x - means[0]).max() for x in means[1:])
    assert shift["soft"] < 3.0 < 8.0 < shift["headlight"]


def test_test_orbit_sits_in_the_training_band():
    cams = resolve_scene(SCENE).cameras
    assert abs(cams.test.elevation_deg - cams.train.elevation_deg) <= cams.train.elevation_wobble_deg
    assert cams.test.azimuth_offset_deg != 0.0  # interleaved with the training azimuths, not on them


def test_supersampled_rgb_is_the_box_mean_of_a_larger_render(spec):
    """supersample=2 gives the rounded 2x2 block mean of a 2x render; masks and depth stay pixel-centred."""
    built = build_scene(spec, 64, 48)
    data = mujoco.MjData(built.model)
    set_object_poses(built, data, sample_states(spec, rng_for(0, "states"), 0)["state1"])
    c2w = look_at_opengl([0.3, -0.6, 0.5], [0.0, 0.0, 0.0])
    with (
        SceneRenderer(built, 64, 48) as big,
        SceneRenderer(built, 32, 24) as point,
        SceneRenderer(built, 32, 24, supersample=2) as ss,
    ):
        hi, _, _ = big.render(data, c2w, seg=False, depth=False)
        rgb_p, ids_p, d_p = point.render(data, c2w)
        rgb_s, ids_s, d_s = ss.render(data, c2w)
    want = np.rint(hi.reshape(24, 2, 32, 2, 3).astype(np.float64).mean((1, 3))).astype(np.uint8)
    np.testing.assert_array_equal(rgb_s, want)
    assert np.abs(rgb_s.astype(int) - rgb_p).max() > 20  # the textures alias without supersampling
    np.testing.assert_array_equal(ids_s, ids_p)
    np.testing.assert_array_equal(d_s, d_p)


def test_supersample_is_validated_and_recorded(spec, tiny_capture):
    built = build_scene(spec, 64, 64)
    with pytest.raises(ValueError, match="offscreen buffer"):
        SceneRenderer(built, 64, 64, supersample=2)
    with pytest.raises(ValueError, match="supersample"):
        SceneRenderer(built, 32, 32, supersample=0)
    for bad in (0, 17, 2.5):
        with pytest.raises(ValueError, match="supersample"):
            GenerateConfig(supersample=bad)
    gen = json.loads((tiny_capture / "scene.json").read_text())["generator"]
    assert gen["supersample"] == TINY.supersample == 4 and gen["version"] == GENERATOR_VERSION
