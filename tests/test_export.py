"""dsg-export / dsg_gym.export (world -> USD stage or 3DGS PLY files) and RecordEpisode episode files."""

from __future__ import annotations

import json
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import dsg_gym  # noqa: F401  (registers DSGWorld-v0)
from dsg_gym.cli.export import main
from dsg_gym.envs.dsg_world import DEFAULT_WORLD
from dsg_gym.envs.recording import EpisodeFileError, RecordEpisode, load_episode, save_episode
from dsg_gym.export import export_world_ply, export_world_usd
from dsg_gym.io import read_ply, write_ply
from dsg_gym.poses import matrix_to_pose7
from dsg_gym.usd import Episode, read_stage, validate_stage
from dsg_gym.world_model import WorldModel, transform_gaussians

FIELDS = ("means", "quats", "scales", "opacities", "sh", "features", "labels")
WORLD = str(DEFAULT_WORLD)


@pytest.fixture(scope="module")
def wm() -> WorldModel:
    return WorldModel.load(DEFAULT_WORLD)


def assert_same_set(a, b, skip=()):
    for f in FIELDS:
        if f not in skip:
            x, y = getattr(a, f), getattr(b, f)
            assert x.dtype == y.dtype and np.array_equal(x, y), f


def assert_clean(path):
    issues = [i for i in validate_stage(path) if i.severity == "Error"]
    assert not issues, issues


def run_cli(argv, capsys):
    """``main(argv)``; returns (exit code, stdout, stderr)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


# ------------------------------------------------------------------------------------------- USD
@pytest.mark.parametrize("suffix,state", [(".usdc", None), (".usda", "state2")])
def test_cli_world_to_usd(tmp_path, capsys, wm, suffix, state):
    out = tmp_path / f"world{suffix}"
    argv = [WORLD, "--out", out] + ([] if state is None else ["--poses", state])
    code, stdout, _ = run_cli(argv, capsys)
    assert code == 0 and Path(stdout.strip()) == out and out.is_file()
    assert_clean(out)
    c = read_stage(out)
    assert_same_set(c.background, wm.background)
    assert [o.name for o in c.objects] == list(wm.object_names)
    P = wm.state_poses(state or "state1")  # noqa: N806
    for k, o in enumerate(c.objects):
        assert_same_set(o.gaussians, wm.objects[k])
        assert np.abs(o.pose - P[k]).max() <= 1e-6
        assert not o.kinematic
    assert len(c.cameras) == len(wm.cameras) and c.table_vertices is not None
    assert c.episode is None


def test_usdc_is_default_suffix(tmp_path, wm):
    path = export_world_usd(wm, tmp_path / "plain")
    assert path == tmp_path / "plain.usdc" and path.read_bytes()[:8] == b"PXR-USDC"
    with pytest.raises(ValueError, match="is a folder"):
        export_world_usd(wm, tmp_path)


@pytest.mark.parametrize("kind", ["npy44", "npz7", "json7", "json_obj"])
def test_poses_file(tmp_path, wm, kind):
    rng = np.random.default_rng(0)
    P = wm.state_poses("state2")  # noqa: N806
    P[:, :2, 3] += rng.uniform(-0.05, 0.05, (wm.num_objects, 2))
    p7 = matrix_to_pose7(P)
    f = tmp_path / {"npy44": "p.npy", "npz7": "p.npz", "json7": "p.json", "json_obj": "p.json"}[kind]
    if kind == "npy44":
        np.save(f, P)
    elif kind == "npz7":
        np.savez(f, poses=p7)
    else:
        f.write_text(json.dumps(p7.tolist() if kind == "json7" else {"poses": p7.tolist()}))
    c = read_stage(export_world_usd(WORLD, tmp_path / "w.usdc", poses=str(f)))
    assert max(np.abs(o.pose - P[k]).max() for k, o in enumerate(c.objects)) <= 1e-6
    # arrays work directly as well
    c = read_stage(export_world_usd(wm, tmp_path / "w2.usdc", poses=p7))
    assert max(np.abs(o.pose - P[k]).max() for k, o in enumerate(c.objects)) <= 1e-6


def test_recorded_episode_round_trip(tmp_path, capsys, wm):
    env = RecordEpisode(gym.make("DSGWorld-v0", obs=("rgb",), width=32, height=32))  # no poses in obs
    env.reset(seed=3)
    env.action_space.seed(3)
    for i in range(20):
        a = env.action_space.sample()
        env.step(3.0 * a if i == 0 else a)  # out of range: the env clips, the episode records what it applied
    ep = env.episode()
    assert np.abs(ep.actions).max() <= 1.0 and np.abs(ep.actions[0]).max() == 1.0
    assert ep.num_steps == 21 and ep.num_objects == wm.num_objects and ep.fps == env.metadata["render_fps"]
    assert ep.actions.shape == (20, env.action_space.shape[0]) and ep.rewards.shape == (20,)
    assert np.abs(matrix_to_pose7(ep.poses[-1]) - env.unwrapped._poses).max() < 1e-12
    assert np.ptp(ep.poses[:, :, :3, 3], axis=0).max() > 0.01  # the objects moved
    f = env.save(tmp_path / "ep")
    assert f == tmp_path / "ep.npz"
    loaded = load_episode(f)
    for name in ("poses", "rewards", "actions"):
        assert np.array_equal(getattr(loaded, name), getattr(ep, name)), name
    out = tmp_path / "ep.usdc"
    code, _, err = run_cli([WORLD, "--episode", f, "--out", out], capsys)
    assert code == 0, err
    assert_clean(out)
    c = read_stage(out)
    md = c.metadata
    assert md["timeCodesPerSecond"] == env.metadata["render_fps"] == 10
    assert (md["startTimeCode"], md["endTimeCode"]) == (0.0, 20.0)
    assert all(o.kinematic for o in c.objects)
    assert np.abs(c.episode.poses - ep.poses).max() <= 1e-9
    assert np.array_equal(c.episode.rewards, ep.rewards) and np.array_equal(c.episode.actions, ep.actions)
    assert max(np.abs(o.pose - ep.poses[0, k]).max() for k, o in enumerate(c.objects)) <= 1e-9  # untimed = t0
    env.close()


def test_record_episode_autosaves_finished_episodes(tmp_path):
    env = RecordEpisode(gym.make("DSGWorld-v0", obs=("poses",), max_episode_steps=3), folder=tmp_path / "eps")
    for seed in (0, 1):
        env.reset(seed=seed)
        done = False
        while not done:
            _, _, term, trunc, _ = env.step(np.zeros(env.action_space.shape, np.float32))
            done = term or trunc
    assert [p.name for p in env.saved] == ["episode_000000.npz", "episode_000001.npz"]
    assert load_episode(env.saved[1]).num_steps == 4
    with pytest.raises(ValueError, match="nothing recorded"):
        RecordEpisode(gym.make("DSGWorld-v0", obs=("poses",))).episode()


def test_episode_file_errors(tmp_path, wm):
    ok = Episode(10.0, np.tile(np.eye(4), (3, wm.num_objects, 1, 1)), rewards=np.zeros(2))
    p = save_episode(tmp_path / "ok.npz", ok)
    assert load_episode(p).fps == 10.0 and load_episode(p).actions is None
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    np.save(tmp_path / "single.npy", np.zeros(3))
    np.savez(tmp_path / "nofps.npz", poses=ok.poses)
    np.savez(tmp_path / "badshape.npz", fps=10.0, poses=np.zeros((3, 4, 4)))
    np.savez(tmp_path / "pickled.npz", fps=10.0, poses=np.array([{"a": 1}], dtype=object))
    np.savez(tmp_path / "norigid.npz", fps=10.0, poses=ok.poses * 2)
    p.with_name("cut.npz").write_bytes(p.read_bytes()[:100])
    cases = {
        "missing.npz": "does not exist",
        "junk.npz": "not a readable",
        "single.npy": "single array",
        "nofps.npz": r"lacks \['fps'\]",
        "badshape.npz": "Episode.poses",
        "pickled.npz": "not a readable",
        "norigid.npz": "rigid",
        "cut.npz": "not a readable",
    }
    for name, pattern in cases.items():
        with pytest.raises(EpisodeFileError, match=pattern) as e:
            load_episode(tmp_path / name)
        assert name in str(e.value)
    # an episode of the wrong object count cannot be exported with this world
    wrong = save_episode(tmp_path / "k1.npz", Episode(5.0, np.tile(np.eye(4), (2, 1, 1, 1))))
    with pytest.raises(ValueError, match="1 objects per step, the world has 2"):
        export_world_usd(wm, tmp_path / "x.usdc", episode=wrong)
    with pytest.raises(EpisodeFileError, match="must end in .npz"):
        save_episode(tmp_path / "ep.txt", ok)


def test_cli_bad_inputs(tmp_path, capsys):
    out = tmp_path / "w.usdc"
    np.save(tmp_path / "bad.npy", np.zeros((3, 4, 4)))
    (tmp_path / "bad.json").write_text("{not json")
    (tmp_path / "broken.dsgworld").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{}")
    cases = [
        ([WORLD, "--out", out, "--poses", "state9"], r"unknown state 'state9'.*\['state1', 'state2'"),
        ([tmp_path / "nope.dsgworld", "--out", out], "nope.dsgworld: world file does not exist"),
        ([tmp_path / "broken.dsgworld", "--out", out], "broken.dsgworld: cannot load world file"),
        ([WORLD, "--out", out, "--poses", tmp_path / "bad.npy"], r"bad.npy: poses: expected shape \(2, 7\)"),
        ([WORLD, "--out", out, "--poses", tmp_path / "bad.json"], "bad.json: cannot read poses"),
        (
            [WORLD, "--out", out, "--poses", tmp_path / "missing.npz"],
            "missing.npz: poses file does not exist",
        ),
        ([WORLD, "--out", tmp_path / "w.txt"], r"w.txt: a USD stage must end in .usdc"),
        ([WORLD, "--out", out, "--episode", tmp_path / "none.npz"], "none.npz: episode file does not exist"),
        ([WORLD, "--out", tmp_path / "d", "--ply", "--episode", tmp_path / "e.npz"], "--episode needs a USD"),
        ([WORLD, "--out", tmp_path / "d.usdc", "--ply"], "looks like a USD stage"),
    ]
    for argv, pattern in cases:
        code, _, err = run_cli(argv, capsys)
        assert code == 2 and "dsg-export: error:" in err, (argv, err)
        import re

        assert re.search(pattern, err), (pattern, err)
    assert not out.exists() and not list(tmp_path.glob(".*tmp*"))
    code, stdout, _ = run_cli(["--help"], capsys)
    assert code == 0 and "--episode" in stdout and "--ply" in stdout


# ------------------------------------------------------------------------------------------- PLY
def test_cli_ply_export_reads_back(tmp_path, capsys, wm):
    code, stdout, _ = run_cli([WORLD, "--out", tmp_path / "ply", "--ply"], capsys)
    assert code == 0
    paths = [Path(p) for p in stdout.split()]
    assert [p.name for p in paths] == ["background.ply"] + [f"{n}.ply" for n in wm.object_names]
    sets = [read_ply(p) for p in paths]
    for got, want, oid in zip(sets, [wm.background, *wm.objects], (0, *wm.object_ids)):
        assert_same_set(got, want, skip=("scales", "labels"))
        assert np.all(got.labels == oid)
        # the Inria layout stores float32 log-scales: exact where representable, else a few ulps
        np.testing.assert_allclose(got.scales, want.scales, rtol=3e-7, atol=0)
        # files read from PLY are rewritten byte for byte
        again = write_ply(tmp_path / "again.ply", got, labels=bool(oid))
        assert again.read_bytes() == paths[oid and wm.object_ids.index(oid) + 1].read_bytes()
    # placed at a state's poses: object Gaussians in the world frame
    placed = export_world_ply(wm, tmp_path / "placed", poses="state2")
    P = wm.state_poses("state2")  # noqa: N806
    for k, path in enumerate(placed[1:]):
        want = transform_gaussians(wm.objects[k], matrix_to_pose7(P[k]))
        got = read_ply(path)
        assert_same_set(got, want, skip=("scales", "labels"))
        np.testing.assert_allclose(got.means, wm.compose(P).means[wm.compose(P).labels == k + 1])


def test_ply_file_names_are_safe(tmp_path, wm):
    import dataclasses

    odd = dataclasses.replace(wm, object_names=("a/b c", "background"))
    names = [p.name for p in export_world_ply(odd, tmp_path)]
    assert names == ["background.ply", "a_b_c.ply", "background_2.ply"]


# ------------------------------------------------------------------------------------------- failures
def test_cli_unwritable_place_is_one_error_line(capsys):
    if not Path("/proc/self").is_dir():
        pytest.skip("needs /proc, a folder no one can create files in")
    code, out, err = run_cli([WORLD, "--out", "/proc/dsg.usda"], capsys)
    assert code == 2 and not out
    assert err.count("\n") == 1 and err.startswith(
        "dsg-export: error: export_stage: cannot write '/proc/dsg.usda'"
    )
    assert "Traceback" not in err and "pxr" not in err


def test_a_failed_export_leaves_no_new_folders(tmp_path, capsys, monkeypatch):
    import dsg_gym.io
    import dsg_gym.usd

    def unwritable(path, *args, **kwargs):
        raise OSError(f"export_stage: cannot write {str(path)!r}: No space left on device")

    monkeypatch.setattr(dsg_gym.usd, "export_stage", unwritable)
    code, _, err = run_cli([WORLD, "--out", tmp_path / "new" / "deeper" / "w.usda"], capsys)
    assert code == 2 and err.count("\n") == 1 and "No space left on device" in err
    assert os.listdir(tmp_path) == []

    real, calls = dsg_gym.io.write_ply, []

    def second_fails(path, g, **kw):
        calls.append(path)
        if len(calls) == 2:
            raise OSError(f"{path}: No space left on device")
        return real(path, g, **kw)

    monkeypatch.setattr(dsg_gym.io, "write_ply", second_fails)
    (tmp_path / "ply").mkdir()
    (tmp_path / "ply" / "notes.txt").write_text("kept")
    code, _, err = run_cli([WORLD, "--out", tmp_path / "ply", "--ply"], capsys)
    assert code == 2 and len(calls) == 2 and os.listdir(tmp_path / "ply") == ["notes.txt"]
    calls.clear()
    code, _, err = run_cli([WORLD, "--out", tmp_path / "fresh" / "ply", "--ply"], capsys)
    assert code == 2 and sorted(os.listdir(tmp_path)) == ["ply"]


@pytest.mark.parametrize("ply", [False, True])
def test_cli_folder_that_cannot_be_created_is_one_error_line(tmp_path, capsys, ply):
    (tmp_path / "notes.txt").write_text("a file, not a folder")
    out = tmp_path / "notes.txt" / "deeper" / ("ply" if ply else "w.usda")
    code, stdout, err = run_cli([WORLD, "--out", out, *(["--ply"] if ply else [])], capsys)
    assert code == 2 and not stdout and err.count("\n") == 1
    assert err.startswith("dsg-export: error: cannot create the folder ")
    assert str(tmp_path / "notes.txt") in err and "Traceback" not in err
    assert os.listdir(tmp_path) == ["notes.txt"]


def test_ply_export_of_a_world_without_background_gaussians(tmp_path, wm):
    import dataclasses

    from dsg_gym.gaussians import GaussianSet

    bg = GaussianSet.empty(wm.background.sh_degree, wm.background.num_features)
    bare = dataclasses.replace(wm, background=bg)
    paths = export_world_ply(bare, tmp_path)
    assert [p.name for p in paths] == [f"{n}.ply" for n in wm.object_names]
    assert [read_ply(p).num for p in paths] == [g.num for g in wm.objects]
