"""The far shell: flat background Gaussians for the directions no training view saw."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dsg_gym.cameras import Cameras, look_at
from dsg_gym.gaussians import GaussianSet, rgb_to_sh0
from dsg_gym.poses import quat_to_rotmat
from dsg_gym.splat import rasterize
from dsg_gym.world import World
from train_world.complete.shell import (
    ShellConfig,
    background_shell,
    fibonacci_directions,
    with_background_shell,
)

WALL_RGB = {"+x": (0.9, 0.2, 0.2), "-x": (0.2, 0.9, 0.2), "+y": (0.2, 0.2, 0.9), "-y": (0.9, 0.9, 0.2)}
FLOOR_RGB = (0.5, 0.5, 0.5)


def _room(n_side: int = 40) -> GaussianSet:
    """A 2 x 2 m room 1.2 m high without a ceiling: four walls of one colour each and a grey floor."""
    s = np.linspace(-1.0, 1.0, n_side)
    h = np.linspace(0.0, 1.2, n_side // 2)
    pts, rgb = [], []
    for name, col in WALL_RGB.items():
        a, b = np.meshgrid(s, h)
        fixed = np.full(a.size, 1.0 if name[0] == "+" else -1.0)
        p = (
            np.stack([fixed, a.ravel(), b.ravel()], 1)
            if name[1] == "x"
            else np.stack([a.ravel(), fixed, b.ravel()], 1)
        )
        pts.append(p)
        rgb.append(np.tile(col, (len(p), 1)))
    a, b = np.meshgrid(s, s)
    pts.append(np.stack([a.ravel(), b.ravel(), np.zeros(a.size)], 1))
    rgb.append(np.tile(FLOOR_RGB, (a.size, 1)))
    p, c = np.concatenate(pts), np.concatenate(rgb)
    n = len(p)
    return GaussianSet(
        means=p,
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        scales=np.full((n, 3), 0.05),
        opacities=np.full(n, 0.99),
        sh=rgb_to_sh0(c)[:, None, :],
        features=np.tile([2.0, -1.0], (n, 1)),
    )


def _cameras() -> Cameras:
    """Eight views from inside the room, level and looking at the lower walls: none sees above them."""
    f, size = 40.0, 32
    eyes = [(0.3 * np.cos(a), 0.3 * np.sin(a), 0.4) for a in np.linspace(0, 2 * np.pi, 8, endpoint=False)]
    vms = np.stack([look_at(e, (3 * e[0], 3 * e[1], 0.3)) for e in eyes])
    K = np.array([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1.0]])
    return Cameras(vms, np.repeat(K[None], len(eyes), 0), size, size)


def _projects_inside(points, cams: Cameras) -> np.ndarray:
    inside = np.zeros(len(points), bool)
    for vm, K in zip(cams.viewmats, cams.Ks):
        p = points @ vm[:3, :3].T + vm[:3, 3]
        uvw = p @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = uvw[:, 0] / p[:, 2], uvw[:, 1] / p[:, 2]
        inside |= (p[:, 2] > 0) & (u >= 0) & (u <= cams.width) & (v >= 0) & (v <= cams.height)
    return inside


def test_fibonacci_directions_are_unit_and_even():
    d = fibonacci_directions(2000)
    assert d.shape == (2000, 3) and np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.abs(d.mean(axis=0)).max() < 0.01  # no side favoured
    assert (d[:, 2] > 0).mean() == pytest.approx(0.5, abs=0.01)


def test_shell_lies_behind_the_room_outside_every_view_coloured_by_the_wall_it_continues():
    bg, cams = _room(), _cameras()
    shell = background_shell(bg, [cams])
    cfg = ShellConfig()
    assert 0 < shell.num < cfg.directions
    assert not _projects_inside(shell.means.astype(np.float64), cams).any()  # never covers what a view saw
    centre = np.median(bg.means, axis=0)
    r = np.linalg.norm(shell.means - centre, axis=1)
    assert np.allclose(r, r[0], rtol=1e-5) and r[0] > np.linalg.norm(bg.means - centre, axis=1).max()
    # each shell Gaussian is a thin disc facing the centre
    normals = quat_to_rotmat(shell.quats.astype(np.float64))[:, :, 2]
    radial = (shell.means - centre) / r[:, None]
    assert np.allclose(np.abs(np.sum(normals * radial, axis=1)), 1.0, atol=1e-5)
    assert np.all(shell.scales[:, 2] < 0.1 * shell.scales[:, 0])
    # directions straight through the middle of a wall take that wall's colour (no views: nothing dropped)
    whole = background_shell(bg, [])
    assert whole.num == cfg.directions
    radial = (whole.means - centre) / np.linalg.norm(whole.means - centre, axis=1, keepdims=True)
    for name, col in WALL_RGB.items():
        axis = {"x": 0, "y": 1}[name[1]]
        sign = 1.0 if name[0] == "+" else -1.0
        toward = (sign * radial[:, axis] > 0.95) & (radial[:, 2] > 0.1)  # above the corner with the floor
        assert toward.any(), name
        assert np.allclose(whole.sh[toward, 0], rgb_to_sh0(np.array(col)), atol=1e-5), name
    assert np.all(shell.labels == 0) and np.allclose(shell.features, [2.0, -1.0])
    assert np.all(shell.sh[:, 1:] == 0)
    # deterministic
    again = background_shell(bg, [cams])
    assert np.array_equal(again.means, shell.means) and np.array_equal(again.sh, shell.sh)


def _render(g: GaussianSet, vm: np.ndarray, K: np.ndarray, size: int) -> np.ndarray:
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32))  # noqa: E731
    img, _, _ = rasterize(
        t(g.means), t(g.quats), t(g.scales), t(g.opacities), t(g.sh), t(vm[None]), t(K[None]), size, size,
        sh_degree=0, backgrounds=torch.zeros(1, 3),
    )  # fmt: skip
    return img[0].numpy()


def test_a_view_above_the_walls_sees_the_shell_and_the_training_views_do_not():
    bg, cams = _room(), _cameras()
    world = World(bg, {}, {"state1": np.zeros((0, 4, 4))}, {"state1": cams}, np.zeros((1, 2)), np.zeros(1),
                  metadata={"num_gaussians": bg.num})  # fmt: skip
    shelled = with_background_shell(world)
    n = shelled.metadata["background_shell"]["gaussians"]
    assert n > 0 and shelled.background.num == bg.num + n and shelled.metadata["num_gaussians"] == bg.num + n
    assert np.array_equal(shelled.background.means[: bg.num], bg.means)  # the room is untouched
    assert with_background_shell(shelled) is shelled  # once only
    # a camera tilted up past the top of the +x wall: black without the shell, the wall's red with it
    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1.0]])
    up = look_at((0.0, 0.0, 0.6), (1.0, 0.0, 1.9))
    top = slice(0, 4)
    assert _render(bg, up, K, 16)[top].max() < 0.05
    seen_above = _render(shelled.background, up, K, 16)[top].reshape(-1, 3).mean(axis=0)
    nearest = min(WALL_RGB, key=lambda k: np.linalg.norm(seen_above - np.array(WALL_RGB[k])))
    assert nearest == "+x" and seen_above.sum() > 1.0, seen_above  # mostly the red wall's colour
    # the training views render nearly as before: only discs just outside a view show at its edge, through
    # the gaps of this sparse room; dropping every disc that reaches in leaves them exactly as before
    strict = with_background_shell(world, ShellConfig(cull_sigmas=3.0))
    for vm, Kc in zip(cams.viewmats, cams.Ks):
        a, b = _render(bg, vm, Kc, cams.width), _render(shelled.background, vm, Kc, cams.width)
        assert np.abs(a - b).mean() < 0.01 and (np.abs(a - b).max(axis=2) < 1e-3).mean() > 0.8
        c = _render(strict.background, vm, Kc, cams.width)
        assert np.abs(a - c).max() < 1e-4


def test_too_little_background_gives_no_shell():
    bg = _room().subset(np.arange(5))
    assert background_shell(bg, [_cameras()]).num == 0
    with pytest.raises(ValueError, match="far_fraction"):
        ShellConfig(far_fraction=0.0)


def test_cli_adds_the_shell_once(tmp_path, capsys):
    from dsg_gym.world import load_world, write_world
    from train_world.cli.shell import main

    bg, cams = _room(), _cameras()
    world = World(bg, {}, {"state1": np.zeros((0, 4, 4))}, {"state1": cams}, np.zeros((1, 2)), np.zeros(1))
    write_world(tmp_path / "w.dsgworld", world)
    assert main([str(tmp_path / "w.dsgworld"), "--out", str(tmp_path / "s.dsgworld")]) == 0
    s = load_world(tmp_path / "s.dsgworld")
    assert s.background.num == bg.num + s.metadata["background_shell"]["gaussians"] > bg.num
    assert main([str(tmp_path / "s.dsgworld"), "--out", str(tmp_path / "t.dsgworld")]) == 2
    assert "already" in capsys.readouterr().err and not (tmp_path / "t.dsgworld").exists()
    assert main([str(tmp_path / "missing.dsgworld"), "--out", str(tmp_path / "t.dsgworld")]) == 2


def test_without_undoes_with_exactly():
    from dsg_gym.world import encode_world
    from train_world.complete.shell import without_background_shell

    world = World(_room(), {}, {"state1": np.zeros((0, 4, 4))}, {"state1": _cameras()}, np.zeros((1, 2)),
                  np.zeros(1), metadata={"num_gaussians": _room().num})  # fmt: skip
    shelled = with_background_shell(world)
    assert shelled.metadata["background_shell"]["gaussians"] > 0
    assert encode_world(without_background_shell(shelled)) == encode_world(world)
    assert without_background_shell(world) is world


def test_render_colours_continue_what_the_cameras_saw_not_what_they_never_saw():
    # the room's walls end at 0.5 m, within what the level cameras see; above the +x wall, out of every view,
    # float untrained Gaussians of another colour (magenta), as a trained world has beyond its views
    room = _room().subset(np.flatnonzero(_room().means[:, 2] <= 0.5))
    s = np.linspace(-1.0, 1.0, 40)
    a, b = np.meshgrid(s, np.linspace(0.95, 1.2, 6))
    stray = GaussianSet(
        means=np.stack([np.full(a.size, 1.0), a.ravel(), b.ravel()], 1),
        quats=np.tile([1.0, 0, 0, 0], (a.size, 1)),
        scales=np.full((a.size, 3), 0.05),
        opacities=np.full(a.size, 0.99),
        sh=rgb_to_sh0(np.tile([0.9, 0.1, 0.9], (a.size, 1)))[:, None, :],
        features=np.tile([2.0, -1.0], (a.size, 1)),
    )
    bg, cams = GaussianSet.concat([room, stray]), _cameras()
    assert not _projects_inside(stray.means.astype(np.float64), cams).any()
    rendered = background_shell(bg, [cams])
    mean = background_shell(bg, [cams], ShellConfig(colours="mean"))
    assert np.array_equal(rendered.means, mean.means) and np.array_equal(rendered.features, mean.features)
    centre = np.median(bg.means[bg.opacities >= ShellConfig().min_opacity], axis=0)
    d = rendered.means - centre
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    above = (d[:, 0] > 0.8) & (d[:, 2] > 0.2)  # over the +x wall, where the stray Gaussians are
    assert above.sum() > 10
    red = rgb_to_sh0(np.array(WALL_RGB["+x"]))
    assert np.allclose(rendered.sh[above, 0], red, atol=rgb_to_sh0(np.array([0.55] * 3))[0] + 0.2)
    assert np.abs(rendered.sh[above, 0] - red).max() < 0.35  # the wall's red, continued up
    assert np.abs(mean.sh[above, 0] - red).max() > 1.0  # the mean takes the stray magenta
    # no cameras: nothing was seen, so the mean colour stays
    assert np.array_equal(
        background_shell(bg, []).sh, background_shell(bg, [], ShellConfig(colours="mean")).sh
    )
    with pytest.raises(ValueError, match="colours"):
        ShellConfig(colours="nearest")


def test_the_floor_continues_where_the_captured_floor_ends_at_its_own_height():
    # the room's floor is cut away within 0.6 m of the middle, which no training view sees (they look out at
    # the walls), as a trained world has no floor where no view looked
    room, cams = _room(), _cameras()
    r = np.linalg.norm(room.means[:, :2], axis=1)
    bg = room.subset(np.flatnonzero((room.means[:, 2] > 0) | (r > 0.6)))
    hole = room.means[(room.means[:, 2] == 0) & (r < 0.5)].astype(np.float64)
    assert not _projects_inside(hole, cams).any()
    dome = background_shell(bg, [cams], z_up=True)
    mean = ShellConfig(colours="mean")  # the geometry is the colours' business of neither
    sphere = background_shell(bg, [cams], dataclasses.replace(mean, floor=False), z_up=True)
    assert np.array_equal(background_shell(bg, [cams], mean).means, sphere.means)  # z not known up: no floor
    assert sphere.means[:, 2].min() < -0.5 and dome.means[:, 2].min() == pytest.approx(0.0, abs=1e-6)
    on_floor = np.abs(dome.means[:, 2]) < 1e-6
    normals = quat_to_rotmat(dome.quats.astype(np.float64))[:, :, 2]
    assert on_floor.sum() > 20 and np.allclose(np.abs(normals[on_floor, 2]), 1.0, atol=1e-6)
    assert not _projects_inside(dome.means.astype(np.float64), cams).any()
    # the hole is filled at the floor's height, grey like the floor around it
    middle = on_floor & (np.linalg.norm(dome.means[:, :2], axis=1) < 0.5)
    assert middle.sum() > 5
    assert np.abs(dome.sh[middle, 0] - rgb_to_sh0(np.array(FLOOR_RGB))).max() < 0.1
    # a camera looking straight down into the hole: black without a shell, the floor's grey with the dome
    K = np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1.0]])
    down = look_at((0.0, 0.0, 0.8), (0.0, 0.01, 0.0))
    assert _render(bg, down, K, 16)[6:10, 6:10].max() < 0.05
    seen = _render(GaussianSet.concat([bg, dome]), down, K, 16)[6:10, 6:10]
    assert np.allclose(seen, FLOOR_RGB, atol=0.1)
    # a world that records its table is z-up: with_background_shell lays the floor
    world = World(bg, {}, {"state1": np.zeros((0, 4, 4))}, {"state1": cams}, np.zeros((1, 2)), np.zeros(1),
                  metadata={"table": {"bounds": [[-1, -1, 0], [1, 1, 0]]}})  # fmt: skip
    shelled = with_background_shell(world, mean)
    assert np.array_equal(shelled.background.means[bg.num :], dome.means)
    assert np.array_equal(shelled.background.sh[bg.num :], background_shell(bg, [cams], mean, z_up=True).sh)
    with pytest.raises(ValueError, match="floor_percentile"):
        ShellConfig(floor_percentile=101.0)
