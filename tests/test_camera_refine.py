"""Training cameras as parameters: a correction renders what the corrected camera sees, perturbed cameras are
pulled back towards the truth, the option (off by default), and both trainers store, checkpoint and resume
the refined cameras."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.cameras import look_at
from dsg_gym.world import load_world
from train_world.capture.alignment import rotation_angle_deg
from train_world.cli import train as train_cli
from train_world.single_state.camera_refine import CameraCorrections, correction_lrs
from train_world.single_state.field import rigid_transform_gaussians

SIZE = 48
K = np.array([[60.0, 0, SIZE / 2], [0, 60.0, SIZE / 2], [0, 0, 1]])


def _scene(n: int = 1500, seed: int = 0):
    """A textured table of small opaque Gaussians with a few blocks on it (float32 tensors)."""
    rng = np.random.default_rng(seed)
    means = np.concatenate(
        [
            np.c_[rng.uniform(-0.3, 0.3, (n, 2)), np.zeros(n)],
            rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.1], (n // 3, 3)),
        ]
    )
    m = len(means)
    cols = np.where((np.floor(means[:, :1] / 0.03) + np.floor(means[:, 1:2] / 0.03)) % 2, 0.9, 0.15)
    cols = cols * rng.uniform(0.6, 1.0, (m, 3))
    t = lambda a: torch.from_numpy(np.asarray(a, np.float32))  # noqa: E731
    return dict(
        means=t(means),
        quats=t(np.tile([1.0, 0, 0, 0], (m, 1))),
        scales=t(np.full((m, 3), 0.008)),
        opacities=t(np.full(m, 0.9)),
        colors=t(cols),
    )


def _cameras(v: int = 4) -> np.ndarray:
    angles = np.linspace(0, 2 * np.pi, v, endpoint=False)
    return np.stack(
        [look_at([0.5 * np.cos(a), 0.5 * np.sin(a), 0.45], [0, 0, 0], [0, 0, 1.0]) for a in angles]
    )


def _render(scene, viewmat, transform=None):
    from dsg_gym.splat import rasterize

    means, quats = scene["means"], scene["quats"]
    if transform is not None:
        means, quats = rigid_transform_gaussians(means, quats, transform)
    out, _, _ = rasterize(
        means, quats, scene["scales"], scene["opacities"], scene["colors"],
        torch.as_tensor(np.asarray(viewmat, np.float32))[None], torch.from_numpy(K[None].astype(np.float32)),
        SIZE, SIZE,
    )  # fmt: skip
    return out[0]


def _rot(axis, deg):
    a = math.radians(deg)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


def _pose_errors(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per view: the angle (degrees) and camera-centre distance between view matrices ``a`` and ``b``."""
    ang = rotation_angle_deg(a[:, :3, :3] @ np.swapaxes(b[:, :3, :3], 1, 2))
    c = lambda m: -np.einsum("vji,vj->vi", m[:, :3, :3], m[:, :3, 3])  # noqa: E731
    return ang, np.linalg.norm(c(a) - c(b), axis=1)


# ----------------------------------------------------------------------------------- algebra
def test_a_correction_renders_what_the_corrected_camera_sees_and_zero_is_the_given_camera():
    scene, vms = _scene(), _cameras(2)
    cams = CameraCorrections(vms)
    assert np.allclose(cams.viewmats().numpy(), vms, atol=1e-15)
    assert torch.allclose(cams.transform(1), torch.eye(4), atol=1e-6)
    with torch.no_grad():
        cams.rotvecs[1].copy_(torch.tensor([0.004, -0.003, 0.002], dtype=torch.float64))
        cams.translations[1].copy_(torch.tensor([0.002, -0.001, 0.003], dtype=torch.float64))
    corrected = cams.viewmats().numpy()
    assert np.allclose(corrected[0], vms[0], atol=1e-15) and not np.allclose(corrected[1], vms[1], atol=1e-4)
    R = corrected[1, :3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14)
    direct = _render(scene, corrected[1])
    moved = _render(scene, vms[1], cams.transform(1))
    assert float((direct - moved).detach().abs().max()) < 2e-3  # float32 rounding of the moved means only
    assert float((direct - _render(scene, vms[1])).abs().max()) > 0.1  # the correction does move the image
    ang, dist = _pose_errors(corrected, vms)
    s = cams.summary("metres")
    assert s["views"] == 2 and s["rotation_deg_max"] == pytest.approx(ang.max(), abs=1e-6)
    assert s["translation_mm_max"] == pytest.approx(1000 * dist.max(), abs=1e-3)


def test_gradients_reach_the_rendered_view_only_and_adam_moves_it_alone():
    scene, vms = _scene(), _cameras(2)
    cams = CameraCorrections(vms)
    opt = cams.make_optimizer(1e-3, 1e-3)
    targets = [_render(scene, vm).detach().roll(1, 1) for vm in vms]  # a one-pixel shift to correct

    def step(i):
        opt.zero_grad(set_to_none=True)
        _render(scene, vms[i], cams.transform(i)).sub(targets[i]).square().mean().backward()
        opt.step()

    step(0)
    for ps in (cams.rotvecs, cams.translations):
        assert ps[0].grad is not None and bool(torch.isfinite(ps[0].grad).all())
        assert float(ps[0].grad.abs().sum()) > 0 and ps[1].grad is None
    assert float(cams.translation[0].abs().sum()) > 0 and float(cams.translation[1].abs().sum()) == 0
    moved = cams.rotvec[0].clone(), cams.translation[0].clone()
    step(1)  # view 0 is not rendered: its correction stays (no coasting on its momentum)
    assert torch.equal(cams.rotvec[0], moved[0]) and torch.equal(cams.translation[0], moved[1])
    assert float(cams.translation[1].abs().sum()) > 0
    assert torch.equal(cams.viewmat(1)[0], cams.viewmats()[1].float())
    assert correction_lrs(10, 10, 110, 1e-4, 3e-4) == (1e-4, 3e-4)
    lt, lr = correction_lrs(110, 10, 110, 1e-4, 3e-4)
    assert lt == pytest.approx(1e-5) and lr == pytest.approx(3e-5)
    assert correction_lrs(0, 10, 110, 1.0, 1.0) == (1.0, 1.0)
    with pytest.raises(ValueError, match="viewmats"):
        CameraCorrections(np.zeros((3, 3)))


def test_perturbed_cameras_are_pulled_back_towards_the_truth():
    scene, truth = _scene(), _cameras(4)
    targets = [_render(scene, vm).detach() for vm in truth]
    given = truth.copy()
    for i in range(len(given)):  # 0.6 degrees and 4 mm off, as structure from motion can be
        D = np.eye(4)
        D[:3, :3] = _rot([0.2 * i + 0.3, 1.0, -0.4], 0.6)
        D[:3, 3] = 0.004 * np.array([np.cos(i), np.sin(i), 0.3])
        given[i] = D @ truth[i]
    cams = CameraCorrections(given)
    opt = cams.make_optimizer(5e-4, 1e-3)
    ang0, dist0 = _pose_errors(given, truth)
    for _ in range(240):
        opt.zero_grad()
        loss = sum(
            (_render(scene, given[i], cams.transform(i)) - targets[i]).square().mean()
            for i in range(len(given))
        )
        loss.backward()
        opt.step()
    ang1, dist1 = _pose_errors(cams.viewmats().numpy(), truth)
    assert (ang1 < 0.1 * ang0).all() and (dist1 < 0.15 * dist0).all(), (ang0, ang1, dist0, dist1)


# ----------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("cams"), test_views=2, test_states=1)


def _estimated(src, dst):
    """``src`` marked as made by dsg-capture (estimated cameras and motions)."""
    shutil.copytree(src, dst)
    scene = json.loads((dst / "scene.json").read_text())
    scene["generator"] = {"name": "dsg-capture", "version": "1.0"}
    (dst / "scene.json").write_text(json.dumps(scene))
    return dst


def test_cameras_are_refined_on_request_only(capture, tmp_path):
    est = _estimated(capture, tmp_path / "est")

    def two(path, *extra):
        args = train_cli.two_state_parser().parse_args([str(path), "--out", "x", "--preset", "quick", *extra])
        return train_cli.two_state_config(args).base

    assert not two(est).refine_cameras and not two(capture).refine_cameras  # estimated cameras too
    cfg = two(est, "--refine-cameras", "--camera-lr-rotation", "2e-4")
    assert cfg.refine_cameras and cfg.camera_lr_rotation == 2e-4 and cfg.camera_lr_translation == 1e-4
    single = train_cli.single_state_parser().parse_args([str(capture), "--out", "x", "--refine-cameras"])
    assert single.refine_cameras
    with pytest.raises(ValueError, match="camera_lr_rotation"):
        two(capture, "--camera-lr-rotation", "nan")


def test_single_state_world_stores_the_refined_training_cameras(capture, tmp_path, capsys):
    out = tmp_path / "w.dsgworld"
    # single-state --iterations keeps the preset's schedule: corrections from step 50, every view seen after it
    args = [str(capture), "--out", str(out), "--preset", "quick", "--iterations", "90", "--quiet"]
    assert train_cli.main([*args, "--single-state", "--holdout-every", "4", "--refine-cameras"]) == 0
    w = load_world(out)
    rec = w.metadata["camera_refinement"]
    assert w.metadata["train_config"]["refine_cameras"] and rec["views"] == 12
    from train_world.capture.loader import load_views

    given = load_views(capture / "state1" / "transforms.json", load_depth=False).viewmats.numpy()
    stored = np.asarray(w.cameras["state1"].viewmats)
    held = set(w.metadata["heldout_views"])
    assert held == {0, 4, 8, 12}
    for i in range(len(given)):
        same = np.array_equal(stored[i], given[i])
        assert same if i in held else not same  # held-out cameras have no loss to refine them
    ang, dist = _pose_errors(stored.astype(np.float64), given.astype(np.float64))
    assert rec["rotation_deg_max"] == pytest.approx(ang.max(), abs=1e-3) and 0 < ang.max() < 2.0
    assert rec["translation_max"] == pytest.approx(dist.max(), rel=1e-3, abs=1e-6)
    assert train_cli.main([*args[:2], str(tmp_path / "f.dsgworld"), *args[3:], "--single-state"]) == 0
    assert "camera_refinement" not in load_world(tmp_path / "f.dsgworld").metadata


def test_two_state_refined_cameras_resume_bit_for_bit_and_feed_the_refinement(capture, tmp_path, capsys):
    from train_world.dual_state.refine import training_views_of
    from train_world.dual_state.trainer import DualTrainer
    from train_world.single_state.checkpoint import load_checkpoint

    est = _estimated(capture, tmp_path / "est")
    common = (
        "--preset quick --iterations 60 --prune-every 10 --quiet --refine-steps 0 --refine-cameras".split()
    )
    assert train_cli.main_two_state([str(est), "--out", str(tmp_path / "full.dsgworld"), *common]) == 0
    err = capsys.readouterr().err
    assert "cameras refined" in err and "cameras of state2 refined: median" in err
    cfg = train_cli.two_state_config(
        train_cli.two_state_parser().parse_args([str(est), "--out", "x", *common])
    )
    tr = DualTrainer(est, cfg, checkpoint=tmp_path / "res.dsgworld.ckpt")
    tr.train(progress=False, stop_after=45)
    assert tr.last_checkpoint_step is not None and 30 < tr.last_checkpoint_step <= 45
    tensors, _ = load_checkpoint(tmp_path / "res.dsgworld.ckpt")
    assert float(tensors["g2/cameras/rotvec"].abs().sum()) > 0
    assert any(k.startswith("g1/adam/cameras/") for k in tensors)
    resumed = [str(est), "--out", str(tmp_path / "res.dsgworld"), *common, "--resume"]
    assert train_cli.main_two_state(resumed) == 0
    full, res = load_world(tmp_path / "full.dsgworld"), load_world(tmp_path / "res.dsgworld")
    assert full.metadata["camera_refinement"] == res.metadata["camera_refinement"]
    assert set(full.metadata["camera_refinement"]) == {"state1", "state2"}
    for s in ("state1", "state2"):
        assert np.array_equal(full.cameras[s].viewmats, res.cameras[s].viewmats)
    assert np.array_equal(full.background.means, res.background.means)
    # the merged world's refinement (dsg-train --refine-steps, train_world.cli.refine) sees the same cameras
    views = training_views_of(full, est)
    assert np.array_equal(views["state2"].viewmats.numpy(), np.asarray(full.cameras["state2"].viewmats))
