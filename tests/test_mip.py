"""Mip-Splatting in training and at runtime: the 3D filter, baking it into the world, the world's rasterize mode."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import encode_world, load_world
from dsg_gym.world_model import WorldModel
from train_world.cli import train as cli
from train_world.eval.evaluate import render_gaussians
from train_world.single_state.checkpoint import load_checkpoint
from train_world.single_state.data import load_training_data
from train_world.single_state.field import SegmentedField, filter3d_variance
from train_world.single_state.presets import MIP_FILTER3D_SCALE, TrainConfig, get_preset, mip_overrides
from train_world.single_state.trainer import Trainer


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("cap"), test_views=2)


def _config(**overrides) -> TrainConfig:
    return TrainConfig(
        preset=get_preset("quick", **mip_overrides(True), **overrides), single_state=True, seed=3
    )


def _camera(z_offset: float, f: float = 100.0, size: int = 64):
    V = torch.eye(4, dtype=torch.float64)
    V[2, 3] = z_offset  # camera at (0, 0, -z_offset) looking down +z
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    return V, K


def test_filter3d_uses_the_finest_sampling_camera_and_covers_unseen_points():
    (V1, K1), (V2, K2) = _camera(0.0, f=100.0), _camera(-1.0, f=50.0)  # second camera 1 m further forward
    means = torch.tensor(
        [
            [0.0, 0.0, 2.0],  # depth 2 (f 100) and 1 (f 50): 0.02 vs 0.02 -> 0.02
            [0.0, 0.0, 4.0],  # depth 4 / 100 = 0.04, 3 / 50 = 0.06 -> 0.04
            [0.0, 0.0, 1.1],  # depth 1.1 / 100 = 0.011; 0.1 m in front of camera 2 (< near)
            [50.0, 0.0, 2.0],
        ]
    )  # outside both images: gets the largest value
    var = filter3d_variance(means, torch.stack([V1, V2]), torch.stack([K1, K2]), 64, 64, scale=0.2)
    want = 0.2 * torch.tensor([0.02, 0.04, 0.011, 0.04], dtype=torch.float64) ** 2
    assert torch.allclose(var.double(), want, rtol=1e-6)


def test_filtered_field_keeps_integrated_weight_and_bakes_into_the_world():
    g = torch.Generator().manual_seed(0)
    n = 50
    f = SegmentedField.from_points(
        torch.rand(n, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]),
        torch.rand(n, 3, generator=g),
        torch.full((n,), 0.004),
        sh_degree=1,
        opacity=0.9,
    )
    V, K = _camera(0.0)
    f.configure_filters("antialiased", 0.2, (V[None].float(), K[None].float(), 64, 64))
    s, o = f.scales_opacities()
    s0, o0 = f.scales(), f.opacities()
    assert bool((s > s0).all()) and bool((o < o0).all())
    # a 3D Gaussian's integral o * (2 pi)^1.5 * prod(scales) is unchanged by the filter's compensation
    assert torch.allclose(o * s.prod(-1), o0 * s0.prod(-1), rtol=1e-4)
    gs = f.to_gaussian_set()
    assert np.allclose(gs.scales, s.detach().numpy()) and np.allclose(gs.opacities, o.detach().numpy())
    baked = SegmentedField(*f.baked_params().values())
    baked.configure_filters("antialiased")
    with torch.no_grad():
        a = f.render(V[None].float(), K[None].float(), 64, 64, with_features=False).rgb
        b = baked.render(V[None].float(), K[None].float(), 64, 64, with_features=False).rgb
    assert float((a - b).abs().max()) < 1e-5 and float(a.max()) > 0.05, float(a.max())
    with pytest.raises(ValueError, match="cameras"):
        f.configure_filters("antialiased", 0.2)
    with pytest.raises(ValueError, match="rasterize_mode"):
        f.configure_filters("mip")


def test_mip_training_writes_an_antialiased_world_that_renders_as_trained(tiny, tmp_path):
    cfg = _config(iterations=60)
    data = load_training_data(tiny, cfg)
    t = Trainer(data, cfg)
    t.train(progress=False)
    assert t.field.filter3d is not None and t.field.filter3d.shape == (t.field.num,)
    path = t.write_world(tmp_path / "mip.dsgworld")
    w = load_world(path)
    assert w.splat_options == {"rasterize_mode": "antialiased", "eps2d": 0.1}
    assert w.metadata["train_config"]["preset"]["filter3d_scale"] == MIP_FILTER3D_SCALE
    with torch.no_grad():
        out = t.field.render(
            data.viewmats[:2],
            data.Ks[:2],
            data.width,
            data.height,
            background=t.background,
            with_features=False,
        )
    rgb, _ = render_gaussians(
        w.gaussians(),
        data.viewmats[:2].numpy(),
        data.Ks[:2].numpy(),
        data.width,
        data.height,
        tuple(data.background),
        w.splat_options,
    )
    assert np.abs(out.rgb.numpy() - rgb).max() < 1e-5
    classic, _ = render_gaussians(
        w.gaussians(),
        data.viewmats[:2].numpy(),
        data.Ks[:2].numpy(),
        data.width,
        data.height,
        tuple(data.background),
    )
    assert np.abs(classic - rgb).max() > 1e-3  # the mode matters for this world
    # the runtime renders it in its mode
    import gymnasium as gym

    wm = WorldModel.from_world(w)
    assert wm.rasterize_mode == "antialiased" and wm.splat_options == w.splat_options
    env = gym.make("DSGWorld-v0", world=str(path), width=32, height=32)
    try:
        env.reset(seed=0)
        r = env.unwrapped.renderer
        assert r.rasterize_mode == "antialiased" and r.eps2d == 0.1
    finally:
        env.close()


def test_unknown_rasterize_mode_in_a_world_file_is_refused(tiny, tmp_path):
    cfg = _config(iterations=5)
    t = Trainer(load_training_data(tiny, cfg), cfg)
    from dsg_gym.world import WorldFormatError, parse_world_bytes

    for bad, what in (
        ({"rasterize_mode": "mip"}, "rasterize_mode"),
        ({"eps2d": -1.0}, "eps2d"),
        ({"eps2d": "0.1"}, "eps2d"),
    ):
        with pytest.raises(WorldFormatError, match=what):
            parse_world_bytes(encode_world(t.world(bad)))


def test_resume_with_the_3d_filter_gives_the_same_world(tiny, tmp_path):
    cfg = _config(
        iterations=40,
        checkpoint_every=15,
        densify_from=10,
        densify_every=10,
        densify_until=35,
        reset_every=25,
    )
    data = load_training_data(tiny, cfg)
    full = Trainer(data, cfg, checkpoint=tmp_path / "a.ckpt")
    full.train(progress=False)
    killed = Trainer(data, cfg, checkpoint=tmp_path / "b.ckpt")
    killed.train(progress=False, stop_after=22)  # last checkpoint at 15; the filter was last updated at 10
    tensors, meta = load_checkpoint(tmp_path / "b.ckpt")
    assert meta["step"] == 15 and "filter3d" in tensors
    resumed = Trainer(data, cfg, checkpoint=tmp_path / "b.ckpt")
    resumed.load_checkpoint()
    resumed.train(progress=False)
    assert encode_world(resumed.world()) == encode_world(full.world())
    classic = Trainer(
        data, dataclasses.replace(cfg, preset=dataclasses.replace(cfg.preset, **mip_overrides(False)))
    )
    classic.train(progress=False, stop_after=5)
    assert classic.field.filter3d is None and classic.world().metadata["rasterize_mode"] == "classic"


def test_presets_default_to_the_antialiased_rasterizer_except_quick():
    for name in ("default", "paper"):
        p = get_preset(name)
        assert (p.rasterize_mode, p.eps2d, p.filter3d_scale) == ("antialiased", 0.1, 0.0)
        full = get_preset(name, **mip_overrides(True))  # --mip: Mip-Splatting's 3D filter too
        assert (full.rasterize_mode, full.eps2d, full.filter3d_scale) == (
            "antialiased",
            0.1,
            MIP_FILTER3D_SCALE,
        )
    q = get_preset("quick")
    assert (q.rasterize_mode, q.eps2d, q.filter3d_scale) == ("classic", 0.3, 0.0)
    # a configuration stored before these fields existed reads back as the classic renderer it was trained with
    d = TrainConfig(preset=get_preset("default")).to_dict()
    for k in ("rasterize_mode", "eps2d", "filter3d_scale"):
        del d["preset"][k]
    old = TrainConfig.from_dict(d).preset
    assert (old.rasterize_mode, old.eps2d, old.filter3d_scale) == ("classic", 0.3, 0.0)


def test_cli_mip_switch(tiny, tmp_path):
    for flag, mode, scale in (("--mip", "antialiased", MIP_FILTER3D_SCALE), ("--no-mip", "classic", 0.0)):
        out = tmp_path / f"{flag}.dsgworld"
        rc = cli.main(
            [
                str(tiny),
                "--out",
                str(out),
                "--preset",
                "quick",
                "--iterations",
                "10",
                "--single-state",
                "--quiet",
                flag,
            ]
        )
        assert rc == 0
        w = load_world(out)
        assert w.rasterize_mode == mode and w.metadata["train_config"]["preset"]["filter3d_scale"] == scale
