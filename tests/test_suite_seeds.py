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


def _run_table(seed, scene, psnr, wall, rss, **settings):
    train = {"iterations": 4500, "joint_from_step": 3000, "refine_steps": 4000, "holdout_every": 0,
             "wall_seconds": wall, "peak_rss_mb": rss}  # fmt: skip
    t = {"preset": "default", "iterations": None, "mip": None, "max_gaussians": 60000, "synth_args": [],
         "seed": seed, "pseudo_every": None, "align_downscale": None, "two_state_schedule": [4500, 3000, 4000],
         "provenance": {"commit": f"c{seed}{scene}"}, "methods": ["BCP"],
         "scenes": {scene: {"BCP": {"mean": {"psnr": psnr, "ssim": 0.99, "mask_iou": 0.98},
                                    "train": train}}}}  # fmt: skip
    t.update(settings)
    return t


def test_merge_of_separate_scene_seed_runs_writes_each_seed_and_the_summary(tmp_path):
    runs = [
        _run_table(0, "s1", 38.0, 800.0, 1000.0),
        _run_table(1, "s1", 36.0, 1500.0, 1100.0),
        _run_table(0, "s2", 40.0, 700.0, 1200.0),
        _run_table(1, "s2", 39.0, 900.0, 900.0),
    ]
    files = []
    for i, t in enumerate(runs):
        files.append(tmp_path / f"r{i}.json")
        files[-1].write_text(json.dumps(t))
    out = tmp_path / "merged"
    assert suite_main(["--out", str(out), "--merge", *map(str, files)]) == 0
    s = json.loads((out / "seeds.json").read_text())
    b = s["methods"]["BCP"]
    assert s["seeds"] == [0, 1] and b["scene_seeds"] == 4
    assert b["scenes"]["s1"]["psnr"]["mean"] == pytest.approx(37.0)
    assert b["worst"]["scene"] == "s1" and b["worst"]["seed"] == 1
    assert b["train"]["slowest"] == {"scene": "s1", "seed": 1, "wall_seconds": 1500.0}
    assert b["train"]["peak_rss_mb_max"] == 1200.0
    assert b["train"]["wall_seconds"]["mean"] == pytest.approx(975.0)
    md = (out / "seeds.md").read_text()
    assert "25.0 min (s1, seed 1)" in md and "1.17 GiB" in md
    seed1 = json.loads((out / "seed-1" / "table.json").read_text())
    assert seed1["seed"] == 1 and list(seed1["scenes"]) == ["s1", "s2"]
    # a table of another setting, or one without a seed, is refused and nothing is written
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(_run_table(2, "s1", 30.0, 1.0, 1.0, iterations=2000)))
    assert suite_main(["--out", str(tmp_path / "no"), "--merge", str(files[0]), str(bad)]) == 2
    other = _run_table(2, "s1", 30.0, 1.0, 1.0, two_state_schedule=[3000, 1500, 0])
    other["scenes"]["s1"]["BCP"]["train"].update(iterations=3000, joint_from_step=1500, refine_steps=0)
    bad.write_text(json.dumps(other))
    assert suite_main(["--out", str(tmp_path / "no"), "--merge", str(files[0]), str(bad)]) == 2
    bad.write_text(json.dumps({k: v for k, v in runs[1].items() if k != "seed"}))
    assert suite_main(["--out", str(tmp_path / "no"), "--merge", str(files[0]), str(bad)]) == 2
    assert not (tmp_path / "no").exists()


def test_summary_without_training_records_has_no_cost():
    r = summarise_seeds({0: _table(0, {"s1": 38.0})})
    assert r["methods"]["BCP"]["train"] is None
