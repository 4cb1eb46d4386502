"""Object motions as parameters of the joint phase: the corrections' algebra, the default (refined for
estimated motions, frozen for synthetic ones), a perturbed motion pulled back towards the truth, frozen motions
left exactly as given, and a resumed run keeping the motion parameters."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import load_world
from train_world.cli import train as train_cli
from train_world.dual_state.motions import ObjectMotions, motion_error
from train_world.dual_state.transfer import ObjectTransfer, relative_transforms
from train_world.dual_state.views import motions_estimated
from train_world.single_state.camera_refine import correction_lrs


def _rot(axis, deg):
    a = math.radians(deg)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _poses():
    P1 = np.tile(np.eye(4), (2, 1, 1))
    P1[0, :3, 3] = [0.1, 0.0, 0.05]
    P1[1, :3, :3] = _rot([0, 0, 1], 40)
    P1[1, :3, 3] = [-0.1, 0.1, 0.04]
    P2 = P1.copy()
    P2[0, :3, :3] = _rot([0, 0, 1], 70)
    P2[0, :3, 3] = [0.2, -0.1, 0.05]
    P2[1, :3, 3] = [-0.15, -0.05, 0.04]
    return P1, P2


# ----------------------------------------------------------------------------------- algebra
def test_zero_correction_is_the_given_motion_and_the_inverse_is_exact():
    P1, P2 = _poses()
    m = ObjectMotions(P1, P2)
    T = P2 @ np.linalg.inv(P1)
    assert np.allclose(m.T12(), T, atol=1e-14) and np.allclose(m.P2(), P2, atol=1e-14)
    with torch.no_grad():
        m.rotvec[0] = torch.tensor([0.01, -0.02, 0.03], dtype=torch.float64)
        m.translation[1] = torch.tensor([0.002, 0.001, -0.003], dtype=torch.float64)
    T12, T21 = m.T12(), m.T21()
    assert np.allclose(T21 @ T12, np.eye(4), atol=1e-15)
    assert np.allclose(np.transpose(T12[:, :3, :3], (0, 2, 1)) @ T12[:, :3, :3], np.eye(3), atol=1e-15)
    _, _, q = m.parts()
    assert torch.allclose(q.norm(dim=-1), torch.ones(2, dtype=torch.float64), atol=1e-15)
    # the correction turns the object about its own state-2 origin and moves that origin by the translation
    dist, ang = motion_error(T12, T, P1)
    assert dist[0] == pytest.approx(0.0, abs=1e-15) and ang[0] == pytest.approx(math.degrees(0.01 * 14**0.5))
    assert dist[1] == pytest.approx(math.sqrt(14) * 1e-3) and ang[1] == pytest.approx(0.0, abs=1e-5)
    # float32 transfers: the matrix form and the quaternion form agree; the inverse direction undoes it
    labels = torch.tensor([0, 1, 2, 1])
    g = torch.Generator().manual_seed(0)
    means = torch.randn(4, 3, generator=g) * 0.05
    quats = torch.nn.functional.normalize(torch.randn(4, 4, generator=g), dim=-1)
    t12, t21 = m.transfers(labels, labels)
    ref_m, ref_q = ObjectTransfer(labels, torch.from_numpy(T12).float())(means, quats)
    got_m, got_q = t12(means, quats)
    assert torch.allclose(got_m, ref_m, atol=1e-6)
    assert torch.allclose(got_q * torch.sign(got_q[:, :1]), ref_q * torch.sign(ref_q[:, :1]), atol=1e-6)
    back, _ = t21(*t12(means, quats))
    assert torch.allclose(back, means, atol=1e-6)


def test_gradients_reach_the_corrections_and_are_finite_at_zero():
    P1, P2 = _poses()
    m = ObjectMotions(P1, P2)
    t12, t21 = m.transfers(torch.tensor([1, 2, 0]), torch.tensor([2, 1, 1]))
    x = torch.tensor([[0.1, 0.02, 0.05], [-0.1, 0.1, 0.02], [0.0, 0.0, 0.0]])
    q = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3)
    (t12(x, q)[0].square().sum() + t21(x, q)[1].sum()).backward()
    for p in (m.rotvec, m.translation):
        assert p.grad is not None and bool(torch.isfinite(p.grad).all()) and float(p.grad.abs().sum()) > 0


def test_motion_learning_rates_decay_over_the_joint_phase():
    assert correction_lrs(100, 100, 200, 1e-4, 3e-4) == (1e-4, 3e-4)
    lt, lr = correction_lrs(200, 100, 200, 1e-4, 3e-4)
    assert lt == pytest.approx(1e-5) and lr == pytest.approx(3e-5)
    assert correction_lrs(150, 100, 200, 1.0, 1.0)[0] == pytest.approx(0.1**0.5)


# ----------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    root = tmp_path_factory.mktemp("motions")
    small = tiny_capture(root / "small", test_views=2, test_states=1)
    sharp = tiny_capture(root / "sharp", size=64, test_views=2, test_states=1)
    return small, sharp


def _perturbed(src, dst, *, deg=1.5, shift=(0.003, -0.002, 0.001)):
    """``src`` with object 1's state-2 pose turned by ``deg`` about an oblique axis through its origin and
    moved by ``shift`` metres; returns the copy and the true and given motions."""
    shutil.copytree(src, dst)
    scene = json.loads((dst / "scene.json").read_text())
    P1 = np.array([p["pose"] for p in scene["states"]["state1"]["object_poses"]])
    P2 = np.array([p["pose"] for p in scene["states"]["state2"]["object_poses"]])
    Q = P2.copy()
    Q[0, :3, :3] = _rot([0.3, 0.2, 1.0], deg) @ Q[0, :3, :3]
    Q[0, :3, 3] += shift
    scene["states"]["state2"]["object_poses"][0]["pose"] = Q[0].tolist()
    (dst / "scene.json").write_text(json.dumps(scene))
    return dst, P1, P2 @ np.linalg.inv(P1), Q @ np.linalg.inv(P1)


def test_estimated_motions_are_refined_by_default_and_synthetic_ones_frozen(captures, tmp_path):
    small, _ = captures
    assert not motions_estimated(small)
    est = tmp_path / "est"
    shutil.copytree(small, est)
    scene = json.loads((est / "scene.json").read_text())
    scene["generator"] = {"name": "dsg-capture", "version": "1.0"}
    (est / "scene.json").write_text(json.dumps(scene))
    assert motions_estimated(est)

    def cfg(path, *extra):
        args = train_cli.two_state_parser().parse_args([str(path), "--out", "x", "--preset", "quick", *extra])
        return train_cli.two_state_config(args)

    assert cfg(est).refine_motions and not cfg(small).refine_motions
    assert not cfg(est, "--freeze-motions").refine_motions and cfg(small, "--refine-motions").refine_motions
    with pytest.raises(SystemExit):
        cfg(small, "--refine-motions", "--freeze-motions")
    with pytest.raises(ValueError, match="motion_lr_rotation"):
        cfg(small, "--motion-lr-rotation", "0")


def test_refinement_pulls_a_perturbed_motion_towards_the_truth(captures, tmp_path, capsys):
    _, sharp = captures
    cap, P1, T_true, T_given = _perturbed(sharp, tmp_path / "cap")
    d0, a0 = motion_error(T_given, T_true, P1)
    assert d0[0] > 0.003 and a0[0] == pytest.approx(1.5)
    out = tmp_path / "w.dsgworld"
    args = [str(cap), "--out", str(out), "--preset", "quick", "--quiet", "--refine-motions"]
    assert train_cli.main_two_state(args) == 0
    err = capsys.readouterr().err
    assert "motions refined" in err and "motion of 'red_box' corrected by" in err and " mm, " in err
    w = load_world(out)
    rec = w.metadata["motions"]
    assert rec["refined"] and np.array_equal(np.array(rec["initial"]), T_given)
    final = np.array(rec["final"])
    d1, a1 = motion_error(final, T_true, P1)
    assert d1[0] <= 0.5 * d0[0] and a1[0] <= 0.5 * a0[0], (d0, a0, d1, a1)
    # the world's state-2 poses are the refined ones; state 1 (the reference) keeps the capture's
    assert np.allclose(w.poses["state2"], final @ P1, atol=1e-12)
    assert np.array_equal(w.poses["state1"], P1)
    moved, turned = motion_error(final, T_given, P1)
    assert rec["objects"][0]["correction_mm"] == pytest.approx(moved[0] * 1000)
    assert rec["objects"][0]["correction_rotation_deg"] == pytest.approx(turned[0])


def test_frozen_motions_stay_exactly_as_given(captures, tmp_path):
    small, _ = captures
    cap, P1, _, T_given = _perturbed(small, tmp_path / "cap")
    out = tmp_path / "w.dsgworld"
    args = [str(cap), "--out", str(out), "--preset", "quick", "--iterations", "40", "--quiet"]
    assert train_cli.main_two_state([*args, "--freeze-motions"]) == 0
    w = load_world(out)
    rec = w.metadata["motions"]
    assert not rec["refined"] and rec["initial"] == rec["final"]
    assert np.array_equal(np.array(rec["final"]), T_given)
    assert all(o["correction_translation"] == 0.0 for o in rec["objects"])
    scene = json.loads((cap / "scene.json").read_text())
    P2 = np.array([p["pose"] for p in scene["states"]["state2"]["object_poses"]])
    assert np.array_equal(w.poses["state2"], P2)


def test_resume_keeps_the_motion_parameters(captures, tmp_path):
    from train_world.dual_state.trainer import DualTrainer
    from train_world.single_state.checkpoint import load_checkpoint

    small, _ = captures
    cap, *_ = _perturbed(small, tmp_path / "cap")
    common = ["--preset", "quick", "--iterations", "60", "--prune-every", "10", "--quiet", "--refine-motions"]
    assert train_cli.main_two_state([str(cap), "--out", str(tmp_path / "full.dsgworld"), *common]) == 0
    cfg = train_cli.two_state_config(
        train_cli.two_state_parser().parse_args([str(cap), "--out", "x", *common])
    )
    tr = DualTrainer(cap, cfg, checkpoint=tmp_path / "res.dsgworld.ckpt")
    tr.train(progress=False, stop_after=45)
    assert tr.last_checkpoint_step is not None and 30 < tr.last_checkpoint_step <= 45
    tensors, _ = load_checkpoint(tmp_path / "res.dsgworld.ckpt")
    assert float(tensors["motions/translation"].abs().sum()) > 0  # the joint phase moved them
    assert any(k.startswith("adam/motions/") for k in tensors)
    assert (
        train_cli.main_two_state([str(cap), "--out", str(tmp_path / "res.dsgworld"), *common, "--resume"])
        == 0
    )
    full, res = load_world(tmp_path / "full.dsgworld"), load_world(tmp_path / "res.dsgworld")
    assert full.metadata["motions"] == res.metadata["motions"]
    assert np.array_equal(full.poses["state2"], res.poses["state2"])
    for k, o in full.objects.items():
        assert np.array_equal(o.gaussians.means, res.objects[k].gaussians.means)
    # relative_transforms of the poses the world stores reproduce the recorded motion
    T = relative_transforms(full.poses["state1"], full.poses["state2"]).double().numpy()
    assert np.allclose(T, np.array(full.metadata["motions"]["final"]), atol=1e-6)
