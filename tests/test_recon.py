"""Single-state reconstruction: training improves a tiny scene, losses, densification, resume, NaN, CLI."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import encode_world, load_world
from train_world.cli import train as cli
from train_world.single_state.checkpoint import load_checkpoint
from train_world.single_state.data import load_training_data
from train_world.single_state.field import SegmentedField
from train_world.single_state.losses import identity_loss, neighbour_kl_loss, photometric_loss, ssim
from train_world.single_state.presets import TrainConfig, get_preset
from train_world.single_state.strategy import DensifyStrategy, StrategyConfig
from train_world.single_state.trainer import Trainer, TrainingDiverged, make_optimizers


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("cap"), test_views=2)


def _config(**preset_overrides) -> TrainConfig:
    return TrainConfig(preset=get_preset("quick", **preset_overrides), single_state=True, seed=3)


@torch.no_grad()
def _train_view_metrics(trainer: Trainer) -> tuple[float, float]:
    d = trainer.data
    out = trainer.field.render(d.viewmats, d.Ks, d.width, d.height, background=trainer.background)
    mse = float(((out.rgb.clamp(0, 1) - d.images) ** 2).mean())
    pred = trainer.classifier(out.features).argmax(-1)
    acc = float((pred == d.classes).double().mean())
    return -10 * math.log10(mse), acc


def test_quick_training_improves_psnr_and_masks_beat_chance(tiny):
    data = load_training_data(tiny, _config())
    assert data.heldout == (0, 8) and len(data) == 14 and data.num_classes == 3
    trainer = Trainer(data, _config())
    psnr0, _ = _train_view_metrics(trainer)
    trainer.train(progress=False)
    psnr1, acc = _train_view_metrics(trainer)
    assert psnr1 > psnr0 + 5.0, (psnr0, psnr1)
    counts = torch.bincount(data.classes.reshape(-1), minlength=3).double()
    majority = float(counts.max() / counts.sum())  # always guessing the commonest class
    assert acc > majority + 0.5 * (1 - majority), (acc, majority)
    assert trainer.field.num != 3000  # densification/pruning changed the count


def test_losses_are_zero_for_identical_inputs_and_positive_otherwise():
    g = torch.Generator().manual_seed(0)
    img = torch.rand((16, 20, 3), generator=g)
    assert float(photometric_loss(img, img)) == pytest.approx(0.0, abs=1e-6)
    assert float(ssim(img, img)) == pytest.approx(1.0, abs=1e-6)
    other = (img + 0.1 * torch.randn(img.shape, generator=g)).clamp(0, 1)
    assert float(photometric_loss(other, img)) > 0.01
    assert float(ssim(other, img)) < 0.99
    target = torch.randint(0, 4, (16, 20), generator=g)
    perfect = 50.0 * torch.nn.functional.one_hot(target, 4).float()
    assert float(identity_loss(perfect, target)) == pytest.approx(0.0, abs=1e-6)
    uniform = torch.zeros(16, 20, 4)
    assert float(identity_loss(uniform, target)) == pytest.approx(1.0, abs=1e-6)  # log(4) / log(4)
    means = torch.rand((50, 3), generator=g)
    same = torch.zeros(50, 3)
    assert float(neighbour_kl_loss(means, same, generator=g)) == pytest.approx(0.0, abs=1e-7)
    assert float(neighbour_kl_loss(means, 5 * torch.randn((50, 3), generator=g), generator=g)) > 0.1


def _hand_field() -> SegmentedField:
    means = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    scales = torch.tensor([0.001, 0.5, 0.001, 0.001])
    f = SegmentedField.from_points(means, torch.full((4, 3), 0.5), scales, sh_degree=1, num_features=4)
    with torch.no_grad():
        f.opacity_logits[2] = -8.0  # opacity 3e-4: pruned
        f.features.copy_(torch.arange(16.0).reshape(4, 4))
    return f


def test_densification_clones_splits_and_prunes_hand_made_cases():
    f = _hand_field()
    opts = make_optimizers(f, get_preset("quick").lrs, 1.0)
    for p in f.params().values():  # one Adam step so there are moments to carry
        p.grad = torch.ones_like(p)
    for o in opts.values():
        o.step()
    before = [tuple(r.tolist()) for r in f.features.detach()]
    s = DensifyStrategy(StrategyConfig(grad_threshold=1e-3, percent_dense=0.01, scene_extent=1.0), f.num)
    s.grad2d = torch.tensor([1.0, 1.0, 0.0, 0.0], dtype=torch.float64)  # 0: small+high, 1: big+high
    s.count = torch.tensor([1, 1, 1, 1])
    info = s.densify_and_prune(f, opts, torch.Generator().manual_seed(0))
    assert info == {"clone": 1, "split": 1, "prune": 1}
    assert f.num == 4 + 1 + 1 - 1
    feats = f.features.detach()
    rows = [tuple(r.tolist()) for r in feats]
    assert rows.count(before[0]) == 2  # cloned
    assert rows.count(before[1]) == 2  # split in two ...
    split_scales = f.scales().detach()[feats[:, 0] == before[1][0]]
    big = math.exp(math.log(0.5) - 5e-3)  # the Adam step moved the log-scale by -lr
    assert torch.allclose(
        split_scales, torch.full_like(split_scales, big / 1.6), rtol=1e-4
    )  # ... scale / 1.6
    assert before[2] not in rows  # pruned
    assert before[3] in rows  # untouched
    for name, p in f.params().items():
        st = opts[name].state[p]
        assert st["exp_avg"].shape == p.shape and opts[name].param_groups[0]["params"][0] is p
        new_rows = st["exp_avg"][-3:]  # clone + 2 split halves are appended with zero moments
        assert float(new_rows.abs().sum()) == 0.0
        assert float(st["exp_avg"][0].abs().sum()) > 0  # the kept original keeps its moments
    assert s.grad2d.shape == (f.num,) and float(s.grad2d.sum()) == 0.0


def test_opacity_reset_caps_opacities_and_zeroes_moments():
    f = _hand_field()
    opts = make_optimizers(f, get_preset("quick").lrs, 1.0)
    f.opacity_logits.grad = torch.ones_like(f.opacity_logits)
    opts["opacity_logits"].step()
    DensifyStrategy.reset_opacity(f, opts, 0.01)
    op = f.opacities().detach()
    assert float(op.max()) <= 0.01 + 1e-6 and float(op[2]) < 0.01  # lower ones are kept
    st = opts["opacity_logits"].state[f.opacity_logits]
    assert float(st["exp_avg"].abs().sum()) == 0.0 and float(st["exp_avg_sq"].abs().sum()) == 0.0


def test_schedule_resets_opacity_during_training(tiny):
    cfg = _config(iterations=31, reset_every=30, densify_from=10, densify_every=10, densify_until=100)
    t = Trainer(load_training_data(tiny, cfg), cfg)
    t.train(progress=False, stop_after=30)
    assert float(t.field.opacities().detach().max()) <= 0.01 + 1e-6
    t.train(progress=False)
    assert t.step == 31


def test_render_transform_hook_matches_moving_the_camera(tiny):
    cfg = _config()
    t = Trainer(load_training_data(tiny, cfg), cfg)
    d = t.data
    T = torch.eye(4)
    c, s = math.cos(0.3), math.sin(0.3)
    T[:3, :3] = torch.tensor([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    T[:3, 3] = torch.tensor([0.05, -0.02, 0.01])
    with torch.no_grad():
        a = t.field.render(d.viewmats[:2], d.Ks[:2], d.width, d.height, transform=T, sh_degree=0)
        b = t.field.render(d.viewmats[:2] @ T, d.Ks[:2], d.width, d.height, sh_degree=0)
        per = t.field.render(
            d.viewmats[:2], d.Ks[:2], d.width, d.height, sh_degree=0, transform=T.expand(t.field.num, 4, 4)
        )
        plain = t.field.render(d.viewmats[:2], d.Ks[:2], d.width, d.height, sh_degree=0)
    assert torch.allclose(a.rgb, b.rgb, atol=2e-3) and torch.allclose(a.features, b.features, atol=2e-3)
    assert torch.allclose(a.rgb, per.rgb, atol=1e-5)
    assert float((a.rgb - plain.rgb).abs().mean()) > 1e-3


def test_resume_after_kill_gives_the_same_world(tiny, tmp_path):
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
    killed.train(progress=False, stop_after=37)  # "killed" at 37: the last checkpoint is step 30
    _, meta = load_checkpoint(tmp_path / "b.ckpt")
    assert meta["step"] == 30
    resumed = Trainer(data, cfg, checkpoint=tmp_path / "b.ckpt")
    resumed.load_checkpoint()
    assert resumed.step == 30
    resumed.train(progress=False)
    assert encode_world(resumed.world()) == encode_world(full.world())
    # and a different seed gives a different world
    other = Trainer(data, dataclasses.replace(cfg, seed=4))
    other.train(progress=False, stop_after=5)
    assert other.field.num != full.field.num or not torch.equal(other.field.means, full.field.means)


def test_resume_refuses_a_different_configuration(tiny, tmp_path):
    cfg = _config(iterations=5, checkpoint_every=5)
    data = load_training_data(tiny, cfg)
    Trainer(data, cfg, checkpoint=tmp_path / "c.ckpt").train(progress=False)
    other = Trainer(data, dataclasses.replace(cfg, seed=9), checkpoint=tmp_path / "c.ckpt")
    with pytest.raises(ValueError, match="different configuration"):
        other.load_checkpoint()


def test_nan_loss_stops_and_keeps_the_last_good_checkpoint(tiny, tmp_path):
    cfg = _config(iterations=30, checkpoint_every=10)
    data = load_training_data(tiny, cfg)
    t = Trainer(data, cfg, checkpoint=tmp_path / "n.ckpt")
    t.train(progress=False, stop_after=10)
    good = (tmp_path / "n.ckpt").read_bytes()
    bad = data.images.clone()
    bad[:, 0, 0, 0] = float("nan")
    t.data = dataclasses.replace(data, images=bad)
    with pytest.raises(TrainingDiverged, match=r"loss became nan at step 11.*step 10"):
        t.train(progress=False)
    assert (tmp_path / "n.ckpt").read_bytes() == good
    assert load_checkpoint(tmp_path / "n.ckpt")[1]["step"] == 10


def test_two_state_capture_needs_single_state(tiny):
    with pytest.raises(ValueError, match="--single-state"):
        load_training_data(tiny, TrainConfig(preset=get_preset("quick")))
    d = load_training_data(tiny, TrainConfig(preset=get_preset("quick"), state="state2", holdout_every=0))
    assert d.state == "state2" and d.heldout == () and len(d) == 16


def test_cli_help_and_quick_run(tiny, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--help"])
    assert e.value.code == 0 and "--preset" in capsys.readouterr().out
    out = tmp_path / "w.dsgworld"
    rc = cli.main(
        [str(tiny), "--out", str(out), "--preset", "quick", "--iterations", "20", "--single-state", "--quiet"]
    )
    assert rc == 0
    w = load_world(out)
    assert w.object_names == ("red_box", "blue_cylinder") and w.metadata["iterations"] == 20
    assert w.metadata["heldout_views"] == [0, 8] and len(w.cameras["state1"]) == 16
    gen = w.metadata["source"]["generator"]  # what regenerates the ground truth of a synthetic capture
    assert gen["name"] == "dsg-synth" and gen["lighting"] in ("soft", "spot") and "seed" in gen
    assert gen["supersample"] == json.loads((tiny / "scene.json").read_text())["generator"]["supersample"]
    n = w.background.num + sum(o.gaussians.num for o in w.objects.values())
    assert n == w.metadata["num_gaussians"]
    assert (tmp_path / "w.dsgworld.ckpt").exists()
    # (without --single-state, dsg-train hands two-state captures to train_world.dual_state; not exercised here)
    bad = tmp_path / "nothing"
    bad.mkdir()
    assert cli.main([str(bad), "--out", str(out), "--single-state", "--quiet"]) == 2
    assert "not a capture" in capsys.readouterr().err
