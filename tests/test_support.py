"""The support term (train_world.dual_state.losses.support_loss): object Gaussians kept above the table top, in the
joint phase of dsg-train and in the merged world's refinement."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from dsg_gym.world import load_world
from tests._captures import tiny_capture
from train_world.cli import train as dual_cli
from train_world.dual_state.losses import support_loss
from train_world.dual_state.refine import RefineConfig, refine_world, training_views_of
from train_world.dual_state.trainer import DualTrainer


def _one(z, scales, quat=(1.0, 0.0, 0.0, 0.0), logit=0.0, poses=None):
    t = lambda a: torch.tensor(np.asarray([a], np.float32))  # noqa: E731
    return support_loss(t((0.3, -0.2, z)), t(quat), t(np.log(scales)), t(logit), poses)


def test_support_loss_is_the_opacity_weighted_reach_below_the_table():
    assert float(_one(0.05, (0.01, 0.01, 0.02))) == 0.0  # 2 sigma = 4 cm, centre 5 cm up
    # centre 1 cm up, sigma_z 2 cm: reaches 3 cm below at 2 sigma; opacity 0.5; in units of 1 cm
    assert float(_one(0.01, (0.01, 0.01, 0.02))) == pytest.approx(0.5 * 3.0, rel=1e-5)
    # turned 90 degrees about x: the 2 cm axis lies along y, sigma_z is 1 cm
    c = math.cos(math.pi / 4)
    assert float(_one(0.01, (0.01, 0.02, 0.01), quat=(c, c, 0.0, 0.0))) == pytest.approx(0.5 * 3.0, rel=1e-5)
    assert float(_one(0.01, (0.01, 0.01, 0.02), quat=(c, c, 0.0, 0.0))) == pytest.approx(0.5 * 1.0, rel=1e-4)
    # an object pose lifts the Gaussian 10 cm: nothing below
    lift = torch.eye(4)[None].clone()
    lift[0, 2, 3] = 0.1
    assert float(_one(0.01, (0.01, 0.01, 0.02), poses=lift)) == 0.0
    empty = torch.zeros(0, 3)
    assert float(support_loss(empty, torch.zeros(0, 4), empty, torch.zeros(0))) == 0.0


def test_support_loss_pushes_up_shrinks_and_fades_what_reaches_below():
    means = torch.tensor([[0.0, 0.0, 0.01]], requires_grad=True)
    log_scales = torch.tensor(np.log([[0.01, 0.01, 0.02]]), dtype=torch.float32, requires_grad=True)
    logits = torch.tensor([0.0], requires_grad=True)
    support_loss(means, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), log_scales, logits).backward()
    assert means.grad[0, 2] < 0 and means.grad[0, :2].abs().max() == 0  # descent raises the centre
    assert log_scales.grad[0, 2] > 0 and log_scales.grad[0, :2].abs().max() == 0  # and shrinks it along z
    assert logits.grad[0] > 0  # and lowers its opacity


def test_refine_config_refuses_a_bad_support_weight():
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="support_weight"):
            RefineConfig(support_weight=bad)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    d = tmp_path_factory.mktemp("support")
    cap = tiny_capture(d / "cap", size=24, views=8, test_views=1)
    out = d / "w.dsgworld"
    args = [str(cap), "--out", str(out), "--preset", "quick", "--iterations", "60", "--refine-steps", "20"]
    assert dual_cli.main_two_state([*args, "--support-weight", "0.5", "--quiet"]) == 0
    return cap, out


def test_dsg_train_records_the_support_weight_and_joint_steps_report_the_term(trained):
    cap, out = trained
    w = load_world(out)
    assert w.metadata["dual"]["support_weight"] == 0.5
    assert w.metadata["refine"]["support_weight"] == 0.5
    args = dual_cli.two_state_parser().parse_args(
        [str(cap), "--out", "x", "--preset", "quick", "--iterations", "60"]
    )
    config = dataclasses.replace(dual_cli.two_state_config(args), support_weight=0.5)
    with pytest.raises(ValueError, match="support_weight"):
        dataclasses.replace(config, support_weight=-1.0)
    tr = DualTrainer(cap, config)
    tr.step = tr.t1.step = tr.t2.step = tr.joint_start
    stats = tr.train_step()
    assert "support" in stats and math.isfinite(stats["support"]) and stats["support"] >= 0
    tr.step = tr.t1.step = tr.t2.step = 0
    assert "support" not in tr.train_step()  # the reconstruction phase has no cross-state terms


def _below(world, state: str) -> float:
    """The support term of every object Gaussian of ``world`` at ``state``'s poses."""
    parts = [world.objects[i].gaussians for i in world.object_ids]
    cat = lambda k: torch.from_numpy(np.concatenate([getattr(p, k) for p in parts]))  # noqa: E731
    poses = np.repeat(np.asarray(world.poses[state], np.float32), [p.num for p in parts], axis=0)
    op = cat("opacities").clamp(1e-6, 1 - 1e-6)
    return float(
        support_loss(
            cat("means"), cat("quats"), cat("scales").log(), torch.log(op / (1 - op)), torch.from_numpy(poses)
        )
    )


def test_refinement_with_the_support_term_lifts_what_reaches_below_the_table(trained):
    cap, out = trained
    w = load_world(out)
    # sink every object 1.5 cm into the table, in its own frame
    objects = {
        i: o._replace(gaussians=dataclasses.replace(o.gaussians, means=o.gaussians.means - [0, 0, 0.015]))
        for i, o in w.objects.items()
    }
    sunk = dataclasses.replace(w, objects=objects)
    views = training_views_of(sunk, cap)
    plain, _ = refine_world(sunk, views, RefineConfig(steps=30))
    held, _ = refine_world(sunk, views, RefineConfig(steps=30, support_weight=1.0))
    for s in ("state1", "state2"):
        before, after_plain, after_held = _below(sunk, s), _below(plain, s), _below(held, s)
        assert before > 0.005  # the sunk bases reach below the table
        assert after_held < min(before, 0.75 * after_plain), (s, before, after_plain, after_held)
