"""dsg-import-ply / train_world.capture.ply_import: a 3DGS PLY as a world's background or as a new object."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import dsg_gym  # noqa: F401  (registers DSGWorld-v0)
from dsg_gym.envs.dsg_world import GEOMETRY_WORLD as DEFAULT_WORLD  # a base world without identity features
from dsg_gym.export import export_world_ply
from dsg_gym.io import PlyFormatError, read_ply, write_ply
from dsg_gym.scene_renderer import SceneRenderer
from dsg_gym.world import load_world, write_world
from dsg_gym.world_model import WorldModel
from train_world.capture.ply_import import world_from_ply
from train_world.cli.import_ply import main

EXTERNAL = Path(__file__).resolve().parents[2] / "shared" / "external"
REAL_PLY = EXTERNAL / "gs_ply_small" / "point_cloud_iter7000.ply"
FIELDS = ("means", "quats", "scales", "opacities", "sh", "features")
HALF = 0.015


def hand_written_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A 4x4x4 grid cube (3 cm, resting on z = 0) written by hand: shuffled property order, an extra property,
    no normals, SH degree 0. Returns (means, rgb)."""
    g = np.linspace(-HALF, HALF, 4)
    means = np.array([[x, y, z + HALF] for x in g for y in g for z in g], np.float32)
    n = len(means)
    rgb = np.tile(np.float32([0.1, 0.8, 0.2]), (n, 1))
    dc = (rgb - 0.5) / 0.28209479177387814
    props = [
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
        "x",
        "y",
        "z",
        "extra",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
    ]
    header = f"ply\nformat binary_little_endian 1.0\ncomment hand-written\nelement vertex {n}\n"
    header += "".join(f"property float {p}\n" for p in props) + "end_header\n"
    body = b"".join(
        struct.pack("<15f", 1, 0, 0, 0, *means[i], 7.0, *dc[i], 3.0, *([np.log(0.005)] * 3)) for i in range(n)
    )
    path.write_bytes(header.encode("ascii") + body)
    return means, rgb


def run_cli(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def test_hand_written_ply_as_object_in_default_world(tmp_path, capsys):
    ply = tmp_path / "cube.ply"
    means, rgb = hand_written_ply(ply)
    g = read_ply(ply)
    np.testing.assert_array_equal(g.means, means)
    np.testing.assert_allclose(g.colors, rgb, atol=1e-6)
    out = tmp_path / "with_cube.dsgworld"
    code, stdout, err = run_cli(
        [ply, "--out", out, "--as", "object", "--object-name", "green_cube", "--base", DEFAULT_WORLD], capsys
    )
    assert code == 0, err
    base = WorldModel.load(DEFAULT_WORLD)
    wm = WorldModel.load(out)
    k = base.num_objects
    assert wm.num_objects == k + 1 and wm.object_names == (*base.object_names, "green_cube")
    assert wm.object_ids == (*base.object_ids, max(base.object_ids) + 1)
    for f in FIELDS:
        assert np.array_equal(getattr(wm.objects[k], f), getattr(g, f)), f
    assert np.all(wm.objects[k].labels == wm.object_ids[k])
    assert wm.table == base.table
    for s, P in base.states.items():
        np.testing.assert_array_equal(wm.states[s][:k], P)
        np.testing.assert_array_equal(wm.states[s][k], np.eye(4))
    env = gym.make("DSGWorld-v0", world=str(out), width=64, height=64)
    obs, _ = env.reset(seed=0)
    assert env.action_space.shape == ((k + 1) * 4,) and obs["poses"].shape == (k + 1, 7)
    env.action_space.seed(0)
    for _ in range(5):
        obs, reward, *_ = env.step(env.action_space.sample())
        assert np.isfinite(reward)
    env.close()
    # the same name again is refused
    code, _, err = run_cli(
        [
            ply,
            "--out",
            tmp_path / "x.dsgworld",
            "--as",
            "object",
            "--object-name",
            "green_cube",
            "--base",
            out,
        ],
        capsys,
    )
    assert code == 2 and "already has an object named 'green_cube'" in err


def test_object_without_base_makes_an_env_world(tmp_path):
    ply = tmp_path / "cube.ply"
    hand_written_ply(ply)
    out = write_world(
        tmp_path / "cube.dsgworld", world_from_ply(ply, role="object", num_views=4, width=32, height=32)
    )
    env = gym.make("DSGWorld-v0", world=str(out), width=32, height=32)
    obs, _ = env.reset(seed=0)
    obs, *_ = env.step(env.action_space.sample())
    assert obs["poses"].shape == (1, 7) and 1 in obs["mask"]
    env.close()


def test_background_replaced_in_base(tmp_path):
    g = read_ply(write_ply(tmp_path / "bg.ply", WorldModel.load(DEFAULT_WORLD).objects[0]))  # any splats
    w = world_from_ply(tmp_path / "bg.ply", DEFAULT_WORLD)
    base = load_world(DEFAULT_WORLD)
    assert w.object_names == base.object_names and dict(w.poses).keys() == dict(base.poses).keys()
    for f in FIELDS:
        assert np.array_equal(getattr(w.background, f), getattr(g, f))
    assert not w.background.labels.any()
    assert w.metadata["table"] == base.metadata["table"] and w.metadata["imports"][0]["role"] == "background"


@pytest.mark.skipif(not REAL_PLY.is_file(), reason="external test data absent")
def test_real_ply_as_background_renders(tmp_path, capsys):
    out = tmp_path / "real.dsgworld"
    code, stdout, err = run_cli([REAL_PLY, "--out", out, "--views", 4, "--width", 64, "--height", 64], capsys)
    assert code == 0 and Path(stdout.strip()) == out
    assert "no objects" in err and "--as object" in err
    src = read_ply(REAL_PLY)
    w = load_world(out)
    assert w.num_objects == 0
    for f in FIELDS:
        assert np.array_equal(getattr(w.background, f), getattr(src, f)), f
    cams = w.cameras["orbit"]
    assert len(cams) == 4 and (cams.width, cams.height) == (64, 64)
    r = SceneRenderer(w.background, [], cams.viewmats, cams.Ks, cams.width, cams.height)
    img = r.render(np.zeros((0, 4, 4)), rgb=True, mask=False)
    coverage = (img.alpha > 0.5).mean(axis=(1, 2))
    assert coverage.min() > 0.05, coverage  # every camera sees the scene
    assert img.rgb.std() > 5
    # DSGWorld-v0 needs objects: a clear refusal up front, and the env refuses the file
    with pytest.raises(ValueError, match="needs at least one object.*role='object'"):
        world_from_ply(REAL_PLY, for_env=True)
    with pytest.raises(ValueError, match="real.dsgworld"):
        gym.make("DSGWorld-v0", world=str(out))
    # imported splats keep their stored encodings: exporting them again rewrites the source file byte for byte
    # (the source has zero normals and no comments)
    wm = WorldModel.from_world(
        load_world(write_world(tmp_path / "sw.dsgworld", world_from_ply(REAL_PLY, DEFAULT_WORLD)))
    )
    assert export_world_ply(wm, tmp_path / "ply")[0].read_bytes() == REAL_PLY.read_bytes()


def test_bad_ply_clear_errors(tmp_path, capsys):
    ply = tmp_path / "cube.ply"
    hand_written_ply(ply)
    data = ply.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 10])
    (tmp_path / "noheader.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    (tmp_path / "notply.ply").write_bytes(b"hello world\n")
    bad = data.replace(b"property float opacity\n", b"property float opacit\n")
    (tmp_path / "missing_prop.ply").write_bytes(bad)
    for name in ("cut.ply", "noheader.ply", "notply.ply", "missing_prop.ply"):
        with pytest.raises(PlyFormatError, match=re.escape(name)):
            world_from_ply(tmp_path / name)
        code, _, err = run_cli([tmp_path / name, "--out", tmp_path / "o.dsgworld"], capsys)
        assert code == 2 and name in err, err
    code, _, err = run_cli([tmp_path / "absent.ply", "--out", tmp_path / "o.dsgworld"], capsys)
    assert code == 2 and "absent.ply: PLY file does not exist" in err
    code, _, err = run_cli([ply, "--out", tmp_path / "o.dsgworld", "--object-name", "x"], capsys)
    assert code == 2 and "--object-name needs --as object" in err
    assert not (tmp_path / "o.dsgworld").exists()
