"""Tests for dsg_gym.usd: bad input raises a clear error, and writes are atomic (a failed or killed export
leaves the previous file and no temporary behind)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from _usd_scenes import example_world

from dsg_gym.usd import Episode, EpisodeRecorder, UsdCamera, UsdObject, export_stage, read_stage
from dsg_gym.usd import stage as stage_mod


@pytest.fixture(scope="module")
def world():
    return example_world()


def test_bad_inputs_raise_value_error(tmp_path, world):
    background, objects, cameras = world
    bad_pose = np.eye(4)
    bad_pose[0, 3] = np.nan
    skew = np.eye(4)
    skew[0, 1] = 0.3
    K_skew = cameras[0].K.copy()
    K_skew[0, 1] = 1.0
    cases = [
        (dict(path=tmp_path / "w.ply"), r"\.usdc .*\.usda"),
        (dict(path=tmp_path / "w.usd"), r"\.usdc .*\.usda"),
        (dict(path=tmp_path / "w.usdz"), r"\.usdc .*\.usda"),
        (dict(objects=[UsdObject("a", background, bad_pose)]), r"'a' pose: contains non-finite"),
        (dict(objects=[UsdObject("a", background, skew)]), r"'a' pose: not a rigid transform"),
        (dict(objects=[UsdObject("a", background, np.eye(3))]), r"pose must be \[4, 4\]"),
        (dict(objects=[UsdObject("a", background, np.eye(4), mass=0.0)]), r"mass"),
        (dict(objects=[UsdObject("a", background, np.eye(4))] * 2), r"same prim name"),
        (
            dict(objects=[UsdObject("a b", background, np.eye(4)), UsdObject("a_b", background, np.eye(4))]),
            r"same prim name",
        ),
        (dict(episode=Episode(10.0, np.stack([np.eye(4)] * 2)[None])), r"episode\.poses .*\[T, 3, 4, 4\]"),
        (dict(cameras=[UsdCamera("c", cameras[0].viewmat, K_skew, 10, 10)]), r"'c'\.K: .*no skew"),
        (dict(cameras=[UsdCamera("c", cameras[0].viewmat, cameras[0].K, 0, 10)]), r"'c'\.width"),
        (dict(up_axis="X"), r"up_axis"),
        (dict(meters_per_unit=float("inf")), r"meters_per_unit"),
        (dict(background="nope"), r"background must be a GaussianSet"),
        (dict(table_bounds=[[0, 0, 0]]), r"table_bounds"),
    ]
    for override, pattern in cases:
        kwargs = dict(path=tmp_path / "w.usdc", background=background, objects=objects, cameras=cameras)
        kwargs.update(override)
        with pytest.raises(ValueError, match=pattern):
            export_stage(**kwargs)
    assert os.listdir(tmp_path) == []


def test_bad_episodes_raise_value_error():
    eye = np.eye(4)[None, None]
    with pytest.raises(ValueError, match=r"Episode\.poses: expected shape"):
        Episode(10.0, np.eye(4))
    with pytest.raises(ValueError, match=r"Episode\.poses: contains non-finite"):
        Episode(10.0, np.full((2, 1, 4, 4), np.inf))
    with pytest.raises(ValueError, match=r"Episode\.fps"):
        Episode(0.0, eye)
    with pytest.raises(ValueError, match=r"Episode\.rewards: expected shape \(1,\)"):
        Episode(10.0, np.concatenate([eye, eye]), rewards=[1.0, 2.0])
    with pytest.raises(ValueError, match=r"Episode\.actions"):
        Episode(10.0, np.concatenate([eye, eye]), actions=np.zeros((3, 2)))
    rec = EpisodeRecorder(10.0)
    with pytest.raises(ValueError, match="reset"):
        rec.step(np.eye(4)[None])


def test_write_is_atomic_on_failure_mid_build(tmp_path, world, monkeypatch):
    background, objects, cameras = world
    target = tmp_path / "w.usdc"
    target.write_bytes(b"previous")

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(stage_mod, "write_collider", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        export_stage(target, background, objects, cameras)
    assert target.read_bytes() == b"previous"
    assert os.listdir(tmp_path) == ["w.usdc"]


def test_write_is_atomic_on_failure_after_temp_written(tmp_path, world, monkeypatch):
    background, objects, cameras = world
    target = tmp_path / "w.usda"
    target.write_bytes(b"previous")
    seen = []

    def failing_replace(src, dst):
        seen.append(Path(src))
        assert Path(src).is_file() and Path(src).suffix == ".usda" and Path(src).parent == tmp_path
        raise OSError("rename failed")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        export_stage(target, background, objects, cameras)
    assert seen and not seen[0].exists()
    assert target.read_bytes() == b"previous"
    assert os.listdir(tmp_path) == ["w.usda"]


def test_overwrite_replaces_existing_stage(tmp_path, world):
    background, objects, _ = world
    target = tmp_path / "w.usdc"
    export_stage(target, background, objects)
    export_stage(target, background, objects[:1])
    assert [o.name for o in read_stage(target).objects] == ["mug"]


def test_an_unwritable_place_is_an_os_error_naming_it(tmp_path, world):
    background, objects, _ = world
    if not Path("/proc/self").is_dir():
        pytest.skip("needs /proc, a folder no one can create files in")
    with pytest.raises(OSError, match=r"export_stage: cannot write '/proc/w.usda': Unable to create") as err:
        export_stage("/proc/w.usda", background, objects)
    assert "\n" not in str(err.value) and ".cpp" not in str(err.value)  # USD's reason, without its sources


def test_an_export_removes_what_killed_exports_to_its_path_left(tmp_path, world):
    import subprocess
    import sys
    import textwrap

    background, objects, _ = world
    target = tmp_path / "w.usda"
    code = f"""
        import contextlib, os, signal
        import numpy as np
        import dsg_gym.usd.stage as stage
        from dsg_gym.gaussians import GaussianSet
        real = stage.atomic_path

        @contextlib.contextmanager
        def killed_after_writing(path, **kw):
            with real(path, **kw) as tmp:
                yield tmp
                os.kill(os.getpid(), signal.SIGKILL)  # USD wrote the temporary; it is never renamed

        stage.atomic_path = killed_after_writing
        g = GaussianSet.from_rgb(np.zeros((5, 3)), np.tile([1.0, 0, 0, 0], (5, 1)), np.full((5, 3), 0.01),
                                 np.full(5, 0.5), np.full((5, 3), 0.5))
        stage.export_stage({str(target)!r}, g)
    """
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True)
    assert res.returncode != 0, res.stderr
    left = os.listdir(tmp_path)
    assert len(left) == 1 and left[0].startswith(".w.usda.tmp-") and (tmp_path / left[0]).stat().st_size > 0
    pid, host, rest = left[0][len(".w.usda.tmp-") :].split("-", 2)
    live = f".w.usda.tmp-{os.getppid()}-{host}-{rest}"  # a writer that still runs keeps its temporary
    elsewhere = f".w.usda.tmp-{pid}-{int(host, 16) ^ 1:08x}-{rest}"  # so does one on another machine
    for name in (live, elsewhere):
        (tmp_path / name).write_bytes(b"partial")
    export_stage(target, background, objects)
    assert sorted(os.listdir(tmp_path)) == sorted([live, elsewhere, "w.usda"])
    assert read_stage(target).background.num == background.num
