"""Moved objects against the directions the captures showed them from: interior PSNR at the test states by the
angle to the nearest training direction, in the object's own frame.

    python -m benchmarks.view_coverage RUN [RUN ...] [--methods BCP] [--out FILE]

Each ``RUN`` is a ``dsg-suite`` output folder (``table.json``, ``worlds/<scene>/<method>.dsgworld``,
``data/<scene>``). For every test view and object of every scene the world is rendered as ``dsg-eval`` renders
it, and the object's interior (its pixels in the ``objects`` region of
:func:`train_world.eval.regions.region_masks`: its true mask less the outline) is scored. Beside the score stand the
direction from the object's centre to the camera, in the object's frame at that state (:func:`object_directions`),
and the angle between it and the nearest such direction of any training view of either training state
(:func:`nearest_gap_deg`): zero where a training view saw the object from the same side, large where the object
was moved so that the camera sees it from a side no training view did. The distance to the camera is
compared likewise (its ratio to the nearest training direction's distance).

Writes ``{runs: [{run, seed, scene, method, rows: [{state, view, object, pixels, sq, psnr, gap_deg,
elevation_deg, seen_elevation_deg: [min, max] over the training directions, distance_ratio}], bins, corr_gap_psnr,
corr_distance_psnr}], summary: {bins, corr_gap_psnr, corr_distance_psnr}}`` to
``benchmarks/results/view_coverage/<date>-<commit>.json``. ``bins`` pool the squared error of the rows whose
gap is below 3 degrees, from 3 to 8, and from 8 up (PSNR over the pooled pixels).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from train_world.eval.metrics import psnr_from_mse

from ._results import default_out, write_result

#: upper edges of the gap bins, degrees (the last bin is open)
BIN_EDGES = (3.0, 8.0)


def object_directions(viewmats: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions ``[V,3]`` from the object's origin to each camera centre, in the object's frame, and the
    distances ``[V]``. ``viewmats``: ``[V,4,4]`` world-to-camera; ``pose``: ``[4,4]`` object-to-world."""
    c2w = np.linalg.inv(np.asarray(viewmats, dtype=np.float64))
    pose = np.asarray(pose, dtype=np.float64)
    d = c2w[:, :3, 3] - pose[:3, 3]
    dist = np.linalg.norm(d, axis=1)
    return (d @ pose[:3, :3]) / dist[:, None], dist


def nearest_gap_deg(seen: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For unit directions ``dirs [V,3]``: the angle in degrees to the nearest of the unit directions ``seen
    [M,3]`` and that direction's index."""
    cos = np.clip(np.asarray(dirs, np.float64) @ np.asarray(seen, np.float64).T, -1.0, 1.0)
    j = np.argmax(cos, axis=1)
    return np.degrees(np.arccos(cos[np.arange(len(j)), j])), j


def _bin_name(gap: float) -> str:
    lo = 0.0
    for hi in BIN_EDGES:
        if gap < hi:
            return f"{lo:g}-{hi:g}"
        lo = hi
    return f">={lo:g}"


def pooled_bins(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """PSNR over the pooled interior pixels of the rows in each gap bin (rows carry ``sq`` and ``pixels``)."""
    out: dict[str, dict[str, float]] = {}
    for name in [_bin_name(x) for x in (0.0, *BIN_EDGES)]:
        rs = [r for r in rows if _bin_name(r["gap_deg"]) == name]
        sq, n = sum(r["sq"] for r in rs), sum(3 * r["pixels"] for r in rs)
        out[name] = {
            "views": len(rs),
            "pixels": n // 3,
            "psnr": psnr_from_mse(sq / n) if sq > 0 else None,
        }
    return out


def _corr(a: list[float], b: list[float]) -> float | None:
    return float(np.corrcoef(a, b)[0, 1]) if len(a) > 2 and np.std(a) > 0 and np.std(b) > 0 else None


def score_world(world_path: Path, capture: Path) -> list[dict[str, Any]]:
    """One row per test view and object seen over at least 10 interior pixels."""
    from dsg_gym.world import load_world
    from train_world.capture import load_capture
    from train_world.eval.evaluate import layer_mask, render_gaussians
    from train_world.eval.regions import region_masks

    world = load_world(world_path)
    bg = tuple(world.metadata.get("background", (0.0, 0.0, 0.0)))
    cap = load_capture(capture, load_depth=False, background=bg)
    if cap.object_ids != world.object_ids:
        raise ValueError(f"{capture}: objects {cap.object_ids} differ from the world's {world.object_ids}")
    trained = [s for s, split in cap.splits.items() if split == "train"]
    tests = [s for s, split in cap.splits.items() if split == "test"]
    if not trained or not tests:
        raise ValueError(f"{capture}: needs training and test states (has {dict(cap.splits)})")
    seen = []  # per object: the training directions and distances
    for k in range(world.num_objects):
        parts = [object_directions(cap.states[s].viewmats.numpy(), cap.poses[s][k]) for s in trained]
        seen.append((np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])))
    seen_elev = [
        [float(np.degrees(np.arcsin(np.clip(f(u[:, 2]), -1.0, 1.0)))) for f in (np.min, np.max)]
        for u, _ in seen
    ]
    rows = []
    for s in tests:
        v = cap.states[s]
        poses = np.asarray(cap.poses[s], dtype=np.float64)
        g = world.gaussians(poses=poses)
        vm, Ks = v.viewmats.numpy(), v.Ks.numpy()
        rgb, _ = render_gaussians(g, vm, Ks, v.width, v.height, bg, world.splat_options, layer_mask(world))
        gt, masks = v.images.numpy(), v.masks.numpy()
        interiors = [region_masks(m)["objects"] for m in masks]
        for k, oid in enumerate(world.object_ids):
            dirs, dist = object_directions(vm, poses[k])
            gap, j = nearest_gap_deg(seen[k][0], dirs)
            for i in range(len(gt)):
                inside = interiors[i] & (masks[i] == oid)
                n = int(inside.sum())
                if n < 10:
                    continue
                sq = float(((np.clip(rgb[i][inside], 0.0, 1.0) - gt[i][inside]) ** 2).sum())
                rows.append({
                    "state": s,
                    "view": i,
                    "object": world.object_names[k],
                    "pixels": n,
                    "sq": sq,
                    "psnr": psnr_from_mse(sq / (3 * n)) if sq > 0 else None,
                    "gap_deg": float(gap[i]),
                    "elevation_deg": float(np.degrees(np.arcsin(np.clip(dirs[i, 2], -1.0, 1.0)))),
                    "seen_elevation_deg": seen_elev[k],
                    "distance_ratio": float(dist[i] / seen[k][1][j[i]]),
                })  # fmt: skip
    return rows


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    scored = [r for r in rows if r["psnr"] is not None]
    return {
        "bins": pooled_bins(rows),
        "corr_gap_psnr": _corr([r["gap_deg"] for r in scored], [r["psnr"] for r in scored]),
        "corr_distance_psnr": _corr([r["distance_ratio"] for r in scored], [r["psnr"] for r in scored]),
    }


def run(runs: list[Path], methods: list[str]) -> dict[str, Any]:
    out, every = [], []
    for folder in runs:
        table = json.loads((folder / "table.json").read_text())
        for scene, per_method in table["scenes"].items():
            for m in methods:
                world = folder / "worlds" / scene / f"{m}.dsgworld"
                if m not in per_method or not world.is_file():
                    continue
                rows = score_world(world, folder / "data" / scene)
                every += rows
                out.append({"run": str(folder), "seed": table.get("seed"), "scene": scene, "method": m,
                            "rows": rows, **summarise(rows)})  # fmt: skip
    if not out:
        raise ValueError(f"no world of methods {methods} in {[str(r) for r in runs]}")
    return {"config": {"runs": [str(r) for r in runs], "methods": methods, "bin_edges_deg": list(BIN_EDGES)},
            "runs": out, "summary": summarise(every)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.view_coverage", description=__doc__.split("\n")[0])
    p.add_argument("runs", nargs="+", type=Path, help="dsg-suite output folders")
    p.add_argument("--methods", default="BCP", help="comma-separated methods (default BCP)")
    p.add_argument("--out", type=Path, default=None, help="result JSON (default: benchmarks/results/...)")
    args = p.parse_args(argv)
    try:
        result = run(args.runs, [m for m in args.methods.split(",") if m])
    except (OSError, ValueError, KeyError) as e:
        print(f"view_coverage: error: {e}", file=sys.stderr)
        return 2
    out = args.out or default_out("view_coverage")
    write_result(out, result)
    for r in result["runs"]:
        bins = ", ".join(
            f"{k} deg {b['psnr']:.2f} dB ({b['views']})" for k, b in r["bins"].items() if b["psnr"]
        )
        print(f"{r['scene']} seed {r['seed']} {r['method']}: {bins}; corr(gap, PSNR) {r['corr_gap_psnr']}")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
