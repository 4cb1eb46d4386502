"""``dsg-compact`` (train_world.compact.compaction): scores, SH cut, pruning, budget, refit, CLI, runtime features."""

from __future__ import annotations

import dataclasses
import json
from types import MappingProxyType

import numpy as np
import pytest
import torch
from _worlds import box_gaussians

from dsg_gym.cameras import Cameras, look_at
from dsg_gym.gaussians import GaussianSet
from dsg_gym.splat import rasterize
from dsg_gym.world import encode_world, load_world, write_world
from dsg_gym.world_model import TableBounds, WorldModel
from train_world.capture.ply_import import world_from_model
from train_world.cli.compact import main
from train_world.compact.checks import SelfCheck
from train_world.compact.compaction import (
    CompactConfig,
    compact_world,
    hull_vertices,
    sh_change_bound,
    truncate_sh,
)
from train_world.compact.importance import gaussian_importance, scene_cameras, view_colors

# small and quick: few plausible cameras, tiny images
FAST = {"rings": 2, "per_ring": 6, "object_views": 12, "validation_views": 8, "refit_steps": 0, "step": 0.25}
HIDDEN = np.array([0.0, 0.0, 0.02])  # inside the closed opaque shell of the background
FAR = np.array([0.0, 0.0, 50.0])  # straight above every camera: outside all views
FAINT = np.array([0.1, 0.1, 0.0])  # opacity 0.002 < 1/255: never composited


def _t(a) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, np.float32))


def _random_set(n: int, seed: int, opacity=(0.2, 0.7)) -> GaussianSet:
    rng = np.random.default_rng(seed)
    means = rng.uniform(-0.25, 0.25, (n, 3))
    means[:, 2] = rng.uniform(-0.1, 0.1, n)
    return GaussianSet.from_rgb(
        means,
        rng.normal(size=(n, 4)),
        rng.uniform(0.02, 0.06, (n, 3)),
        rng.uniform(*opacity, n),
        rng.uniform(0, 1, (n, 3)),
    )


def _two_cameras():
    vm = np.stack(
        [look_at([0.0, -0.3, 1.4], [0, 0, 0], [0, 0, 1.0]), look_at([0.4, 0.2, 1.3], [0, 0, 0], [0, 0, 1.0])]
    )
    K = np.repeat(np.array([[50.0, 0, 24], [0, 50, 20], [0, 0, 1]])[None], 2, 0)
    return vm, K, 48, 40


def _shell(half: float, spacing: float) -> GaussianSet:
    """A closed cube of overlapping near-opaque discs: nothing inside it can be seen."""
    g = box_gaussians(half, (0.5, 0.5, 0.5), spacing=spacing)
    return dataclasses.replace(
        g, scales=np.full((g.num, 3), 1.5 * spacing, np.float32), opacities=np.full(g.num, 0.99, np.float32)
    )


def tiny_world(features: int = 0):
    """A checker plane with a closed opaque shell (and three invisible Gaussians) plus one box object, three
    capture cameras at 48x48."""
    xs, ys = np.arange(-0.2, 0.2, 0.02) + 0.01, np.arange(-0.15, 0.15, 0.02) + 0.01
    x, y = np.meshgrid(xs, ys, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    chk = ((np.floor(pts[:, 0] / 0.04) + np.floor(pts[:, 1] / 0.04)) % 2)[:, None]
    n = len(pts)
    plane = GaussianSet.from_rgb(
        pts,
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.tile([0.014, 0.014, 0.002], (n, 1)),
        np.full(n, 0.95),
        0.3 + 0.4 * chk * np.ones((1, 3)),
    )
    shell = _shell(0.035, 0.01)
    shell = dataclasses.replace(shell, means=shell.means + np.float32([0.0, 0.0, 0.02]))
    odd = GaussianSet.from_rgb(
        np.stack([HIDDEN, FAR, FAINT]),
        np.tile([1.0, 0, 0, 0], (3, 1)),
        np.full((3, 3), 0.004),
        np.array([0.95, 0.95, 0.002]),
        np.full((3, 3), 0.9),
    )
    bg = GaussianSet.concat([plane, shell, odd])
    obj = box_gaussians(0.03, (0.9, 0.1, 0.1), spacing=0.012)
    if features:
        rng = np.random.default_rng(0)
        bg = dataclasses.replace(bg, features=rng.normal(size=(bg.num, features)))
        obj = dataclasses.replace(obj, features=rng.normal(size=(obj.num, features)))
    s1 = np.eye(4)[None].copy()
    s1[0, :3, 3] = (0.12, 0.0, 0.03)
    s2 = s1.copy()
    s2[0, :3, 3] = (-0.12, 0.05, 0.03)
    vms = [
        look_at([0.6 * np.cos(a), 0.6 * np.sin(a), 0.5], [0, 0, 0], [0, 0, 1.0]) for a in (-1.6, -0.5, 0.6)
    ]
    K = np.array([[50.0, 0, 24], [0, 50, 24], [0, 0, 1]])
    wm = WorldModel(
        background=bg,
        objects=(obj,),
        object_names=("box",),
        table=TableBounds(-0.2, 0.2, -0.15, 0.15),
        cameras=Cameras(np.stack(vms), np.repeat(K[None], 3, 0), 48, 48),
        states={"state1": s1, "state2": s2},
        name="tiny",
    )
    return world_from_model(wm)


def _has(g: GaussianSet, p: np.ndarray) -> bool:
    return bool((np.abs(g.means - p).max(1) < 1e-6).any())


# ----------------------------------------------------------------------------------------------- scores
@pytest.mark.parametrize("splat", [{}, {"rasterize_mode": "antialiased", "eps2d": 0.1}])
def test_accumulated_weight_is_the_colour_gradient_of_ones(splat):
    g = _random_set(40, 0)
    vm, K, W, H = _two_cameras()
    imp = gaussian_importance(g, vm, K, W, H, **splat)
    ones = torch.ones((2, g.num, 1), requires_grad=True)
    img, _, _ = rasterize(
        _t(g.means), _t(g.quats), _t(g.scales), _t(g.opacities), ones, _t(vm), _t(K), W, H, **splat
    )
    img.sum().backward()
    per_cam = ones.grad[..., 0].double().numpy()  # d(sum of image)/d(colour) = sum_p T alpha
    assert imp.num_cameras == 2 and per_cam.max() > 1.0  # the Gaussians are visible
    np.testing.assert_allclose(imp.weight_sum, per_cam.sum(0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(imp.weight_max, per_cam.max(0), rtol=1e-5, atol=1e-6)


def test_accumulated_weight_matches_a_direct_per_pixel_sum():
    """sum_p T alpha from the renderer's own projection, composited pixel by pixel in numpy (float32, the
    kernel's arithmetic: alpha = min(0.99, o exp(-sigma)), skipped below 1/255, stop at T < 1e-4)."""
    g = _random_set(12, 4, opacity=(0.5, 0.99))
    vm, K, W, H = _two_cameras()
    imp = gaussian_importance(g, vm, K, W, H)
    _, _, meta = rasterize(_t(g.means), _t(g.quats), _t(g.scales), _t(g.opacities), _t(np.ones((g.num, 1))),
                           _t(vm), _t(K), W, H)  # fmt: skip
    m2, cn, dp = (meta[k].numpy() for k in ("means2d", "conics", "depths"))
    vis = meta["radii"].numpy().max(-1) > 0
    o = g.opacities.astype(np.float32)
    per_cam = np.zeros((2, g.num))
    half, one = np.float32(0.5), np.float32(1.0)
    for c in range(2):
        order = [i for i in np.argsort(dp[c], kind="stable") if vis[c, i]]
        for y in range(H):
            for x in range(W):
                T = one
                for i in order:
                    dx, dy = np.float32(x + 0.5) - m2[c, i, 0], np.float32(y + 0.5) - m2[c, i, 1]
                    sigma = (cn[c, i, 0] * half * dx + cn[c, i, 1] * dy) * dx + cn[c, i, 2] * half * dy * dy
                    if sigma < 0:
                        continue
                    alpha = min(np.float32(0.99), o[i] * np.float32(np.exp(-sigma)))
                    if alpha < np.float32(1 / 255) or T * (one - alpha) < np.float32(1e-4):
                        if alpha >= np.float32(1 / 255):
                            break
                        continue
                    per_cam[c, i] += alpha * T
                    T = T * (one - alpha)
    assert per_cam.max() > 5.0
    np.testing.assert_allclose(imp.weight_sum, per_cam.sum(0), rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(imp.weight_max, per_cam.max(0), rtol=1e-4, atol=1e-4)


def test_removal_error_matches_renders_without_each_gaussian():
    g = _random_set(20, 1)
    vm, K, W, H = _two_cameras()
    bg = (0.2, 0.3, 0.4)
    imp = gaussian_importance(g, vm, K, W, H, background=bg)
    cols = _t(view_colors(g, vm))

    def render(keep):
        out, _, _ = rasterize(
            _t(g.means[keep]),
            _t(g.quats[keep]),
            _t(g.scales[keep]),
            _t(g.opacities[keep]),
            cols[:, keep],
            _t(vm),
            _t(K),
            W,
            H,
            backgrounds=_t(bg),
        )
        return out.double().numpy()

    full = render(np.arange(g.num))
    direct = np.array([((full - render(np.delete(np.arange(g.num), i))) ** 2).sum() for i in range(g.num)])
    assert direct.max() > 0.1
    np.testing.assert_allclose(imp.error_sum, direct, rtol=1e-4, atol=1e-6)


def test_scene_cameras_orbit_the_capture_target():
    eyes = [[0.1 + 0.8 * np.cos(a), 0.8 * np.sin(a), 0.6] for a in (0.0, 2.0, 4.0)]
    vm = np.stack([look_at(e, [0.1, 0, 0], [0, 0, 1.0]) for e in eyes])
    cams = scene_cameras(vm, np.repeat(np.eye(3)[None], 3, 0), 32, 32, rings=3, per_ring=5)
    assert len(cams) == 3 + 15 and cams.num_capture == 3
    np.testing.assert_allclose(cams.target, [0.1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(cams.up, [0, 0, 1], atol=1e-9)
    assert cams.radius == pytest.approx(1.0)  # |(0.8, 0, 0.6)|
    assert cams.elevations_deg[0] == pytest.approx(np.degrees(np.arcsin(0.6)) - 10)
    eyes = -np.einsum("cji,cj->ci", cams.viewmats[3:, :3, :3], cams.viewmats[3:, :3, 3])
    np.testing.assert_allclose(np.linalg.norm(eyes - cams.target, axis=1), 1.0, atol=1e-9)


# ----------------------------------------------------------------------------------------------- SH
def test_sh_cut_keeps_view_independent_colours_and_respects_the_bound():
    rng = np.random.default_rng(2)
    n = 12
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = rng.normal(size=(n, 3))
    sh[4:8, 1:] = 1e-3 * rng.normal(size=(4, 15, 3))  # tiny view dependence: cut
    sh[8:, 1:4] = 0.5 * rng.normal(size=(4, 3, 3))  # strong first band: kept, bands 2-3 are zero anyway
    g = GaussianSet(
        rng.uniform(-0.1, 0.1, (n, 3)),
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.full((n, 3), 0.01),
        np.full(n, 0.9),
        sh,
    )
    cut, need = truncate_sh(g, 0.01)
    assert cut.sh_degree == 1 and need.tolist() == [0] * 8 + [1] * 4
    eyes = rng.normal(size=(20, 3))
    vm = np.stack([look_at(3 * e / np.linalg.norm(e), [0, 0, 0], [0.3, 0.2, 1.0]) for e in eyes])
    before, after = view_colors(g, vm), view_colors(cut, vm)
    np.testing.assert_array_equal(after[:, :4], before[:, :4])  # no higher bands: bit for bit
    np.testing.assert_array_equal(after[:, 8:], before[:, 8:])  # kept bands: bit for bit
    assert np.abs(after[:, 4:8] - before[:, 4:8]).max() <= sh_change_bound(g.sh[4:8], 0).max() <= 0.01
    # all view-independent: degree 0, identical colours
    flat = dataclasses.replace(g, sh=np.concatenate([sh[:, :1], np.zeros((n, 15, 3), np.float32)], 1))
    cut0, _ = truncate_sh(flat, 0.0)
    assert cut0.sh_degree == 0
    np.testing.assert_array_equal(view_colors(cut0, vm), view_colors(flat, vm))


def test_sh_bound_is_an_upper_bound_over_directions():
    rng = np.random.default_rng(3)
    sh = rng.normal(size=(50, 16, 3))
    dirs = rng.normal(size=(4000, 3))
    from dsg_gym.splat import spherical_harmonics

    for L in range(3):
        high = torch.from_numpy(sh).clone()
        high[:, : (L + 1) ** 2] = 0
        vals = (
            spherical_harmonics(3, torch.from_numpy(dirs)[:, None], high[None]).abs().amax(dim=(0, 2)).numpy()
        )
        bound = sh_change_bound(sh, L)
        assert (vals <= bound + 1e-12).all() and (vals >= 0.3 * bound).all()  # valid and not loose


# ----------------------------------------------------------------------------------------------- pruning
def test_invisible_gaussians_go_visible_ones_stay():
    w = tiny_world()
    out, rep = compact_world(w, CompactConfig(fraction=1.0, **FAST))  # only the invisible ones
    bg = out.background
    for p in (HIDDEN, FAR, FAINT):
        assert _has(w.background, p) and not _has(bg, p)
    assert rep["parts"]["background"]["after"] == bg.num < w.background.num
    m = w.background.means
    plane = (np.abs(m[:, 2]) < 1e-6) & (np.abs(m[:, :2]).max(1) > 0.05)  # not under the shell
    plane &= np.abs(m - FAINT).max(1) > 1e-6
    assert plane.sum() > 100 and all(_has(bg, p) for p in m[plane])  # every plane disc in sight stays
    assert out.objects[1].gaussians.num == w.objects[1].gaussians.num  # a visible box keeps everything


def test_budget_is_respected_and_hull_and_table_are_unchanged(tmp_path):
    from dsg_gym.physics import PhysicsProxy

    w = tiny_world()
    cfg = CompactConfig(max_psnr_drop=0.3, reference_psnr=25.0, **FAST)
    out, rep = compact_world(w, cfg)
    assert rep["within_budget"] and rep["psnr_drop"] <= 0.3
    assert rep["gaussians_after"] < 0.8 * rep["gaussians_before"]  # redundant ones went too
    assert [r["kept"] for r in rep["rounds"]] == sorted((r["kept"] for r in rep["rounds"]), reverse=True)
    # an independent check of the result with the same cameras
    from train_world.compact.compaction import _capture_cameras

    vm, Ks, W, H = _capture_cameras(w)
    chk = SelfCheck(w, scene_cameras(vm, Ks, W, H, rings=2, per_ring=6), (0, 0, 0), cfg, 25.0)
    assert chk(out.background, [out.objects[1].gaussians])["psnr_drop"] == pytest.approx(rep["psnr_drop"])
    a, b = WorldModel.from_world(w), WorldModel.from_world(out)
    assert a.table == b.table
    ha, hb = PhysicsProxy(a).hulls[0], PhysicsProxy(b).hulls[0]
    assert {tuple(p) for p in ha.round(9)} == {tuple(p) for p in hb.round(9)}
    assert hull_vertices(w.objects[1].gaussians).sum() >= 8
    # deterministic
    again, _ = compact_world(w, cfg)
    assert encode_world(again) == encode_world(out)


def test_refit_lowers_the_error_and_keeps_hull_opacities():
    w = tiny_world()
    base = dict(FAST, refit_steps=0)
    _plain, r0 = compact_world(w, CompactConfig(fraction=0.5, **base))
    fitted, r1 = compact_world(
        w, CompactConfig(fraction=0.5, **{**base, "refit_steps": 40, "refit_cycles": 1})
    )
    assert r1["refits"] == 1 and r1["gaussians_after"] == r0["gaussians_after"]
    assert r1["check"]["self_psnr"] > r0["check"]["self_psnr"]
    g, g0 = fitted.objects[1].gaussians, w.objects[1].gaussians
    corners = g0.means[hull_vertices(g0)]  # object means are not refitted: the hull stays
    for m in corners:
        i = np.flatnonzero(np.abs(g.means - m).max(1) < 1e-7)
        assert len(i) == 1 and g.opacities[i[0]] >= 0.2


def test_round_trip_of_a_compacted_world(tmp_path):
    w = tiny_world(features=16)
    g = w.objects[1].gaussians  # stored with SH degree 2 but view-independent: goes back to degree 0
    sh = np.concatenate([g.sh, np.zeros((g.num, 8, 3), np.float32)], 1)
    w = dataclasses.replace(
        w, objects=MappingProxyType({1: w.objects[1]._replace(gaussians=dataclasses.replace(g, sh=sh))})
    )
    out, rep = compact_world(w, CompactConfig(fraction=0.6, **FAST))
    assert (
        rep["parts"]["object_1"]["sh_degree_before"] == 2 and rep["parts"]["object_1"]["sh_degree_after"] == 0
    )
    path = write_world(tmp_path / "c.dsgworld", out)
    back = load_world(path)
    assert back.background.num == out.background.num < w.background.num
    np.testing.assert_array_equal(back.background.means, out.background.means)
    np.testing.assert_array_equal(back.objects[1].gaussians.features, out.objects[1].gaussians.features)
    assert back.background.num_features == 16  # dsg-eval's mask IoU still has its features
    assert back.metadata["compacted"]["gaussians_after"] == rep["gaussians_after"]
    assert back.metadata["compacted"]["options"]["fraction"] == 0.6
    assert dict(back.poses).keys() == dict(w.poses).keys()
    assert back.objects[1].gaussians.sh.shape[1] == 1


# ----------------------------------------------------------------------------------------------- runtime
def test_env_does_not_keep_identity_features(tmp_path):
    import gymnasium as gym

    import dsg_gym  # noqa: F401  registers DSGWorld-v0

    path = write_world(tmp_path / "f.dsgworld", tiny_world(features=16))
    wm = WorldModel.load(path)
    assert wm.background.num_features == 16
    slim = wm.without_features()
    assert slim.background.num_features == 0 and all(o.num_features == 0 for o in slim.objects)
    assert np.shares_memory(slim.background.means, wm.background.means)
    env = gym.make("DSGWorld-v0", world=str(path), width=32, height=32)
    try:
        env.reset(seed=0)
        u = env.unwrapped
        assert u.world.background.num_features == 0 and u.world.objects[0].num_features == 0
        obs, *_ = env.step(env.action_space.sample())
        assert obs["mask"].max() <= 1
    finally:
        env.close()


# ----------------------------------------------------------------------------------------------- CLI
def test_cli_help_and_a_tiny_run(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0 and "--max-psnr-drop" in capsys.readouterr().out
    src = write_world(tmp_path / "w.dsgworld", tiny_world())
    args = [
        str(src),
        "--out",
        str(tmp_path / "o.dsgworld"),
        "--report",
        str(tmp_path / "r.json"),
        "--quiet",
        "--rings",
        "2",
        "--per-ring",
        "6",
        "--object-views",
        "12",
        "--validation-views",
        "8",
        "--refit-steps",
        "0",
        "--reference-psnr",
        "25",
    ]
    assert main(args) == 0
    printed = json.loads(capsys.readouterr().out)
    report = json.loads((tmp_path / "r.json").read_text())
    assert printed == report
    assert report["gaussians_after"] < report["gaussians_before"] and report["psnr_drop"] <= 0.3
    assert load_world(tmp_path / "o.dsgworld").background.num == report["parts"]["background"]["after"]


def test_bad_input_gives_clear_errors(tmp_path, capsys):
    assert main([str(tmp_path / "none.dsgworld"), "--out", str(tmp_path / "o.dsgworld")]) == 2
    assert "does not exist" in capsys.readouterr().err
    src = write_world(tmp_path / "w.dsgworld", tiny_world())
    assert main([str(src), "--out", str(tmp_path / "o.dsgworld"), "--max-psnr-drop", "-1"]) == 2
    assert "max_psnr_drop must be a finite number >= 0" in capsys.readouterr().err
    assert main([str(src), "--out", str(tmp_path / "o.dsgworld"), "--capture", str(tmp_path)]) == 2
    assert "not a capture folder" in capsys.readouterr().err
    (tmp_path / "junk.dsgworld").write_bytes(b"not a world")
    assert main([str(tmp_path / "junk.dsgworld"), "--out", str(tmp_path / "o.dsgworld")]) == 2
    assert "truncated" in capsys.readouterr().err
    assert not (tmp_path / "o.dsgworld").exists()
    for bad in ({"fraction": 0.0}, {"step": 1.0}, {"reference_psnr": -3.0}, {"object_views": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            CompactConfig(**bad)
    with pytest.raises(ValueError, match="no capture cameras"):
        compact_world(dataclasses.replace(tiny_world(), cameras=MappingProxyType({})))


def test_the_far_shell_count_follows_its_kept_gaussians():
    from train_world.complete.shell import without_background_shell

    w = tiny_world()
    n = 3 + _shell(0.035, 0.01).num  # the cube and the three odd Gaussians, the background's last rows
    w = dataclasses.replace(
        w, metadata=MappingProxyType({**w.metadata, "background_shell": {"gaussians": n}})
    )
    out, _ = compact_world(w, CompactConfig(fraction=0.8, **FAST))
    tail = w.background.means[-n:]
    in_tail = np.array([(np.abs(tail - p).max(1) < 1e-6).any() for p in out.background.means])
    kept = out.metadata["background_shell"]["gaussians"]
    assert 0 < kept < n and kept == in_tail.sum() and in_tail[-kept:].all()
    plain = without_background_shell(out)
    assert plain.background.num == out.background.num - kept and "background_shell" not in plain.metadata
