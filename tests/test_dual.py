"""DSG-World two-state training: state transfer, L_align / L_pseudo, pseudo-states, co-pruning, co-pasting,
the merged world, the dsg-train dispatch and the comparison with baseline (a) on a tiny scene."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.world import load_world
from train_world.cli import train as recon_cli
from train_world.cli.eval import main as ev_main
from train_world.dual_state.losses import align_loss, pseudo_loss
from train_world.dual_state.merge import co_paste_background, co_prune_masks, object_footprints_xy
from train_world.dual_state.pseudo import footprint_radii, pseudo_state_valid, sample_pseudo_state
from train_world.dual_state.transfer import ObjectTransfer, gaussian_transforms, relative_transforms
from train_world.eval.evaluate import evaluate
from train_world.single_state.field import Classifier, SegmentedField
from train_world.suite.baselines import knn_complete, train_single_state


def _pose(x, y, z=0.05, yaw=0.0):
    P = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    P[:2, :2] = [[c, -s], [s, c]]
    P[:3, 3] = [x, y, z]
    return P


# ----------------------------------------------------------------------------------- transfer
def test_object_transfer_moves_objects_and_keeps_background():
    P1 = np.stack([_pose(0.1, 0.0), _pose(-0.1, 0.1, yaw=0.5)])
    P2 = np.stack([_pose(-0.2, 0.1, yaw=1.0), _pose(0.2, -0.1)])
    T = relative_transforms(P1, P2)
    labels = torch.tensor([0, 1, 2, 1, 0])
    g = torch.Generator().manual_seed(0)
    means = torch.randn(5, 3, generator=g) * 0.05
    quats = torch.nn.functional.normalize(torch.randn(5, 4, generator=g), dim=-1)
    M = gaussian_transforms(labels, T)
    assert torch.equal(M[0], torch.eye(4)) and torch.allclose(M[2], T[1])
    m2, _ = ObjectTransfer(labels, T)(means, quats)
    assert torch.allclose(m2[[0, 4]], means[[0, 4]])  # background stays
    # a point at object 1's origin in state 1 lands at its origin in state 2
    o1 = torch.tensor(P1[0, :3, 3], dtype=torch.float32)
    m_o, _ = ObjectTransfer(torch.tensor([1]), T)(o1[None], quats[:1])
    assert torch.allclose(m_o[0], torch.tensor(P2[0, :3, 3], dtype=torch.float32), atol=1e-6)
    with pytest.raises(ValueError):
        gaussian_transforms(torch.tensor([3]), T)
    # the object-rows-only callable agrees with the per-Gaussian matrices; background rows are untouched bits
    from train_world.single_state.field import rigid_transform_gaussians

    tr = ObjectTransfer(labels, T)
    m2, q2 = tr(means, quats)
    mr, qr = rigid_transform_gaussians(means, quats, M)
    assert torch.allclose(m2, mr, atol=1e-6) and torch.allclose(
        q2 * torch.sign(q2[:, :1]), qr * torch.sign(qr[:, :1]), atol=1e-6
    )
    assert torch.equal(m2[[0, 4]], means[[0, 4]]) and torch.equal(q2[[0, 4]], quats[[0, 4]])
    dirs = torch.randn(2, 5, 3, generator=g)
    assert torch.allclose(tr.rotate_dirs(dirs), torch.einsum("cnj,nji->cni", dirs, tr.rotations()), atol=1e-6)
    empty = ObjectTransfer(torch.zeros(5, dtype=torch.int64), T)  # no object Gaussian: nothing moves
    assert empty(means, quats)[0] is means and empty.rotate_dirs(dirs) is dirs


def test_object_transfer_renders_like_per_gaussian_matrices_with_sh_turning():
    g = torch.Generator().manual_seed(3)
    n = 60
    pts = torch.randn(n, 3, generator=g) * 0.1 + torch.tensor([0.0, 0.0, 1.5])
    f = SegmentedField.from_points(
        pts,
        torch.rand(n, 3, generator=g),
        torch.full((n,), 0.04),
        sh_degree=2,
        opacity=0.7,
        features=torch.randn(n, 16, generator=g),
    )
    with torch.no_grad():
        f.shN.normal_(0.0, 0.2, generator=g)  # view-dependent colour, so turning the SH matters
    labels = (torch.arange(n) % 3).long()  # background, object 1, object 2
    T = relative_transforms(
        np.stack([_pose(0.0, 0.0), _pose(0.05, 0.0)]),
        np.stack([_pose(0.03, 0.02, yaw=0.7), _pose(-0.02, 0.04, yaw=-1.1)]),
    )
    vm, K = _camera()
    outs, grads = [], []
    for transform in (ObjectTransfer(labels, T), gaussian_transforms(labels, T)):
        for p in f.params().values():
            p.grad = None
        o = f.render(vm, K, 32, 32, transform=transform, sh_degree=2)
        (o.rgb.square().sum() + o.features.square().sum()).backward()
        outs.append(o.rgb.detach())
        grads.append({k: v.grad.clone() for k, v in f.params().items()})
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    for k in grads[0]:
        assert torch.allclose(grads[0][k], grads[1][k], atol=1e-4, rtol=1e-3), k


# ----------------------------------------------------------------------------------- losses
def _scene_field(obj_offset=(0.0, 0.0)):
    """An opaque background wall of class 0 and a small opaque object cluster of class 1 in front."""
    g = torch.Generator().manual_seed(1)
    xs = torch.linspace(-0.6, 0.6, 14)
    wall = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    wall = torch.cat([wall, torch.full((len(wall), 1), 2.0)], 1)
    obj = 0.05 * torch.randn(40, 3, generator=g) + torch.tensor([obj_offset[0], obj_offset[1], 1.2])
    pts = torch.cat([wall, obj])
    rgb = torch.cat([torch.full((len(wall), 3), 0.3), torch.rand(len(obj), 3, generator=g)])
    scales = torch.cat([torch.full((len(wall),), 0.08), torch.full((len(obj),), 0.03)])
    feats = torch.zeros(len(pts), 16)
    feats[: len(wall), 0] = 1.0
    feats[len(wall) :, 1] = 1.0
    f = SegmentedField.from_points(pts, rgb, scales, sh_degree=0, opacity=0.99, features=feats)
    labels = torch.cat([torch.zeros(len(wall), dtype=torch.int64), torch.ones(len(obj), dtype=torch.int64)])
    return f, labels


def _camera():
    vm = torch.eye(4)[None]
    K = torch.tensor([[[40.0, 0, 16], [0, 40.0, 16], [0, 0, 1]]])
    return vm, K


@torch.no_grad()
def test_align_and_pseudo_losses_are_zero_for_aligned_fields_and_positive_otherwise():
    vm, K = _camera()
    clf = Classifier(16, 2)
    with torch.no_grad():  # a confident classifier: feature channel c -> class c
        clf.weight.zero_()
        clf.weight[0, 0] = clf.weight[1, 1] = 1000.0
        clf.bias.zero_()
    P1 = _pose(0.0, 0.0, 1.2)[None]
    P2 = _pose(0.15, -0.1, 1.2, yaw=0.7)[None]
    g1, lab = _scene_field()
    # G2 is G1 in state 2 exactly: its object Gaussians moved by T_1->2
    m2, q2 = ObjectTransfer(lab, relative_transforms(P1, P2))(g1.means.detach(), g1.quats.detach())
    g2 = SegmentedField(m2, q2, g1.log_scales, g1.opacity_logits, g1.sh0, g1.shN, g1.features)

    def render(field, transform=None):
        return field.render(vm, K, 32, 32, transform=transform, background=torch.zeros(3))

    obs1, obs2 = render(g1), render(g2)  # the "captured" states
    cls1, cls2 = clf(obs1.features[0]).argmax(-1), clf(obs2.features[0]).argmax(-1)
    assert 0 < int(cls2.sum()) < 32 * 32  # the object is in view
    o12 = render(g1, ObjectTransfer(lab, relative_transforms(P1, P2)))
    o21 = render(g2, ObjectTransfer(lab, relative_transforms(P2, P1)))
    l_align = align_loss(o12.rgb[0], o12.features[0], obs2.rgb[0], cls2, clf) + align_loss(
        o21.rgb[0], o21.features[0], obs1.rgb[0], cls1, clf
    )
    assert float(l_align) < 1e-4
    Pp = _pose(-0.1, 0.12, 1.2, yaw=-1.1)[None]
    a = render(g1, ObjectTransfer(lab, relative_transforms(P1, Pp)))
    b = render(g2, ObjectTransfer(lab, relative_transforms(P2, Pp)))
    assert float(pseudo_loss(a.rgb[0], a.features[0], b.rgb[0], b.features[0], clf)) < 1e-4
    # misaligned: G2's object is 6 cm off where T says it is
    g2_off = SegmentedField(
        m2 + torch.where(lab[:, None] == 1, torch.tensor([0.06, 0.0, 0.0]), torch.zeros(3)),
        q2,
        g1.log_scales,
        g1.opacity_logits,
        g1.sh0,
        g1.shN,
        g1.features,
    )
    o21b = render(g2_off, ObjectTransfer(lab, relative_transforms(P2, P1)))
    assert float(align_loss(o21b.rgb[0], o21b.features[0], obs1.rgb[0], cls1, clf)) > 0.01
    b2 = render(g2_off, ObjectTransfer(lab, relative_transforms(P2, Pp)))
    assert float(pseudo_loss(a.rgb[0], a.features[0], b2.rgb[0], b2.features[0], clf)) > 0.01


# ----------------------------------------------------------------------------------- pseudo-states
def test_pseudo_states_are_collision_free_and_on_the_table():
    rng = np.random.default_rng(0)
    bounds = np.array([[-0.4, -0.3, 0.0], [0.4, 0.3, 0.0]])
    ref = np.stack([_pose(-0.2, 0.0, 0.045), _pose(0.0, 0.1, 0.065), _pose(0.2, -0.1, 0.03)])
    radii = np.array([0.09, 0.06, 0.05])
    seen = []
    for _ in range(200):
        P = sample_pseudo_state(ref, radii, bounds, rng, margin=0.005)
        assert pseudo_state_valid(P, radii, bounds, margin=0.005)
        xy = P[:, :2, 3]
        assert np.all(xy - radii[:, None] >= bounds[0, :2] - 1e-9) and np.all(
            xy + radii[:, None] <= bounds[1, :2] + 1e-9
        )
        for i in range(3):
            for j in range(i + 1, 3):
                assert np.linalg.norm(xy[i] - xy[j]) >= radii[i] + radii[j] + 0.005 - 1e-9
        assert np.allclose(P[:, 2, 3], ref[:, 2, 3]) and np.allclose(P[:, 2, 2], 1.0)  # upright, same height
        seen.append(xy)
    assert np.std(np.stack(seen)[:, :, 0]) > 0.05  # configurations vary
    # an overlapping configuration is invalid; impossible footprints fall back to the reference poses
    assert not pseudo_state_valid(np.stack([_pose(0, 0), _pose(0.05, 0)]), np.array([0.05, 0.05]), bounds)
    assert not pseudo_state_valid(np.stack([_pose(0.38, 0)]), np.array([0.05]), bounds)
    big = sample_pseudo_state(ref[:2], np.array([0.29, 0.29]), bounds, rng, max_tries=5, max_restarts=2)
    assert np.array_equal(big, ref[:2])
    r = footprint_radii([np.array([[0.05, 0.0, 0.0], [0.0, -0.03, 0.02]]), np.zeros((0, 3))], quantile=1.0)
    assert np.allclose(r, [0.05, 0.05])


# ----------------------------------------------------------------------------------- co-pruning / co-pasting
def _table_grid(step=0.01):
    xs = np.arange(-0.2, 0.2001, step)
    return np.stack(np.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)


def _square(cx, cy, h=0.05):
    return np.array([[cx - h, cy - h, 0], [cx + h, cy - h, 0], [cx + h, cy + h, 0], [cx - h, cy + h, 0.1]])


def test_co_pruning_removes_unexplained_gaussians_only():
    tau = 0.02  # metres
    bounds = np.array([[-0.2, -0.2, 0.0], [0.2, 0.2, 0.0]])
    grid = np.concatenate([_table_grid(), np.zeros((len(_table_grid()), 1))], 1)
    fp1 = object_footprints_xy([_square(-0.1, -0.1)])
    fp2 = object_footprints_xy([_square(0.1, 0.1)])
    g2 = grid.copy()
    extra1 = np.array(
        [
            [0.0, 0.0, 0.10],  # floater 10 cm above the table: pruned
            [0.0, 0.0, 0.015],  # 1.5 cm from the table surface (< tau): kept
            [0.1, 0.1, 0.08],  # background floater inside the state-2 footprint: G2 never saw it, kept
            [0.6, 0.0, 0.5],  # off the table (a wall): not tested, kept
        ]
    )
    g1 = np.concatenate([grid, extra1])
    bg1 = np.ones(len(g1), bool)
    p1, p2 = co_prune_masks(
        g1,
        g2,
        g2,
        g1,
        tau,
        background_1=bg1,
        background_2=np.ones(len(g2), bool),
        footprints_1=fp1,
        footprints_2=fp2,
        table_bounds=bounds,
    )
    assert p1[: len(grid)].sum() == 0 and p1[len(grid) :].tolist() == [True, False, False, False]
    assert p2.sum() == 0
    # the same floater as an *object* Gaussian (not background) inside the state-2 footprint is pruned
    p1b, _ = co_prune_masks(
        g1,
        g2,
        g2,
        g1,
        tau,
        background_1=np.r_[np.ones(len(grid), bool), [1, 1, 0, 1]].astype(bool),
        background_2=np.ones(len(g2), bool),
        footprints_1=fp1,
        footprints_2=fp2,
        table_bounds=bounds,
    )
    assert p1b[len(grid) + 2]
    # symmetric: a floater in G2 is pruned against G1; a larger tau keeps it
    g2f = np.concatenate([g2, [[0.05, -0.05, 0.2]]])
    _, p2f = co_prune_masks(g1, g2f, g2f, g1, tau, table_bounds=bounds)
    assert p2f[-1] and p2f[:-1].sum() == 0
    _, p2g = co_prune_masks(g1, g2f, g2f, g1, 0.25, table_bounds=bounds)
    assert not p2g.any()


def test_co_pasting_fills_each_hole_from_the_other_state():
    grid = _table_grid()
    fp1 = object_footprints_xy([_square(-0.1, -0.1)])  # state-1 object (hole in G1's table)
    fp2 = object_footprints_xy([_square(0.1, 0.1)])  # state-2 object (hole in G2's table)
    in1 = (np.abs(grid[:, 0] + 0.1) <= 0.05) & (np.abs(grid[:, 1] + 0.1) <= 0.05)
    in2 = (np.abs(grid[:, 0] - 0.1) <= 0.05) & (np.abs(grid[:, 1] - 0.1) <= 0.05)
    z = lambda a, h=0.0: np.concatenate([a, np.full((len(a), 1), h)], 1)
    junk1 = z(np.array([[-0.1, -0.1], [-0.12, -0.08]]), 0.03)  # G1's residue under its own object
    bg1 = np.concatenate([z(grid[~in1]), junk1])
    bg2 = z(grid[~in2])
    keep1, keep2 = co_paste_background(bg1, bg2, fp1, fp2)
    merged = np.concatenate([bg1[keep1], bg2[keep2]])
    assert not keep1[-2:].any()  # the residue goes
    assert len(merged) == len(grid)  # every table cell exactly once
    got = {tuple(np.round(p[:2], 4)) for p in merged}
    assert got == {tuple(np.round(p, 4)) for p in grid}
    assert np.all(keep2 == in1[~in2])  # G2 contributes exactly the state-1 footprint


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
    # on a capture with test states both train on every view of their states (the test states evaluate them)
    assert w.metadata["heldout_views_by_state"] == {"state1": [], "state2": []}
    wa = load_world(base)
    assert wa.metadata["heldout_views"] == [] and wa.metadata["train_config"]["holdout_every"] == 0
    # so dsg-eval evaluates the single-state world at the test states too (it has no held-out views of its own
    # state to evaluate on); --state picks another state, all of whose views are evaluated
    assert ev_main([str(base), str(tiny), "--out", str(tmp_path / "eval_a1")]) == 0
    assert json.loads((tmp_path / "eval_a1" / "report.json").read_text())["states"]["test_0"]["mean"] == r_a
    assert ev_main([str(base), str(tiny), "--out", str(tmp_path / "eval_a2"), "--state", "state1"]) == 2
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


def test_knn_completion_fills_the_hole_not_the_table_seen_around_the_object():
    from dsg_gym.gaussians import GaussianSet
    from dsg_gym.world import World, WorldObject

    # a table of flat Gaussians (2 mm grid) with a hole of radius 2 cm where a 3 cm-radius object stood: the
    # ring 2-3 cm from its axis was seen around its base; the footprint dilated by 1 cm reaches 4 cm
    g = np.arange(-0.1, 0.1001, 0.002)
    x, y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    pts = pts[np.linalg.norm(pts[:, :2], axis=1) > 0.02]
    n = len(pts)
    feats = np.zeros((n, 4), np.float32)
    feats[:, 0] = 1.0
    bg = GaussianSet.from_rgb(
        pts,
        np.tile([1.0, 0, 0, 0], (n, 1)),
        np.tile([0.0015, 0.0015, 0.0003], (n, 1)),
        np.full(n, 0.9),
        np.full((n, 3), 0.4),
        features=feats,
    )
    ang = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    obj_pts = np.concatenate(
        [np.stack([0.03 * np.cos(ang), 0.03 * np.sin(ang), np.full(64, h)], 1) for h in (-0.02, 0.0, 0.02)]
    )
    m = len(obj_pts)
    obj = GaussianSet.from_rgb(
        obj_pts,
        np.tile([1.0, 0, 0, 0], (m, 1)),
        np.full((m, 3), 0.003),
        np.full(m, 0.9),
        np.full((m, 3), 0.8),
        features=np.zeros((m, 4), np.float32),
    )
    pose = np.eye(4)[None].copy()
    pose[0, 2, 3] = 0.02
    world = World(
        background=bg,
        objects={1: WorldObject("can", obj)},
        poses={"state1": pose},
        cameras={},
        classifier_weight=np.zeros((2, 4), np.float32),
        classifier_bias=np.zeros(2, np.float32),
        metadata={"reference_state": "state1", "table": {"bounds": [[-0.1, -0.1, 0.0], [0.1, 0.1, 0.0]]}},
    )
    done = knn_complete(world, spacing=0.004)
    added = done.background.means[bg.num :]
    r = np.linalg.norm(added[:, :2], axis=1)
    assert len(added) > 0 and r.max() < 0.02 + 0.004 + 1e-6  # nothing over the table that was seen
    hole = np.stack(np.meshgrid(np.linspace(-0.019, 0.019, 15), np.linspace(-0.019, 0.019, 15)), -1).reshape(
        -1, 2
    )
    hole = hole[np.linalg.norm(hole, axis=1) < 0.019]
    near = np.concatenate([added[:, :2], pts[np.linalg.norm(pts[:, :2], axis=1) < 0.03, :2]])
    gap = np.min(np.linalg.norm(hole[:, None] - near[None], axis=-1), axis=1)
    assert gap.max() < 0.004  # every point of the hole is within a grid step of a new or a table Gaussian
    everywhere = knn_complete(world, spacing=0.004, covered_opacity=1.01)  # the old behaviour: all of it
    r_all = np.linalg.norm(everywhere.background.means[bg.num :, :2], axis=1)
    assert r_all.max() > 0.035 and len(r_all) > len(added)


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
