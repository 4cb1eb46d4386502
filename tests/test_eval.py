"""dsg-eval: report files, metric definitions, refusal of bad worlds."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from train_world.cli import eval as eval_cli
from train_world.cli import train as cli
from train_world.cli.synth import main as synth_main
from train_world.eval import evaluate as ev
from train_world.eval.metrics import mask_iou, psnr, ssim

LEGO = Path(__file__).resolve().parents[2] / "shared" / "external" / "nerf_synthetic_lego"


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    cap = root / "cap"
    assert (
        synth_main(
            [
                "--scene",
                "three_primitives",
                "--out",
                str(cap),
                "--width",
                "32",
                "--height",
                "32",
                "--views",
                "10",
                "--test-views",
                "3",
                "--test-states",
                "1",
                "--quiet",
            ]
        )
        == 0
    )
    world = root / "w.dsgworld"
    assert (
        cli.main(
            [
                str(cap),
                "--out",
                str(world),
                "--preset",
                "quick",
                "--iterations",
                "60",
                "--single-state",
                "--holdout-every",
                "4",
                "--quiet",
            ]
        )
        == 0
    )
    return cap, world, root


def test_report_of_heldout_views(trained):
    cap, world, root = trained
    out = root / "report"
    assert eval_cli.main([str(world), str(cap), "--out", str(out)]) == 0
    r = json.loads((out / "report.json").read_text())
    assert [v["index"] for v in r["per_view"]] == [0, 4, 8]  # every 4th view of state1 was held out
    assert set(r["mean"]) == {"psnr", "ssim", "mask_iou"}
    assert math.isfinite(r["mean"]["psnr"]) and 5 < r["mean"]["psnr"] < 60
    assert -1 <= r["mean"]["ssim"] <= 1 and 0 <= r["mean"]["mask_iou"] <= 1
    assert r["mean"]["psnr"] == pytest.approx(np.mean([v["psnr"] for v in r["per_view"]]))
    assert set(r["object_iou"]) == {"yellow_box", "green_ball", "purple_capsule"}
    regions = r["error_by_region"]["regions"]
    assert set(regions) == {"outline", "objects", "background", "unseen"}
    # held-out views of the training state: the training views saw most of their background
    assert r["error_by_region"]["coverage_views"] == r["views"] == 3
    assert regions["unseen"]["pixel_share"] < regions["background"]["pixel_share"]
    assert sum(e["pixel_share"] for e in regions.values()) == pytest.approx(1.0)
    assert sum(e["error_share"] for e in regions.values()) == pytest.approx(1.0)
    # the regions' squared errors add up to the views' mean squared errors
    mse = np.mean([10 ** (-v["psnr"] / 10) for v in r["per_view"]])
    total = sum(e["squared_error"] for e in regions.values()) / sum(e["pixels"] for e in regions.values())
    assert total == pytest.approx(mse, rel=1e-9)
    assert set(r["error_by_region"]["per_object"]) == set(r["object_iou"])
    # the synthetic capture has depth and a table: the background split by the surface each pixel shows
    parts = r["error_by_region"]["background_parts"]
    assert sum(e["pixels"] for e in parts.values()) == regions["background"]["pixels"]
    assert parts["table_top"]["pixels"] > 0 and parts["other"]["pixels"] > 0
    md = (out / "report.md").read_text()
    assert "| **mean** |" in md and md.count("\n| state1/") == 3
    assert "| outline |" in md and "| object yellow_box |" in md and "| background: table top |" in md
    grid = Image.open(out / "grid.png")
    # 3 rows of (GT | ours | error | GT mask | our mask), 32 px tiles with 2 px borders, and the labels
    # (column names above, state and view left of each row) take room beyond the tiles
    assert grid.size[0] > 5 * 34 + 2 and grid.size[1] > 3 * 34 + 2


def test_novel_state_uses_its_object_poses(trained):
    cap, world, root = trained
    from dsg_gym.world import load_world
    from train_world.capture import load_capture

    r_same = ev.evaluate(world, cap, root / "s1", state="state1")  # the training state: held-out views
    r_test = ev.evaluate(world, cap, root / "t0", state="test_0")  # a test state: all its views
    assert r_same["views"] == 3 and r_test["views"] == 3
    assert all(v["view"].startswith("test_0/") for v in r_test["per_view"])
    w, c = load_world(world), load_capture(cap, states=[])
    assert np.array_equal(ev._poses_for(w, cap, "test_0"), c.poses["test_0"])
    assert not np.allclose(c.poses["test_0"], w.poses["state1"])


def test_test_state_poses_come_from_the_capture(trained):
    """A world that holds other poses under a test state's name is scored at the capture's poses there; at a
    training state it keeps its own (they may be refined)."""
    cap, world, _ = trained
    from dsg_gym.world import load_world
    from train_world.capture import load_capture

    w, c = load_world(world), load_capture(cap, states=[])
    other = {}
    for state, poses in (("state1", w.poses["state1"]), ("test_0", c.poses["test_0"])):
        moved = np.array(poses, dtype=np.float64)
        moved[:, :3, 3] += 0.05  # the same objects, 5 cm away
        other[state] = moved
    w2 = dataclasses.replace(w, poses={**w.poses, **other})
    assert np.array_equal(ev._poses_for(w2, cap, "test_0"), c.poses["test_0"])
    assert np.array_equal(ev._poses_for(w2, cap, "state1"), other["state1"])
    assert not np.allclose(other["state1"], c.poses["state1"])


def test_metric_definitions():
    rng = np.random.default_rng(0)
    a = rng.random((16, 16, 3))
    assert psnr(a, a) == float("inf")
    assert psnr(a, np.clip(a + 0.1, 0, 1)) < 30
    assert ssim(a.astype(np.float32), a.astype(np.float32)) == pytest.approx(1.0)
    gt = np.zeros((4, 4), np.int64)
    gt[:2, :2] = 1
    pred = np.zeros((4, 4), np.int64)
    pred[:2, :3] = 1
    ious = mask_iou(pred, gt, range(1, 3))
    assert ious[1] == pytest.approx(4 / 6) and ious[2] is None


def test_bad_world_is_refused(trained, tmp_path, capsys):
    cap, world, _ = trained
    bad = tmp_path / "bad.dsgworld"
    bad.write_bytes(world.read_bytes()[:-10])
    assert eval_cli.main([str(bad), str(cap), "--out", str(tmp_path / "o")]) == 2
    assert "truncated" in capsys.readouterr().err
    assert not (tmp_path / "o" / "report.json").exists()


def test_default_views_follow_what_the_world_held_out(trained, tmp_path, monkeypatch):
    cap, world, _ = trained
    assert ev.default_state(world, cap) is None  # a single-state world with held-out views: those
    meta = {"heldout_views": []}
    monkeypatch.setattr(ev, "load_world", lambda p: type("W", (), {"metadata": meta})())
    assert ev.default_state(world, cap) == "test"  # none held out: the capture's test states
    blender = tmp_path / "blender"
    blender.mkdir()
    (blender / "transforms_train.json").write_text("{}")
    assert ev.default_state(world, blender) is None  # NeRF-Blender data: its test split, no capture to read
    meta["dual"] = {}
    meta["heldout_views"] = [0]
    assert ev.default_state(world, cap) == "test"  # a two-state world: always the test states


@pytest.mark.skipif(not LEGO.is_dir(), reason="shared NeRF-Blender lego data not present")
def test_blender_world_evaluates_on_the_test_split(tmp_path):
    world = tmp_path / "lego.dsgworld"
    assert (
        cli.main(
            [
                str(LEGO),
                "--out",
                str(world),
                "--preset",
                "quick",
                "--iterations",
                "15",
                "--downscale",
                "16",
                "--quiet",
            ]
        )
        == 0
    )
    r = ev.evaluate(world, LEGO, tmp_path / "r")
    assert r["views"] == 10 and r["image_size"] == [50, 50] and r["mean"]["mask_iou"] is None
    assert r["mean"]["psnr"] > 8  # white background over white: even a poor world gets the background right
