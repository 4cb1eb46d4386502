"""DSG-World two-state training, its parts: state transfer, L_align / L_pseudo, pseudo-states, co-pruning,
co-pasting and the kNN completion of baseline (b)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from train_world.dual_state.losses import align_loss, pseudo_loss
from train_world.dual_state.merge import co_paste_background, co_prune_masks, object_footprints_xy
from train_world.dual_state.pseudo import footprint_radii, pseudo_state_valid, sample_pseudo_state
from train_world.dual_state.transfer import ObjectTransfer, gaussian_transforms, relative_transforms
from train_world.single_state.field import Classifier, SegmentedField
from train_world.suite.baselines import knn_complete


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


# ----------------------------------------------------------------------------------- baseline (b)
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
