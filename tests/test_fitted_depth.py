"""Depth maps from a first reconstruction (train_world.capture.fitted_depth) on a tiny synthetic capture whose
true depth is known: the capture's depth maps are taken away, fitted again and compared with the truth."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from dsg_gym.cameras import unproject
from tests._captures import tiny_capture
from train_world.capture import load_capture
from train_world.capture.fitted_depth import (
    DepthFit,
    drop_depth_jumps,
    fit_depth_maps,
    fitted_depths,
    jump_limits,
    rendered_depths,
)
from train_world.capture.format import DEPTH_SCALE
from train_world.capture.points import write_points_ply

FIT = DepthFit(steps=300, max_gaussians=5000, downscale=1)  # at the photos' size (the default halves it)


def _strip_depth(capture):
    """The capture without its depth maps (as a capture from photos comes)."""
    for s in ("state1", "state2"):
        tj = capture / s / "transforms.json"
        doc = json.loads(tj.read_text())
        for f in doc["frames"]:
            f.pop("depth_path", None)
        tj.write_text(json.dumps(doc))
        shutil.rmtree(capture / s / "depth", ignore_errors=True)
    return capture


@pytest.fixture(scope="module")
def truth(tmp_path_factory):
    return tiny_capture(tmp_path_factory.mktemp("truth"))


@pytest.fixture(scope="module")
def fitted(truth, tmp_path_factory):
    cap = tmp_path_factory.mktemp("fitted") / "cap"
    shutil.copytree(truth, cap)
    _strip_depth(cap)
    assert load_capture(cap, ["state1"]).states["state1"].depths is None
    return cap, fit_depth_maps(cap, ["state1", "state2"], FIT)


def test_rendered_depth_is_camera_z_where_opaque():
    import torch

    from train_world.single_state.field import SegmentedField

    # two small opaque Gaussians off the optical axis, where camera z and distance differ by 6-13 %
    pts = torch.tensor([[0.6, 0.4, 2.0], [-0.5, -0.5, 1.0]], dtype=torch.float64)
    field = SegmentedField.from_points(pts, torch.full((2, 3), 0.5, dtype=torch.float64),
                                       torch.full((2,), 0.04, dtype=torch.float64), sh_degree=0, num_features=4,
                                       opacity=0.999)  # fmt: skip
    K = torch.tensor([[[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]]])
    d = rendered_depths(field, torch.eye(4)[None], K, 32, 32, torch.zeros(3), 0.5)[0].numpy()
    for (x, y, z), want in zip(pts.numpy(), (2.0, 1.0), strict=True):
        u, v = int(32 * x / z + 16), int(32 * y / z + 16)  # the pixel the centre falls in
        assert d[v, u] == pytest.approx(want, rel=1e-4)
    assert (d > 0).mean() < 0.1 and d[0, 31] == 0.0  # nothing opaque elsewhere: no depth


def test_faint_gaussians_do_not_pull_the_depth_nearer():
    import torch

    from train_world.single_state.field import SegmentedField

    # an opaque Gaussian at z = 2 behind a faint one (opacity 0.05) at z = 1 on the same ray
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    field = SegmentedField.from_points(pts, torch.full((2, 3), 0.5, dtype=torch.float64),
                                       torch.tensor([0.08, 0.04], dtype=torch.float64), sh_degree=0,
                                       num_features=4, opacity=0.999)  # fmt: skip
    with torch.no_grad():
        field.opacity_logits[1] = torch.logit(torch.tensor(0.05))
    K = torch.tensor([[[32.0, 0.0, 16.0], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]]])
    every = rendered_depths(field, torch.eye(4)[None], K, 32, 32, torch.zeros(3), 0.5)[0, 16, 16].item()
    opaque = rendered_depths(field, torch.eye(4)[None], K, 32, 32, torch.zeros(3), 0.5, 0.1)[0, 16, 16].item()
    assert opaque == pytest.approx(2.0, rel=1e-4)
    assert every < 1.99  # the faint one in front pulls the expected depth towards the camera
    assert DepthFit().min_opacity == 0.2 and DepthFit().downscale == 2


def test_fitted_depth_is_written_into_the_capture(fitted):
    cap, result = fitted
    coverage = result["coverage"]
    assert result["floor"] is None and result["on_floor"] == {}  # no structure-from-motion points: no floor
    assert result["dropped"] == {} and DepthFit().edge_angle_deg == 0.0  # no jumps dropped by default
    for s in ("state1", "state2"):
        est = load_capture(cap, [s]).states[s]
        assert est.depths is not None and est.depths.shape[0] == 16
        d = est.depths.numpy()
        assert coverage[s] == pytest.approx(float((d > 0).mean()), abs=1e-4) and coverage[s] > 0.8
        frames = json.loads((cap / s / "transforms.json").read_text())["frames"]
        assert all(f["depth_path"] == f"depth/{f['file_path'].split('/')[-1]}" for f in frames)


def test_training_starts_from_the_fitted_depth(fitted):
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, get_preset
    from train_world.single_state.trainer import Trainer

    cap, _ = fitted
    cfg = TrainConfig(preset=get_preset("quick"), state="state1", holdout_every=0)
    data = load_training_data(cap, cfg)
    cover = float((data.depths > 0).double().mean())
    means = Trainer(data, cfg).field.means.detach().double().numpy()
    assert len(means) == round(cover * get_preset("quick").num_init_points)  # back-projected, in proportion


def test_the_maps_are_the_fit_to_the_millimetre_and_the_fit_is_deterministic(truth, fitted, tmp_path, capsys):
    cap, _ = fitted
    again = _strip_depth(shutil.copytree(truth, tmp_path / "again"))
    # the same fit once more, from the same start and seed; its progress bar names what it trains
    d = fitted_depths(again, "state1", FIT, progress=True).numpy()
    assert "depth fit state1" in capsys.readouterr().err
    written = load_capture(cap, ["state1"]).states["state1"].depths.numpy()
    units = np.rint(d.astype(np.float64) / DEPTH_SCALE).astype(np.float32)
    assert np.array_equal(units * np.float32(DEPTH_SCALE), written)


def _median_error(est, true):
    ok = (est > 0) & (true > 0)
    return float(np.median(np.abs(est[ok] - true[ok]) / true[ok]))


def test_a_fit_at_half_size_gives_depth_at_the_photos_size(truth, fitted, tmp_path):
    cap, _ = fitted
    true = load_capture(truth, ["state1"]).states["state1"].depths.numpy()
    full = load_capture(cap, ["state1"]).states["state1"].depths.numpy()
    again = _strip_depth(shutil.copytree(truth, tmp_path / "again"))
    half = fitted_depths(again, "state1", dataclasses.replace(FIT, downscale=2)).numpy()
    assert half.shape == true.shape == (16, 32, 32)  # trained at 16x16, rendered at 32x32
    assert (half > 0).mean() > 0.8
    err_full, err_half = _median_error(full, true), _median_error(half, true)
    # 300 steps at 32x32 (16x16) are far from converged: the full-size fit is 16 % off, the half-size one 34 %
    assert err_half < 3 * err_full < 0.6, (err_full, err_half)
    assert not np.array_equal(half, full)  # a fit of its own
    # the caller's full-size views (as fit_depth_maps passes, with masks) give the same maps bit for bit
    views = load_capture(again, ["state1"], load_depth=False).states["state1"]
    assert np.array_equal(
        fitted_depths(again, "state1", dataclasses.replace(FIT, downscale=2), views=views).numpy(), half
    )
    with pytest.raises(ValueError, match="downscale must be an integer >= 1"):
        DepthFit(downscale=0)


def _floor_points(truth, n=200):
    """Points of the true floor (z = -0.74, below the table top at 0) beyond the table, from the truth's depth."""
    views = load_capture(truth, ["state1"]).states["state1"]
    pts = []
    for i in range(len(views)):
        d, m = views.depths[i].numpy(), views.masks[i].numpy()
        v, u = np.nonzero((d > 0) & (m == 0))
        pts.append(unproject(u + 0.5, v + 0.5, d[v, u], views.viewmats[i].double().numpy(),
                             views.Ks[i].double().numpy()))  # fmt: skip
    pts = np.concatenate(pts)
    floor = pts[(pts[:, 2] < -0.735) & ((np.abs(pts[:, 0]) > 0.5) | (np.abs(pts[:, 1]) > 0.4))]
    return floor[np.random.default_rng(0).choice(len(floor), n, replace=False)]


def test_the_floor_of_the_structure_from_motion_points_takes_the_floors_depth(truth, tmp_path):
    with_points = _strip_depth(shutil.copytree(truth, tmp_path / "on"))
    write_points_ply(with_points / "points3d.ply", _floor_points(truth), np.full((200, 3), 128, np.uint8))
    scene = json.loads((with_points / "scene.json").read_text())
    (with_points / "scene.json").write_text(json.dumps({**scene, "points": {"path": "points3d.ply"}}))
    off = shutil.copytree(with_points, tmp_path / "off")
    result = fit_depth_maps(with_points, ["state1"], FIT)
    assert result["floor"]["z"] == pytest.approx(-0.74, abs=2e-3) and result["floor"]["points"] == 200
    assert fit_depth_maps(off, ["state1"], dataclasses.replace(FIT, floor_tolerance=0.0))["floor"] is None
    views = load_capture(truth, ["state1"]).states["state1"]
    true, masks = views.depths.numpy(), views.masks.numpy()
    with_floor = load_capture(with_points, ["state1"]).states["state1"].depths.numpy()
    without = load_capture(off, ["state1"]).states["state1"].depths.numpy()
    moved = with_floor != without
    assert result["on_floor"]["state1"] == pytest.approx(moved.mean(), abs=1e-3) and moved.mean() > 0.05
    assert (masks[moved] == 0).all()  # background only
    # the moved pixels: on the true floor to a few millimetres, where the fit alone was centimetres off
    err_with = np.median(np.abs(with_floor[moved] - true[moved]) / true[moved])
    err_without = np.median(np.abs(without[moved] - true[moved]) / true[moved])
    assert err_with < 0.005 < err_without, (err_with, err_without)
    with pytest.raises(ValueError, match="floor_tolerance"):
        DepthFit(floor_tolerance=1.0)


def test_jump_limits_are_a_plane_seen_at_the_edge_angle():
    K = np.array([[200.0, 0.0, 64.0], [0.0, 100.0, 64.0], [0.0, 0.0, 1.0]])
    for deg in (2.0, 5.0, 30.0):
        ly, lx = jump_limits(K, deg)
        for f, limit in ((100.0, ly), (200.0, lx)):
            # the depth along two rays 1/f apart to a plane that the first meets at `deg` from edge-on
            a, p = np.radians(deg), 1.0 / f
            d0, d1 = 1.0 / np.sin(a), 1.0 / np.sin(a + p)  # distance to the plane y = 1 along each ray
            assert limit == pytest.approx(d0 / d1 - 1.0, rel=1e-12) and limit > 0
    assert jump_limits(K, 5.0)[0] > jump_limits(K, 10.0)[0]  # a larger angle: stricter
    # nearly in proportion to the pixel's angle
    assert jump_limits(K, 5.0)[0] == pytest.approx(2 * jump_limits(K, 5.0)[1], rel=0.05)


def test_depth_jumps_are_dropped_on_both_sides_and_slopes_kept():
    # a ramp that deepens by 2 % a pixel (a floor at a grazing angle), a step of 50 % at column 6, a hole
    d = (1.02 ** np.arange(12, dtype=np.float32))[None, :].repeat(8, 0)
    d[:, 6:] *= 1.5
    d[4, 2] = 0.0
    before = d.copy()
    out = drop_depth_jumps(d, (0.05, 0.05))
    assert np.array_equal(d, before)  # the input is left as it was
    dropped = (out == 0) & (d > 0)
    assert dropped[:, 5].all() and dropped[:, 6].all()  # both sides of the step
    assert dropped[3, 2] and dropped[5, 2] and dropped[4, 1] and dropped[4, 3]  # the hole's 4-neighbours
    assert dropped.sum() == 16 + 4 and np.array_equal(out[~dropped], d[~dropped])  # nothing else: the slope,
    assert out[0, 0] > 0 and out[7, 11] > 0  # the image's border
    assert (drop_depth_jumps(d, (0.05, 0.6)) == 0).sum() == 1 + 4  # a step under the limit stays
    assert (drop_depth_jumps(d, (0.05, 0.01)) > 0).sum() == 0  # the slope too steep for 1 %: all of it
    # the limits' order: rows, then columns
    assert (drop_depth_jumps(d.T, (0.05, 0.6)) > 0).sum() == 12 * 8 - 16 - 5
    with pytest.raises(ValueError, match="edge_angle_deg"):
        DepthFit(edge_angle_deg=90.0)


def test_the_fit_drops_its_blended_depth_at_outlines(truth, fitted, tmp_path):
    cap, _ = fitted
    jumps = _strip_depth(shutil.copytree(truth, tmp_path / "jumps"))
    result = fit_depth_maps(jumps, ["state1"], dataclasses.replace(FIT, edge_angle_deg=5.0))
    views = load_capture(jumps, ["state1"]).states["state1"]
    kept = views.depths.numpy()
    whole = load_capture(cap, ["state1"]).states["state1"].depths.numpy()  # the same fit, nothing dropped
    limits = [jump_limits(K.numpy(), 5.0) for K in views.Ks]
    again = np.stack([drop_depth_jumps(d, lim) for d, lim in zip(whole, limits, strict=True)])
    # the same pixels kept, but where the stored maps' 1 mm rounding carries a jump across the limit
    assert np.array_equal(kept[(kept > 0) & (again > 0)], again[(kept > 0) & (again > 0)])
    assert ((kept > 0) != (again > 0)).mean() < 0.005
    gone = (whole > 0) & (kept == 0)
    assert result["dropped"]["state1"] == pytest.approx(gone.mean(), abs=1e-4) and 0.01 < gone.mean() < 0.5
    assert result["coverage"]["state1"] == pytest.approx((kept > 0).mean(), abs=1e-4)
    # the depths dropped are the fit's worst: off by far more than those kept
    true = load_capture(truth, ["state1"]).states["state1"].depths.numpy()
    err = np.abs(whole - true) / np.maximum(true, 1e-6)
    ok = (true > 0) & (whole > 0)
    worst, rest = np.median(err[gone & ok]), np.median(err[~gone & ok])
    assert worst > 2 * rest, (worst, rest)


def test_a_capture_with_depth_is_refused_and_left_unchanged(truth):
    before = (truth / "state1" / "transforms.json").read_bytes()
    with pytest.raises(ValueError, match="has depth maps already"):
        fit_depth_maps(truth, ["state1"], FIT)
    assert (truth / "state1" / "transforms.json").read_bytes() == before


@pytest.mark.parametrize(
    "kw, what",
    [({"steps": 10}, "at least 100 steps"), ({"max_gaussians": 10}, "1000 Gaussians"),
     ({"min_alpha": 1.0}, "min_alpha"), ({"min_opacity": 1.0}, "min_opacity")],
)  # fmt: skip
def test_bad_settings_are_refused(kw, what):
    with pytest.raises(ValueError, match=what):
        DepthFit(**kw)


def test_dsg_capture_fits_depth_by_default(tmp_path, capsys, monkeypatch):
    pytest.importorskip("pycolmap")
    from train_world.capture import photo_capture
    from train_world.cli import capture as capture_cli

    given = []

    def fake_build(photos, out, **kw):  # what dsg-capture asks of build_capture, without building
        given.append((kw["stereo"], kw["depth_fit"]))
        raise ValueError("stop here")

    monkeypatch.setattr(photo_capture, "build_capture", fake_build)
    base = [str(tmp_path), "--out", str(tmp_path / "out"), "--quiet"]
    for extra in (
        [],
        ["--fit-steps", "1500"],
        ["--fit-downscale", "1"],
        ["--floor-tolerance", "0"],
        ["--edge-angle", "10"],
        ["--depth", "stereo"],
        ["--depth", "none"],
    ):
        assert capture_cli.main([*base, *extra]) == 2 and "stop here" in capsys.readouterr().err
    assert given == [
        (False, DepthFit()),
        (False, DepthFit(steps=1500)),
        (False, DepthFit(downscale=1)),
        (False, DepthFit(floor_tolerance=0.0)),
        (False, DepthFit(edge_angle_deg=10.0)),
        (True, None),
        (False, None),
    ]


def test_bad_depth_options_are_refused(tmp_path, capsys):
    from train_world.cli import capture as capture_cli

    for extra, what in (
        (["--depth", "stereo", "--fit-steps", "3000"], "--fit-steps is for --depth fit, not --depth stereo"),
        (["--fit-steps", "5"], "at least 100 steps"),
        (["--depth", "none", "--fit-downscale", "2"], "--fit-downscale is for --depth fit, not --depth none"),
        (["--fit-downscale", "0"], "--fit-downscale must be an integer >= 1"),
        (["--depth", "stereo", "--floor-tolerance", "0.2"], "--floor-tolerance is for --depth fit, not"),
        (["--floor-tolerance", "1"], "--floor-tolerance must lie in [0, 1) (0: never), got 1.0"),
        (["--floor-tolerance", "nan"], "--floor-tolerance must lie in [0, 1)"),
        (["--depth", "none", "--edge-angle", "5"], "--edge-angle is for --depth fit, not --depth none"),
        (["--edge-angle", "90"], "--edge-angle must lie in [0, 90) degrees (0: never), got 90.0"),
        (["--depth", "lidar"], "invalid choice: 'lidar'"),
        (["--max-size", "8"], "--max-size must be at least 16 pixels"),
    ):
        with pytest.raises(SystemExit) as e:
            capture_cli.main([str(tmp_path), "--out", str(tmp_path / "out"), *extra])
        assert e.value.code == 2 and what in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    pytest.importorskip("pycolmap")
    from train_world.capture.photo_capture import build_capture

    with pytest.raises(ValueError, match="one source of depth maps"):
        build_capture(tmp_path, tmp_path / "out", stereo=True, depth_fit=DepthFit())
    with pytest.raises(ValueError, match="at least 16 pixels"):
        build_capture(tmp_path, tmp_path / "out", max_size=8)
    assert not (tmp_path / "out").exists()
