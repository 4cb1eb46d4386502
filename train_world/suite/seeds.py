"""The suite over several capture seeds: every scene generated (and trained) once per seed, then per scene and
method the mean, spread and worst case over the seeds.

A user's scene is a new seed every time, so a method is judged by its mean and its worst scene-seed, not by one
seed per scene. ``dsg-suite --seeds 0,1,2`` runs :func:`train_world.suite.runner.run_suite` once per seed into
``OUT/seed-<s>/`` and writes ``OUT/seeds.json`` and ``OUT/seeds.md`` (:func:`summarise_seeds`). Runs made
apart (one scene and seed at a time) join the same way: ``dsg-suite --out OUT --merge A/table.json B/table.json
...`` with tables of more than one seed merges each seed's tables (:func:`merge_by_seed`) and writes both.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["merge_by_seed", "run_seeds", "seed_folder", "summarise_seeds", "write_seed_tables"]

_METRICS = ("psnr", "ssim", "mask_iou")


def seed_folder(out: str | Path, seed: int) -> Path:
    """Where one seed's suite run goes."""
    return Path(out) / f"seed-{int(seed)}"


def _stats(values: list[float]) -> dict[str, float]:
    v = np.asarray(values, np.float64)
    return {"mean": float(v.mean()), "std": float(v.std()), "min": float(v.min()), "max": float(v.max())}


def merge_by_seed(tables: Sequence[Mapping[str, Any]], methods: list[str] | None = None) -> dict[int, dict]:
    """Seed -> one table joined (:func:`train_world.suite.runner.merge_tables`, keeping ``methods``) from the
    ``tables`` (suite ``table.json`` dictionaries, in order) of that seed. Raises ``ValueError`` when a table
    records no seed or when tables differ in a setting other than the seed."""
    from train_world.suite.runner import _SETTINGS, merge_tables

    groups: dict[int, list[dict[str, Any]]] = {}
    for i, t in enumerate(tables):
        seed = t.get("seed")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"table {i} records no seed: merge the table.json files dsg-suite writes")
        for k in _SETTINGS:
            if k != "seed" and t.get(k) != tables[0].get(k):
                raise ValueError(
                    f"table {i} has {k}={t.get(k)!r} but table 0 has {tables[0].get(k)!r}: "
                    "runs with different settings do not share a table"
                )
        groups.setdefault(seed, []).append(dict(t))
    merged = {seed: merge_tables(ts, methods) for seed, ts in sorted(groups.items())}
    first = next(iter(merged.values()))
    for seed, m in merged.items():
        for k in ("two_state_schedule", "holdout_every"):  # what merge_tables checks within one seed
            if m.get(k) != first.get(k):
                raise ValueError(
                    f"seed {seed}'s rows have {k}={m.get(k)!r} but seed {min(merged)}'s have {first.get(k)!r}: "
                    "runs with different settings do not share a table"
                )
    return merged


def _train_cost(rows: list[tuple[str, int, Mapping[str, Any]]]) -> dict[str, Any] | None:
    """The slowest training (``dsg-train`` wall seconds) and the largest peak RSS over scene-seeds whose rows
    record them (``train.wall_seconds``, ``train.peak_rss_mb``); None where none does."""
    timed = [(sc, sd, r["wall_seconds"]) for sc, sd, r in rows if r.get("wall_seconds") is not None]
    rss = [r["peak_rss_mb"] for _, _, r in rows if r.get("peak_rss_mb") is not None]
    if not timed:
        return None
    slow = max(timed, key=lambda c: c[2])
    return {
        "wall_seconds": _stats([c[2] for c in timed]),
        "slowest": {"scene": slow[0], "seed": slow[1], "wall_seconds": float(slow[2])},
        "peak_rss_mb_max": max(rss) if rss else None,
        "scene_seeds": len(timed),
    }


def summarise_seeds(tables: Mapping[int, Mapping[str, Any]]) -> dict[str, Any]:
    """Per method: per scene the mean / std (population, over seeds) / min / max of each metric, the mean over
    every scene-seed, the worst scene-seed by PSNR, and the training cost (``train``: wall-seconds statistics,
    the slowest scene-seed, the largest peak RSS; None where the rows record no times). ``tables``: seed ->
    that seed's ``table.json``."""
    if not tables:
        raise ValueError("no seed tables to summarise")
    methods = list(next(iter(tables.values()))["methods"])
    scenes = sorted({s for t in tables.values() for s in t["scenes"]})
    out: dict[str, Any] = {"seeds": sorted(int(s) for s in tables), "scenes": scenes, "methods": {}}
    for m in methods:
        per_scene: dict[str, Any] = {}
        cells: list[tuple[str, int, dict[str, float]]] = []
        trains: list[tuple[str, int, Mapping[str, Any]]] = []
        for scene in scenes:
            rows = [(seed, t["scenes"][scene][m]["mean"]) for seed, t in sorted(tables.items())
                    if scene in t["scenes"] and m in t["scenes"][scene]]  # fmt: skip
            rows = [(seed, r) for seed, r in rows if r.get("psnr") is not None]
            if not rows:
                continue
            trains += [(scene, seed, tables[seed]["scenes"][scene][m].get("train") or {}) for seed, _ in rows]
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
            "train": _train_cost(trains),
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
    costs = [(m, r["train"]) for m, r in summary["methods"].items() if r.get("train")]
    if costs:
        lines += ["", "| method | mean dsg-train wall | slowest scene-seed | largest peak RSS |",
                  "| --- | --- | --- | --- |"]  # fmt: skip
        for m, c in costs:
            w, sl, rss = c["wall_seconds"], c["slowest"], c["peak_rss_mb_max"]
            lines.append(
                f"| {labels.get(m, m)} | {w['mean'] / 60:.1f} min | {sl['wall_seconds'] / 60:.1f} min "
                f"({sl['scene']}, seed {sl['seed']}) | "
                + ("-" if rss is None else f"{rss / 1024:.2f} GiB")
                + " |"
            )
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
