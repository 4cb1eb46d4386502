"""benchmarks.far_shell: suite worlds scored without the shell and with each kind of shell."""

from __future__ import annotations

import json

from _captures import tiny_suite_folder

from benchmarks import far_shell
from dsg_gym.world import load_world


def test_far_shell_scores_without_and_with_each_kind_of_shell(tmp_path):
    run = tmp_path / "run"
    world = tiny_suite_folder(run)
    out = tmp_path / "fs.json"
    assert far_shell.main([str(run), "--shells", "render,mean,mean-sphere", "--out", str(out)]) == 0
    r = json.loads(out.read_text())
    (row,) = r["runs"]
    assert row["scene"] == "two_blocks" and row["shell_gaussians"] > 0
    assert row["with"] == row["with_render"]
    assert set(row) >= {"without", "with_render", "with_mean", "with_mean-sphere"}
    for k in ("without", "with_render", "with_mean", "with_mean-sphere"):
        assert 0 < row[k]["psnr"] < 100
    assert row["with_render"]["psnr"] != row["with_mean"]["psnr"]  # the two colourings differ somewhere
    assert r["summary"]["worlds"] == 1 and "mean_psnr_with_mean" in r["summary"]
    assert r["summary"]["worst_seen_change_db"] is None  # this world records no training views: no coverage
    assert load_world(run / "worlds" / "two_blocks" / "BCP.dsgworld").background.num == world.background.num
    assert far_shell.shell_config("mean-sphere") == far_shell.ShellConfig(colours="mean", floor=False)
    # a kind it does not know: a one-line error, nothing written
    assert far_shell.main([str(run), "--colours", "nearest", "--out", str(tmp_path / "x.json")]) == 2
    assert not (tmp_path / "x.json").exists()
