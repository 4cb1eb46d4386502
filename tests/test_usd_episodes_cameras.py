"""Tests for dsg_gym.usd: episodes as time samples (and the recorder), and the exported cameras."""

from __future__ import annotations

import math

import numpy as np
import pytest
from _usd_scenes import example_world, make_camera, random_pose, random_set, rot_z
from pxr import Gf, Usd, UsdGeom, UsdPhysics

from dsg_gym.cameras import look_at
from dsg_gym.usd import Episode, EpisodeRecorder, UsdCamera, UsdObject, export_stage, read_stage
from dsg_gym.usd import stage as stage_mod
from dsg_gym.usd.cameras import K_from_usd_lens, usd_lens_from_K


@pytest.fixture(scope="module")
def world():
    return example_world()


def test_episode_time_samples_play_back(tmp_path, world):
    background, objects, _ = world
    rng = np.random.default_rng(11)
    t_count, k = 7, len(objects)
    rec = EpisodeRecorder(fps=15.0)
    rec.reset([o.pose for o in objects])
    for t in range(1, t_count):
        poses = [random_pose(rng) for _ in range(k)]
        poses[1] = rot_z(170.0 * t) @ poses[1]  # large rotations: hemisphere flips
        rec.step(poses, reward=float(t), action=rng.normal(size=(k, 6)))
    episode = rec.episode()
    assert episode.num_steps == t_count and episode.actions.shape == (t_count - 1, k, 6)
    path = export_stage(tmp_path / "ep.usdc", background, objects, episode=episode)

    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 15.0 and stage.GetFramesPerSecond() == 15.0
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == t_count - 1
    for k_i, o in enumerate(objects):
        prim = stage.GetPrimAtPath(f"/World/Objects/{stage_mod._prim_names('o', [o.name])[0]}")
        assert UsdPhysics.RigidBodyAPI(prim).GetKinematicEnabledAttr().Get() is True
        xf = UsdGeom.Xformable(prim)
        for op in xf.GetOrderedXformOps():
            assert op.GetTimeSamples() == [float(t) for t in range(t_count)]
        for t in range(t_count):
            m = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(t))).T
            assert np.abs(m - episode.poses[t, k_i]).max() <= 1e-6
        # the untimed default is the object's own pose
        m = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
        assert np.abs(m - o.pose).max() <= 1e-6
        # consecutive quaternions are in the same hemisphere (interpolation takes the short way)
        orient = xf.GetOrderedXformOps()[1]
        qs = [orient.Get(Usd.TimeCode(t)) for t in range(t_count)]
        dots = [Gf.Dot(a, b) for a, b in zip(qs[:-1], qs[1:])]
        assert min(dots) >= 0

    got = read_stage(path)
    assert got.episode is not None and got.episode.fps == 15.0
    assert np.abs(got.episode.poses - episode.poses).max() <= 1e-6
    np.testing.assert_array_equal(got.episode.rewards, episode.rewards)
    np.testing.assert_array_equal(got.episode.actions, episode.actions)
    assert all(o.kinematic for o in got.objects)


def test_episode_single_step_and_no_objects(tmp_path):
    rng = np.random.default_rng(4)
    bg = random_set(rng, 10)
    path = export_stage(tmp_path / "e.usda", bg, [], episode=Episode(30, np.zeros((4, 0, 4, 4))))
    got = read_stage(path)
    assert got.episode.poses.shape == (4, 0, 4, 4) and got.metadata["endTimeCode"] == 3
    obj = UsdObject("a", random_set(rng, 5), np.eye(4))
    path = export_stage(tmp_path / "e1.usda", bg, [obj], episode=Episode(30, np.eye(4)[None, None]))
    got = read_stage(path)
    assert got.episode.poses.shape == (1, 1, 4, 4) and got.episode.rewards is None


def test_recorder_accepts_pose7_vectors():
    rec = EpisodeRecorder(fps=10)
    half = math.sqrt(0.5)
    rec.reset([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])
    rec.step([[0.0, 0.0, 0.0, 2 * half, 0.0, 0.0, 2 * half]], reward=1.0)  # unnormalised: renormalised
    ep = rec.episode()
    np.testing.assert_allclose(ep.poses[0, 0, :3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(ep.poses[1, 0], rot_z(90.0), atol=1e-12)
    with pytest.raises(ValueError, match=r"\[K, 4, 4\] or \[K, 7\]"):
        rec.step(np.zeros((1, 6)))


def _usd_project(stage: Usd.Stage, prim_path: str, points: np.ndarray, w: int, h: int) -> np.ndarray:
    gf_cam = UsdGeom.Camera(stage.GetPrimAtPath(prim_path)).GetCamera(Usd.TimeCode.Default())
    frustum = gf_cam.frustum
    view = np.array(frustum.ComputeViewMatrix())
    proj = np.array(frustum.ComputeProjectionMatrix())
    hom = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ view @ proj  # row vectors
    ndc = hom[:, :2] / hom[:, 3:4]
    return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1)


def test_cameras_project_consistently(tmp_path, world):
    background, _, _ = world
    rng = np.random.default_rng(9)
    cams = [
        make_camera("a"),
        UsdCamera(
            "b",
            look_at((0.1, 0.9, 0.3), (0.05, 0.0, 0.1)),
            np.array([[400.0, 0, 300.5], [0, 380.0, 170.25], [0, 0, 1]]),
            640,
            360,
        ),
    ]
    path = export_stage(tmp_path / "c.usdc", background, [], cams)
    stage = Usd.Stage.Open(str(path))
    for cam in cams:
        pts = rng.uniform(-0.15, 0.15, (50, 3))
        cam_pts = (cam.viewmat[:3, :3] @ pts.T + cam.viewmat[:3, 3:4]).T
        assert (cam_pts[:, 2] > 0).all()
        uv_cv = (cam.K @ (cam_pts / cam_pts[:, 2:3]).T).T[:, :2]
        uv_usd = _usd_project(stage, f"/World/Cameras/{cam.name}", pts, cam.width, cam.height)
        np.testing.assert_allclose(uv_usd, uv_cv, atol=1e-3)
        usd_cam = UsdGeom.Camera(stage.GetPrimAtPath(f"/World/Cameras/{cam.name}"))
        assert usd_cam.GetHorizontalApertureAttr().Get() == pytest.approx(20.955)
        assert tuple(usd_cam.GetClippingRangeAttr().Get()) == pytest.approx((0.01, 100.0))


def test_lens_conversion_inverse():
    K = np.array([[321.5, 0, 100.25], [0, 333.0, 77.0], [0, 0, 1]])
    np.testing.assert_allclose(K_from_usd_lens(usd_lens_from_K(K, 211, 149), 211, 149), K, rtol=1e-12)


def test_cameras_from_arrays(tmp_path, world):
    background = world[0]
    cams = [make_camera("x"), make_camera("y", eye=(0.2, 0.7, 0.4))]
    from dsg_gym.usd import cameras_from_arrays

    made = cameras_from_arrays([c.viewmat for c in cams], [c.K for c in cams], 160, 120)
    assert [c.name for c in made] == ["cam_000", "cam_001"]
    got = read_stage(export_stage(tmp_path / "c.usda", background, [], made))
    assert [c.name for c in got.cameras] == ["cam_000", "cam_001"]
    np.testing.assert_allclose(got.cameras[1].viewmat, cams[1].viewmat, atol=1e-9)
    with pytest.raises(ValueError, match="bad shapes"):
        cameras_from_arrays(np.eye(4), np.eye(3), 10, 10)
