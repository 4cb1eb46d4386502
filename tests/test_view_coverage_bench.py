"""benchmarks.view_coverage: directions to the camera in an object's frame, the gap to the nearest training
direction, pooled bins, and a run over a suite-shaped folder (a tiny capture and its geometry world)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from _captures import tiny_suite_folder

from benchmarks import view_coverage as vc
from train_world.capture import load_capture
from train_world.eval.regions import region_masks


def _viewmat(centre) -> np.ndarray:
    c2w = np.eye(4)
    c2w[:3, 3] = centre
    return np.linalg.inv(c2w)


def test_directions_are_taken_in_the_objects_frame():
    vms = np.stack([_viewmat((1.0, 0.0, 1.0)), _viewmat((0.0, 3.0, 0.5))])
    pose = np.eye(4)
    pose[:3, 3] = (0.0, 0.0, 0.5)
    dirs, dist = vc.object_directions(vms, pose)
    assert np.allclose(dirs, [[2 / math.sqrt(5), 0, 1 / math.sqrt(5)], [0, 1, 0]]) and np.allclose(
        dist, [math.sqrt(1.25), 3]
    )
    turned = pose.copy()
    turned[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # a quarter turn about z: the world's +y is its +x
    dirs_t, dist_t = vc.object_directions(vms, turned)
    assert np.allclose(dirs_t[1], [1, 0, 0]) and np.allclose(dist_t, dist)
    assert np.allclose(np.linalg.norm(dirs_t, axis=1), 1.0)


def test_gap_is_the_angle_to_the_nearest_seen_direction():
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    a = math.radians(10.0)
    gap, j = vc.nearest_gap_deg(
        seen, np.array([[math.cos(a), math.sin(a), 0.0], [0.0, 0.0, 1.0], [0, 1.0, 0]])
    )
    assert np.allclose(gap, [10.0, 90.0, 0.0], atol=1e-9) and j[0] == 0 and j[2] == 1


def test_bins_pool_the_squared_error():
    rows = [
        {"gap_deg": 1.0, "sq": 3e-3, "pixels": 10},
        {"gap_deg": 2.5, "sq": 3e-2, "pixels": 10},
        {"gap_deg": 20.0, "sq": 0.3, "pixels": 100},
    ]
    b = vc.pooled_bins(rows)
    assert list(b) == ["0-3", "3-8", ">=8"]
    assert b["0-3"]["views"] == 2 and b["0-3"]["pixels"] == 20
    assert b["0-3"]["psnr"] == pytest.approx(10 * math.log10(60 / 0.033))
    assert b["3-8"] == {"views": 0, "pixels": 0, "psnr": None}
    assert b[">=8"]["psnr"] == pytest.approx(30.0)


def test_run_over_a_suite_folder(tmp_path):
    run = tmp_path / "run"
    world = tiny_suite_folder(run, test_views=3)
    out = tmp_path / "vc.json"
    assert vc.main([str(run), "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert "machine" in r and r["config"]["bin_edges_deg"] == [3.0, 8.0]
    (entry,) = r["runs"]
    rows = entry["rows"]
    assert 0 < len(rows) <= 3 * 2 and {x["object"] for x in rows} <= set(world.object_names)
    assert sum(b["views"] for b in entry["bins"].values()) == len(rows)
    for x in rows:
        assert x["state"] == "test_0" and 0.0 <= x["gap_deg"] <= 180.0 and x["pixels"] >= 10
        assert -90.0 <= x["elevation_deg"] <= 90.0 and x["distance_ratio"] > 0 and math.isfinite(x["psnr"])
        lo, hi = x["seen_elevation_deg"]
        assert -90.0 <= lo <= hi <= 90.0 and (x["gap_deg"] > 0 or lo <= x["elevation_deg"] <= hi)
    assert r["summary"]["bins"] == entry["bins"]
    # the interior is the object's share of the evaluation's ``objects`` region (its mask less the outline)
    cap = load_capture(run / "data" / "two_blocks", load_depth=False)
    masks = cap.states["test_0"].masks.numpy()
    for x in rows:
        m = masks[x["view"]]
        oid = world.object_ids[world.object_names.index(x["object"])]
        assert x["pixels"] == int((region_masks(m)["objects"] & (m == oid)).sum()) < int((m == oid).sum())
    # no world of the asked method: a one-line error, nothing written
    assert vc.main([str(run), "--methods", "B", "--out", str(tmp_path / "none.json")]) == 2
    assert not (tmp_path / "none.json").exists()
