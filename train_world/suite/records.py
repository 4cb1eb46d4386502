"""What a ``dsg-suite`` folder's training records say: where a method's world file is, which two-state schedule
trained a row, and whether a world found there may be reused by a run with the given settings."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

__all__ = [
    "OURS",
    "LEGACY_HOLDOUT",
    "refuse_mismatched_worlds",
    "row_schedule",
    "two_state_schedule",
    "world_file",
]


def world_file(folder: Path, method: str) -> Path:
    """The world file of ``method`` in a suite's per-scene folder: ``METHOD.dsgworld``, or an existing
    ``METHOD.dsgw`` (the extension of older suite runs, reused as it is)."""
    old = folder / f"{method}.dsgw"
    new = folder / f"{method}.dsgworld"
    return old if old.is_file() and not new.is_file() else new


def two_state_schedule(preset: str, iterations: int | None, refine_steps: int | None = None) -> list[int]:
    """[steps, first joint step, refinement steps] of ``dsg-train``'s two-state run with this preset,
    ``--iterations`` and ``--refine-steps`` (``None``: the preset's)."""
    from train_world.dual_state.trainer import joint_start_step
    from train_world.single_state.presets import scaled_preset

    p = scaled_preset(preset, iterations, two_state=True)
    refine = p.dual_refine_steps if refine_steps is None else int(refine_steps)
    return [p.iterations, joint_start_step(p.dual_joint_from, p.iterations), refine]


def ours_options(
    preset: str, schedule: list[int], support_weight: float | None, layers: bool | None
) -> tuple[float, bool]:
    """The support weight and the layers ours train with: the given ones or (``None``) the preset's. The
    preset's layers are off when ``schedule`` (:func:`two_state_schedule`) has no refinement; asking for layers
    then is a ``ValueError``, as in ``dsg-train``."""
    from train_world.single_state.presets import get_preset

    if layers and schedule[2] == 0:
        raise ValueError("--layers acts in the refinement; this run has none: drop --layers or refine")
    p = get_preset(preset)
    weight = p.dual_support_weight if support_weight is None else float(support_weight)
    return weight, (p.dual_layers if layers is None else bool(layers)) and schedule[2] > 0


OURS = ("B", "BC", "BCP")
# what dsg-train did for tables that do not record their schedule: the joint phase from half the steps, and
# ``default`` trained 3000 two-state steps
_LEGACY_DEFAULT_STEPS = 3000
# and every training (baselines too) of such tables held out every 8th view of each state
LEGACY_HOLDOUT = 8


def row_schedule(row: dict[str, Any], table: dict[str, Any]) -> tuple[int, ...]:
    """(steps, first joint step, refinement steps) that trained one of ours' rows: from its training record,
    else the table's (records and tables without ``refine_steps`` had no refinement: 0); () when neither tells."""
    from train_world.dual_state.trainer import joint_start_step

    train = row.get("train") or {}
    if "iterations" in train:
        steps = int(train["iterations"])
        return (
            steps,
            int(train.get("joint_from_step", joint_start_step(0.5, steps))),
            int(train.get("refine_steps", 0)),
        )
    if table.get("two_state_schedule"):
        return (tuple(table["two_state_schedule"]) + (0,))[:3]
    steps = table.get("iterations") or (_LEGACY_DEFAULT_STEPS if table.get("preset") == "default" else None)
    return () if steps is None else (int(steps), joint_start_step(0.5, int(steps)), 0)


def refuse_mismatched_worlds(out: Path, scenes: list[str], methods: list[str], table: dict[str, Any]) -> None:
    """Before anything runs: raises ``ValueError`` when a world of ours that this run would reuse (its file and
    training record in ``OUT/worlds/<scene>/``) was trained with another two-state schedule than the run's
    (steps, first joint step, refinement steps), or with other joint-phase options (``JOINT_OPTIONS``, where
    its record has them), which would silently mix rows of two methods in one table."""
    from train_world.dual_state.config import JOINT_OPTIONS, DualConfig

    want = tuple(table["two_state_schedule"])
    defaults = {f.name: f.default for f in dataclasses.fields(DualConfig)}
    want_options = {k: defaults[k] if table.get(k) is None else table[k] for k in JOINT_OPTIONS}
    for scene in scenes:
        for m in methods:
            info_path = out / "worlds" / scene / f"{m}.json"
            if (
                m not in OURS
                or not world_file(out / "worlds" / scene, m).is_file()
                or not info_path.is_file()
            ):
                continue
            record = json.loads(info_path.read_text())
            have = row_schedule({"train": record}, table)
            if have and have != want:
                raise ValueError(
                    f"{scene}/{m}: the world in {info_path.parent} was trained with the two-state schedule "
                    f"{list(have)} (steps, first joint step, refinement steps), this run asks for {list(want)}; "
                    "use another --out, or the matching --iterations / --refine-steps"
                )
            for k, v in {**want_options, "layers": bool(table.get("layers"))}.items():
                if k in record and float(record[k]) != float(v):
                    flag = "--" + k.replace("_", "-")
                    if isinstance(v, bool):
                        had = "with" if record[k] else "without"
                        now = "with" if v else "without"
                        raise ValueError(
                            f"{scene}/{m}: the world in {info_path.parent} was trained {had} {flag}, this run is "
                            f"{now} it; use another --out, or run {had} {flag}"
                        )
                    raise ValueError(
                        f"{scene}/{m}: the world in {info_path.parent} was trained with {flag} {record[k]}, "
                        f"this run asks for {v}; use another --out, or {flag} {record[k]}"
                    )
