"""benchmarks.pareto: the front, the recommended-point rule, world variants, error measurement, and one
``--quick`` run end to end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import pareto_core as C
from benchmarks.pareto_training import eval_times
from dsg_gym.gaussians import GaussianSet
from dsg_gym.scene_renderer import SceneRenderer
from tests._worlds import two_box_world

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------------------------------ front
def test_front_excludes_dominated_points():
    #            fast+bad  mid+good  slow+best  dominated (slower and worse than mid)  slow+worse than best
    times = [1.0, 2.0, 3.0, 2.5, 3.5]
    psnrs = [20.0, 25.0, 27.0, 24.0, 26.0]
    assert C.pareto_front(times, psnrs) == [True, True, True, False, False]


def test_front_ties():
    # identical points: neither dominates the other; equal time with lower PSNR (or equal PSNR, slower) is
    # dominated
    times = [1.0, 1.0, 1.0, 2.0, 0.5]
    psnrs = [25.0, 25.0, 24.0, 25.0, 10.0]
    assert C.pareto_front(times, psnrs) == [True, True, False, False, True]
    assert C.pareto_front([], []) == []
    assert C.pareto_front([3.0], [1.0]) == [True]


def _row(name, step_ms, psnr, **kw):
    return {"name": name, "point": C.Point(name, "x", **kw), "step_ms": step_ms, "psnr": psnr}


def test_recommend_fastest_front_point_within_tolerance():
    rows = [
        _row("default", 2.0, 27.00),
        _row("more accurate", 2.4, 27.05),  # the most accurate: the reference
        _row("fast, close", 1.7, 26.96),  # within 0.1 dB of 27.05: chosen
        _row("faster, too far", 1.5, 26.90),  # 0.15 dB below: excluded
        _row("slow dominated", 1.8, 26.95),  # dominated by "fast, close"
        _row("pruned", 1.0, 27.10, fraction=0.5),  # not env-settable: ignored
        _row("small", 0.5, 30.0, size=64),  # other size: ignored
    ]
    best = C.recommend(rows, tol=0.1, size=128)
    assert best["name"] == "fast, close"
    # a looser tolerance admits the faster point; a tighter one keeps the most accurate
    assert C.recommend(rows, tol=0.2)["name"] == "faster, too far"
    assert C.recommend(rows, tol=0.01)["name"] == "more accurate"
    assert C.recommend([rows[5], rows[6]]) is None


def test_recommend_tie_in_time_prefers_accuracy():
    rows = [_row("a", 1.0, 26.0), _row("b", 1.0, 26.05), _row("c", 2.0, 26.05)]
    assert C.recommend(rows, tol=0.1)["name"] == "b"


def test_combined_points_take_the_cheapest_value_within_tolerance():
    pts = [
        C.Point("default", "default"),
        C.Point("a2", "alpha_min", alpha_min=2 / 255),
        C.Point("a8", "alpha_min", alpha_min=8 / 255),
        C.Point("t3", "t_min", t_min=1e-3),
        C.Point("t5", "t_min", t_min=1e-5),
        C.Point("sh0", "sh_degree", sh_degree=0),
        C.Point("sh2", "sh_degree", sh_degree=2),
    ]
    psnr = {"default": 27.0, "a2": 26.95, "a8": 26.5, "t3": 27.01, "t5": 27.0, "sh0": 26.6, "sh2": 26.99}
    c01, c05 = C.combined_points(pts, psnr)
    assert (c01.alpha_min, c01.t_min, c01.sh_degree) == (2 / 255, 1e-3, 2)
    assert (c05.alpha_min, c05.t_min, c05.sh_degree) == (8 / 255, 1e-3, 0)
    assert c01.env_settable and c01.axis == "combined"
    # nothing cheaper than the default within tolerance: no combined point
    assert C.combined_points(pts, {**psnr, "a2": 20, "a8": 20, "t3": 20, "sh0": 20, "sh2": 20}) == []


def test_point_validation():
    with pytest.raises(ValueError):
        C.Point("x", "x", alpha_min=0.0)
    with pytest.raises(ValueError):
        C.Point("x", "x", fraction=0.0)
    with pytest.raises(ValueError):
        C.Point("x", "x", storage="int8")
    assert not C.Point("x", "x", storage="float16").env_settable
    names = [p.name for p in C.sweep_points()]
    assert len(names) == len(set(names)) and names[0] == "default"


# ----------------------------------------------------------------------------------------- world variants
def test_round_float16():
    a = np.array([0.0, 1.0, 0.5, -2.0, 1 / 3, 1e-3, 70000.0], np.float32)
    r = C.round_float16(a)
    assert r.dtype == np.float32
    np.testing.assert_array_equal(r[:4], a[:4])  # exactly representable
    assert r[4] != a[4] and abs(r[4] - a[4]) <= 2.0**-12  # 11 significant bits
    assert abs(r[5] - a[5]) / a[5] <= 2.0**-11
    assert np.isinf(r[6])  # beyond float16's range
    np.testing.assert_array_equal(C.round_float16(r[:6]), r[:6])  # idempotent


def test_float16_world_rounds_colours_and_opacities_only():
    w = two_box_world()
    h = C.float16_world(w)
    for a, b in [(w.background, h.background)] + list(zip(w.objects, h.objects)):
        np.testing.assert_array_equal(b.sh, C.round_float16(a.sh))
        np.testing.assert_array_equal(b.opacities, C.round_float16(a.opacities))
        np.testing.assert_array_equal(b.means, a.means)
        np.testing.assert_array_equal(b.scales, a.scales)
    assert not np.array_equal(h.background.sh, w.background.sh)  # something did change
    hh = C.float16_world(w, all_fields=True)
    np.testing.assert_array_equal(hh.background.means, C.round_float16(w.background.means))


def test_keep_top():
    s = np.array([0.5, 3.0, 1.0, 3.0, 0.1, 2.0])
    np.testing.assert_array_equal(C.keep_top(s, 0.5), [False, True, False, True, False, True])
    # ties broken by index; protected entries count towards the total
    np.testing.assert_array_equal(C.keep_top(s, 1 / 3), [False, True, False, True, False, False])
    prot = np.array([False, False, False, False, True, False])
    np.testing.assert_array_equal(C.keep_top(s, 0.5, prot), [False, True, False, True, True, False])
    assert C.keep_top(s, 1.0).all()


def test_budget_pruning_keeps_the_most_important_gaussians():
    w = two_box_world()
    bg = w.background
    # one Gaussian that shows nowhere (almost transparent): the least important
    ghost = GaussianSet.from_rgb(
        np.array([[0.0, 0.0, 0.001]]),
        np.array([[1.0, 0, 0, 0]]),
        np.full((1, 3), 0.007),
        np.array([0.001]),
        np.array([[0.9, 0.9, 0.9]]),
    )
    w = __import__("dataclasses").replace(w, background=GaussianSet.concat([bg, ghost]))
    scores = C.importance_scores(w, object_views=8, rings=1, per_ring=6)
    n = w.background.num
    assert scores[0].shape == (n,) and [s.shape for s in scores[1]] == [(o.num,) for o in w.objects]
    assert scores[0][-1] == scores[0].min() and scores[0][-1] < 1e-3 * np.median(scores[0])
    p = C.pruned_world(w, scores, (n - 1) / n)
    assert p.background.num == n - 1
    assert not np.any(np.all(p.background.means == ghost.means[0], axis=1))  # the ghost went
    half = C.pruned_world(w, scores, 0.5)
    keep = C.keep_top(scores[0], 0.5)
    assert half.background.num == keep.sum() == int(np.ceil(0.5 * n))
    assert scores[0][keep].min() >= scores[0][~keep].max()
    from train_world.compact.compaction import hull_vertices

    for o, po in zip(w.objects, half.objects):
        hv = o.means[hull_vertices(o)]
        assert po.num < o.num
        assert all(np.any(np.all(po.means == v, axis=1)) for v in hv)  # hull vertices survive
    assert C.pruned_world(w, scores, 1.0) is w


# ------------------------------------------------------------------------------------------------ errors
def test_area_downsample_and_classes():
    img = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_allclose(C.area_downsample(img, 2, 2), [[2.5, 4.5], [10.5, 12.5]])
    rgb = np.random.default_rng(0).random((6, 6, 3)).astype(np.float32)
    np.testing.assert_allclose(
        C.area_downsample(rgb, 3, 3), rgb.reshape(3, 2, 3, 2, 3).mean((1, 3)), atol=1e-6
    )
    cls = np.array([[0, 1, 2, 2], [1, 1, 2, 0], [0, 0, 0, 0], [0, 2, 0, 0]], np.uint8)
    np.testing.assert_array_equal(C.downsample_classes(cls, 3, 2, 2), [[1, 2], [0, 0]])


def _self_test_states(w) -> C.TestStates:
    """Ground truth = the world's own render at default settings (state2's poses, the world camera)."""
    cams = w.cameras
    r = SceneRenderer(w.background, list(w.objects), cams.viewmats, cams.Ks, cams.width, cams.height)
    out = r.render(w.states["state2"], rgb=True, mask=True, incremental=False)
    return C.TestStates(
        "self",
        {"s": out.rgb.astype(np.float32) / 255},
        {"s": out.mask},
        {"s": w.states["state2"]},
        cams.viewmats,
        cams.Ks,
        cams.width,
        cams.height,
    )


def test_render_error_against_own_render():
    w = two_box_world()
    test = _self_test_states(w)
    exact = C.render_error(w, test, C.Point("d", "d", size=64))
    assert exact["psnr"] == float("inf") and exact["ssim"] == pytest.approx(1.0) and exact["mask_iou"] == 1.0
    assert exact["views"] == 1 and exact["gaussians"] == w.num_gaussians
    worse = C.render_error(w, test, C.Point("a", "a", size=64, alpha_min=0.5))
    assert np.isfinite(worse["psnr"]) and worse["psnr"] < 40 and worse["ssim"] < 1.0
    small = C.render_error(w, test, C.Point("s", "s", size=32))
    assert 10 < small["psnr"] < 60 and 0.5 < small["mask_iou"] <= 1.0


def test_eval_times():
    assert eval_times(15, 100) == [15, 30, 60, 100]
    assert eval_times(15, 10) == [10]
    with pytest.raises(ValueError):
        eval_times(0, 10)


# ---------------------------------------------------------------------------------------------- end to end
def test_quick_run_writes_json_markdown_and_png(tmp_path):
    pytest.importorskip("matplotlib", reason="the plots need the bench extra (pip install -e .[bench])")
    out = tmp_path / "p"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_THREADING_LAYER"}
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks.pareto", "--out", str(out), "--quick", "--training"],
        check=False,
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads((out / "pareto.json").read_text())
    rows = res["bundled"]["points"]
    assert rows[0]["name"] == "default" and len(rows) >= 6
    for row in rows:
        assert (
            row["step_ms"] > 0 and 10 < row["psnr"] < 60 and 0 < row["ssim"] <= 1 and 0 < row["mask_iou"] <= 1
        )
    # the front is consistent with the rows
    flags = C.pareto_front([q["step_ms"] for q in rows], [q["psnr"] for q in rows])
    assert [q["name"] for q, f in zip(rows, flags) if f] == res["bundled"]["front"]
    rec = res["recommended"]
    cand = [q for q in rows if q["env_settable"] and q["size"] == 128]
    front = [
        q for q, f in zip(cand, C.pareto_front([q["step_ms"] for q in cand], [q["psnr"] for q in cand])) if f
    ]
    assert rec["name"] in [q["name"] for q in front] and rec["size"] == 128
    C.RenderSettings(**rec["render_settings"])  # a valid env setting
    best = max(q["psnr"] for q in cand)
    assert rec["psnr"] >= best - 0.1 - 1e-9 and "0.1 dB" in rec["rule"]
    faster = [q for q in front if q["step_ms"] < rec["step_ms"]]
    assert all(q["psnr"] < best - 0.1 for q in faster)  # nothing faster on the front qualifies
    f16 = next(q for q in rows if q["storage"] == "float16")
    assert f16["time_from"] == "default" and abs(f16["psnr"] - rows[0]["psnr"]) < 0.05
    assert res["scenes"] is None
    curve = res["training"]["curves"][0]
    assert curve["preset"] == "quick" and curve["finished"] and curve["points"][-1]["step"] == 30
    md = (out / "pareto.md").read_text()
    assert "| setting |" in md and rec["name"] in md and "Training time against error" in md
    for png in ("pareto.png", "training.png"):
        data = (out / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert not list(out.glob(".*"))  # no temporary files left


def test_world_generator_settings_read_the_generator_or_fall_back_to_older_ones():
    from types import SimpleNamespace

    from benchmarks.pareto import world_generator_settings as settings

    def world(meta):
        return SimpleNamespace(metadata=meta)

    assert settings(world({"source": {"generator": {"lighting": "soft", "supersample": 4}}})) == {
        "lighting": "soft",
        "supersample": 4,
    }
    # generator 1.1 recorded its lighting but no supersampling: one point sample per pixel
    assert settings(world({"source": {"generator": {"lighting": "soft"}}})) == {
        "lighting": "soft",
        "supersample": 1,
    }
    assert settings(world({"source": {"kind": "capture"}})) == {"lighting": "spot", "supersample": 1}
    assert settings(world({})) == {"lighting": "spot", "supersample": 1}
