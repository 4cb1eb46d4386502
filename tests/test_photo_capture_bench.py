"""benchmarks.photo_capture: dsg-capture scored against the ground truth, scene by scene."""

from __future__ import annotations

import json

import pytest

from benchmarks.photo_capture import TARGETS, main, summarise


def test_photo_capture_scores_a_scene_against_its_truth(tmp_path):
    out = tmp_path / "pc.json"
    work = tmp_path / "work"
    args = ["--out", str(out), "--scenes", "two_blocks", "--views", "24", "--work", str(work)]
    assert main(args) == 0
    r = json.loads(out.read_text())
    s = r["scenes"]["two_blocks"]
    assert s["registered"] == {"state1": "24/24", "state2": "24/24"}
    assert set(s["objects"]) == {"red_box", "blue_cylinder"}
    for o in s["objects"].values():
        assert 0 <= o["position_mm"] < 50 and 0 <= o["rotation_deg"] <= 180
        assert o["rotation_deg"] <= o["rotation_mod_texture_deg"] + 1e-9  # fewer symmetries forgive less
        assert o["true_translation_mm"] > 10  # both objects move in two_blocks
    assert 0 < s["cameras"]["centre_median_percent_of_radius"] < 5
    assert s["cameras"]["rotation_median_deg"] <= s["cameras"]["rotation_max_deg"] < 5
    assert 0 < abs(s["cameras"]["focal_error_percent"]) < 3
    assert s["units"] == "metres" and 0 <= s["scale_error_percent"] < 5  # the marker gives metric scale
    assert s["capture_s"] > 0 and s["peak_rss_mib"] > 50
    assert r["summary"]["worst_motion_mm"] == max(o["position_mm"] for o in s["objects"].values())
    assert r["summary"]["objects"] == 2 and r["targets"] == TARGETS
    assert set(r["met"]) == set(TARGETS)
    assert (work / "two_blocks" / "est" / "report.json").is_file()
    assert (work / "two_blocks" / "photos" / "ground_truth" / "scene.json").is_file()


def _scene(
    centre_pct: float, motions: list[tuple[float, ...]], scale: float | None, focal: float = 0.1, exact=None
) -> dict:
    """``motions``: (mm, deg modulo shape symmetry[, deg modulo texture symmetry, default the same]);
    ``exact``: the same per object on the true cameras (``--true-cameras``), or None."""
    objects = {
        f"o{i}": {"position_mm": m[0], "rotation_deg": m[1], "rotation_mod_texture_deg": m[-1]}
        for i, m in enumerate(motions)
    }
    for i, m in enumerate(exact or []):
        objects[f"o{i}"]["true_cameras"] = {
            "position_mm": m[0],
            "rotation_deg": m[1],
            "rotation_mod_texture_deg": m[-1],
        }
    return {
        "capture_s": 30.0,
        "cameras": {
            "centre_median_percent_of_radius": centre_pct,
            "rotation_median_deg": 0.1,
            "focal_error_percent": focal,
        },
        "scale_error_percent": scale,
        "objects": objects,
    }


def test_summary_takes_the_worst_scene_and_counts_objects_within_both_motion_targets():
    summary, met = summarise(
        {
            "a": _scene(0.2, [(1.0, 0.5), (4.0, 0.2), (0.5, 0.0, 35.0)], 0.3),
            "b": _scene(0.6, [(2.0, 2.0)], None),
        }
    )
    assert summary["worst_camera_centre_percent_of_radius"] == 0.6
    assert (summary["worst_motion_mm"], summary["worst_motion_deg"]) == (4.0, 2.0)
    assert summary["objects"] == 4 and summary["objects_within_motion_targets"] == 2
    assert summary["objects_within_motion_targets_mod_texture"] == 1  # a dotted ball turned the wrong way
    assert summary["worst_scale_percent"] == 0.3  # a scene without a marker has no scale to score
    assert met == {
        "camera_centre_percent_of_radius": False,
        "camera_rotation_deg": True,
        "motion_mm": False,
        "motion_deg": False,
        "scale_percent": True,
        "capture_s": True,
    }
    assert summary["worst_focal_error_percent"] == 0.1
    assert "objects_within_motion_targets_true_cameras" not in summary  # not asked for
    _, met = summarise({"a": _scene(0.2, [(1.0, 0.5)], None)})
    assert met["scale_percent"] is False  # not measured is not met


def test_summary_counts_the_motions_on_the_true_cameras_apart():
    summary, met = summarise(
        {
            "a": _scene(0.2, [(1.0, 2.0), (4.0, 0.2)], 0.3, focal=-0.5, exact=[(1.0, 0.3), (0.5, 0.2)]),
            "b": _scene(0.2, [(1.0, 0.5)], 0.3, focal=0.2, exact=[(1.0, 1.5)]),
        }
    )
    assert summary["objects_within_motion_targets"] == 1
    assert summary["objects_within_motion_targets_true_cameras"] == 2
    assert summary["worst_focal_error_percent"] == 0.5  # the largest error either way
    assert (met["motion_mm"], met["motion_deg"]) == (False, False)  # the targets are the estimate's


def test_photo_capture_refuses_unknown_scenes(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "x.json"), "--scenes", "kitchen"])
    assert e.value.code == 2 and "unknown scene" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
