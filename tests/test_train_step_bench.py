"""benchmarks.train_step: reconstruction and joint step times from initial fields and from a checkpoint."""

from __future__ import annotations

import json

import pytest
from _captures import tiny_capture

from benchmarks.train_step import main
from train_world.cli import train as dual_cli


def _check(r: dict, renders_joint: float) -> None:
    for phase, renders in (("recon", 2.0), ("joint", renders_joint)):
        s = r[phase]
        assert s["steps"] == 2 and s["renders_per_step"] == renders
        assert 0 < s["ms_median"] and abs(s["ms_per_render"] - s["ms_median"] / renders) < 0.01
    assert r["joint_over_recon"] == round(r["joint"]["ms_median"] / r["recon"]["ms_median"], 3)


def test_train_step_benchmark_from_initial_fields_and_from_a_checkpoint(tmp_path):
    out = tmp_path / "step.json"
    assert main(["--out", str(out), "--quick", "--steps", "2", "--warmup", "1", "--profile"]) == 0
    r = json.loads(out.read_text())
    _check(r, 5.0)  # 2 own views + 2 transfers + 2 pseudo-state renders every second step
    assert r["config"]["scene"] == "two_blocks" and r["config"]["checkpoint"] is None
    assert r["profile"] and all(0 <= row["share"] <= 1 for row in r["profile"])
    assert any("composite" in row["function"] for row in r["profile"])
    # trained fields: a checkpoint at the joint phase's start, as dsg-suite's recon.ckpt
    cap = tiny_capture(tmp_path, size=24, views=8)
    ckpt = tmp_path / "recon.ckpt"
    assert (
        dual_cli.main_two_state(
            [
                str(cap),
                "--out",
                str(tmp_path / "w.dsgworld"),
                "--preset",
                "quick",
                "--iterations",
                "20",
                "--stop-at-joint",
                "--checkpoint",
                str(ckpt),
                "--quiet",
            ]
        )
        == 0
    )
    out2 = tmp_path / "step2.json"
    assert (
        main(
            [
                "--out",
                str(out2),
                "--quick",
                "--iterations",
                "20",
                "--capture",
                str(cap),
                "--checkpoint",
                str(ckpt),
                "--steps",
                "2",
                "--warmup",
                "1",
            ]
        )
        == 0
    )
    r2 = json.loads(out2.read_text())
    _check(r2, 5.0)
    assert r2["config"]["checkpoint"] == str(ckpt) and "profile" not in r2
    # a checkpoint needs its capture; a checkpoint from another step count is refused by the trainer
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x.json"), "--quick", "--checkpoint", str(ckpt)])
    with pytest.raises(ValueError, match="differ in B/C/P and the motion refinement alone"):
        main(["--out", str(tmp_path / "x.json"), "--quick", "--capture", str(cap), "--checkpoint", str(ckpt)])
    assert not (tmp_path / "x.json").exists()
