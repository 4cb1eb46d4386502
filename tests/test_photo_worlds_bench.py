"""benchmarks.photo_worlds: a world from photos against one from the true cameras, on a small quick run."""

from __future__ import annotations

import json
import math
import shutil

import pytest

from benchmarks.photo_worlds import main


def test_photo_worlds_quick(tmp_path):
    out = tmp_path / "pw.json"
    args = [
        "--out",
        str(out),
        "--scenes",
        "four_mixed",
        "--views",
        "24",
        "--preset",
        "quick",
        "--iterations",
        "60",
        "--depth",
        "none",
    ]
    assert main([*args, "--work", str(tmp_path / "work"), "--align-views", "4"]) == 0
    r = json.loads(out.read_text())
    s = r["scenes"]["four_mixed"]
    assert r["config"]["eval_args"] == ["--align-views", "4"]
    assert r["config"]["capture_args"] == ["--depth", "none"]
    assert len(s["motions"]) == 4  # four objects, each against the truth, as estimated and as refined
    for m in s["motions"].values():
        assert 0 <= m["estimate_mm"] < 50 and 0 <= m["refined_rotation_mod_symmetry_deg"] < 20
        assert m["refined_rotation_mod_symmetry_deg"] <= m["refined_rotation_deg"] + 1e-9
        assert m["refined_rotation_mod_symmetry_deg"] <= m["refined_rotation_mod_texture_deg"] + 1e-9
        assert m["refined_rotation_mod_texture_deg"] <= m["refined_rotation_deg"] + 1e-9
        assert m["estimate_px"] > 0 and m["refined_px"] > 0  # the errors in pixels of the truth's views
    assert r["summary"]["worst_estimate_mm"] == max(m["estimate_mm"] for m in s["motions"].values())
    assert r["summary"]["worst_refined_px"] == max(m["refined_px"] for m in s["motions"].values())
    assert s["gap_db_unaligned"] == pytest.approx(
        s["reference"]["psnr_unaligned"] - s["photo"]["psnr_unaligned"], abs=1e-3
    )
    assert s["registered"] == {"state1": "24/24", "state2": "24/24"}
    assert s["camera_refinement"] is None  # the photo world's cameras as dsg-capture estimated them
    for k in ("photo", "reference"):
        assert math.isfinite(s[k]["psnr"]) and 5 < s[k]["psnr"] < 60 and 0 <= s[k]["mask_iou"] <= 1
        # where each world's error is: dsg-eval's regions and the background's parts (the truth has depth)
        assert {"outline", "objects", "background", "table_top", "floor", "other"} <= set(s[k]["regions"])
        assert 5 < s[k]["regions"]["table_top"] < 80
    assert r["summary"]["mean_region_gap_db"]["floor"] == pytest.approx(
        s["reference"]["regions"]["floor"] - s["photo"]["regions"]["floor"], abs=1e-3
    )
    assert s["gap_db"] == pytest.approx(s["reference"]["psnr"] - s["photo"]["psnr"], abs=1e-3)
    assert s["photos_to_world_min"] == pytest.approx((s["capture_s"] + s["train_s"]) / 60, abs=0.01)
    assert s["peak_rss_gib"] > 0.05
    assert r["summary"]["worst_gap_db"] == s["gap_db"] and r["targets"]["gap_db"] == 0.5
    report = json.loads((tmp_path / "work" / "four_mixed" / "eval_photo" / "report.json").read_text())
    assert "frame_alignment" in report  # the photo world was scored in the ground truth's frame
    assert report["mean_unaligned"]["psnr"] == pytest.approx(s["photo"]["psnr_unaligned"])
    for state in report["states"]:
        per_state = json.loads(
            (tmp_path / "work" / "four_mixed" / "eval_photo" / state / "report.json").read_text()
        )
        assert per_state["view_alignment"]["settings"]["steps"] == 4
    # a second run in the same folder reuses every finished step (their times too) and scores again
    steps = json.loads((tmp_path / "work" / "four_mixed" / "steps.json").read_text())
    assert set(steps) == {"synth", "capture", "train", "train_reference"}
    assert "--holdout-every" in steps["train"]["cmd"]  # every photo trains, as every true view does
    assert main([*args, "--work", str(tmp_path / "work"), "--align-views", "0"]) == 0
    again = json.loads(out.read_text())["scenes"]["four_mixed"]
    assert (again["train_s"], again["capture_s"]) == (s["train_s"], s["capture_s"])
    assert again["photo"]["psnr"] == pytest.approx(s["photo"]["psnr_unaligned"], abs=1e-6)
    assert "gap_db_unaligned" not in again
    # without the capture's output, the capture and the photo world run again; the reference stays
    d = tmp_path / "work" / "four_mixed"
    before = {k: v["wall_s"] for k, v in json.loads((d / "steps.json").read_text()).items()}
    mtimes = {w: (d / w).stat().st_mtime_ns for w in ("photo.dsgworld", "reference.dsgworld")}
    shutil.rmtree(d / "est")
    assert main([*args, "--work", str(tmp_path / "work"), "--align-views", "0"]) == 0
    after = {k: v["wall_s"] for k, v in json.loads((d / "steps.json").read_text()).items()}
    assert after["train_reference"] == before["train_reference"] and after["synth"] == before["synth"]
    assert after["capture"] != before["capture"] and after["train"] != before["train"]  # timed afresh
    assert (d / "reference.dsgworld").stat().st_mtime_ns == mtimes["reference.dsgworld"]
    assert (d / "photo.dsgworld").stat().st_mtime_ns != mtimes["photo.dsgworld"]
    assert (d / "est" / "scene.json").is_file()


def test_photo_worlds_refuses_unknown_scenes(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "x.json"), "--scenes", "kitchen"])
    assert e.value.code == 2 and "unknown scene" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_photo_worlds_refuses_unknown_depth_sources(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "x.json"), "--scenes", "two_blocks", "--depth", "lidar"])
    assert e.value.code == 2 and "invalid choice: 'lidar'" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def test_photo_scale_trains_the_photo_world_at_the_ground_truths_size(tmp_path, capsys):
    import argparse

    from benchmarks.photo_worlds import photo_path_args

    def ns(**kw):
        base = {"photo_scale": 1, "depth": None, "depth_weight": None, "refine_cameras": False}
        return argparse.Namespace(**{**base, **kw})

    assert photo_path_args(ns()) == ([], [], [])
    synth, cap, train = photo_path_args(ns(photo_scale=2))
    assert (
        synth == ["--photo-scale", "2"] and cap == ["--fit-downscale", "4"] and train == ["--downscale", "2"]
    )
    synth, cap, train = photo_path_args(ns(photo_scale=3, depth="none", refine_cameras=True))
    assert cap == ["--depth", "none"] and train == ["--downscale", "3", "--refine-cameras"]
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "x.json"), "--scenes", "two_blocks", "--photo-scale", "0"])
    assert e.value.code == 2 and "--photo-scale" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()


def _stored(path, scene, gap, minutes, cpu="AMD EPYC", **config):
    base = {
        "synth_args": ["--seed", "0", "--photo-scale", "2"],
        "train_args": ["--seed", "0"],
        "marker_m": 0.1,
    }
    figures = {
        "gap_db": gap,
        "gap_db_unaligned": gap + 0.5,
        "photos_to_world_min": minutes,
        "photo": {"psnr": 37.0, "regions": {"floor": 30.0, "walls": 40.0}},
        "reference": {"psnr": 37.0 + gap, "regions": {"floor": 30.0 + 2 * gap, "walls": None}},
        "motions": {"box": {"estimate_mm": 10 * gap, "refined_px": gap / 10}},
    }
    doc = {
        "config": {**base, **config, "scenes": [scene]},
        "scenes": {scene: figures},
        "machine": {"cpu": cpu},
    }
    path.write_text(json.dumps(doc))
    return path


def test_merge_joins_the_scenes_of_several_runs(tmp_path, capsys):
    a = _stored(tmp_path / "a.json", "two_blocks", 1.5, 40.0)
    b = _stored(tmp_path / "b.json", "five_small", 0.5, 30.0, cpu="other", cpus=4)
    out = tmp_path / "all.json"
    assert main(["--merge", str(a), str(b), "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["config"]["scenes"] == ["two_blocks", "five_small"]
    assert r["config"]["merged_from"] == ["a.json", "b.json"] and r["config"]["marker_m"] == 0.1
    s = r["summary"]
    assert s["mean_gap_db"] == pytest.approx(1.0) and s["worst_gap_db"] == 1.5
    assert s["mean_gap_db_unaligned"] == pytest.approx(1.5) and s["slowest_min"] == 40.0
    assert s["worst_estimate_mm"] == 15.0 and s["mean_reference_psnr"] == pytest.approx(38.0)
    assert s["mean_region_gap_db"] == {"floor": pytest.approx(2.0)}  # regions without a PSNR are left out
    # each scene keeps the machine that timed it; the whole names none when they differ
    assert r["scenes"]["five_small"]["machine"] == {"cpu": "other"} and r["machine"] is None
    assert r["config"]["cpus"] is None  # the machines' CPU counts differ: not a setting, so not refused
    assert json.loads(capsys.readouterr().out)["mean_gap_db"] == pytest.approx(1.0)


@pytest.mark.parametrize("problem", ["settings", "twice", "not_json"])
def test_merge_refuses_results_that_do_not_go_together(tmp_path, capsys, problem):
    a = _stored(tmp_path / "a.json", "two_blocks", 1.5, 40.0)
    if problem == "settings":
        b = _stored(tmp_path / "b.json", "five_small", 0.5, 30.0, marker_m=0.0)
        said = "differ from"
    elif problem == "twice":
        b = _stored(tmp_path / "b.json", "two_blocks", 0.5, 30.0)
        said = "scene two_blocks is in an earlier file"
    else:
        b = tmp_path / "b.json"
        b.write_text("not json")
        said = "not a benchmarks.photo_worlds result"
    out = tmp_path / "all.json"
    with pytest.raises(SystemExit) as e:
        main(["--merge", str(a), str(b), "--out", str(out)])
    err = capsys.readouterr().err
    assert e.value.code == 2 and said in err and "b.json" in err
    assert not out.exists()
