"""The suite over several capture seeds: every scene generated (and trained) once per seed, then per scene and
method the mean, spread and worst case over the seeds.

A user's scene is a new seed every time, so a method is judged by its mean and its worst scene-seed, not by one
seed per scene. ``dsg-suite --seeds 0,1,2`` runs :func:`train_world.suite.runner.run_suite` once per seed into
``OUT/seed-<s>/`` and writes ``OUT/seeds.json`` and ``OUT/seeds.md`` (:func:`summarise_seeds`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["run_seeds", "seed_folder", "summarise_seeds", "write_seed_tables"]

_METRICS = ("psnr", "ssim", "mask_iou")


def seed_folder(out: str | Path, seed: int) -> Path:
    """Where one seed's suite run goes."""
    return Path(out) / f"seed-{int(seed)}"


def _stats(values: list[float]) -> dict[str, float]:
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "std": float(v.std()), "min": float(v.min()), "max": float(v.max())}


def summarise_seeds(tables: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Per method: per scene the mean / std (population, over seeds) / min / max of each metric, the mean over
    every scene-seed, and the worst scene-seed by PSNR. ``tables``: seed -> that seed's ``table.json``."""
    if not tables:
        raise ValueError("no seed tables to summarise")
    methods = list(next(iter(tables.values()))["methods"])
    scenes = sorted({s for t in tables.values() for s in t["scenes"]})
    out: dict[str, Any] = {"seeds": sorted(int(s) for s in tables), "scenes": scenes, "methods": {}}
    for m in methods:
        per_scene: dict[str, Any] = {}
        cells: list[tuple[str, int, dict[str, float]]] = []
        for scene in scenes:
            rows = [(seed, t["scenes"][scene][m]["mean"]) for seed, t in sorted(tables.items())
                    if scene in t["scenes"] and m in t["scenes"][scene]]  # fmt: skip
            rows = [(seed, r) for seed, r in rows if r.get("psnr") is not None]
            if not rows:
                continue
            per_scene[scene] = {
                k: _stats([r[k] for _, r in rows]) for k in _METRICS if rows[0][1].get(k) is not None
            }
            per_scene[scene]["seeds"] = [seed for seed, _ in rows]
            cells += [(scene, seed, r) for seed, r in rows]
        if not cells:
            continue
        worst = min(cells, key=lambda c: c[2]["psnr"])
        out["methods"][m] = {
            "scenes": per_scene,
            "all": {k: _stats([c[2][k] for c in cells]) for k in _METRICS if cells[0][2].get(k) is not None},
            "scene_seeds": len(cells),
            "worst": {"scene": worst[0], "seed": worst[1], **{k: worst[2].get(k) for k in _METRICS}},
        }
    return out


def write_seed_tables(out: str | Path, summary: Mapping[str, Any], labels: Mapping[str, str]) -> None:
    """``OUT/seeds.json`` and ``OUT/seeds.md`` (mean +- std over seeds per scene, the mean over scene-seeds and
    the worst scene-seed); ``labels``: method -> row label."""
    from train_world.capture.format import atomic_write_bytes, atomic_write_json

    out = Path(out)
    scenes = summary["scenes"]
    lines = [
        f"# DSG-World suite over seeds {', '.join(map(str, summary['seeds']))}",
        "",
        "Novel-state PSNR (dB), mean +- standard deviation over the seeds; the last columns: the mean PSNR / SSIM / "
        "mask IoU over every scene-seed and the worst scene-seed.",
        "",
        "| method | " + " | ".join(scenes) + " | **mean** | worst |",
        "| --- |" + " --- |" * (len(scenes) + 2),
    ]
    for m, r in summary["methods"].items():
        cells = []
        for s in scenes:
            c = r["scenes"].get(s)
            cells.append("-" if c is None else f"{c['psnr']['mean']:.2f} +- {c['psnr']['std']:.2f}")
        a, w = r["all"], r["worst"]
        ssim = f" / {a['ssim']['mean']:.3f}" if "ssim" in a else ""
        iou = f" / {a['mask_iou']['mean']:.3f}" if "mask_iou" in a else ""
        cells.append(f"**{a['psnr']['mean']:.2f}{ssim}{iou}** ({r['scene_seeds']} scene-seeds)")
        cells.append(f"{w['psnr']:.2f} ({w['scene']}, seed {w['seed']})")
        lines.append(f"| {labels.get(m, m)} | " + " | ".join(cells) + " |")
    atomic_write_json(out / "seeds.json", dict(summary))
    atomic_write_bytes(out / "seeds.md", ("\n".join(lines) + "\n").encode("utf-8"))


def run_seeds(
    out: str | Path,
    seeds: Sequence[int],
    run_one: Callable[[Path, int], Mapping[str, Any]],
    labels: Mapping[str, str],
) -> dict[str, Any]:
    """``run_one(folder, seed)`` (a suite run returning its table) for each seed, then the summary tables; a
    seed whose ``table.json`` covers the run is still trained again only where the suite itself would."""
    if not seeds or len(set(seeds)) != len(seeds):
        raise ValueError(f"seeds must be distinct and at least one, got {list(seeds)}")
    tables = {int(s): run_one(seed_folder(out, s), int(s)) for s in seeds}
    summary = summarise_seeds(tables)
    write_seed_tables(out, summary, labels)
    return summary
