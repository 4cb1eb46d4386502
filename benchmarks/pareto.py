"""Run time against error: ``python -m benchmarks.pareto [--out DIR]``.

Sweeps the settings that trade speed for accuracy, one axis at a time around the env's default (plus
combined points), on the bundled world and the seven synthetic scenes' held-out test states (ground truth
rendered by MuJoCo):

* resolution (64, 96, 128 px; error against the ground truth area-downsampled to that size),
* SH degree cap 0..3, early termination (``t_min``) and alpha threshold (``alpha_min``) of the renderer
  (``dsg_gym.scene_renderer.RenderSettings``),
* Gaussian budget: keep 70 / 50 / 30 % of each part's Gaussians by removal error
  (``train_world.compact.importance``, as ``dsg-compact`` scores them) without refit (``--extra-world`` adds
  whole world files, e.g. the bundled world before ``dsg-compact``),
* float16 storage of colours and opacities (emulated: rounded to float16 and back; ``float16_all`` rounds
  every attribute), which changes the error only, not the float32 renderer's speed.

For each point: ``DSGWorld-v0`` step time (obs rgb + mask, one random object moved per step, incremental
rendering, the same seeded episode for every point, interleaved rounds, median) and the render error of the
env's renderer at the test poses and cameras (PSNR and SSIM as ``dsg-eval``, mask IoU of the env's mask).
Writes ``DIR/pareto.json``, ``DIR/pareto.md`` and ``DIR/pareto.png`` (step time against PSNR, Pareto front
marked) and the recommended renderer settings (``recommended`` in the JSON; rule in ``recommended.rule``).
The bundled world's ground truth is ``two_blocks`` regenerated with the lighting and supersampling it was
trained under (``world_generator_settings``: bit for bit the images it was trained on; the generator's own
test cameras). The seven scenes have no trained worlds (training each is long), so their geometry worlds
(``train_world.synth.geom_world``, baked under the generator's default lighting) stand in (``--scenes none``
skips them). ``--training`` adds novel-state PSNR against training wall-clock for the three ``dsg-train``
presets (``benchmarks.pareto_training``, heavy: ``3 x --train-minutes``) and ``DIR/training.png``.
``--quick``: bundled world, a few points, a few steps (what the test runs). ``DIR`` defaults to
``benchmarks/results/pareto/<date>-<commit>/``.
"""

from __future__ import annotations

import os

# numba's workqueue layer, on which the published front was measured (the runtime takes numba's own choice,
# OpenMP where it loads, with faster steps; the front compares settings on one layer); train_world would
# pick OpenMP for training
_LAYER_SET_HERE = "NUMBA_THREADING_LAYER" not in os.environ
_WAIT_SET_HERE = "OMP_WAIT_POLICY" not in os.environ
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")
os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import dataclasses
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from . import pareto_core as C
from . import pareto_report as report
from ._results import default_out, machine_info

TOLERANCE_DB = 0.1
REPO = Path(__file__).resolve().parents[1]


def _log(msg: str) -> None:
    print(f"[pareto] {msg}", file=sys.stderr, flush=True)


def _git() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], check=False, cwd=REPO, capture_output=True, text=True,
                              timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], check=False, cwd=REPO,
                               capture_output=True, text=True, timeout=10).stdout.split("\n")
        dirty = [ln[3:] for ln in dirty if ln.strip()]
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if not head:
        return "unknown (not a git checkout)"
    return head + (f" + uncommitted changes in {', '.join(dirty)}" if dirty else "")


def world_generator_settings(world) -> dict:
    """The ``GenerateConfig`` image settings of the dsg-synth capture a world was trained on, from
    ``metadata.source.generator``: ``lighting`` and ``supersample``. Missing keys mean an older generator:
    no lighting recorded = 1.0, whose strong world-fixed lights 1.1 reproduces bit for bit with ``"spot"``;
    no supersample recorded = before 1.2, one point sample per pixel. (Geometry worlds bake their colours
    under the generator's defaults.)"""
    src = world.metadata.get("source") or {}
    gen = src.get("generator") if isinstance(src, dict) else None
    gen = gen if isinstance(gen, dict) else {}
    return {"lighting": str(gen.get("lighting", "spot")), "supersample": int(gen.get("supersample", 1))}


def _capture(work: Path, scene: str, quick: bool, settings: dict | None = None) -> Path:
    """A ``dsg-synth`` capture of ``scene`` (seed 0, 128x128, the generator's test cameras; ``settings``:
    ``GenerateConfig`` fields such as lighting and supersampling, the generator's defaults unless given)."""
    from train_world.synth.generate import GenerateConfig, generate_scene

    kw = dict(settings or {})
    out = work / "_".join([scene] + [f"{k}-{v}" for k, v in sorted(kw.items())])
    if not (out / "scene.json").is_file():
        generate_scene(scene, out, GenerateConfig(seed=0, views=8 if quick else 48, progress=False, **kw))
    return out


def _storage_mb(world, storage: str) -> float:
    """Bytes the runtime arrays would take: means, quats, scales (float16 with ``float16_all``), opacities
    and SH colours (float16 unless ``float32``)."""
    n = world.num_gaussians
    k = max([world.background.sh.shape[1]] + [o.sh.shape[1] for o in world.objects])
    geo = 2 if storage == "float16_all" else 4
    col = 4 if storage == "float32" else 2
    return n * (geo * 10 + col * (1 + 3 * k)) / 1e6


class Sweep:
    """Errors and step times of a list of points on one world and one capture's test states."""

    def __init__(self, world, test: C.TestStates, args, label: str):
        self.world, self.test, self.args, self.label = world, test, args, label
        self.variants: dict[tuple, object] = {}
        self.scores = None
        self.errors: dict[str, dict] = {}
        self.points: list[C.Point] = []

    def variant(self, p: C.Point):
        if p.world_key not in self.variants:
            if p.fraction < 1.0 and self.scores is None:
                t0 = time.perf_counter()
                kw = {"object_views": 8, "rings": 1, "per_ring": 8} if self.args.quick else {}
                self.scores = C.importance_scores(self.world, **kw)
                _log(f"{self.label}: importance scores in {time.perf_counter() - t0:.1f} s")
            self.variants[p.world_key] = C.world_variant(self.world, p, self.scores)
        return self.variants[p.world_key]

    def measure_errors(self, points: list[C.Point]) -> None:
        for p in points:
            if p.name not in self.errors:
                w = self.variant(p)
                self.errors[p.name] = {**C.render_error(w, self.test, p), "storage_mb": _storage_mb(w, p.storage)}
                self.points.append(p)

    def measure_times(self) -> dict[str, dict]:
        timer = C.StepTimer(self.args.steps, seed=self.args.seed)
        twins: dict[str, str] = {}
        for p in self.points:
            twin = next((q for q in self.points if q.storage == "float32" and
                         dataclasses.replace(q, name=p.name, axis=p.axis, storage=p.storage) == p), None)
            if p.storage != "float32" and twin is not None:
                twins[p.name] = twin.name  # emulated storage: the float32 renderer's time is the same
            else:
                timer.add(p.name, self.variant(p), p)
        t0 = time.perf_counter()
        for _ in range(self.args.rounds):
            timer.round()
        _log(f"{self.label}: {len(timer.envs)} envs x {self.args.rounds} rounds x {self.args.steps} steps in "
             f"{time.perf_counter() - t0:.0f} s")
        out = {n: timer.result(n) for n in timer.envs}
        timer.close()
        for name, twin in twins.items():
            out[name] = {**out[twin], "time_from": twin}
        return out

    def rows(self) -> list[dict]:
        times = self.measure_times()
        rows = []
        for p in self.points:
            d = p.to_dict()
            if p.world:
                d["world_label"] = Path(p.world).name
            rows.append({**d, **self.errors[p.name], **times[p.name], "env_settable": p.env_settable})
        mark_fronts(rows, self.args.size)
        return rows


def mark_fronts(rows: list[dict], size: int) -> None:
    """``on_front`` over all rows, ``on_front_default_size`` over the rows at ``size``."""
    for r, f in zip(rows, C.pareto_front([r["step_ms"] for r in rows], [r["psnr"] for r in rows])):
        r["on_front"] = f
    at = [r for r in rows if r["size"] == size]
    for r, f in zip(at, C.pareto_front([r["step_ms"] for r in at], [r["psnr"] for r in at])):
        r["on_front_default_size"] = f


def recommended(rows: list[dict], points: dict[str, C.Point], size: int) -> dict | None:
    cand = [{**r, "point": points[r["name"]]} for r in rows]
    best = C.recommend(cand, TOLERANCE_DB, size)
    if best is None:
        return None
    base = rows[0]
    return {
        "rule": C.RECOMMEND_RULE.format(tol=TOLERANCE_DB),
        "name": best["name"],
        "render_settings": best["point"].render_settings.kwargs(),
        "size": size,
        "psnr": best["psnr"], "ssim": best["ssim"], "mask_iou": best["mask_iou"],
        "step_ms": best["step_ms"], "steps_per_s": best["steps_per_s"],
        "vs_default": {"psnr_delta_db": best["psnr"] - base["psnr"], "step_speedup": base["step_ms"] / best["step_ms"]},
    }


def _world_level_note(rows: list[dict], rec: dict | None, size: int) -> str | None:
    if rec is None:
        return None
    best = max(r["psnr"] for r in rows if r["env_settable"] and r["size"] == size)
    better = [r for r in rows if not r["env_settable"] and r["size"] == size and r.get("on_front_default_size")
              and r["psnr"] >= best - TOLERANCE_DB and r["step_ms"] < rec["step_ms"]]
    if not better:
        return ("No world-level change (pruning without refit, float16 storage, other world files) is both "
                f"within {TOLERANCE_DB} dB and faster than the recommended renderer settings.")
    return ("World-level points on the front within the tolerance and faster than the recommendation: "
            + ", ".join(f"{r['name']} ({r['psnr']:.2f} dB, {r['step_ms']:.2f} ms)" for r in better)
            + "; they need a different world file, not an env default.")


def run_bundled(args, work: Path) -> tuple[dict, dict | None, list[C.Point]]:
    from dsg_gym.envs.dsg_world import DEFAULT_WORLD
    from dsg_gym.world_model import WorldModel

    world = WorldModel.load(DEFAULT_WORLD).without_features()
    cap = _capture(work, "two_blocks", args.quick, world_generator_settings(world))
    test = C.load_test_states(cap, world.object_ids, max_views=4 if args.quick else None)
    for s, P in test.poses.items():
        if s in world.states and not np.allclose(world.states[s], P, atol=1e-9):
            raise RuntimeError(f"the generated capture's {s} poses differ from the bundled world's")
    sw = Sweep(world, test, args, "bundled")
    points = C.sweep_points(args.quick)
    points += [C.Point(f"world {Path(w).name}", "world", world=str(w)) for w in args.extra_world]
    t0 = time.perf_counter()
    sw.measure_errors(points)
    combos = C.combined_points(points, {n: e["psnr"] for n, e in sw.errors.items()})
    sw.measure_errors(combos)
    _log(f"bundled: errors of {len(sw.points)} points in {time.perf_counter() - t0:.0f} s")
    rows = sw.rows()
    pts = {p.name: p for p in sw.points}
    rec = recommended(rows, pts, args.size)
    gen = json.loads((cap / "scene.json").read_text())["generator"]
    res = {
        "capture": {k: gen.get(k) for k in ("name", "version", "seed", "width", "height", "test_views",
                                            "test_states", "lighting", "supersample")},
        "world": str(DEFAULT_WORLD.relative_to(REPO)) if DEFAULT_WORLD.is_relative_to(REPO) else str(DEFAULT_WORLD),
        "kind": "trained DSG-World (B+C+P), compacted by dsg-compact",
        "scene": "two_blocks",
        "test_views": rows[0]["views"],
        "points": rows,
        "front": [r["name"] for r in rows if r["on_front"]],
        "front_default_size": [r["name"] for r in rows if r.get("on_front_default_size")],
    }
    return res, rec, sw.points


def run_scenes(args, work: Path, points: list[C.Point], rec: dict | None) -> dict:
    from train_world.synth.geom_world import build_geom_world
    from train_world.synth.spec import default_scene_names

    names = default_scene_names() if args.scenes == "all" else [s for s in args.scenes.split(",") if s]
    per_scene: dict[str, dict] = {}
    for scene in names:
        t0 = time.perf_counter()
        cap = _capture(work, scene, args.quick)
        world = build_geom_world(scene).without_features()
        test = C.load_test_states(cap, world.object_ids)
        deg = max([world.background.sh_degree] + [o.sh_degree for o in world.objects])
        pts = [p for p in points if p.world is None and not (p.axis == "sh_degree" and p.sh_degree >= deg)]
        sw = Sweep(world, test, args, scene)
        sw.measure_errors(pts)
        rows = sw.rows()
        gen = json.loads((cap / "scene.json").read_text())["generator"]
        entry = {"gaussians": world.num_gaussians, "sh_degree": deg, "lighting": gen.get("lighting"),
                 "generator": gen.get("version"), "points": rows}
        if rec is not None:
            by = {r["name"]: r for r in rows}
            cand = [r for r in rows if r["env_settable"] and r["size"] == args.size]
            best = max(cand, key=lambda r: r["psnr"])
            if rec["name"] in by:
                entry["recommended_check"] = {
                    "best": best["name"],
                    "psnr_delta_vs_default": by[rec["name"]]["psnr"] - rows[0]["psnr"],
                    "psnr_delta_vs_best": by[rec["name"]]["psnr"] - best["psnr"],
                    "step_speedup": rows[0]["step_ms"] / by[rec["name"]]["step_ms"],
                }
        per_scene[scene] = entry
        _log(f"{scene}: {len(rows)} points in {time.perf_counter() - t0:.0f} s; default "
             f"{rows[0]['psnr']:.2f} dB, {rows[0]['steps_per_s']:.0f} steps/s")
    common = [r["name"] for r in per_scene[names[0]]["points"]
              if all(any(q["name"] == r["name"] for q in s["points"]) for s in per_scene.values())]
    mean_rows = []
    for name in common:
        rs = [next(q for q in s["points"] if q["name"] == name) for s in per_scene.values()]
        m = {k: v for k, v in rs[0].items() if k not in ("psnr", "ssim", "mask_iou", "step_ms", "steps_per_s",
                                                          "full_render_ms", "gaussians", "rounds_ms")}
        for k in ("psnr", "ssim", "mask_iou", "step_ms", "full_render_ms"):
            vals = [q[k] for q in rs if q.get(k) is not None]
            m[k] = float(np.mean(vals)) if vals else None
        m["steps_per_s"] = 1e3 / m["step_ms"]
        m["gaussians"] = round(float(np.mean([q["gaussians"] for q in rs])))
        mean_rows.append(m)
    mark_fronts(mean_rows, args.size)
    return {
        "kind": "geometry worlds (train_world.synth.geom_world) standing in for trained worlds",
        "note": ("No trained worlds exist for these scenes (training takes about 30 min each): each scene's "
                 "geometry world (Gaussians laid on the MuJoCo geoms, colours baked from MuJoCo renders under "
                 "the generator's default lighting, SH degree 0, so the SH axis is skipped) is measured against "
                 "a capture with that lighting. Geometry worlds are denser (40-85k Gaussians) and their own "
                 "error dominates."),
        "names": names,
        "per_scene": per_scene,
        "mean_points": mean_rows,
        "front": [r["name"] for r in mean_rows if r["on_front"]],
    }


def run_training(args, work: Path, out: Path) -> dict:
    cap = _capture(work, args.train_scene, False)  # the generator's default lighting
    tmp = out / ".training.json"
    env = dict(os.environ)
    if _LAYER_SET_HERE:
        env.pop("NUMBA_THREADING_LAYER", None)  # training runs on train_world's OpenMP layer, as dsg-train
    if _WAIT_SET_HERE:
        env.pop("OMP_WAIT_POLICY", None)  # and waits as train_world chooses (train_world._openmp), as dsg-train
    ds = 4 if args.quick else args.train_downscale
    cmd = [sys.executable, "-m", "benchmarks.pareto_training", "--capture", str(cap), "--out", str(tmp),
           "--train-minutes", str(args.train_minutes), "--downscale", str(ds), "--seed", str(args.seed)]
    if args.quick:  # the mechanics only: a 30-step quick schedule at 32 px
        cmd += ["--presets", "quick", "--iterations", "30", "--first-eval", "1"]
    _log("training: " + " ".join(cmd[2:]))
    subprocess.run(cmd, cwd=REPO, env=env, check=True)
    tr = json.loads(tmp.read_text())
    tmp.unlink()
    tr["scene"] = args.train_scene
    tr["size"] = tr["curves"][0]["image_size"][0]
    tr["note"] = (f"`{args.train_scene}` capture at {tr['size']} px (`--downscale {ds}`), each "
                  f"preset capped at {args.train_minutes:g} min of training steps (evaluations not counted); "
                  "novel-state PSNR of the merged world on all test states, rendered by the env's renderer. "
                  "The schedules are the presets' own (full length), so a capped run stops part-way.")
    return tr


NOTES = [
    ("Step time: DSGWorld-v0, obs rgb + mask, capture camera 0, incremental rendering, collision 'reject', one "
     "random object moved per step; every point replays the same seeded episode (same start, same actions) in "
     "interleaved rounds; the median round; numba's workqueue layer (the runtime default). 'full render' is the "
     "renderer alone re-rendering the env camera from scratch."),
    ("Error: the env's SceneRenderer with the point's settings, objects at each test state's poses, the "
     "capture's test cameras (a full render), against the MuJoCo ground truth. Below 128 px the ground truth is "
     "area-averaged down to the render size (PIL box filter; masks: the class covering most of each pixel). "
     "PSNR and SSIM are dsg-eval's (mean over views); mask IoU uses the env's mask (argmax of the object label "
     "weights, not dsg-eval's classifier), accumulated over a state's views, mean over objects and states."),
    ("Budget: removal-error importance (train_world.compact.importance: background alone from its capture cameras plus "
     "an orbit, objects alone from a sphere of cameras) keeps the top fraction of each part at once, without "
     "dsg-compact's rounds and refit; object hull vertices are kept. The bundled world is already a dsg-compact "
     "output (pruned with refit within 0.3 dB), so pruning it further without refit costs much more."),
    ("float16: emulated by rounding to float16 and back; the renderer computes in float32, so these points "
     "reuse the float32 point's step time ('time_from'); storage_mb is what the arrays would take."),
]


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.pareto", description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n", 2)[2])
    ap.add_argument("--out", type=Path, help="output folder (pareto.json, .md, .png; default: "
                                                  "benchmarks/results/pareto/<date>-<commit>/)")
    ap.add_argument("--quick", action="store_true", help="tiny run: bundled world, few points and steps")
    ap.add_argument("--scenes", default=None, help="'all' (default), 'none' or a comma-separated list of "
                    "scene names for the geometry-world part (--quick: none)")
    ap.add_argument("--steps", type=int, help="env steps per round (default 200; --quick 30)")
    ap.add_argument("--rounds", type=int, help="timed rounds per point (default 7; --quick 2)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--extra-world", action="append", default=[], type=Path, metavar="FILE",
                    help="another world of the two_blocks scene to add as a point (e.g. before dsg-compact)")
    ap.add_argument("--training", action="store_true", help="also training time against error (heavy)")
    ap.add_argument("--train-minutes", type=float, default=6.0, help="cap per preset (default 6)")
    ap.add_argument("--train-downscale", type=int, default=2, help="training image downscale (default 2)")
    ap.add_argument("--train-scene", default="two_blocks", help="scene of the training curves")
    ap.add_argument("--work", type=Path, help="folder for the generated captures (default: a temporary one)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    args.out = args.out or default_out("pareto", "")
    from train_world.capture.format import atomic_write_bytes, atomic_write_json

    args.size = C.DEFAULT_SIZE
    args.steps = args.steps or (30 if args.quick else 200)
    args.rounds = args.rounds or (2 if args.quick else 7)
    args.scenes = args.scenes or ("none" if args.quick else "all")
    for w in args.extra_world:
        if not w.is_file():
            print(f"error: --extra-world {w}: no such file", file=sys.stderr)
            return 2
    t0 = time.perf_counter()
    args.out.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="dsg-pareto-"))
    try:
        bundled, rec, points = run_bundled(args, work)
        res = {
            "benchmark": "pareto",
            "mode": "quick" if args.quick else "full",
            "git": _git(),
            "machine": machine_info(),
            "options": {"steps": args.steps, "rounds": args.rounds, "seed": args.seed, "scenes": args.scenes,
                        "tolerance_db": TOLERANCE_DB},
            "default_size": args.size,
            "default_settings": {"alpha_min": C.DEFAULT_ALPHA_MIN, "t_min": C.DEFAULT_T_MIN, "sh_degree": None},
            "env_default_settings": C.RenderSettings().kwargs(),
            "env_default_is_recommended": bool(rec) and all(
                rec["render_settings"].get(k) == v for k, v in C.RenderSettings().kwargs().items()),
            "method": NOTES[1],
            "bundled": bundled,
            "recommended": rec,
            "world_level_note": _world_level_note(bundled["points"], rec, args.size),
            "scenes": None if args.scenes == "none" else run_scenes(args, work, points, rec),
            "training": run_training(args, work, args.out) if args.training else None,
            "notes": NOTES,
        }
        res["wall_seconds"] = round(time.perf_counter() - t0, 1)
        atomic_write_json(args.out / "pareto.json", res)
        atomic_write_bytes(args.out / "pareto.md", report.markdown(res).encode("utf-8"))
        atomic_write_bytes(args.out / "pareto.png", report.pareto_png(res))
        if res["training"]:
            atomic_write_bytes(args.out / "training.png", report.training_png(res["training"]))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    if rec:
        print(json.dumps({"out": str(args.out), "recommended": rec["render_settings"], "name": rec["name"],
                          "psnr": round(rec["psnr"], 3), "steps_per_s": round(rec["steps_per_s"], 1),
                          "wall_seconds": res["wall_seconds"]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
