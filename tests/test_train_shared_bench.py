"""benchmarks.train_shared: training step times per mode, alone and beside a busy process or a second training
(started before the measured one, or after it has loaded)."""

from __future__ import annotations

import json

import pytest

from benchmarks.train_shared import SETTINGS, _env, main


def test_train_shared_benchmark_quick(tmp_path):
    out = tmp_path / "shared.json"
    args = ["--out", str(out), "--quick", "--steps", "1", "--rounds", "1", "--threads", "1", "--stagger", "0"]
    assert main([*args, "--modes", "default,spin"]) == 0
    r = json.loads(out.read_text())
    assert [(x["mode"], x["setting"]) for x in r["runs"]] == [
        (m, s) for m in ("default", "spin") for s in SETTINGS
    ]
    assert all(x["joint_ms"] > 0 and x["recon_ms"] > 0 for x in r["runs"])
    for x in r["runs"]:
        key = f"{x['mode']}@1"
        assert r["summary"][key][x["setting"]]["joint_ms"] == x["joint_ms"]
        assert r["speed"][key][x["setting"]] == round(
            r["summary"]["default@1"]["idle"]["joint_ms"] / x["joint_ms"], 3
        )
    assert r["speed"]["default@1"]["idle"] == 1.0
    # each mode's training reports the waiting and thread count it ran with
    default = {x["waiting"] for x in r["runs"] if x["mode"] == "default"}
    spin = {x["waiting"] for x in r["runs"] if x["mode"] == "spin"}
    assert default == {"the OpenMP pool sleeps; torch on 1 thread, numba on 1"} or all(
        "layer is" in w
        for w in default  # a session that forces another numba layer
    )
    assert all("GOMP_SPINCOUNT=300000" in w and "torch on 1 thread" in w for w in spin)


def test_modes_set_only_their_own_variables(monkeypatch):
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")  # what the caller had set never reaches a mode
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    d, t, s = _env("default", 2), _env("torch_threads", 2), _env("spin", 2)
    assert all(e["NUMBA_NUM_THREADS"] == "2" and "OMP_WAIT_POLICY" not in e for e in (d, t, s))
    assert "OMP_NUM_THREADS" not in d and "GOMP_SPINCOUNT" not in d
    assert t["OMP_NUM_THREADS"] == "2" and "GOMP_SPINCOUNT" not in t
    assert s["OMP_NUM_THREADS"] == "2" and s["GOMP_SPINCOUNT"] == "300000"


@pytest.mark.parametrize(
    "bad",
    [
        ["--settings", "crowd"],
        ["--modes", "fast"],
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
