"""``dsg-capture`` against the ground truth, scene by scene: camera poses, table frame, metric scale and object
motions from photos alone, without training a world.

``python -m benchmarks.photo_capture [--scenes all] [--seed 0] [--marker 0.1] [--photo-noise S]
[--photo-scale S] [--work DIR] [--true-cameras] [--out FILE]``

Per scene: ``dsg-synth --scene S --as-photos [--marker M]`` writes JPEG photos, masks and the true capture
(``ground_truth/``); ``dsg-capture --depth none`` estimates the capture from the photos (timed, with its peak
RSS; no depth maps, which only training's start needs); and
:func:`train_world.capture.compare.compare_captures` scores it against the truth after a similarity fit of the
camera centres. Metric scale is scored by that similarity's scale (1 when the marker's scale is exact).
``--photo-scale S`` makes the photos S times the ground truth's size (``dsg-synth --photo-scale``); the capture
is scored at the ground truth's size (its intrinsics divided by S), so the focal error stays comparable.
``--true-cameras`` builds each capture a second time with the truth's cameras in place of the estimated ones
(:func:`train_world.capture.compare.with_true_cameras`; structure from motion still runs, for its points) and
scores its motions too: what the motion step misses by itself, apart from what the cameras' errors cost it.

Writes ``{config, scenes: {scene: {capture_s, peak_rss_mib, registered, reprojection_px, cameras, frame,
scale_error_percent, objects: {name: {method, position_mm, rotation_deg, rotation_mod_texture_deg,
true_cameras?}}}}, summary, targets, met}``; ``cameras`` includes the focal length's error in percent;
``rotation_deg`` is modulo the object's shape symmetry (a ball has none to score),
``rotation_mod_texture_deg`` modulo only the symmetries that also keep a patterned object's look (a dotted
ball's turn counts; :func:`train_world.capture.compare.texture_symmetries`). The targets are the capture step's:
camera centres within 0.5 % of the scene radius (median), rotations within 0.3 degrees (median), every object's
motion within 3 mm and 1 degree, the scale within 1 %, and the capture within 2 minutes for 2 x 48 photos.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from ._results import default_out, write_result
from .photo_worlds import CAPTURE, SYNTH, _run, checked_scene_args

TARGETS = {
    "camera_centre_percent_of_radius": 0.5,
    "camera_rotation_deg": 0.3,
    "motion_mm": 3.0,
    "motion_deg": 1.0,
    "scale_percent": 1.0,
    "capture_s": 120.0,
}


def _motions(c: dict[str, Any]) -> dict[str, dict[str, float]]:
    return {
        o["name"]: {
            "position_mm": round(1000 * o["position_error"], 3),
            "rotation_deg": round(o["rotation_error_mod_symmetry_deg"], 4),
            "rotation_mod_texture_deg": round(o["rotation_error_mod_texture_deg"], 4),
        }
        for o in c["objects"]
    }


def _with_true_cameras(photos: Path, out: Path, marker: float | None) -> dict[str, dict[str, Any]]:
    """Build the capture of ``photos`` again into ``out`` on the truth's cameras; each object's method and
    motion errors."""
    from train_world.capture import load_capture
    from train_world.capture.compare import compare_captures, with_true_cameras
    from train_world.capture.photo_capture import build_capture
    from train_world.capture.sfm import run_sfm

    truth = load_capture(photos / "ground_truth", load_masks=False)

    def reconstruct(capture, work, **kw):
        return with_true_cameras(run_sfm(capture, work, **kw), truth)

    report = build_capture(
        photos, out, marker_size=marker, overwrite=True, progress=False, reconstruct=reconstruct
    )
    methods = {o["name"]: o.get("method") for o in report.get("objects", [])}
    scores = _motions(compare_captures(load_capture(out, load_masks=False), truth))
    return {k: {"method": methods.get(k), **v} for k, v in scores.items()}


def scene(
    name: str,
    work: Path,
    seed: int,
    marker: float | None,
    synth_args: list[str],
    true_cameras: bool = False,
    photo_scale: int = 1,
) -> dict[str, Any]:
    """Photos, capture and scores of one scene under ``work/name``."""
    from train_world.capture import load_capture
    from train_world.capture.compare import compare_captures

    d = work / name
    d.mkdir(parents=True, exist_ok=True)
    photos, est = d / "photos", d / "est"
    mk = ["--marker", str(marker)] if marker else []
    _run([*SYNTH, "--scene", name, "--as-photos", "--seed", str(seed), "--out", str(photos), "--overwrite",
          "--quiet", *mk, *synth_args, *(["--photo-scale", str(photo_scale)] if photo_scale > 1 else [])],
         d / "synth.log")  # fmt: skip
    wall, rss = _run(
        [*CAPTURE, str(photos), "--out", str(est), "--overwrite", "--quiet", "--depth", "none",
         *(["--marker-size", str(marker)] if marker else [])],
        d / "capture.log",
    )  # fmt: skip
    report = json.loads((est / "report.json").read_text())
    c = compare_captures(
        load_capture(est, load_masks=False, downscale=photo_scale),
        load_capture(photos / "ground_truth", load_masks=False),
    )
    methods = {o["name"]: o.get("method") for o in report.get("objects", [])}
    motions = _motions(c)
    exact = _with_true_cameras(photos, d / "est_true_cameras", marker) if true_cameras else {}
    return {
        "capture_s": round(wall, 1),
        "peak_rss_mib": round(rss / 2**20, 1),
        "registered": {k: f"{v['views']}/{v['of']}" for k, v in report["registered"].items()},
        "reprojection_px": report.get("mean_reprojection_error_px"),
        "cameras": {
            "centre_median_mm": round(1000 * c["camera_centre_error_median"], 3),
            "centre_median_percent_of_radius": round(c["camera_centre_error_median_percent_of_radius"], 4),
            "centre_max_mm": round(1000 * c["camera_centre_error_max"], 3),
            "rotation_median_deg": round(c["camera_rotation_error_median_deg"], 4),
            "rotation_max_deg": round(c["camera_rotation_error_max_deg"], 4),
            "scene_radius_m": round(c["scene_radius"], 4),
            "focal_error_percent": round(c["focal_error_percent"], 4),
        },
        "frame": {
            "up_axis_error_deg": round(c["up_axis_error_deg"], 4),
            "table_top_error_mm": round(1000 * c["table_top_error"], 3),
        },
        "units": report.get("units"),
        "scale_error_percent": round(100 * abs(c["similarity_scale"] - 1.0), 4) if marker else None,
        "objects": {
            o["name"]: {
                "method": methods.get(o["name"]),
                **motions[o["name"]],
                "true_rotation_deg": round(o["true_rotation_deg"], 2),
                "true_translation_mm": round(1000 * o["true_translation"], 1),
                **({"true_cameras": exact[o["name"]]} if o["name"] in exact else {}),
            }
            for o in c["objects"]
        },
    }


def summarise(scenes: dict[str, dict[str, Any]]) -> tuple[dict[str, Any], dict[str, bool]]:
    """Worst figures over ``scenes`` and, per target, whether every scene meets it."""
    objs = [o for r in scenes.values() for o in r["objects"].values()]
    scales = [r["scale_error_percent"] for r in scenes.values() if r["scale_error_percent"] is not None]
    worst = {
        "camera_centre_percent_of_radius": max(
            r["cameras"]["centre_median_percent_of_radius"] for r in scenes.values()
        ),
        "camera_rotation_deg": max(r["cameras"]["rotation_median_deg"] for r in scenes.values()),
        "motion_mm": max(o["position_mm"] for o in objs) if objs else None,
        "motion_deg": max(o["rotation_deg"] for o in objs) if objs else None,
        "scale_percent": max(scales) if scales else None,
        "capture_s": max(r["capture_s"] for r in scenes.values()),
    }
    summary = {f"worst_{k}": v for k, v in worst.items()} | {
        "objects": len(objs),
        "objects_within_motion_targets": sum(
            o["position_mm"] <= TARGETS["motion_mm"] and o["rotation_deg"] <= TARGETS["motion_deg"]
            for o in objs
        ),
        "objects_within_motion_targets_mod_texture": sum(
            o["position_mm"] <= TARGETS["motion_mm"]
            and o["rotation_mod_texture_deg"] <= TARGETS["motion_deg"]
            for o in objs
        ),
        "median_motion_mm": sorted(o["position_mm"] for o in objs)[len(objs) // 2] if objs else None,
        "worst_focal_error_percent": max(abs(r["cameras"]["focal_error_percent"]) for r in scenes.values()),
    }
    exact = [o["true_cameras"] for o in objs if "true_cameras" in o]
    if exact:
        summary["objects_within_motion_targets_true_cameras"] = sum(
            o["position_mm"] <= TARGETS["motion_mm"] and o["rotation_deg"] <= TARGETS["motion_deg"]
            for o in exact
        )
    met = {k: v is not None and v <= TARGETS[k] for k, v in worst.items()}
    return summary, met


def run(out: Path, scenes: list[str], work: Path | None, seed: int, marker: float | None,
        synth_args: list[str], true_cameras: bool = False, photo_scale: int = 1) -> dict[str, Any]:  # fmt: skip
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(work) if work is not None else Path(tmp)
        for s in scenes:
            results[s] = scene(s, root, seed, marker, synth_args, true_cameras, photo_scale)
            print(s, json.dumps(results[s]), flush=True)
    summary, met = summarise(results)
    result = {
        "benchmark": "photo_capture",
        "config": {"scenes": scenes, "seed": seed, "marker_m": marker, "synth_args": synth_args,
                   "true_cameras": true_cameras, "photo_scale": photo_scale, "cpus": os.cpu_count()},
        "scenes": results,
        "summary": summary,
        "targets": TARGETS,
        "met": met,
    }  # fmt: skip
    write_result(out, result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--out", type=Path, help="JSON file (default: benchmarks/results/photo_capture/<date>-<commit>.json)"
    )
    p.add_argument("--scenes", default="all", help="comma-separated dsg-synth scenes or 'all' (default)")
    p.add_argument("--work", type=Path, help="keep every scene's photos, captures and logs here")
    p.add_argument("--seed", type=int, default=0, help="dsg-synth seed (default 0)")
    p.add_argument(
        "--marker", type=float, default=0.1, help="ArUco marker side in metres for scale (0: none)"
    )
    p.add_argument("--views", type=int, help="photos per state (default: dsg-synth's)")
    p.add_argument("--photo-noise", type=float, help="dsg-synth --photo-noise SIGMA (grey levels)")
    p.add_argument(
        "--true-cameras",
        action="store_true",
        help="also build each capture on the truth's cameras and score its motions (what the motion step "
        "misses by itself)",
    )
    p.add_argument(
        "--photo-scale",
        type=int,
        default=1,
        metavar="S",
        help="dsg-synth --photo-scale S: photos S times the ground truth's size (default 1)",
    )
    args = p.parse_args(argv)
    scenes = checked_scene_args(p, args)
    if not 1 <= args.photo_scale <= 16:
        p.error(f"--photo-scale must be an integer in 1..16, got {args.photo_scale}")
    if args.photo_scale > 1 and args.true_cameras:
        p.error("--true-cameras needs photos at the ground truth's size (--photo-scale 1)")
    synth = (["--views", str(args.views)] if args.views else []) + (
        ["--photo-noise", str(args.photo_noise)] if args.photo_noise else []
    )
    result = run(
        args.out or default_out("photo_capture"),
        scenes,
        args.work,
        args.seed,
        args.marker or None,
        synth,
        args.true_cameras,
        args.photo_scale,
    )
    print(json.dumps({"summary": result["summary"], "met": result["met"]}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
