"""Worlds made from photos against worlds made from the true cameras: test-state PSNR and photos -> world time.

    python -m benchmarks.photo_worlds [--scenes all] [--seed 0] [--work DIR] [--out FILE]
    python -m benchmarks.photo_worlds --scenes four_mixed --views 24 --preset quick --iterations 200  # a quick look
    python -m benchmarks.photo_worlds --merge A.json B.json --out all.json  # one result of several runs' scenes

Per scene, each step a fresh process, in ``--work`` (kept) or a temporary folder:

1. ``dsg-synth --scene S --as-photos [--marker M] [--photo-scale S]``: photos, and the true capture under
   ``ground_truth/``; with ``--photo-scale S`` the photos are S times its size, as a phone's are larger than
   the size a world trains at;
2. ``dsg-capture photos --out est [--marker-size M] [--depth D]``: camera poses, table frame, object motions
   and depth maps (``--depth``: dsg-capture's default, a first reconstruction of each state) from the images
   alone (timed);
3. ``dsg-train est --holdout-every 0``: the world from the photos, every photo training as every true view
   trains the reference (timed, with its peak RSS); with ``--refine-cameras`` its cameras are refined in
   training; with ``--photo-scale S`` it trains at the ground truth's size (``--downscale S``) and the
   capture's depth fit at half that (``--fit-downscale 2S``);
4. ``dsg-train photos/ground_truth``: the reference, the same training on the true cameras and poses;
5. ``dsg-eval --align-views 60`` of both worlds at the ground truth's test states (the photo world with
   ``--align-frames``): each test camera aligned to the world it scores before scoring, as pose-free
   evaluations do (:mod:`train_world.eval.view_align`); the unaligned figures are kept
   (``psnr_unaligned``, ``gap_db_unaligned``).

With ``--work``, a second run reuses every step an earlier run in that folder finished with the same command
(its time is kept in ``<scene>/steps.json``) unless a step it builds on ran again (the photo world builds on
the photos and the capture, the reference on the photos); remove a step's output to make it run again. The
evaluations always run again.

Writes ``{config, scenes: {S: {capture_s, train_s, photos_to_world_min, peak_rss_gib, photo: {psnr, ssim,
mask_iou, psnr_unaligned, regions: {region: PSNR}}, reference: {...}, gap_db, gap_db_unaligned,
motions: {object: {estimate_mm, estimate_rotation_deg, estimate_rotation_mod_symmetry_deg, estimate_px, refined_...}},
camera_refinement: {state: {rotation_deg_median, ...}}}}, summary: {mean_gap_db,
mean_gap_db_unaligned, worst_gap_db, worst_estimate_mm, ..., slowest_min, mean_photo_psnr,
mean_reference_psnr}, targets}``. The motions are the photo world's against the ground truth's (``dsg-eval``'s
``motion_errors``): as ``dsg-capture`` estimated them and as the joint phase refined them; ``*_px`` is how
far the error moves the object's surface in the truth's views, at most.
``gap_db`` is the reference's PSNR minus the photo world's. Times depend on the machine and its load: run it
on an idle machine. ``--merge`` joins the scenes of stored results of the same settings (one scene per run, as
a scene takes about an hour) into one result with the summary over all of them.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from train_world.cli.capture import DEPTH_SOURCES

from ._results import default_out, write_result

TARGET_GAP_DB = 0.5
TARGET_MINUTES = 20.0
#: object motions from dsg-capture, and after the joint phase refined them (mm, degrees)
TARGET_MOTIONS = {"estimate_mm": 3.0, "estimate_deg": 1.0, "refined_mm": 1.0, "refined_deg": 0.3}


def _worst_motions(results: dict[str, Any]) -> dict[str, float]:
    """The largest object motion errors over all scenes (``worst_estimate_mm`` ...), where measured."""
    objs = [o for r in results.values() for o in (r.get("motions") or {}).values()]
    out = {}
    for k in (
        "estimate_mm",
        "estimate_rotation_mod_symmetry_deg",
        "refined_mm",
        "refined_rotation_mod_symmetry_deg",
        "estimate_px",
        "refined_px",
    ):
        vals = [o[k] for o in objs if o.get(k) is not None]
        if vals:
            out[f"worst_{k}"] = max(vals)
    return out


def _run(cmd: list[str], log: Path) -> tuple[float, int]:
    """Run ``cmd`` (its output to ``log``); returns (wall seconds, peak RSS in bytes) or raises naming the step."""
    t0 = time.perf_counter()
    with open(log, "wb") as f:
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = log.read_text(errors="replace")[-1500:]
        raise RuntimeError(f"{' '.join(cmd[:2])} failed (exit {proc.returncode}), see {log}:\n{tail}")
    return wall, int(usage.ru_maxrss) * 1024


def _cli(name: str) -> list[str]:
    return [sys.executable, "-c", f"import sys; from {name} import main; sys.exit(main())"]


SYNTH, CAPTURE, TRAIN, EVAL = (
    _cli(m)
    for m in (
        "train_world.cli.synth",
        "train_world.cli.capture",
        "train_world.cli.train",
        "train_world.cli.eval",
    )
)


def _metrics(report: Path) -> dict[str, Any]:
    """``dsg-eval``'s means, and the PSNR of each region (``regions``: ``outline``, ``objects``,
    ``background``, ``unseen`` and the background's parts ``table_top``, ``floor``, ``other``) where found."""
    r = json.loads(report.read_text())
    out: dict[str, Any] = {k: r["mean"].get(k) for k in ("psnr", "ssim", "mask_iou")}
    if "mean_unaligned" in r:
        out["psnr_unaligned"] = r["mean_unaligned"]["psnr"]
    by_region = r.get("error_by_region") or {}
    entries = {**(by_region.get("regions") or {}), **(by_region.get("background_parts") or {})}
    if entries:
        out["regions"] = {k: e["psnr"] for k, e in entries.items()}
    return out


def _step(
    d: Path, name: str, cmd: list[str], done: Path, ran: list[str], needs: tuple[str, ...] = ()
) -> tuple[float, int]:
    """Run one step of a scene unless an earlier run in the same ``--work`` folder ran the same command, left
    ``done`` and recorded its figures in ``d/steps.json``, and none of the steps it ``needs`` ran again in
    this run (``ran``: the steps run so far); records (wall seconds, peak RSS bytes) there."""
    record = d / "steps.json"
    steps = json.loads(record.read_text()) if record.is_file() else {}
    old = steps.get(name)
    fresh = any(n in ran for n in needs)
    if not fresh and done.exists() and isinstance(old, dict) and old.get("cmd") == cmd[1:]:
        return float(old["wall_s"]), int(old["peak_rss"])
    wall, rss = _run(cmd, d / f"{name}.log")
    ran.append(name)
    steps = json.loads(record.read_text()) if record.is_file() else {}  # as it is now, not before the run
    steps[name] = {"cmd": cmd[1:], "wall_s": wall, "peak_rss": rss}
    tmp = record.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(steps, indent=1))
    os.replace(tmp, record)
    return wall, rss


def scene(name: str, work: Path, synth_args: list[str], train_args: list[str], marker: float | None,
          eval_args: list[str] | None = None, capture_args: list[str] | None = None,
          photo_train_args: list[str] | None = None) -> dict:  # fmt: skip
    """Every step for one scene under ``work/name``; returns the scene's figures. Steps whose outputs an
    earlier run left in ``work/name`` (with their times in ``steps.json``) are not run again.
    ``capture_args`` go to ``dsg-capture``, ``photo_train_args`` to the photo world's ``dsg-train`` only."""
    d = work / name
    d.mkdir(parents=True, exist_ok=True)
    photos, est, truth = d / "photos", d / "est", d / "photos" / "ground_truth"
    mk = ["--marker", str(marker)] if marker else []
    ev, ran = list(eval_args or []), []
    _step(d, "synth", [*SYNTH, "--scene", name, "--as-photos", "--out", str(photos), "--overwrite", "--quiet",
                       *mk, *synth_args], truth / "scene.json", ran)  # fmt: skip
    cap_s, _ = _step(d, "capture", [*CAPTURE, str(photos), "--out", str(est), "--overwrite",
                                    *(["--marker-size", str(marker)] if marker else []), *(capture_args or [])],
                     est / "scene.json", ran, ("synth",))  # fmt: skip
    # every photo trains, as every true view trains the reference: the test states are the evaluation
    train_s, rss = _step(d, "train", [*TRAIN, str(est), "--out", str(d / "photo.dsgworld"), "--quiet",
                                      "--holdout-every", "0", *train_args,
                                      *(photo_train_args or [])],
                         d / "photo.dsgworld", ran, ("synth", "capture"))  # fmt: skip
    ref_s, ref_rss = _step(d, "train_reference", [*TRAIN, str(truth), "--out", str(d / "reference.dsgworld"),
                                                  "--quiet", *train_args],
                           d / "reference.dsgworld", ran, ("synth",))  # fmt: skip
    _run([*EVAL, str(d / "photo.dsgworld"), str(truth), "--align-frames", "--out", str(d / "eval_photo"), *ev],
         d / "eval_photo.log")  # fmt: skip
    _run([*EVAL, str(d / "reference.dsgworld"), str(truth), "--out", str(d / "eval_reference"), *ev],
         d / "eval_reference.log")  # fmt: skip
    photo, ref = _metrics(d / "eval_photo" / "report.json"), _metrics(d / "eval_reference" / "report.json")
    report = json.loads((est / "report.json").read_text()) if (est / "report.json").is_file() else {}
    errors = json.loads((d / "eval_photo" / "report.json").read_text()).get("motion_errors")
    motions = None
    if errors is not None:
        motions = {
            o["name"]: {
                k: None if v is None else round(v, 4)
                for k, v in o.items()
                if k != "name" and not k.endswith("_translation")
            }
            for o in errors["objects"]
        }
    return {
        "capture_s": round(cap_s, 1),
        "train_s": round(train_s, 1),
        "photos_to_world_min": round((cap_s + train_s) / 60.0, 2),
        "peak_rss_gib": round(rss / 2**30, 3),
        "reference_train_s": round(ref_s, 1),
        "reference_peak_rss_gib": round(ref_rss / 2**30, 3),
        "registered": {k: f"{v['views']}/{v['of']}" for k, v in report.get("registered", {}).items()},
        "photo": photo,
        "reference": ref,
        "gap_db": round(ref["psnr"] - photo["psnr"], 3),
        "motions": motions,
        "camera_refinement": _camera_refinement(d / "photo.dsgworld"),
        **(
            {"gap_db_unaligned": round(ref["psnr_unaligned"] - photo["psnr_unaligned"], 3)}
            if "psnr_unaligned" in photo and "psnr_unaligned" in ref
            else {}
        ),
    }


def _camera_refinement(world: Path) -> dict[str, Any] | None:
    """How far training moved the photo world's cameras (``metadata.camera_refinement``), or None when they
    were not refined."""
    from dsg_gym.world import load_world

    return load_world(world).metadata.get("camera_refinement")


def run(out: Path, scenes: list[str], work: Path | None, synth_args: list[str], train_args: list[str],
        marker: float | None, eval_args: list[str] | None = None, capture_args: list[str] | None = None,
        photo_train_args: list[str] | None = None) -> dict[str, Any]:  # fmt: skip
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(work) if work is not None else Path(tmp)
        for s in scenes:
            results[s] = scene(
                s, root, synth_args, train_args, marker, eval_args, capture_args, photo_train_args
            )
    result = {
        "config": {"scenes": scenes, "synth_args": synth_args, "train_args": train_args, "marker_m": marker,
                   "eval_args": list(eval_args or []), "capture_args": list(capture_args or []),
                   "photo_train_args": list(photo_train_args or []), "cpus": os.cpu_count()},
        "scenes": results,
        "summary": summarise(results),
        "targets": {"gap_db": TARGET_GAP_DB, "photos_to_world_min": TARGET_MINUTES, **TARGET_MOTIONS},
    }  # fmt: skip
    write_result(out, result)
    return result


def summarise(results: dict[str, Any]) -> dict[str, Any]:
    """The ``summary`` over the scenes' figures ``results`` (``{scene: scene()'s dict}``): the mean and worst
    gap, the slowest photos -> world, the worst motions and the mean PSNRs."""
    gaps = [r["gap_db"] for r in results.values()]
    n = len(gaps)
    out: dict[str, Any] = {"mean_gap_db": round(sum(gaps) / n, 3)}
    if all("gap_db_unaligned" in r for r in results.values()):
        out["mean_gap_db_unaligned"] = round(sum(r["gap_db_unaligned"] for r in results.values()) / n, 3)
    shared = None
    for r in results.values():
        for k in ("photo", "reference"):
            names = {name for name, v in (r[k].get("regions") or {}).items() if v is not None}
            shared = names if shared is None else shared & names
    if shared:  # per region, the reference's PSNR minus the photo world's, averaged over the scenes
        out["mean_region_gap_db"] = {
            region: round(sum(r["reference"]["regions"][region] - r["photo"]["regions"][region]
                              for r in results.values()) / n, 3)
            for region in sorted(shared)
        }  # fmt: skip
    return {
        **out,
        "worst_gap_db": max(gaps),
        "slowest_min": max(r["photos_to_world_min"] for r in results.values()),
        **_worst_motions(results),
        "mean_photo_psnr": round(sum(r["photo"]["psnr"] for r in results.values()) / n, 3),
        "mean_reference_psnr": round(sum(r["reference"]["psnr"] for r in results.values()) / n, 3),
    }


def merge(files: list[Path], out: Path) -> dict[str, Any]:
    """One result of the scenes of several stored results ``files`` (runs of one scene each, say), with their
    summary over all of them, written to ``out``. The results must agree on every setting but the scenes, and
    name each scene once; ``config.merged_from`` lists the files, each scene keeps the machine that measured
    it (``machine``), as its times are that machine's. Raises ``ValueError`` naming the file otherwise."""
    if not files:
        raise ValueError("--merge needs at least one result file")
    scenes: dict[str, Any] = {}
    first: dict[str, Any] | None = None
    cpus: set[int | None] = set()
    for f in files:
        try:
            doc = json.loads(Path(f).read_text())
            config, found = dict(doc["config"]), doc["scenes"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            raise ValueError(
                f"{f}: not a benchmarks.photo_worlds result ({e}); pass the JSON files it wrote"
            ) from None
        config.pop("scenes", None)
        cpus.add(config.pop("cpus", None))  # the machine's, not a setting: each scene keeps its machine
        if first is None:
            first = config
        elif config != first:
            keys = sorted(k for k in {*config, *first} if config.get(k) != first.get(k))
            raise ValueError(f"{f}: its settings differ from {files[0]}'s in {', '.join(keys)}; "
                             "merge results of the same settings")  # fmt: skip
        for name, figures in found.items():
            if name in scenes:
                raise ValueError(f"{f}: scene {name} is in an earlier file too; pass one result per scene")
            scenes[name] = {**figures, "machine": figures.get("machine", doc.get("machine"))}
    assert first is not None
    result = {
        "config": {
            **first,
            "scenes": list(scenes),
            "merged_from": [Path(f).name for f in files],
            "cpus": cpus.pop() if len(cpus) == 1 else None,
        },
        "scenes": scenes,
        "summary": summarise(scenes),
        "targets": {"gap_db": TARGET_GAP_DB, "photos_to_world_min": TARGET_MINUTES, **TARGET_MOTIONS},
    }
    machines = {json.dumps(s["machine"], sort_keys=True) for s in scenes.values()}
    result["machine"] = scenes[next(iter(scenes))]["machine"] if len(machines) == 1 else None
    write_result(out, result)
    return result


def checked_scene_args(p: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """The scenes ``args.scenes`` names (``all``: every default scene), after checking them, ``--marker`` and
    ``--views``; ``p.error`` (exit 2) otherwise."""
    from train_world.synth.spec import default_scene_names

    known = list(default_scene_names())
    scenes = known if args.scenes == "all" else [s for s in args.scenes.split(",") if s]
    unknown = [s for s in scenes if s not in known]
    if not scenes or unknown:
        p.error(f"--scenes: unknown scene(s) {unknown or args.scenes!r}; choose from {', '.join(known)}")
    if args.marker < 0 or (args.views is not None and args.views < 1):
        p.error("--marker must be >= 0 and --views >= 1")
    return scenes


def photo_path_args(args: argparse.Namespace) -> tuple[list[str], list[str], list[str]]:
    """What the photo path adds to ``dsg-synth``, ``dsg-capture`` and the photo world's ``dsg-train`` for
    ``--photo-scale``, ``--depth``, ``--depth-weight`` and ``--refine-cameras``."""
    scale = int(args.photo_scale)
    synth = ["--photo-scale", str(scale)] if scale > 1 else []
    cap = ["--depth", args.depth] if args.depth else []
    if scale > 1 and args.depth in (None, "fit"):
        cap += ["--fit-downscale", str(2 * scale)]
    train = ["--downscale", str(scale)] if scale > 1 else []
    train += ["--depth-weight", str(args.depth_weight)] if args.depth_weight is not None else []
    train += ["--refine-cameras"] if args.refine_cameras else []
    return synth, cap, train


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.photo_worlds",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out",
        type=Path,
        help="JSON to write (default: benchmarks/results/photo_worlds/<date>-<commit>.json)",
    )
    p.add_argument("--scenes", default="all", help="comma-separated dsg-synth scenes or 'all' (default)")
    p.add_argument("--work", type=Path, help="keep every scene's photos, captures, worlds and logs here")
    p.add_argument("--seed", type=int, default=0, help="dsg-synth and dsg-train seed (default 0)")
    p.add_argument("--views", type=int, help="photos per state (default: dsg-synth's)")
    p.add_argument(
        "--marker", type=float, default=0.1, help="ArUco marker side in metres for scale (0: none)"
    )
    p.add_argument(
        "--align-views",
        type=int,
        default=60,
        metavar="STEPS",
        help="dsg-eval --align-views STEPS for both worlds (default 60; 0: score the cameras as given)",
    )
    p.add_argument("--preset", default=None, help="dsg-train preset (default: dsg-train's)")
    p.add_argument("--iterations", type=int, help="dsg-train steps (default: the preset's)")
    p.add_argument(
        "--depth",
        choices=DEPTH_SOURCES,
        default=None,
        help="dsg-capture --depth: the photo capture's depth maps (default: dsg-capture's, fit)",
    )
    p.add_argument(
        "--depth-weight",
        type=float,
        metavar="W",
        help="dsg-train --depth-weight W for the photo world (on its capture's depth maps)",
    )
    p.add_argument(
        "--photo-scale",
        type=int,
        default=1,
        metavar="S",
        help="dsg-synth --photo-scale S: photos S times the ground truth's size, as a phone's are larger than "
        "the size a world trains at; the photo world trains at the ground truth's size (dsg-train --downscale "
        "S) and dsg-capture's depth fit at half of it (--fit-downscale 2S) (default 1)",
    )
    p.add_argument(
        "--refine-cameras",
        action="store_true",
        help="dsg-train --refine-cameras for the photo world (its cameras refined in training)",
    )
    p.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        metavar="RESULT",
        help="instead of running: one result of the scenes of these stored results (of the same settings), "
        "with the summary over all of them, written to --out",
    )
    args = p.parse_args(argv)
    if args.merge:
        try:
            r = merge(args.merge, args.out or default_out("photo_worlds"))
        except ValueError as e:
            p.error(str(e))
        print(json.dumps(r["summary"]))
        return 0
    scenes = checked_scene_args(p, args)
    synth = ["--seed", str(args.seed)] + (["--views", str(args.views)] if args.views else [])
    train = ["--seed", str(args.seed)] + (["--preset", args.preset] if args.preset else [])
    train += ["--iterations", str(args.iterations)] if args.iterations else []
    out = args.out or default_out("photo_worlds")
    ev = ["--align-views", str(args.align_views)] if args.align_views else []
    if not 1 <= args.photo_scale <= 16:
        p.error(f"--photo-scale must be an integer in 1..16, got {args.photo_scale}")
    photo_synth, cap, photo_train = photo_path_args(args)
    synth += photo_synth
    r = run(out, scenes, args.work, synth, train, args.marker or None, ev, cap, photo_train)
    print(json.dumps(r["summary"]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
