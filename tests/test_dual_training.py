"""DSG-World two-state training end to end on a tiny scene: the merged world, the dsg-train dispatch and the
comparison with baseline (a), resume and branching, divergence, the two-state step count and held-out views."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import load_world
from train_world.cli import train as recon_cli
from train_world.cli.eval import main as ev_main
from train_world.eval.evaluate import evaluate
from train_world.suite.baselines import knn_complete, train_single_state


# ----------------------------------------------------------------------------------- end to end
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("dual"), test_views=4, test_states=2)


def test_dsg_train_two_states_beats_single_state_baseline(tiny, tmp_path):
    ours = tmp_path / "ours.dsgworld"
    rc = recon_cli.main(
        [str(tiny), "--out", str(ours), "--preset", "quick", "--prune-every", "50", "--quiet"]
    )
    assert rc == 0  # dispatched to the two-state trainer (no --single-state)
    w = load_world(ours)
    d = w.metadata["dual"]
    assert d["ablation"] == "B+C+P" and w.metadata["training_states"] == ["state1", "state2"]
    assert d["background_from_2"] > 0 and d["background_dropped_1"] > 0  # co-pasting used both fields
    assert set(w.cameras) == {"state1", "state2"} and "test_0" in w.poses
    n = w.background.num + sum(o.gaussians.num for o in w.objects.values())
    assert n == w.metadata["num_gaussians"] and all(o.gaussians.num > 20 for o in w.objects.values())
    base = tmp_path / "a.dsgworld"
    train_single_state(tiny, base, preset="quick")  # same preset, 300 steps of one field
    r_ours = evaluate(ours, tiny, tmp_path / "eval_ours", state="test_0")["mean"]
    r_a = evaluate(base, tiny, tmp_path / "eval_a", state="test_0")["mean"]
    assert r_ours["psnr"] > r_a["psnr"] + 0.5, (r_ours, r_a)
    assert r_ours["ssim"] > r_a["ssim"] and r_ours["mask_iou"] > r_a["mask_iou"], (r_ours, r_a)
    # dsg-eval on a two-state world evaluates every test state by default; their mean is the report's
    assert ev_main([str(ours), str(tiny), "--out", str(tmp_path / "eval_all")]) == 0
    rep = json.loads((tmp_path / "eval_all" / "report.json").read_text())
    assert list(rep["states"]) == ["test_0", "test_1"] and rep["views"] == 8
    assert rep["states"]["test_0"]["mean"] == r_ours
    for k in ("psnr", "ssim", "mask_iou"):
        assert rep["mean"][k] == np.mean([rep["states"][s]["mean"][k] for s in ("test_0", "test_1")])
    assert (tmp_path / "eval_all" / "test_1" / "grid.png").is_file()
    assert "| **mean** | 8 |" in (tmp_path / "eval_all" / "report.md").read_text()
    # a training state's views: it held none out, so naming it alone is refused; --training-views scores them all
    assert ev_main([str(ours), str(tiny), "--out", str(tmp_path / "fit"), "--state", "state2"]) == 2
    assert (
        ev_main(
            [str(ours), str(tiny), "--out", str(tmp_path / "fit"), "--state", "state2", "--training-views"]
        )
        == 0
    )
    fit = json.loads((tmp_path / "fit" / "report.json").read_text())
    assert fit["state"] == "state2" and fit["training_views"] is True and fit["views"] == 16
    assert fit["mean"]["psnr"] > r_ours["psnr"], (
        fit["mean"],
        r_ours,
    )  # it fits what it saw better than new states
    assert "training views included" in (tmp_path / "fit" / "report.md").read_text()
    assert (
        json.loads((tmp_path / "eval_all" / "test_0" / "report.json").read_text())["training_views"] is False
    )
    for bad in (["--state", "test_0"], ["--state", "test"], []):  # not a training state, or none named
        assert ev_main([str(ours), str(tiny), "--out", str(tmp_path / "bad"), *bad, "--training-views"]) == 2
    # on a capture with test states both train on every view of their states (the test states evaluate them)
    assert w.metadata["heldout_views_by_state"] == {"state1": [], "state2": []}
    wa = load_world(base)
    assert wa.metadata["heldout_views"] == [] and wa.metadata["train_config"]["holdout_every"] == 0
    # so dsg-eval evaluates the single-state world at the test states too (it has no held-out views of its own
    # state to evaluate on); --state picks another state, all of whose views are evaluated
    assert ev_main([str(base), str(tiny), "--out", str(tmp_path / "eval_a1")]) == 0
    assert json.loads((tmp_path / "eval_a1" / "report.json").read_text())["states"]["test_0"]["mean"] == r_a
    assert ev_main([str(base), str(tiny), "--out", str(tmp_path / "eval_a2"), "--state", "state1"]) == 2
    assert (
        ev_main(
            [str(base), str(tiny), "--out", str(tmp_path / "fit_a"), "--state", "state1", "--training-views"]
        )
        == 0
    )
    assert json.loads((tmp_path / "fit_a" / "report.json").read_text())["views"] == 16
    assert ev_main([str(base), str(tiny), "--out", str(tmp_path / "eval_a2"), "--state", "state2"]) == 0
    rep = json.loads((tmp_path / "eval_a2" / "report.json").read_text())
    assert rep["state"] == "state2" and rep["views"] == 16
    # baseline (b): kNN completion adds flat background Gaussians inside the state-1 footprints
    wb = knn_complete(wa)
    added = wb.metadata["knn_completion"]["added"]
    assert added > 0 and wb.background.num == wa.background.num + added
    assert np.all(np.abs(wb.background.means[-added:, 2]) < 1e-6)  # on the table top (z = 0)


def _dual_cli(tiny, out, *extra):
    from train_world.cli import train as dual_cli

    args = [
        str(tiny),
        "--out",
        str(out),
        "--preset",
        "quick",
        "--iterations",
        "60",
        "--prune-every",
        "10",
        "--quiet",
        *extra,
    ]
    assert dual_cli.main_two_state(args) == 0
    return load_world(out)


def _same_world(a, b):
    assert a.background.num == b.background.num and np.array_equal(a.background.means, b.background.means)
    for k, o in a.objects.items():
        assert np.array_equal(o.gaussians.means, b.objects[k].gaussians.means)
        assert np.array_equal(o.gaussians.sh, b.objects[k].gaussians.sh)


def test_dual_resume_and_branch_reproduce_uninterrupted_runs(tiny, tmp_path):
    from train_world.cli import train as dual_cli
    from train_world.dual_state.trainer import DualTrainer

    full = _dual_cli(tiny, tmp_path / "full.dsgworld")
    # killed at step 45 (past the joint start 30, checkpoint every 10 at this length), then --resume
    cfg = dual_cli.two_state_config(
        dual_cli.two_state_parser().parse_args(
            [str(tiny), "--out", "x", "--preset", "quick", "--iterations", "60", "--prune-every", "10"]
        )
    )
    tr = DualTrainer(tiny, cfg, checkpoint=tmp_path / "res.dsgworld.ckpt")
    tr.train(progress=False, stop_after=45)
    assert tr.last_checkpoint_step is not None and 30 < tr.last_checkpoint_step <= 45
    resumed = _dual_cli(tiny, tmp_path / "res.dsgworld", "--resume")
    _same_world(full, resumed)
    # the ablation B+C shares its reconstruction phase with B+C+P: branching from a checkpoint taken at the
    # joint start gives the same world as a separate B+C run
    ck = tmp_path / "recon.ckpt"
    assert (
        dual_cli.main_two_state(
            [
                str(tiny),
                "--out",
                str(tmp_path / "r.dsgworld"),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--prune-every",
                "10",
                "--quiet",
                "--stop-at-joint",
                "--checkpoint",
                str(ck),
            ]
        )
        == 0
    )
    assert not (tmp_path / "r.dsgworld").exists()
    sep = _dual_cli(tiny, tmp_path / "bc.dsgworld", "--no-pseudo")
    br = _dual_cli(tiny, tmp_path / "bc_branch.dsgworld", "--no-pseudo", "--branch-from", str(ck))
    _same_world(sep, br)
    # a checkpoint past the joint start, or from other options, cannot be branched from
    assert (
        dual_cli.main_two_state(
            [
                str(tiny),
                "--out",
                str(tmp_path / "z.dsgworld"),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--prune-every",
                "10",
                "--quiet",
                "--branch-from",
                str(tmp_path / "full.dsgworld.ckpt"),
            ]
        )
        == 2
    )
    assert (
        dual_cli.main_two_state(
            [
                str(tiny),
                "--out",
                str(tmp_path / "z.dsgworld"),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--prune-every",
                "10",
                "--tau",
                "0.05",
                "--quiet",
                "--branch-from",
                str(ck),
            ]
        )
        == 2
    )


def test_dual_non_finite_gradient_stops_before_the_fields_change(tiny, tmp_path):
    from train_world.cli import train as dual_cli
    from train_world.dual_state.trainer import DualTrainer
    from train_world.single_state.trainer import TrainingDiverged

    cfg = dual_cli.two_state_config(
        dual_cli.two_state_parser().parse_args(
            [str(tiny), "--out", "x", "--preset", "quick", "--iterations", "40"]
        )
    )
    tr = DualTrainer(tiny, cfg)
    tr.train(progress=False, stop_after=25)  # into the joint phase
    before = {k: v.detach().clone() for k, v in tr.t2.field.params().items()}
    hook = tr.t2.field.sh0.register_hook(lambda g: g * float("nan"))
    with pytest.raises(TrainingDiverged, match=r"g2\.sh0"):
        tr.train_step()
    hook.remove()
    assert tr.step == 25
    assert all(torch.equal(v, before[k]) for k, v in tr.t2.field.params().items())


def test_two_state_training_has_its_own_step_count_and_field_cap():
    import dataclasses

    from train_world.cli import train as dual_cli
    from train_world.single_state.presets import get_preset

    p = get_preset("default")
    assert p.dual_iterations is not None and p.dual_iterations < p.iterations
    assert p.dual_max_gaussians is not None and p.dual_max_gaussians < p.max_gaussians
    d = dual_cli.scaled_preset("default", two_state=True)
    assert (d.iterations, d.max_gaussians) == (p.dual_iterations, p.dual_max_gaussians)
    f = p.dual_iterations / p.iterations  # the whole schedule follows the step count
    assert (d.densify_until, d.reset_every) == (round(p.densify_until * f), round(p.reset_every * f))
    cfg = dual_cli.two_state_config(
        dual_cli.two_state_parser().parse_args(["cap", "--out", "x", "--holdout-every", "8"])
    )
    assert cfg.base.preset == d  # what dsg-train on two states uses by default
    # the joint phase starts at the preset's fraction unless --joint-from says otherwise
    assert cfg.joint_from == p.dual_joint_from and 0.5 <= p.dual_joint_from < 1
    assert round(cfg.joint_from * d.iterations) == round(p.dual_iterations * p.dual_joint_from)
    cfg = dual_cli.two_state_config(
        dual_cli.two_state_parser().parse_args(
            ["cap", "--out", "x", "--holdout-every", "8", "--joint-from", "0.25"]
        )
    )
    assert cfg.joint_from == 0.25
    assert get_preset("paper").dual_joint_from == 0.5  # DSG-World's 10k + 10k
    with pytest.raises(ValueError, match="dual_joint_from"):
        dataclasses.replace(p, dual_joint_from=1.5)
    # explicit values win; single-state training and presets without two-state values are unchanged
    e = dual_cli.scaled_preset("default", 1000, 5000, two_state=True)
    assert (e.iterations, e.max_gaussians) == (1000, 5000)
    assert dual_cli.scaled_preset("default") == p
    assert dual_cli.scaled_preset("quick", two_state=True) == get_preset("quick")
    with pytest.raises(ValueError, match="dual_iterations"):
        dataclasses.replace(p, dual_iterations=0)
    with pytest.raises(ValueError, match="--iterations"):
        dual_cli.scaled_preset("default", 0)


def test_two_state_training_holds_out_views_only_when_the_capture_has_no_test_states(tiny, tmp_path):
    from train_world.cli.train import two_state_config as config_from_args
    from train_world.cli.train import two_state_parser as _parser
    from train_world.dual_state.views import default_holdout_every

    bare = tiny_capture(tmp_path, views=8, test_views=0, test_states=0)
    assert default_holdout_every(tiny) == 0 and default_holdout_every(bare) == 8

    def held(capture, *extra):
        return config_from_args(
            _parser().parse_args([str(capture), "--out", "w.dsgworld", *extra])
        ).base.holdout_every

    assert held(tiny) == 0 and held(bare) == 8  # without test states, every 8th view is kept to evaluate on
    assert held(bare, "--holdout-every", "0") == 0 and held(tiny, "--holdout-every", "4") == 4
    with pytest.raises(ValueError, match="holdout_every"):
        held(tiny, "--holdout-every", "1")


def test_dsg_train_adds_the_far_shell_unless_told_not_to(tiny, tmp_path):
    plain = _dual_cli(tiny, tmp_path / "plain.dsgworld", "--no-shell")
    shelled = _dual_cli(tiny, tmp_path / "shelled.dsgworld")
    assert "background_shell" not in plain.metadata
    n = shelled.metadata["background_shell"]["gaussians"]
    nb = plain.background.num
    assert shelled.background.num == nb + n
    assert np.array_equal(shelled.background.means[:nb], plain.background.means)  # the trained part as it was
    assert shelled.metadata["num_gaussians"] == plain.metadata["num_gaussians"] + n
    for oid, o in plain.objects.items():
        assert np.array_equal(o.gaussians.means, shelled.objects[oid].gaussians.means)
