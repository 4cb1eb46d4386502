"""benchmarks.omp_waiting: joint step times per OpenMP waiting mode, alone and in staggered pairs."""

from __future__ import annotations

import json

import pytest

from benchmarks.omp_waiting import main


def test_omp_waiting_benchmark_quick(tmp_path):
    out = tmp_path / "wait.json"
    args = ["--out", str(out), "--quick", "--steps", "1", "--rounds", "1", "--stagger", "0"]
    assert main(args) == 0
    r = json.loads(out.read_text())
    assert len(r["runs"]) == 6  # per mode: one alone, two in the pair
    for s in ("alone", "pair"):
        for m in ("auto", "passive"):
            rows = [x for x in r["runs"] if x["setting"] == s and x["mode"] == m]
            assert len(rows) == (1 if s == "alone" else 2)
            assert all(x["joint_ms"] > 0 and x["recon_ms"] > 0 for x in rows)
            assert r["summary"][s][m] == min(x["joint_ms"] for x in rows)
        assert r["auto_over_passive"][s] == round(r["summary"][s]["auto"] / r["summary"][s]["passive"], 3)
    assert all("from the environment" in x["waiting"] for x in r["runs"] if x["mode"] == "passive")
    assert not any("from the environment" in x["waiting"] for x in r["runs"] if x["mode"] == "auto")
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x.json"), "--settings", "alone"])  # neither --quick nor a checkpoint
    with pytest.raises(SystemExit):
        main(["--out", str(tmp_path / "x.json"), "--quick", "--settings", "crowd"])
    assert not (tmp_path / "x.json").exists()
