"""What the far shell changes at the test states: suite worlds scored as written and with the shell added.

    python -m benchmarks.far_shell RUN [RUN ...] [--methods BCP] [--out FILE]

Each ``RUN`` is a ``dsg-suite`` output folder (``table.json``, ``worlds/<scene>/<method>.dsgworld``,
``data/<scene>``) whose worlds were written without the shell (``dsg-train --no-shell``, or before it was
added). Per scene and method the world is scored at every test state as it is and with
:func:`train_world.complete.shell.with_background_shell` (what ``dsg-train`` writes from the same training),
with ``dsg-eval``'s region split (``error_by_region``): PSNR over all pixels, over the pixels some training view
saw (``psnr_seen``) and over those none saw (``unseen``). ``--shells render,mean,render-sphere`` scores each
kind of shell: coloured by the world's render or by the mean colour (``ShellConfig.colours``), ``-sphere``
without the floor (``ShellConfig(floor=False)``); the first is ``with``, each also ``with_<kind>``. Writes
``{runs: [{run, seed, scene, method, shell_gaussians, without: {...}, with: {...}, with_render: {...}, ...}],
summary}`` to ``benchmarks/results/far_shell/<date>-<commit>.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

from train_world.complete.shell import ShellConfig

from ._results import default_out, write_result


def _scores(report: dict[str, Any]) -> dict[str, Any]:
    regions = report.get("error_by_region") or {}
    unseen = (regions.get("regions") or {}).get("unseen") or {}
    return {
        **{k: report["mean"].get(k) for k in ("psnr", "ssim", "mask_iou")},
        "psnr_seen": regions.get("mean_psnr_seen"),
        "unseen_pixel_share": unseen.get("pixel_share"),
        "unseen_psnr": unseen.get("psnr"),
        "unseen_error_share": unseen.get("error_share"),
    }


def shell_config(kind: str) -> ShellConfig:
    """The :class:`ShellConfig` of a ``--shells`` kind: ``render`` or ``mean``, ``-sphere`` for no floor."""
    colours, sphere = (kind[: -len("-sphere")], True) if kind.endswith("-sphere") else (kind, False)
    return ShellConfig(colours=colours, floor=not sphere)


def score_run(
    run: Path, methods: list[str], work: Path, kinds: tuple[str, ...] = ("render",)
) -> list[dict[str, Any]]:
    """The scores of every world of ``methods`` in one suite folder without the shell and with each of
    ``kinds`` (:func:`shell_config`; evaluations under ``work``)."""
    from dsg_gym.world import load_world, write_world
    from train_world.complete.shell import with_background_shell, without_background_shell
    from train_world.eval.evaluate import evaluate_test_states

    table = json.loads((run / "table.json").read_text())
    rows = []
    for scene, runs in table["scenes"].items():
        for m in methods:
            world_path = run / "worlds" / scene / f"{m}.dsgworld"
            if m not in runs or not world_path.is_file():
                continue
            plain = without_background_shell(load_world(world_path))
            name = f"{scene}-{m}-{table.get('seed')}"
            write_world(work / f"{name}-without.dsgworld", plain)
            cap = run / "data" / scene
            without = evaluate_test_states(work / f"{name}-without.dsgworld", cap, work / f"{name}-without")
            row = {"run": str(run), "seed": table.get("seed"), "scene": scene, "method": m,
                   "without": _scores(without)}  # fmt: skip
            for mode in kinds:
                shelled = with_background_shell(plain, shell_config(mode))
                write_world(work / f"{name}-{mode}.dsgworld", shelled)
                scores = _scores(
                    evaluate_test_states(work / f"{name}-{mode}.dsgworld", cap, work / f"{name}-{mode}")
                )
                row.setdefault("shell_gaussians", shelled.metadata["background_shell"]["gaussians"])
                row.setdefault("with", scores)
                row[f"with_{mode}"] = scores
            rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.far_shell",
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("runs", type=Path, nargs="+", help="dsg-suite output folders")
    p.add_argument("--methods", default="BCP", help="comma-separated suite methods (default BCP)")
    p.add_argument(
        "--shells",
        "--colours",
        dest="shells",
        default="render",
        help="comma-separated kinds of shell: render or mean (ShellConfig.colours), each with -sphere for no "
        "floor (default render)",
    )
    p.add_argument(
        "--out", type=Path, help="JSON to write (default: benchmarks/results/far_shell/<date>-<commit>.json)"
    )
    args = p.parse_args(argv)
    methods = [m for m in args.methods.split(",") if m]
    kinds = tuple(c for c in args.shells.split(",") if c)
    try:
        if not kinds:
            raise ValueError("--shells names no kind of shell")
        for c in kinds:
            shell_config(c)  # a bad name fails here, before any evaluation
        with tempfile.TemporaryDirectory() as tmp:
            rows = [r for run in args.runs for r in score_run(run, methods, Path(tmp), kinds)]
    except (OSError, ValueError, KeyError) as e:
        print(f"far_shell: error: {e}", file=sys.stderr)
        return 2
    if not rows:
        print("far_shell: error: no worlds of those methods in those folders", file=sys.stderr)
        return 2
    gains = [r["with"]["psnr"] - r["without"]["psnr"] for r in rows]
    seen_changes = [
        r["with"]["psnr_seen"] - r["without"]["psnr_seen"]
        for r in rows
        if r["with"]["psnr_seen"] is not None and r["without"]["psnr_seen"] is not None
    ]
    summary = {
        "worlds": len(rows),
        "mean_psnr_without": sum(r["without"]["psnr"] for r in rows) / len(rows),
        "mean_psnr_with": sum(r["with"]["psnr"] for r in rows) / len(rows),
        "mean_gain_db": sum(gains) / len(gains),
        "min_gain_db": min(gains),
        "worst_seen_change_db": min(seen_changes, default=None),
        **{f"mean_psnr_with_{c}": sum(r[f"with_{c}"]["psnr"] for r in rows) / len(rows) for c in kinds},
    }  # fmt: skip
    out = args.out or default_out("far_shell")
    write_result(out, {"runs": rows, "summary": summary})
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
