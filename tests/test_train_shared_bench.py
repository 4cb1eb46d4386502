"""benchmarks.train_shared: training step times alone, beside a busy process and beside a second training."""

from __future__ import annotations

import json

import pytest

from benchmarks.train_shared import main


def test_train_shared_benchmark_quick(tmp_path):
    out = tmp_path / "shared.json"
    args = ["--out", str(out), "--quick", "--steps", "1", "--rounds", "1", "--threads", "1", "--stagger", "0"]
    assert main(args) == 0
    r = json.loads(out.read_text())
    assert [(x["threads"], x["setting"]) for x in r["runs"]] == [(1, "idle"), (1, "busy"), (1, "training")]
    assert all(x["joint_ms"] > 0 and x["recon_ms"] > 0 for x in r["runs"])
    for x in r["runs"]:
        assert r["summary"]["1"][x["setting"]]["joint_ms"] == x["joint_ms"]
        assert r["speed"]["1"][x["setting"]] == round(
            r["summary"]["1"]["idle"]["joint_ms"] / x["joint_ms"], 3
        )
    assert r["speed"]["1"]["idle"] == 1.0


@pytest.mark.parametrize(
    "bad",
    [
        ["--settings", "crowd"],
        ["--threads", "0"],
        ["--threads", "two"],
        ["--steps", "0"],
        ["--checkpoint", "c"],
    ],
)
def test_train_shared_refuses_bad_options(tmp_path, bad, capsys):
    with pytest.raises(SystemExit) as e:
        main(["--out", str(tmp_path / "x.json"), "--quick", *bad])
    assert e.value.code == 2
    assert "error:" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
