"""Small hand-made worlds for the env / physics tests (two boxes on a table)."""

from __future__ import annotations

import numpy as np

from dsg_gym.cameras import Cameras
from dsg_gym.gaussians import GaussianSet
from dsg_gym.world_model import TableBounds, WorldModel

HALF = 0.04  # boxes are 8 cm cubes


def box_gaussians(half: float, rgb, spacing: float = 0.008) -> GaussianSet:
    pts = []
    n = int(np.ceil(2 * half / spacing))
    g = (np.arange(n) + 0.5) / n * 2 * half - half
    a, b = np.meshgrid(g, g, indexing="ij")
    a, b = a.ravel(), b.ravel()
    for ax in range(3):
        o = [i for i in range(3) if i != ax]
        for s in (-half, half):
            p = np.zeros((a.size, 3))
            p[:, o[0]], p[:, o[1]], p[:, ax] = a, b, s
            pts.append(p)
    # the corners, so the hull is the full cube
    c = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    pts = np.concatenate(pts + [c])
    n = len(pts)
    q = np.tile([1.0, 0, 0, 0], (n, 1))
    return GaussianSet.from_rgb(
        pts, q, np.full((n, 3), 0.6 * spacing), np.full(n, 0.95), np.tile(rgb, (n, 1))
    )


def two_box_world() -> WorldModel:
    xs = np.arange(-0.3, 0.3, 0.01) + 0.005
    ys = np.arange(-0.2, 0.2, 0.01) + 0.005
    x, y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    n = len(pts)
    chk = ((np.floor(pts[:, 0] / 0.05) + np.floor(pts[:, 1] / 0.05)) % 2)[:, None]
    bg = GaussianSet.from_rgb(
        pts, np.tile([1.0, 0, 0, 0], (n, 1)), np.tile([0.007, 0.007, 0.001], (n, 1)), np.full(n, 0.95),
        0.3 + 0.4 * chk * np.ones((1, 3)),
    )  # fmt: skip
    objs = (box_gaussians(HALF, (0.9, 0.1, 0.1)), box_gaussians(HALF, (0.1, 0.2, 0.9)))
    s1 = np.repeat(np.eye(4)[None], 2, 0)
    s1[0, :3, 3] = (-0.1, 0.0, HALF)
    s1[1, :3, 3] = (0.1, 0.0, HALF)
    s2 = s1.copy()
    s2[:, 1, 3] = 0.1
    eye, target = np.array([0.0, -0.6, 0.5]), np.zeros(3)
    z = (target - eye) / np.linalg.norm(target - eye)
    xa = np.cross(z, [0, 0, 1.0])
    xa /= np.linalg.norm(xa)
    vm = np.eye(4)
    vm[:3, :3] = np.stack([xa, np.cross(z, xa), z])
    vm[:3, 3] = -vm[:3, :3] @ eye
    k = np.array([[80.0, 0, 32], [0, 80.0, 32], [0, 0, 1]])
    return WorldModel(
        background=bg,
        objects=objs,
        object_names=("red", "blue"),
        table=TableBounds(-0.3, 0.3, -0.2, 0.2, 0.0),
        cameras=Cameras(vm[None], k[None], 64, 64),
        states={"state1": s1, "state2": s2},
        name="two_boxes",
    )
