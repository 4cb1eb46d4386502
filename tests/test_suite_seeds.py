"""dsg-suite over several capture seeds: mean, spread and worst scene-seed."""

import json

import pytest

from train_world.cli.suite import main as suite_main
from train_world.suite.seeds import run_seeds, summarise_seeds


def _table(seed, values):
    return {
        "methods": ["a", "BCP"],
        "scenes": {
            scene: {m: {"mean": {"psnr": v + (0 if m == "BCP" else -8), "ssim": 0.99, "mask_iou": 0.95}}
                    for m in ("a", "BCP")}
            for scene, v in values.items()
        },
    }  # fmt: skip


def test_summary_means_spread_and_worst():
    tables = {0: _table(0, {"s1": 38.0, "s2": 36.0}), 1: _table(1, {"s1": 40.0, "s2": 35.0})}
    r = summarise_seeds(tables)
    b = r["methods"]["BCP"]
    assert b["scenes"]["s1"]["psnr"] == pytest.approx({"mean": 39.0, "std": 1.0, "min": 38.0, "max": 40.0})
    assert b["all"]["psnr"]["mean"] == pytest.approx(37.25) and b["scene_seeds"] == 4
    assert b["worst"] == {"scene": "s2", "seed": 1, "psnr": 35.0, "ssim": 0.99, "mask_iou": 0.95}
    assert r["methods"]["a"]["worst"]["psnr"] == 27.0
    with pytest.raises(ValueError):
        summarise_seeds({})


def test_run_seeds_runs_each_seed_in_its_folder_and_writes_tables(tmp_path):
    calls = []

    def one(folder, seed):
        calls.append((folder.name, seed))
        return _table(seed, {"s1": 37.0 + seed})

    r = run_seeds(tmp_path, [0, 2], one, {"BCP": "ours"})
    assert r["methods"]["BCP"]["all"]["psnr"]["mean"] == pytest.approx(38.0)
    assert calls == [("seed-0", 0), ("seed-2", 2)]
    md = (tmp_path / "seeds.md").read_text()
    assert "| ours | 38.00 +- 1.00 |" in md and "(s1, seed 0)" in md
    assert json.loads((tmp_path / "seeds.json").read_text())["seeds"] == [0, 2]
    with pytest.raises(ValueError, match="distinct"):
        run_seeds(tmp_path, [1, 1], one, {})


@pytest.mark.parametrize("bad", ["1,x", "1,1", "-1"])
def test_cli_checks_seeds(tmp_path, bad, capsys):
    with pytest.raises(SystemExit):
        suite_main(["--out", str(tmp_path), "--seeds", bad])
    assert "--seeds" in capsys.readouterr().err
