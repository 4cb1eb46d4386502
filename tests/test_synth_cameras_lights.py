"""dsg-synth cameras, lights and rendering: the orbits and held-out test cameras, shadows and lighting presets,
the camera-carried light, and supersampling."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from _synth_scenes import SCENE, TINY, make_tiny_capture  # noqa: E402

from train_world.capture import load_capture  # noqa: E402
from train_world.synth.build import build_scene, set_object_poses  # noqa: E402
from train_world.synth.cameras import look_at_opengl, orbit_c2w  # noqa: E402
from train_world.synth.generate import GENERATOR_VERSION, GenerateConfig, rng_for  # noqa: E402
from train_world.synth.render import SceneRenderer  # noqa: E402
from train_world.synth.spec import resolve_scene  # noqa: E402
from train_world.synth.states import sample_states  # noqa: E402


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    return make_tiny_capture(tmp_path_factory.mktemp("synth"))


@pytest.fixture(scope="session")
def spec():
    return resolve_scene(SCENE)


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
