"""AbsGS densification: the rasterizer's absolute 2D mean gradients equal the per-pixel gradients' absolute
values summed pixel by pixel, they see what cancels in the plain gradient, and ``dsg-train --absgrad`` trains
with them."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _captures import tiny_capture

from dsg_gym.cameras import look_at
from dsg_gym.splat import rasterize
from dsg_gym.world import load_world
from train_world.cli import train as train_cli
from train_world.single_state.presets import get_preset
from train_world.single_state.strategy import DensifyStrategy, StrategyConfig

W = H = 20  # two tiles each way: Gaussians cross tile borders


def _gaussians(n: int, seed: int):
    rng = np.random.default_rng(seed)
    t = lambda a: torch.from_numpy(np.asarray(a, np.float64))  # noqa: E731
    return dict(
        means=t(np.c_[rng.uniform(-0.08, 0.08, (n, 2)), rng.uniform(-0.05, 0.05, n)]).requires_grad_(),
        quats=t(rng.normal(size=(n, 4))),
        scales=t(rng.uniform(0.01, 0.04, (n, 3))),
        opacities=t(rng.uniform(0.3, 0.95, n)),
        colors=t(rng.uniform(0, 1, (n, 3))),
    )


def _render(g, absgrad=False, backend="numba"):
    vm = torch.from_numpy(look_at([0.0, 0.0, 0.5], [0, 0, 0], [0, 1.0, 0]))[None]  # straight down
    K = torch.tensor([[[40.0, 0, W / 2], [0, 40.0, H / 2], [0, 0, 1]]], dtype=torch.float64)
    return rasterize(g["means"], g["quats"], g["scales"], g["opacities"], g["colors"], vm, K, W, H,
                     backend=backend, absgrad=absgrad)  # fmt: skip


def test_absgrad_is_the_sum_over_pixels_of_the_absolute_per_pixel_gradients():
    g = _gaussians(6, 0)
    v = torch.from_numpy(np.random.default_rng(1).normal(size=(1, H, W, 3)))
    va = torch.from_numpy(np.random.default_rng(2).normal(size=(1, H, W, 1)))
    out, alpha, meta = _render(g, absgrad=True)
    meta["means2d"].retain_grad()
    ((out * v).sum() + (alpha * va).sum()).backward()
    got = meta["means2d"].absgrad
    assert got.shape == (1, 6, 2)
    want = torch.zeros_like(got)
    signed = torch.zeros_like(got)
    for y in range(H):
        for x in range(W):
            o, a, m = _render(g)
            m["means2d"].retain_grad()
            ((o[0, y, x] * v[0, y, x]).sum() + a[0, y, x, 0] * va[0, y, x, 0]).backward()
            want += m["means2d"].grad.abs()
            signed += m["means2d"].grad
    assert float(want.min()) >= 0 and float(want.max()) > 0
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)
    torch.testing.assert_close(meta["means2d"].grad, signed, rtol=1e-9, atol=1e-12)
    assert bool((got >= meta["means2d"].grad.abs() - 1e-12).all())
    # without the option the plain gradient is unchanged and nothing is attached
    out2, alpha2, meta2 = _render(g)
    meta2["means2d"].retain_grad()
    ((out2 * v).sum() + (alpha2 * va).sum()).backward()
    assert torch.equal(meta2["means2d"].grad, meta["means2d"].grad)
    assert not hasattr(meta2["means2d"], "absgrad")


def test_absgrad_needs_the_numba_backend():
    with pytest.raises(ValueError, match="absgrad needs the numba backend"):
        _render(_gaussians(2, 0), absgrad=True, backend="torch")


def test_a_gaussian_over_symmetric_texture_is_densified_on_absgrad_only():
    """One large Gaussian centred on stripes symmetric about it: the pixels pull its mean both ways, so the
    plain 2D mean gradient cancels and 3DGS's statistic leaves it alone; AbsGS's does not."""
    t = lambda a: torch.tensor(a, dtype=torch.float64)  # noqa: E731
    g = dict(means=t([[0.0, 0.0, 0.0]]).requires_grad_(), quats=t([[1.0, 0, 0, 0]]), scales=t([[0.05, 0.05, 0.05]]),
             opacities=t([0.9]), colors=t([[0.5, 0.5, 0.5]]))  # fmt: skip
    d = np.abs(np.arange(W) + 0.5 - W / 2)  # pixel centres' distances from the image centre
    rings = (np.floor(d[:, None] / 2) + np.floor(d[None, :] / 2)) % 2  # symmetric about both image axes
    target = torch.from_numpy(np.repeat(rings[:, :, None], 3, axis=2))
    stats = {}
    for absgrad in (False, True):
        s = DensifyStrategy(StrategyConfig(absgrad=absgrad), num=1)
        out, _, meta = _render(g, absgrad=absgrad)
        meta["means2d"].retain_grad()
        ((out[0] - target) ** 2).sum().backward()
        s.accumulate(meta)
        stats[absgrad] = float(s.grad2d[0])
    assert stats[False] < 1e-6 * stats[True]  # cancels by the symmetry
    assert stats[True] > StrategyConfig().absgrad_threshold
    s = DensifyStrategy(StrategyConfig(absgrad=True), num=1)
    out, _, meta = _render(g)  # a render without absgrad cannot feed the AbsGS statistic
    meta["means2d"].retain_grad()
    out.sum().backward()
    with pytest.raises(ValueError, match="absgrad=True"):
        s.accumulate(meta)


def test_dsg_train_absgrad_option_trains_and_records_it(tmp_path):
    capture = tiny_capture(tmp_path / "data")
    args = train_cli.two_state_parser().parse_args([str(capture), "--out", "x", "--absgrad",
                                                    "--absgrad-threshold", "1e-3"])  # fmt: skip
    preset = train_cli.two_state_config(args).base.preset
    assert preset.absgrad and preset.absgrad_threshold == 1e-3
    plain = train_cli.two_state_config(train_cli.two_state_parser().parse_args([str(capture), "--out", "x"]))
    assert not plain.base.preset.absgrad
    with pytest.raises(ValueError, match="absgrad_threshold"):
        get_preset("quick", absgrad=True, absgrad_threshold=float("nan"))
    runs = {}
    for name, extra in (("plain", []), ("abs", ["--absgrad"]), ("abs2", ["--absgrad"])):
        out = tmp_path / f"{name}.dsgworld"
        cmd = [str(capture), "--out", str(out), "--preset", "quick", "--iterations", "160", "--quiet",
               "--single-state", "--holdout-every", "0", "--no-shell", *extra]  # fmt: skip
        assert train_cli.main(cmd) == 0
        w = load_world(out)
        runs[name] = w
    assert runs["abs"].metadata["train_config"]["preset"]["absgrad"] is True
    assert runs["plain"].metadata["train_config"]["preset"]["absgrad"] is False
    a, b, p = (np.asarray(runs[k].background.means) for k in ("abs", "abs2", "plain"))
    assert np.array_equal(a, b)  # deterministic
    assert a.shape != p.shape or not np.array_equal(a, p)  # another densification
