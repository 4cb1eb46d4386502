"""Gaussian sets, poses, cameras and a small world for the USD export tests."""

from __future__ import annotations

import math

import numpy as np

from dsg_gym.cameras import look_at
from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import quat_to_rotmat
from dsg_gym.usd import UsdCamera, UsdObject

FIELDS = ("means", "quats", "scales", "opacities", "sh", "features", "labels")


def random_set(rng, n, degree=3, n_feat=16, spread=0.05):
    k = (degree + 1) ** 2
    return GaussianSet(
        means=rng.normal(size=(n, 3)) * spread,
        quats=rng.normal(size=(n, 4)),
        scales=rng.uniform(0, 0.01, (n, 3)),
        opacities=rng.uniform(0, 1, n),
        sh=rng.normal(size=(n, k, 3)),
        features=rng.normal(size=(n, n_feat)),
        labels=rng.integers(-3, 7, n),
    )


def random_rotation(rng):
    q = rng.normal(size=4)
    return quat_to_rotmat(q / np.linalg.norm(q))


def random_pose(rng, scale=0.3):
    pose = np.eye(4)
    pose[:3, :3] = random_rotation(rng)
    pose[:3, 3] = rng.normal(size=3) * scale
    return pose


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    return pose


def make_camera(name="cam", eye=(0.6, -0.4, 0.5), w=160, h=120):
    K = np.array([[150.0, 0.0, 83.25], [0.0, 141.5, 57.5], [0.0, 0.0, 1.0]])
    return UsdCamera(name, look_at(eye, (0.0, 0.0, 0.02)), K, w, h)


def assert_bits_equal(a: GaussianSet, b: GaussianSet):
    assert a.num == b.num
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        assert x.tobytes() == y.tobytes(), f"{f} differs"


def example_world():
    """``(background, objects, cameras)``: a background, three objects (one of SH degree 1, one empty) and two
    cameras of different image sizes."""
    rng = np.random.default_rng(7)
    background = random_set(rng, 400, degree=3, n_feat=16, spread=0.3)
    objects = [
        UsdObject("mug", random_set(rng, 120, degree=3, n_feat=16), random_pose(rng), mass=0.25),
        UsdObject("red block #2", random_set(rng, 80, degree=1, n_feat=16), rot_z(90.0), mass=0.05),
        UsdObject("empty", GaussianSet.empty(sh_degree=0, num_features=16), np.eye(4)),
    ]
    cameras = [make_camera("cam0"), make_camera("cam 1", eye=(-0.5, 0.3, 0.7), w=64, h=48)]
    return background, objects, cameras
