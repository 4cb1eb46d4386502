"""dsg-synth scene descriptions and states: state sampling and checks, complementary visibility, the default
scenes, textures, and errors in scene files."""

from __future__ import annotations

import json
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from _synth_scenes import SCENE, make_tiny_capture  # noqa: E402

from train_world.capture import load_capture  # noqa: E402
from train_world.synth.build import build_scene  # noqa: E402
from train_world.synth.generate import rng_for  # noqa: E402
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


@pytest.fixture(scope="session")
def tiny_capture(tmp_path_factory) -> Path:
    return make_tiny_capture(tmp_path_factory.mktemp("synth"))


@pytest.fixture(scope="session")
def spec():
    return resolve_scene(SCENE)


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
