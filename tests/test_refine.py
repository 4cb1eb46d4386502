"""Refinement of a merged two-state world on both states' training views (train_world.dual_state.refine)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dsg_gym.world import load_world, write_world
from tests._captures import tiny_capture
from train_world.cli import train as dual_cli
from train_world.cli.refine import main as refine_main
from train_world.dual_state.refine import RefineConfig, StateViews, refine_world, training_views_of
from train_world.eval.evaluate import _poses_for, evaluate, layer_mask, render_gaussians
from train_world.eval.view_align import ViewAlignment
from train_world.single_state.data import load_eval_views


@pytest.fixture(scope="module")
def unrefined(tmp_path_factory):
    d = tmp_path_factory.mktemp("refine")
    cap = tiny_capture(d / "cap", test_views=2, test_states=1)
    out = d / "w.dsgworld"
    assert (
        dual_cli.main_two_state(
            [
                str(cap),
                "--out",
                str(out),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--prune-every",
                "10",
                "--refine-steps",
                "0",
                "--quiet",
            ]
        )
        == 0
    )
    return cap, out


def _train_error(world, views, front=None) -> dict[str, float]:
    """Mean squared error of the world over every training view, per state (``front``: render in layers)."""
    bg = tuple(world.metadata["background"])
    out = {}
    for s, v in views.items():
        g = world.gaussians(poses=world.poses[s])
        h, w = v.images.shape[1:3]
        rgb, _ = render_gaussians(g, v.viewmats.numpy(), v.Ks.numpy(), w, h, bg, world.splat_options, front)
        out[s] = float(((rgb - v.images.numpy()) ** 2).mean())
    return out


def _arrays(world):
    parts = [world.background] + [world.objects[i].gaussians for i in world.object_ids]
    return [
        np.concatenate(
            [
                getattr(p, k).reshape(p.num, -1)
                for k in ("means", "quats", "scales", "opacities", "sh", "features")
            ],
            1,
        )
        for p in parts
    ]


def test_refinement_fits_both_states_and_keeps_the_world_s_structure(unrefined):
    cap, path = unrefined
    world = load_world(path)
    assert "refine" not in world.metadata or world.metadata["refine"]["steps"] == 0
    views = training_views_of(world, cap)
    assert set(views) == {"state1", "state2"} and all(v.images.shape[0] == 16 for v in views.values())
    before = _arrays(world)
    same, info = refine_world(world, views, RefineConfig(steps=0))
    assert same is world and info == {"steps": 0}
    refined, info = refine_world(world, views, RefineConfig(steps=60))
    assert all(np.array_equal(a, b) for a, b in zip(before, _arrays(world)))  # the input world is untouched
    e0, e1 = _train_error(world, views), _train_error(refined, views)
    assert all(e1[s] < 0.9 * e0[s] for s in e0), (e0, e1)  # both states' views fit better
    assert (
        info["steps"] == 60
        and info["loss_last"] < info["loss_first"]
        and info["states"] == ["state1", "state2"]
    )
    assert (
        refined.metadata["refine"] == {k: v for k, v in info.items() if k != "seconds"}
        and info["seconds"] > 0
    )
    # what refinement must not touch: counts, identity features, labels, poses, cameras, classifier
    assert refined.background.num == world.background.num
    for i in world.object_ids:
        a, b = world.objects[i].gaussians, refined.objects[i].gaussians
        assert (
            b.num == a.num and np.array_equal(b.features, a.features) and np.array_equal(b.labels, a.labels)
        )
        # still in the object's own frame: centres move by millimetres, not by the object's pose
        assert np.abs(b.means - a.means).max() < 0.02
        assert np.allclose(np.linalg.norm(b.quats, axis=1), 1.0, atol=1e-5)
        assert np.all(np.isfinite(b.sh)) and np.all((b.opacities >= 0) & (b.opacities <= 1))
    assert all(np.array_equal(refined.poses[s], world.poses[s]) for s in world.poses)
    assert np.array_equal(refined.classifier_weight, world.classifier_weight)
    # deterministic
    again, _ = refine_world(world, views, RefineConfig(steps=60))
    assert all(np.array_equal(a, b) for a, b in zip(_arrays(refined), _arrays(again)))


def test_layered_refinement_is_recorded_and_rendered_in_layers(unrefined, tmp_path):
    cap, path = unrefined
    world = load_world(path)
    views = training_views_of(world, cap)
    assert world.compositing == "sorted" and layer_mask(world) is None
    layered, info = refine_world(world, views, RefineConfig(steps=30, layers=True))
    plain, _ = refine_world(world, views, RefineConfig(steps=30))
    assert layered.compositing == "layers" and layered.metadata["refine"]["layers"] is True
    assert plain.compositing == "sorted" and "compositing" not in plain.metadata
    front = layer_mask(layered)
    n_bg = layered.background.num
    assert front.shape == (n_bg + sum(o.gaussians.num for o in layered.objects.values()),)
    assert not front[:n_bg].any() and front[n_bg:].all()
    # the layered refinement fits its own render: both states' training views fit better than before
    e0 = _train_error(world, views)
    e1 = _train_error(layered, views, front=front)
    assert all(e1[s] < e0[s] for s in e0), (e0, e1)
    assert not all(np.array_equal(a, b) for a, b in zip(_arrays(layered), _arrays(plain)))
    # dsg-eval renders it in layers, with and without aligning the views first
    path_l = tmp_path / "layered.dsgworld"
    write_world(path_l, layered)
    r = evaluate(path_l, cap, tmp_path / "ev", state="test_0", view_alignment=ViewAlignment(steps=4))
    bg = tuple(layered.metadata["background"])
    v = load_eval_views(
        cap,
        state="test_0",
        heldout=(),
        downscale=1,
        background=bg,
        object_ids=layered.object_ids,
        all_views=True,
    )
    g = layered.gaussians(poses=_poses_for(layered, cap, "test_0"))
    args = (g, v.viewmats.numpy(), v.Ks.numpy(), v.width, v.height, bg, layered.splat_options)
    two, one = render_gaussians(*args, front)[0], render_gaussians(*args)[0]
    psnr = [
        float(-10 * np.log10(np.mean((np.clip(x, 0, 1) - y) ** 2))) for x, y in zip(two, v.images.numpy())
    ]
    assert r["mean_unaligned"]["psnr"] == pytest.approx(float(np.mean(psnr)), abs=1e-3)
    assert np.abs(two - one).max() > 1e-3  # the layers are not the sorted render
    # dsg-train refuses --layers without a refinement, before training
    no = tmp_path / "no.dsgworld"
    args = [str(cap), "--out", str(no), "--preset", "quick", "--refine-steps", "0", "--layers", "--quiet"]
    assert dual_cli.main_two_state(args) == 2 and not no.exists()
    # a layered world stays layered when refined by the command, and the command takes the support weight
    out = tmp_path / "l.dsgworld"
    args = [str(path), str(cap), "--out", str(out), "--steps", "30", "--layers", "--support-weight", "0.1"]
    assert refine_main([*args, "--quiet"]) == 0
    w = load_world(out)
    assert w.compositing == "layers" and w.metadata["refine"]["support_weight"] == 0.1
    same, _ = refine_world(world, views, RefineConfig(steps=30, layers=True, support_weight=0.1))
    assert all(np.array_equal(a, b) for a, b in zip(_arrays(w), _arrays(same)))


def test_refinement_rejects_bad_input_and_leaves_the_world_alone(unrefined):
    cap, path = unrefined
    world = load_world(path)
    views = training_views_of(world, cap)
    with pytest.raises(ValueError, match="no poses for state 'nowhere'"):
        refine_world(world, {"nowhere": views["state1"]})
    bad = views["state2"].images.clone()
    bad[0, 1, 2, 0] = float("nan")
    with pytest.raises(ValueError, match="state 'state2': images have NaN"):
        refine_world(
            world, {**views, "state2": StateViews(bad, views["state2"].viewmats, views["state2"].Ks)}
        )
    with pytest.raises(ValueError, match="viewmats"):
        refine_world(
            world,
            {"state1": StateViews(views["state1"].images, views["state1"].viewmats[:2], views["state1"].Ks)},
        )
    with pytest.raises(ValueError, match="no training views"):
        refine_world(world, {})
    with pytest.raises(ValueError, match="steps must be an integer >= 0"):
        RefineConfig(steps=-1)
    with pytest.raises(ValueError, match="lr_sh0"):
        RefineConfig(lr_sh0=float("nan"))
    assert "refine" not in world.metadata or world.metadata["refine"]["steps"] == 0


def test_dsg_train_refines_like_the_standalone_command(unrefined, tmp_path, capsys):
    cap, path = unrefined
    # dsg-train with refinement = the same training without it, then `python -m train_world.cli.refine`
    inproc = tmp_path / "in.dsgworld"
    assert (
        dual_cli.main_two_state(
            [
                str(cap),
                "--out",
                str(inproc),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--prune-every",
                "10",
                "--refine-steps",
                "25",
                "--quiet",
            ]
        )
        == 0
    )
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["refine_steps"] == 25 and summary["refine_seconds"] > 0
    after = tmp_path / "after.dsgworld"
    quick_like = ["--steps", "25", "--no-layers", "--support-weight", "0", "--quiet"]  # quick's refinement
    assert refine_main([str(path), str(cap), "--out", str(after), *quick_like]) == 0
    a, b = load_world(inproc), load_world(after)
    assert all(np.array_equal(x, y) for x, y in zip(_arrays(a), _arrays(b)))
    assert a.metadata["refine"]["steps"] == b.metadata["refine"]["steps"] == 25
    # a refined world is not refined twice; a single-state world is refused with the reason
    assert refine_main([str(after), str(cap), "--out", str(tmp_path / "x.dsgworld"), "--quiet"]) == 2
    assert "refined already" in capsys.readouterr().err
    single = tmp_path / "single.dsgworld"
    from train_world.suite.baselines import train_single_state

    train_single_state(cap, single, preset="quick", iterations=20)
    assert refine_main([str(single), str(cap), "--out", str(tmp_path / "x.dsgworld"), "--quiet"]) == 2
    assert "not a two-state world" in capsys.readouterr().err
    assert not (tmp_path / "x.dsgworld").exists()


def test_refinement_steps_do_not_block_resuming_or_branching(unrefined, tmp_path):
    cap, _ = unrefined
    ck = tmp_path / "recon.ckpt"
    common = [str(cap), "--preset", "quick", "--iterations", "60", "--prune-every", "10", "--quiet"]
    assert (
        dual_cli.main_two_state(
            [
                *common,
                "--out",
                str(tmp_path / "r.dsgworld"),
                "--stop-at-joint",
                "--checkpoint",
                str(ck),
                "--refine-steps",
                "0",
            ]
        )
        == 0
    )
    # the checkpoint was made by a run that would not refine; a refining run still branches from it
    assert (
        dual_cli.main_two_state(
            [*common, "--out", str(tmp_path / "b.dsgworld"), "--branch-from", str(ck), "--refine-steps", "5"]
        )
        == 0
    )
    assert load_world(tmp_path / "b.dsgworld").metadata["refine"]["steps"] == 5
    assert (
        dual_cli.main_two_state([*common, "--out", str(tmp_path / "c.dsgworld"), "--refine-steps", "-3"]) == 2
    )


def test_presets_refine_by_default_except_the_paper_s():
    from train_world.single_state.presets import get_preset

    assert get_preset("default").dual_refine_steps == 4000 and get_preset("paper").dual_refine_steps == 0
    assert get_preset("quick").dual_refine_steps > 0
    with pytest.raises(ValueError, match="dual_refine_steps"):
        get_preset("quick", dual_refine_steps=-1)


def test_the_default_preset_refines_in_layers_with_the_support_term(unrefined, tmp_path):
    import dataclasses

    from train_world.cli.train_options import refine_config
    from train_world.dual_state.config import training_options
    from train_world.single_state.presets import get_preset

    cap, path = unrefined
    d, q, p = (get_preset(n) for n in ("default", "quick", "paper"))
    assert (d.dual_layers, d.dual_support_weight) == (True, 0.1)
    assert (q.dual_layers, q.dual_support_weight) == (p.dual_layers, p.dual_support_weight) == (False, 0.0)
    with pytest.raises(ValueError, match="dual_support_weight"):
        get_preset("quick", dual_support_weight=-1.0)

    def parse(*a):
        return dual_cli.two_state_parser().parse_args([str(cap), "--out", str(tmp_path / "x.dsgworld"), *a])

    # dsg-train: the preset's support weight and layers unless given
    assert dual_cli.two_state_config(parse()).support_weight == 0.1
    assert dual_cli.two_state_config(parse("--support-weight", "0")).support_weight == 0.0
    assert dual_cli.two_state_config(parse("--preset", "paper")).support_weight == 0.0
    assert refine_config(parse(), d).layers is True and refine_config(parse(), d).steps == 4000
    assert refine_config(parse("--no-layers"), d).layers is False
    assert (
        refine_config(parse("--refine-steps", "0"), d).layers is False
    )  # the preset's layers need a refinement
    with pytest.raises(ValueError, match="--layers acts in the refinement"):
        refine_config(parse("--layers", "--refine-steps", "0"), d)
    assert refine_config(parse("--preset", "quick"), q).layers is False
    assert refine_config(parse("--preset", "quick", "--layers"), q).layers is True
    # a checkpoint written before the preset carried them resumes: the preset's refinement settings and its
    # support weight (which the run's ``support_weight`` carries) are not training options
    cfg = dual_cli.two_state_config(parse())
    old = dataclasses.replace(cfg.base.preset, dual_layers=False, dual_support_weight=0.0)
    assert training_options(dataclasses.replace(cfg, base=dataclasses.replace(cfg.base, preset=old))) == (
        training_options(cfg)
    )
    # the refine command defaults to the default preset's: layers, and the support term for a world with a table
    world = load_world(path)
    assert "table" in world.metadata
    out = tmp_path / "d.dsgworld"
    assert refine_main([str(path), str(cap), "--out", str(out), "--steps", "5", "--quiet"]) == 0
    w = load_world(out)
    assert w.compositing == "layers" and w.metadata["refine"]["support_weight"] == 0.1
    bare = tmp_path / "bare.dsgworld"
    write_world(
        bare, dataclasses.replace(world, metadata={k: v for k, v in world.metadata.items() if k != "table"})
    )
    assert refine_main([str(bare), str(cap), "--out", str(out), "--steps", "5", "--quiet"]) == 0
    assert load_world(out).metadata["refine"]["support_weight"] == 0.0
