"""The demo (``dsg-demo``, :mod:`dsg_gym.cli.demo`): a strip of frames written as a PNG.

:func:`run_env_demo` runs the scripted expert policy in ``DSGWorld-v0`` on the bundled world from a seeded
reset to its goal and writes a strip of RGB observations (top) and object masks (bottom), and beside it the
whole episode as an animated GIF (``render()`` frames with the goal drawn as a ghost; an MP4 too when the
``video`` extra is installed);
:func:`run_procedural_demo` renders a small procedural splat scene (a checkered table and three objects seen
from an orbit of cameras, RGB plus one-hot object ids in one ``rasterize`` pass) without any world file.
Both print what they did and return the PNG's path.
"""

from __future__ import annotations

import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from dsg_gym.cameras import orbit_eyes
from dsg_gym.io.atomic import atomic_path

if TYPE_CHECKING:
    import torch

__all__ = ["build_scene", "orbit_cameras", "run_env_demo", "run_procedural_demo"]

PALETTE = np.array([[40, 40, 40], [230, 80, 60], [70, 170, 90], [70, 110, 230]], dtype=np.uint8)


def _table(g: torch.Generator, n_side: int = 48):
    import torch

    xs = torch.linspace(-0.4, 0.4, n_side)
    ys = torch.linspace(-0.3, 0.3, int(n_side * 0.75))
    X, Y = torch.meshgrid(xs, ys, indexing="ij")
    means = torch.stack([X.reshape(-1), Y.reshape(-1), torch.zeros(X.numel())], -1)
    checker = ((X / 0.05).floor() + (Y / 0.05).floor()).remainder(2).reshape(-1)
    noise = torch.rand(means.shape[0], generator=g) * 0.08
    rgb = torch.stack([0.55 + 0.35 * checker, 0.45 + 0.3 * checker, 0.3 + 0.2 * checker], -1) - noise[:, None]
    step = 0.8 / (n_side - 1)
    scales = torch.tensor([step * 0.7, step * 0.7, 0.002]).expand(means.shape[0], 3)
    return means, scales, rgb.clamp(0, 1), torch.zeros(means.shape[0], dtype=torch.long)


def _object(g: torch.Generator, kind: str, centre, size: float, rgb, label: int, n: int = 900):
    import torch

    u = torch.rand(n, 3, generator=g) * 2 - 1
    if kind == "box":
        face = torch.randint(0, 3, (n,), generator=g)
        u[torch.arange(n), face] = torch.sign(u[torch.arange(n), face])
        pts = u * size
    elif kind == "ball":
        pts = u / u.norm(dim=-1, keepdim=True) * size
    else:  # cylinder along z
        ang = u[:, 0] * math.pi
        pts = torch.stack([torch.cos(ang) * size, torch.sin(ang) * size, u[:, 2] * size], -1)
    means = pts + torch.tensor(centre) + torch.tensor([0.0, 0.0, size])
    shade = 0.75 + 0.25 * torch.rand(n, 1, generator=g)
    colors = (torch.tensor(rgb) * shade).clamp(0, 1)
    scales = torch.full((n, 3), size * 0.12)
    return means, scales, colors, torch.full((n,), label, dtype=torch.long)


def build_scene(seed: int = 0):
    """Means, quats, scales, opacities and colours (RGB + 4 one-hot ids) of the demo scene."""
    import torch

    g = torch.Generator().manual_seed(seed)
    parts = [
        _table(g),
        _object(g, "box", (-0.15, -0.05, 0.0), 0.05, (0.9, 0.3, 0.25), 1),
        _object(g, "ball", (0.12, 0.08, 0.0), 0.045, (0.3, 0.75, 0.35), 2),
        _object(g, "cylinder", (0.05, -0.15, 0.0), 0.04, (0.3, 0.45, 0.95), 3),
    ]
    means = torch.cat([p[0] for p in parts])
    scales = torch.cat([p[1] for p in parts])
    rgb = torch.cat([p[2] for p in parts])
    labels = torch.cat([p[3] for p in parts])
    onehot = torch.nn.functional.one_hot(labels, 4).float()
    n = means.shape[0]
    quats = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4).contiguous()
    opacities = torch.full((n,), 0.95)
    return means, quats, scales.contiguous(), opacities, torch.cat([rgb, onehot], -1)


def orbit_cameras(n: int, size: int, radius: float = 0.75, height: float = 0.45):
    """``(viewmats [n,4,4], Ks [n,3,3])`` float32 tensors: ``n`` cameras evenly on a circle of ``radius``
    about the z axis, ``height`` above the table, the first at 0.3 rad from +x, all looking at the origin;
    50 degree vertical field of view, ``size x size`` pixels."""
    import torch

    from dsg_gym.geometry import intrinsics_from_fov, look_at_viewmat

    eyes = orbit_eyes(
        (0.0, 0.0, 0.0),
        (0.0, 0.0, 1.0),
        math.hypot(radius, height),
        (math.atan2(height, radius),),
        n,
        azimuth0=0.3 - 0.5 * math.pi,
    )
    viewmats = look_at_viewmat(
        torch.from_numpy(eyes).float(), torch.zeros(n, 3), torch.tensor([0.0, 0.0, 1.0]).expand(n, 3)
    )
    Ks = intrinsics_from_fov(math.radians(50.0), size, size).expand(n, 3, 3)  # noqa: N806
    return viewmats.float().contiguous(), Ks.float().contiguous()


def _save_png(image: np.ndarray, out: str | os.PathLike) -> Path:
    from PIL import Image

    path = Path(out)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


def run_env_demo(out: str | os.PathLike, size: int, seed: int, frames: int = 6, video: bool = True) -> Path:
    """Expert episode on the bundled world (``size x size`` observations, reset seed ``seed``); a strip of
    ``frames`` RGB and mask frames written to ``out``. With ``video``, the episode's ``render()`` frames (goal
    ghost drawn, :mod:`dsg_gym.envs.goal_overlay`) also go to ``out`` with the suffix ``.gif``, and ``.mp4``
    when the ``video`` extra is installed. Prints the steps/s, whether the goal was reached and the paths."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    import gymnasium as gym

    import dsg_gym  # noqa: F401  (registers DSGWorld-v0)
    from dsg_gym.collect.policies import ExpertPolicy

    env = gym.make(
        "DSGWorld-v0", width=size, height=size, obs=("rgb", "mask", "poses"),
        render_mode="rgb_array" if video else None, render_width=size, render_height=size, render_goal=video,
    )  # fmt: skip
    obs, info = env.reset(seed=seed)
    policy = ExpertPolicy(env)
    shots, steps, done, success = [obs], 0, False, False
    clip = [env.render()] if video else []
    elapsed = 0.0
    while not done:
        t0 = time.perf_counter()
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        elapsed += time.perf_counter() - t0
        steps += 1
        done = terminated or truncated
        success = bool(info.get("success", False))
        shots.append(obs)
        if video:
            clip.append(env.render())
    rate = steps / max(elapsed, 1e-9)
    fps = float(env.metadata.get("render_fps", 10))
    env.close()
    pick = np.unique(np.linspace(0, len(shots) - 1, frames).round().astype(int))
    k = int(max(int(o["mask"].max()) for o in shots)) + 1
    palette = PALETTE[np.arange(max(k, 4)) % len(PALETTE)]
    top = np.concatenate([shots[i]["rgb"] for i in pick], axis=1)
    bottom = np.concatenate([palette[shots[i]["mask"]] for i in pick], axis=1)
    path = _save_png(np.concatenate([top, bottom], axis=0), out)
    print(
        f"DSGWorld-v0 on the bundled world: {steps} expert steps at {rate:.0f} steps/s "
        f"({size}x{size}, rgb+mask), goal {'reached' if success else 'not reached'}"
    )
    print(f"wrote {path.resolve()}")
    if video:
        _write_clip(clip, path, fps)
    return path


def _write_clip(clip: list[np.ndarray], png: Path, fps: float) -> None:
    """The episode's frames beside ``png``: a GIF, and an MP4 when the ``video`` extra is installed."""
    from dsg_gym.video import VIDEO_EXTRA_HINT, mp4_available, write_gif, write_mp4

    print(f"wrote {write_gif(clip, png.with_suffix('.gif'), fps).resolve()} ({len(clip)} frames)")
    if mp4_available():
        print(f"wrote {write_mp4(clip, png.with_suffix('.mp4'), fps).resolve()}")
    else:
        print(f"no MP4 ({VIDEO_EXTRA_HINT})")


def run_procedural_demo(out: str | os.PathLike, size: int, views: int = 4) -> Path:
    """Render the procedural scene (:func:`build_scene`) from ``views`` orbit cameras at ``size x size``; a
    strip of RGB frames over their object ids, written to ``out``. Prints the render time."""
    import torch

    from dsg_gym.splat import rasterize

    means, quats, scales, opacities, colors = build_scene()
    viewmats, Ks = orbit_cameras(views, size)  # noqa: N806
    bg = torch.tensor([0.85, 0.88, 0.92, 1.0, 0.0, 0.0, 0.0])
    rasterize(means, quats, scales, opacities, colors, viewmats, Ks, size, size, backgrounds=bg)  # warm-up
    t0 = time.perf_counter()
    image, _, _ = rasterize(means, quats, scales, opacities, colors, viewmats, Ks, size, size, backgrounds=bg)
    ms = (time.perf_counter() - t0) * 1e3
    rgb = (image[..., :3].clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    ids = image[..., 3:].argmax(-1).numpy()
    top = np.concatenate(list(rgb), axis=1)
    bottom = np.concatenate(list(PALETTE[ids]), axis=1)
    path = _save_png(np.concatenate([top, bottom], axis=0), out)
    print(
        f"rendered {means.shape[0]} Gaussians into {views} views of {size}x{size} "
        f"(RGB + 4 id channels) in {ms:.1f} ms"
    )
    print(f"wrote {path.resolve()}")
    return path
