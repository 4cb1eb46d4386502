"""``dsg-suite``: the DSG-World comparison on the default synthetic scenes (the paper's Tables 1 and 2).

For every scene: generate the capture (``dsg-synth``, skipped when present), train baseline (a) (one field
on ``state1``, segmentation only), derive (b) (a + kNN background completion) and train DSG-World with the
ablations B, B+C and B+C+P (``dsg-train`` on both states); each training runs in its own process (wall time
and peak RSS recorded) and is skipped when its world file exists; a training that was killed continues from its
checkpoint (``WORLD.ckpt``; its ``train_seconds`` count every part, its ``wall_seconds`` the last), so an
interrupted suite resumes. A world of ours found there that was trained with another two-state schedule (say,
another ``--refine-steps``) or other joint-phase options (``--pseudo-every``, ``--align-downscale``,
``--support-weight``, ``--layers``) is refused before anything runs, not reused. Every
world is evaluated with ``dsg-eval`` on every test state of the capture (objects at the test poses, held-out
cameras); a method's figure per scene is the mean over its test states.

Writes ``OUT/table.md`` (methods x scenes, PSNR / SSIM / mask IoU, and the mean over scenes), ``OUT/table.json``,
``OUT/grids/<scene>.png`` (rows: ground truth | baseline (a) | ours B+C+P, first test state), and per run
``OUT/eval/<scene>/<method>/<state>/report.json``. ``table.json`` records the settings and the code's commit.

The full suite takes hours; ``--merge`` joins the ``table.json`` files of runs that each did some of the
scenes (made with the same settings) into one table, a later file's (scene, method) replacing an earlier one's;
``--methods`` picks the rows to keep. It refuses to mix rows of ours (B, B+C, B+C+P) trained with different
two-state schedules (steps, first joint step, refinement steps: ``table.json``'s ``two_state_schedule`` and
each training's record),
and rows of any method that held out different views of the training states (``holdout_every`` in each
training's record: 0, as every suite capture has test states; tables whose records lack it held out 8).

Examples::

    dsg-suite --out suite                                        # 7 scenes, default preset: hours
    dsg-suite --out /tmp/s --scenes two_blocks --iterations 2000 --methods a,b,BCP
    dsg-suite --out /tmp/s --scenes two_blocks --preset quick --width 32 --height 32 --views 16
    dsg-suite --out /tmp/s --methods B,BC,BCP --refine-steps 0     # the ablations without refinement
    dsg-suite --out merged --merge run1/table.json run2/table.json   # one table from two partial runs
    dsg-suite --out merged --merge old/table.json new/table.json --methods a,b,BCP
    dsg-suite --out seeds --merge s0/table.json s1/table.json s2/table.json    # several seeds: seeds.md too
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from train_world.suite.records import (
    LEGACY_HOLDOUT,
    OURS,
    ours_options,
    refuse_mismatched_worlds,
    row_schedule,
    two_state_schedule,
    world_file,
)

__all__ = ["METHODS", "merge_tables", "run_suite"]

# settings that must agree for runs to share one table
_SETTINGS = ("preset", "iterations", "mip", "max_gaussians", "synth_args", "seed", "pseudo_every",
             "align_downscale", "support_weight", "layers")  # fmt: skip


def _setting(table: dict[str, Any], key: str) -> Any:
    """A table's setting; tables from before the preset set the support term and the layers record none
    (``None``, absent) for dsg-train's default then, no support term (0) and one sorted list."""
    v = table.get(key)
    if key == "support_weight":
        return 0.0 if v is None else float(v)
    if key == "layers":
        return bool(v)
    return v


# name -> (label in the table, extra dsg-train options or None for baselines)
METHODS: dict[str, tuple[str, list[str] | None]] = {
    "a": ("(a) single-state, segmentation only", None),
    "b": ("(b) single-state + kNN completion", None),
    "B": ("ours: B", ["--no-prune", "--no-pseudo"]),
    "BC": ("ours: B+C", ["--no-pseudo"]),
    "BCP": ("ours: B+C+P", []),
}


def _run_json(cmd: list[str], log: Path) -> dict[str, Any]:
    t0 = time.perf_counter()
    with open(log, "w") as f:
        r = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=f, text=True, check=False)
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed with status {r.returncode} (see {log})")
    last = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    out = json.loads(last[-1]) if last else {}
    out.setdefault("wall_seconds", round(time.perf_counter() - t0, 1))
    return out


def _provenance() -> dict[str, Any]:
    """Which code made the numbers: the git commit (``-dirty`` with uncommitted changes) and the time."""
    root = Path(__file__).resolve().parents[2]

    def git(*a: str) -> str | None:
        try:
            r = subprocess.run(
                ["git", "-C", str(root), *a], capture_output=True, text=True, timeout=30, check=False
            )
        except (OSError, subprocess.SubprocessError):
            return None
        return r.stdout.strip() if r.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit and git("status", "--porcelain", "--untracked-files=no"):
        commit += "-dirty"
    return {
        "commit": commit,
        "started": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "cpus": os.cpu_count(),
    }


def _one_value(values: dict[tuple[str, str], Any], what: str) -> Any:
    """The one value that every (scene, method) row of ``values`` has (None when there are no rows); raises
    ``ValueError`` starting with ``what`` and listing which rows have which value when they differ."""
    distinct = sorted(set(values.values()))
    if len(distinct) > 1:
        where = {d: [f"{s}/{m}" for (s, m), v in values.items() if v == d] for d in distinct}
        shown = "; ".join(
            f"{list(d) if isinstance(d, tuple) else d}: {', '.join(w[:3])}{' ...' if len(w) > 3 else ''}"
            for d, w in where.items()
        )
        raise ValueError(f"{what} ({shown}); rerun them or leave some out with --methods")
    return distinct[0] if distinct else None


def merge_tables(tables: list[dict[str, Any]], methods: list[str] | None = None) -> dict[str, Any]:
    """One table from several suite runs' ``table.json`` dictionaries (in order: a later run's (scene, method)
    replaces an earlier one's), keeping ``methods`` (None: all). Raises ``ValueError`` naming the setting when
    the runs' settings differ, when the rows kept for ours (B, B+C, B+C+P) were trained with different
    two-state schedules (steps, first joint step, refinement steps), or when the rows kept held out different views
    (``holdout_every`` of their training records; 8 where a record lacks it)."""
    if not tables:
        raise ValueError("merge needs at least one table.json")
    first = tables[0]
    for i, t in enumerate(tables[1:], start=1):
        for k in _SETTINGS:
            if _setting(t, k) != _setting(first, k):
                raise ValueError(
                    f"table {i} has {k}={_setting(t, k)!r} but table 0 has {_setting(first, k)!r}: "
                    "runs with different settings do not share a table"
                )
    out: dict[str, Any] = {k: _setting(first, k) for k in _SETTINGS}
    out.update(scenes={}, methods=[], provenance=[])
    schedules: dict[tuple[str, str], tuple[int, ...]] = {}
    holdouts: dict[tuple[str, str], int] = {}
    for t in tables:
        out["provenance"].extend(
            t["provenance"] if isinstance(t.get("provenance"), list) else [t.get("provenance")]
        )
        for m in t.get("methods", []):
            if m not in out["methods"] and (methods is None or m in methods):
                out["methods"].append(m)
        for scene, runs in t.get("scenes", {}).items():
            kept = {m: r for m, r in runs.items() if methods is None or m in methods}
            if kept:
                out["scenes"].setdefault(scene, {}).update(kept)
            for m, r in kept.items():
                holdouts[(scene, m)] = int((r.get("train") or {}).get("holdout_every", LEGACY_HOLDOUT))
                if m in OURS:
                    schedules[(scene, m)] = row_schedule(r, t)
    schedule = _one_value(
        schedules,
        "ours' rows were trained with different two-state schedules "
        "[steps, first joint step, refinement steps]",
    )
    out["two_state_schedule"] = list(schedule) if schedule else None
    out["holdout_every"] = _one_value(
        holdouts, "rows were trained with different held-out views per state (holdout_every)"
    )
    known = _scene_list("all")  # the default scenes in their usual order, then any others
    order = [s for s in known if s in out["scenes"]] + sorted(s for s in out["scenes"] if s not in known)
    out["scenes"] = {s: out["scenes"][s] for s in order}
    out["methods"] = [m for m in METHODS if m in out["methods"]]
    return out


def _scene_list(arg: str) -> list[str]:
    from train_world.synth.spec import default_scene_names

    if arg == "all":
        return sorted(default_scene_names())
    return [s for s in arg.split(",") if s]


def _grid_png(
    scene_dir: Path, capture: Path, worlds: dict[str, Path], out_png: Path, state: str, rows: int = 4
):
    from dsg_gym.world import load_world
    from train_world.capture.format import atomic_write_bytes, encode_png
    from train_world.eval.evaluate import _poses_for, layer_mask, render_gaussians
    from train_world.eval.report_files import grid as _grid
    from train_world.eval.report_files import u8 as _u8
    from train_world.single_state.data import load_eval_views

    renders = {}
    views = None
    for m, path in worlds.items():
        w = load_world(path)
        bg = tuple(w.metadata.get("background", (0.0, 0.0, 0.0)))
        if views is None:
            views = load_eval_views(
                capture,
                state=state,
                heldout=(),
                downscale=1,
                background=bg,
                object_ids=w.object_ids,
                all_views=True,
            )
        n = min(rows, len(views.images))
        g = w.gaussians(poses=_poses_for(w, capture, state))
        renders[m], _ = render_gaussians(
            g,
            views.viewmats[:n].numpy(),
            views.Ks[:n].numpy(),
            views.width,
            views.height,
            bg,
            w.splat_options,
            front=layer_mask(w),
        )
    n = min(rows, len(views.images))
    grid = [[_u8(views.images[i].numpy())] + [_u8(renders[m][i]) for m in worlds] for i in range(n)]
    atomic_write_bytes(out_png, encode_png(_grid(grid)))


def run_suite(
    out: str | Path,
    scenes: list[str],
    methods: list[str],
    *,
    preset: str = "default",
    iterations: int | None = None,
    synth_args: list[str] | None = None,
    seed: int = 0,
    pseudo_every: int | None = None,
    align_downscale: int | None = None,
    max_gaussians: int | None = None,
    mip: bool | None = None,
    refine_steps: int | None = None,
    support_weight: float | None = None,
    layers: bool | None = None,
) -> dict[str, Any]:
    """Run the comparison (module docstring); returns the table dictionary also written to ``table.json``.
    ``refine_steps``: refinement steps of ours (``dsg-train --refine-steps``; ``None``: the preset's, 0: the
    paper's method without refinement); ``support_weight``: the support term's weight in ours (``dsg-train
    --support-weight``); ``layers``: ours refined and rendered in two layers (``dsg-train --layers``; never
    without refinement). ``None``: the preset's; ``table.json`` records the values used."""
    from train_world.capture import load_capture
    from train_world.eval.evaluate import evaluate_test_states
    from train_world.single_state.presets import get_preset

    if refine_steps is not None and (
        isinstance(refine_steps, bool) or int(refine_steps) != refine_steps or refine_steps < 0
    ):
        raise ValueError(f"refine_steps must be a non-negative integer or None, got {refine_steps!r}")
    out = Path(out)
    py = sys.executable
    if max_gaussians is None:  # baseline (a) gets the two-state cap too: the same field size as each of ours
        max_gaussians = get_preset(preset).dual_max_gaussians
    schedule = two_state_schedule(preset, iterations, refine_steps)
    support_weight, layers = ours_options(preset, schedule, support_weight, layers)
    results: dict[str, Any] = {
        "preset": preset,
        "iterations": iterations,
        "mip": mip,
        "max_gaussians": max_gaussians,
        "synth_args": list(synth_args or []),
        "seed": seed,
        "pseudo_every": pseudo_every,
        "align_downscale": align_downscale,
        "support_weight": float(support_weight),
        "layers": layers,
        "two_state_schedule": schedule,
        "scenes": {},
        "methods": methods,
        "provenance": _provenance(),
    }
    refuse_mismatched_worlds(out, scenes, methods, results)
    for scene in scenes:
        cap = out / "data" / scene
        logs = out / "logs" / scene
        wdir = out / "worlds" / scene
        logs.mkdir(parents=True, exist_ok=True)
        wdir.mkdir(parents=True, exist_ok=True)
        if not (cap / "scene.json").is_file():
            _run_json(
                [
                    py,
                    "-m",
                    "train_world.cli.synth",
                    "--scene",
                    scene,
                    "--out",
                    str(cap),
                    "--quiet",
                    "--seed",
                    str(seed),
                    *(synth_args or []),
                ],
                logs / "synth.log",
            )
        splits = load_capture(cap, states=[], load_depth=False).splits
        test_states = [s for s, split in splits.items() if split == "test"]
        it = [] if iterations is None else ["--iterations", str(iterations)]
        if max_gaussians is not None:
            it += ["--max-gaussians", str(max_gaussians)]
        if mip is not None:
            it += ["--mip" if mip else "--no-mip"]
        single = [
            py,
            "-m",
            "train_world.cli.baselines",
            "single",
            str(cap),
            "--preset",
            preset,
            "--seed",
            str(seed),
            "--resume",
            *it,
        ]
        dual = [
            py,
            "-m",
            "train_world.cli.train",
            str(cap),
            "--preset",
            preset,
            "--seed",
            str(seed),
            "--quiet",
            *([] if pseudo_every is None else ["--pseudo-every", str(pseudo_every)]),
            *([] if align_downscale is None else ["--align-downscale", str(align_downscale)]),
            "--support-weight",
            repr(float(support_weight)),
            "--layers" if layers else "--no-layers",
            "--resume",
            *it,
            *([] if refine_steps is None else ["--refine-steps", str(int(refine_steps))]),
        ]
        recon_ckpt, recon_info = wdir / "recon.ckpt", wdir / "recon.json"
        runs: dict[str, Any] = {}
        for m in methods:
            world = world_file(wdir, m)
            info_path = wdir / f"{m}.json"
            if not world.is_file():
                if m == "a":
                    cmd = [*single, "--out", str(world), "--checkpoint", str(wdir / "a.dsgworld.ckpt")]
                elif m == "b":
                    a_world = wdir / "a.dsgworld"
                    if not a_world.is_file():
                        _run_json(
                            [*single, "--out", str(a_world), "--checkpoint", str(wdir / "a.dsgworld.ckpt")],
                            logs / "a.log",
                        )
                    cmd = [py, "-m", "train_world.cli.baselines", "knn", str(a_world), "--out", str(world)]
                else:
                    # the ablations share one reconstruction phase (identical in all of them), then branch
                    if not recon_info.is_file():
                        r = _run_json(
                            [
                                *dual,
                                "--out",
                                str(wdir / "recon.dsgworld"),
                                "--stop-at-joint",
                                "--checkpoint",
                                str(recon_ckpt),
                            ],
                            logs / "recon.log",
                        )
                        recon_info.write_text(json.dumps(r, indent=1))
                    cmd = [*dual, "--out", str(world), "--branch-from", str(recon_ckpt), *METHODS[m][1]]
                info = _run_json(cmd, logs / f"{m}.log")
                if m in (
                    "B",
                    "BC",
                    "BCP",
                ):  # wall time and memory of the whole training, shared phase included
                    r = json.loads(recon_info.read_text())
                    info["recon_phase_seconds"] = r.get("wall_seconds")
                    info["wall_seconds"] = round(
                        info.get("wall_seconds", 0.0) + r.get("wall_seconds", 0.0), 1
                    )
                    info["peak_rss_mb"] = max(info.get("peak_rss_mb", 0.0), r.get("peak_rss_mb", 0.0))
                info_path.write_text(json.dumps(info, indent=1))
            info = json.loads(info_path.read_text()) if info_path.is_file() else {}
            if test_states:  # each state's report in eval/<scene>/<method>/<state>/, their mean beside them
                r = evaluate_test_states(world, cap, out / "eval" / scene / m)
                per_state, mean = {s: v["mean"] for s, v in r["states"].items()}, r["mean"]
            else:
                per_state, mean = {}, {k: None for k in ("psnr", "ssim", "mask_iou")}
            runs[m] = {"mean": mean, "per_state": per_state, "train": info}
        results["scenes"][scene] = runs
        shown = {m: world_file(wdir, m) for m in ("a", "BCP") if m in methods}
        if shown and test_states:
            (out / "grids").mkdir(parents=True, exist_ok=True)
            _grid_png(out, cap, shown, out / "grids" / f"{scene}.png", test_states[0])
        _write_tables(out, results)
    return results


def _f(v, nd=2):
    return "-" if v is None else f"{v:.{nd}f}"


def _write_tables(out: Path, results: dict[str, Any]) -> None:
    from train_world.capture.format import atomic_write_bytes, atomic_write_json
    from train_world.eval.evaluate import mean_of_means

    scenes = list(results["scenes"])
    methods = results["methods"]
    mean_over = {
        m: mean_of_means([results["scenes"][s][m]["mean"] for s in scenes if m in results["scenes"][s]])
        for m in methods
    }
    results["mean_over_scenes"] = mean_over
    lines = [
        f"# DSG-World suite (preset `{results['preset']}`"
        + (f", {results['iterations']} iterations" if results["iterations"] else "")
        + ")",
        "",
        (
            "Novel-state simulation: objects at each test state's poses, held-out cameras; PSNR (dB) / SSIM / "
            "mask IoU, mean over the test states of each scene."
        ),
        "",
        "| method | " + " | ".join(scenes) + " | **mean** |",
        "| --- |" + " --- |" * (len(scenes) + 1),
    ]
    for m in methods:
        cells = []
        for s in scenes:
            r = results["scenes"][s].get(m)
            cells.append(
                "-"
                if r is None
                else f"{_f(r['mean']['psnr'])} / {_f(r['mean']['ssim'], 3)} / {_f(r['mean']['mask_iou'], 3)}"
            )
        mo = mean_over[m]
        n = sum(m in results["scenes"][s] for s in scenes)
        part = "" if n == len(scenes) else f" ({n} of {len(scenes)} scenes)"
        cells.append(f"**{_f(mo['psnr'])} / {_f(mo['ssim'], 3)} / {_f(mo['mask_iou'], 3)}**{part}")
        lines.append(f"| {METHODS[m][0]} | " + " | ".join(cells) + " |")
    lines += ["", "| method | scene | train s | peak RSS MB |", "| --- | --- | --- | --- |"]
    for s in scenes:
        for m in (m for m in methods if m in results["scenes"][s]):
            t = results["scenes"][s][m].get("train", {})
            lines.append(f"| {m} | {s} | {t.get('wall_seconds', '-')} | {t.get('peak_rss_mb', '-')} |")
    atomic_write_json(out / "table.json", results)
    atomic_write_bytes(out / "table.md", ("\n".join(lines) + "\n").encode("utf-8"))
