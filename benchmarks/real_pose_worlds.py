"""Worlds of a real capture trained on camera poses from its images against the poses it ships with.

Held-out PSNR, SSIM and mask IoU of each world.

    python -m benchmarks.real_pose_worlds --llff ../shared/external/ethiopian_head_llff
    python -m benchmarks.real_pose_worlds --llff DIR [--factor 8] [--downscale 4] [--preset quick]
        [--iterations 3000] [--seed 0] [--align-views STEPS] [--work DIR] [--out FILE]

In ``--work`` (kept) or a temporary folder:

1. ``import_llff``: the LLFF capture (``images_F/``, ``masks_F/``, ``poses_bounds.npy``) as a one-state
   capture in the shipped poses (``all/``);
2. ``estimate_state_poses(..., features="object")``: the cameras from the images alone, features on the object
   only (a turntable capture: the object turns, the room stays; :mod:`train_world.capture.pose_check`);
3. ``estimated/``: the registered views in the estimated poses, photos and masks undistorted with the
   estimated camera to a pinhole one (:func:`train_world.capture.pose_sets.write_estimated_capture`);
4. ``shipped/``: the same views, same order, in the shipped poses (:func:`~train_world.capture.pose_sets.
   subset_capture`), so both worlds train on the same photos and hold out the same ones (every 8th);
5. ``dsg-train`` of each (same preset, iterations, downscale and seed), each a fresh process (wall time, peak
   RSS);
6. ``dsg-eval`` of each at its own capture's held-out views (their stems are checked to be the same).

Defaults: ``--factor 8`` (500x500 photos for ``ethiopian_head_llff``), ``--downscale 4`` (125x125 training and
evaluation images), ``--preset quick --iterations 3000`` (at most 8000 Gaussians, densified in the first 220
steps), seed 0, no view alignment: a few minutes on a 2-core CPU in all. The ``default`` preset densifies
until step 3000 towards 250 000 Gaussians and takes far longer on these photos.

Writes ``{config, views, registered, held_out_stems, shipped: {psnr, ssim, mask_iou, train_s, peak_rss_gib},
estimated: {...}, gap_db, pose_comparison, sfm_s}``; ``gap_db`` is the shipped world's held-out PSNR minus the
estimated one's, ``pose_comparison`` is :func:`~train_world.capture.pose_check.compare_poses` of the two pose
sets. Each world is scored against its own pose set's held-out cameras, so an error in a held-out camera's
pose counts against its world (``--align-views`` also scores each held-out camera aligned to the world first).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from ._results import default_out, write_result
from .photo_worlds import EVAL, TRAIN, _run

HOLDOUT_EVERY = 8
DEFAULTS = {"factor": 8, "downscale": 4, "preset": "quick", "iterations": 3000, "seed": 0}


def _world(name: str, capture: Path, work: Path, train_args: list[str], eval_args: list[str]) -> dict:
    """Train (a fresh process) and score one world on ``capture``; its figures and held-out view stems."""
    world = work / f"{name}.dsgworld"
    train_s, rss = _run(
        [*TRAIN, str(capture), "--out", str(world), "--quiet", *train_args], work / f"train_{name}.log"
    )
    _run([*EVAL, str(world), str(capture), "--same-frame", "--out", str(work / f"eval_{name}"), *eval_args],
         work / f"eval_{name}.log")  # fmt: skip
    report = json.loads((work / f"eval_{name}" / "report.json").read_text())
    figures = {k: report["mean"].get(k) for k in ("psnr", "ssim", "mask_iou")}
    if "mean_unaligned" in report:
        figures["psnr_unaligned"] = report["mean_unaligned"]["psnr"]
    held = [v["view"].split("/", 1)[1] for v in report["per_view"]]
    return {**figures, "train_s": round(train_s, 1), "peak_rss_gib": round(rss / 2**30, 3), "held_out": held}


def run(llff: Path, out: Path, work: Path | None, factor: int, train_args: list[str],
        eval_args: list[str] | None = None) -> dict[str, Any]:  # fmt: skip
    """Every step (module docstring) in ``work`` or a temporary folder; writes and returns the result."""
    from train_world.capture.importers import import_llff
    from train_world.capture.pose_check import compare_poses, estimate_state_poses
    from train_world.capture.pose_sets import subset_capture, write_estimated_capture
    from train_world.capture.sfm import CAMERA_MODEL
    from train_world.single_state.data import heldout_indices

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(work) if work is not None else Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        every = import_llff(llff, root / "all", factor=factor, overwrite=True)
        sfm = root / "sfm"
        shutil.rmtree(sfm, ignore_errors=True)  # structure from motion wants an empty folder
        sfm.mkdir()
        est = estimate_state_poses(every, "state1", sfm, features="object")
        estimated = write_estimated_capture(
            every, "state1", root / "estimated", est.world_to_camera, CAMERA_MODEL, est.camera_params,
            overwrite=True,
        )  # fmt: skip
        frames = json.loads((every / "state1" / "transforms.json").read_text())["frames"]
        registered = [
            Path(f["file_path"]).stem for f in frames if Path(f["file_path"]).stem in est.world_to_camera
        ]
        shipped = subset_capture(every, root / "shipped", registered, overwrite=True)
        held = [registered[i] for i in heldout_indices(len(registered), HOLDOUT_EVERY)]
        args = [*train_args, "--holdout-every", str(HOLDOUT_EVERY)]
        worlds = {name: _world(name, cap, root, args, list(eval_args or []))
                  for name, cap in (("shipped", shipped), ("estimated", estimated))}  # fmt: skip
        for name, w in worlds.items():
            if w.pop("held_out") != held:
                raise RuntimeError(
                    f"the {name} world held out other views than {held}; both must hold out the same"
                )
        cam = json.loads((estimated / "scene.json").read_text())["camera_poses"]
    result = {
        "benchmark": "real_pose_worlds",
        "config": {"capture": llff.name, "factor": factor, "features": "object",
                   "holdout_every": HOLDOUT_EVERY, "train_args": train_args,
                   "eval_args": list(eval_args or []), "cpus": os.cpu_count()},
        "views": est.views,
        "registered": len(registered),
        "held_out_stems": held,
        "shipped": worlds["shipped"],
        "estimated": {**worlds["estimated"], "camera_model": cam["camera_model"],
                      "camera_params": cam["camera_params"], "undistorted_K": cam["undistorted_K"]},
        "gap_db": round(worlds["shipped"]["psnr"] - worlds["estimated"]["psnr"], 3),
        "pose_comparison": compare_poses(est),
        "sfm_s": round(est.seconds, 1),
    }  # fmt: skip
    write_result(out, result)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.real_pose_worlds",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--llff", type=Path, required=True, help="LLFF capture folder (poses_bounds.npy, images_F/)"
    )
    p.add_argument(
        "--factor", type=int, default=DEFAULTS["factor"], help="images_F/ and masks_F/ to use (default 8)"
    )
    p.add_argument(
        "--downscale", type=int, default=DEFAULTS["downscale"], help="dsg-train downscale (default 4)"
    )
    p.add_argument("--preset", default=DEFAULTS["preset"], help="dsg-train preset (default: quick)")
    p.add_argument(
        "--iterations", type=int, default=DEFAULTS["iterations"], help="dsg-train steps (default 3000)"
    )
    p.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="dsg-train seed (default 0)")
    p.add_argument(
        "--align-views",
        type=int,
        default=0,
        metavar="STEPS",
        help="dsg-eval --align-views STEPS for both worlds (default 0: score the cameras as given)",
    )
    p.add_argument("--work", type=Path, help="keep the captures, worlds, evaluations and logs here")
    p.add_argument("--out", type=Path, help="JSON to write (default: benchmarks/results/real_pose_worlds/"
                                            "<date>-<commit>.json)")  # fmt: skip
    args = p.parse_args(argv)
    if not (args.llff / "poses_bounds.npy").is_file():
        p.error(f"--llff {args.llff}: no poses_bounds.npy there; name an LLFF capture folder")
    if min(args.factor, args.downscale, args.iterations) < 1 or args.align_views < 0:
        p.error("--factor, --downscale and --iterations must be >= 1 and --align-views >= 0")
    train = ["--preset", args.preset, "--iterations", str(args.iterations),
             "--downscale", str(args.downscale), "--seed", str(args.seed)]  # fmt: skip
    ev = ["--align-views", str(args.align_views)] if args.align_views else []
    out = args.out or default_out("real_pose_worlds")
    r = run(args.llff, out, args.work, args.factor, train, ev)
    print(json.dumps({k: r[k] for k in ("registered", "shipped", "estimated", "gap_db")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
