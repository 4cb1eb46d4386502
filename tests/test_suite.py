"""``dsg-suite`` end to end on one tiny scene: baselines, two ablations sharing one reconstruction phase, the
table files and the per-scene grid."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dsg_gym.world import load_world
from train_world.cli.eval import main as ev_main
from train_world.cli.suite import main as suite_main


def test_suite_runs_baselines_and_shared_phase_ablations(tmp_path):
    out = tmp_path / "suite"
    rc = suite_main(
        [
            "--out",
            str(out),
            "--scenes",
            "two_blocks",
            "--methods",
            "a,b,BC,BCP",
            "--preset",
            "quick",
            "--iterations",
            "40",
            "--width",
            "24",
            "--height",
            "24",
            "--views",
            "8",
            "--test-views",
            "2",
            "--test-states",
            "1",
            "--max-gaussians",
            "4000",
            "--mip",
            "--support-weight",
            "0.25",
            "--layers",
        ]
    )
    assert rc == 0
    table = json.loads((out / "table.json").read_text())
    assert table["support_weight"] == 0.25 and table["layers"] is True
    runs = table["scenes"]["two_blocks"]
    assert set(runs) == {"a", "b", "BC", "BCP"}
    for m, r in runs.items():
        assert np.isfinite(r["mean"]["psnr"]) and 0 < r["mean"]["ssim"] <= 1, (m, r)
        assert set(r["per_state"]) == {"test_0"}
    wdir = out / "worlds" / "two_blocks"
    assert table["mip"] is True  # every world trained (or derived) with the Mip-Splatting filters
    assert load_world(wdir / "BCP.dsgworld").metadata["dual"]["support_weight"] == 0.25
    assert (
        load_world(wdir / "BCP.dsgworld").compositing == "layers" and runs["BCP"]["train"]["layers"] is True
    )
    assert load_world(wdir / "a.dsgworld").compositing == "sorted"  # the baselines are not ours
    assert all(
        load_world(wdir / f"{m}.dsgworld").splat_options == {"rasterize_mode": "antialiased", "eps2d": 0.1}
        for m in runs
    )
    # one shared reconstruction phase, recorded in both ablations' training figures
    recon = json.loads((wdir / "recon.json").read_text())
    assert recon["step"] == 20
    for m in ("BC", "BCP"):
        info = runs[m]["train"]
        assert (
            info["recon_phase_seconds"] == recon["wall_seconds"]
            and info["wall_seconds"] > recon["wall_seconds"]
        )
        assert info["ablation"] == {"BC": "B+C", "BCP": "B+C+P"}[m]
        assert (
            [info["iterations"], info["joint_from_step"], info["refine_steps"]]
            == table["two_state_schedule"]
            == [40, recon["step"], 40]
        )  # quick: 40 refinement steps after merging
    # the suite's captures have test states: every training used all views of its states, (b) records (a)'s
    assert {m: r["train"]["holdout_every"] for m, r in runs.items()} == {"a": 0, "b": 0, "BC": 0, "BCP": 0}
    assert runs["BCP"]["train"]["training_views"] == [8, 8] and runs["a"]["train"]["training_views"] == [8]
    md = (out / "table.md").read_text()
    assert "ours: B+C+P" in md and "(a) single-state" in md and "**mean**" in md
    assert (out / "grids" / "two_blocks.png").stat().st_size > 0
    # rerunning with the same settings finds every world and trains nothing: same table
    before = {m: (wdir / f"{m}.dsgworld").stat().st_mtime_ns for m in runs}
    assert (
        suite_main(
            [
                "--out",
                str(out),
                "--scenes",
                "two_blocks",
                "--methods",
                "a,b,BC,BCP",
                "--preset",
                "quick",
                "--iterations",
                "40",
                "--support-weight",
                "0.25",
                "--layers",
            ]
        )
        == 0
    )
    assert {m: (wdir / f"{m}.dsgworld").stat().st_mtime_ns for m in runs} == before
    # without --support-weight the run would put those worlds in a table of the default weight: refused
    from train_world.suite.runner import run_suite

    with pytest.raises(ValueError, match=r"trained with --support-weight 0.25, this run asks for 0.0"):
        run_suite(out, ["two_blocks"], ["BC", "BCP"], preset="quick", iterations=40)
    with pytest.raises(ValueError, match=r"trained with --layers, this run is without it"):
        run_suite(out, ["two_blocks"], ["BC", "BCP"], preset="quick", iterations=40, support_weight=0.25)
    assert {m: (wdir / f"{m}.dsgworld").stat().st_mtime_ns for m in runs} == before
    # a training killed after its last checkpoint continues from it: nothing is retrained, same world
    for m in ("a", "BCP"):
        assert (wdir / f"{m}.dsgworld.ckpt").is_file()
        data = (wdir / f"{m}.dsgworld").read_bytes()
        trained = json.loads((wdir / f"{m}.json").read_text())["train_seconds"]
        (wdir / f"{m}.dsgworld").unlink()
        (wdir / f"{m}.json").unlink()
        assert (
            suite_main(
                [
                    "--out",
                    str(out),
                    "--scenes",
                    "two_blocks",
                    "--methods",
                    m,
                    "--preset",
                    "quick",
                    "--iterations",
                    "40",
                    "--max-gaussians",
                    "4000",
                    "--mip",
                    "--support-weight",
                    "0.25",
                    "--layers",
                ]
            )
            == 0
        )
        assert (wdir / f"{m}.dsgworld").read_bytes() == data, m
        assert json.loads((wdir / f"{m}.json").read_text())["train_seconds"] == trained, m
    # --refine-steps 0: ours without the refinement (the paper's method), recorded in the schedule and the rows
    import shutil

    out0 = tmp_path / "suite0"
    shutil.copytree(out / "data", out0 / "data")  # same capture, nothing regenerated
    assert (
        suite_main(
            [
                "--out",
                str(out0),
                "--scenes",
                "two_blocks",
                "--methods",
                "BCP",
                "--preset",
                "quick",
                "--iterations",
                "40",
                "--max-gaussians",
                "4000",
                "--mip",
                "--refine-steps",
                "0",
            ]
        )
        == 0
    )
    t0 = json.loads((out0 / "table.json").read_text())
    info0 = t0["scenes"]["two_blocks"]["BCP"]["train"]
    assert t0["two_state_schedule"] == [40, 20, 0] and info0["refine_steps"] == 0
    assert (out0 / "worlds" / "two_blocks" / "BCP.dsgworld").read_bytes() != (
        wdir / "BCP.dsgworld"
    ).read_bytes()
    # a rerun into the same folder with the preset's refinement would reuse that unrefined world: refused, with
    # both schedules named, before anything was written
    table_before = (out0 / "table.json").read_bytes()
    with pytest.raises(
        ValueError, match=r"two_blocks/BCP: .*schedule \[40, 20, 0\].*asks for \[40, 20, 40\]"
    ):
        from train_world.suite.runner import run_suite

        run_suite(out0, ["two_blocks"], ["BCP"], preset="quick", iterations=40)
    assert (out0 / "table.json").read_bytes() == table_before
    # the training record holds the joint-phase options; a rerun asking for others is refused the same way
    assert (info0["pseudo_every"], info0["align_downscale"], info0["support_weight"]) == (2, 1, 0.0)
    for option, flag in (
        ({"support_weight": 0.1}, "--support-weight 0.0"),
        ({"align_downscale": 2}, "--align-downscale 1"),
    ):
        with pytest.raises(
            ValueError, match=rf"two_blocks/BCP: .*trained with {flag}, this run asks for .*use another --out"
        ):
            run_suite(out0, ["two_blocks"], ["BCP"], preset="quick", iterations=40, refine_steps=0, **option)
        assert (out0 / "table.json").read_bytes() == table_before
    with pytest.raises(ValueError, match="refine_steps must be a non-negative integer"):
        from train_world.suite.runner import run_suite

        run_suite(tmp_path / "bad", ["two_blocks"], ["BCP"], refine_steps=-1)
    assert not (tmp_path / "bad").exists()  # refused before anything was written


def _run(psnr: float, seconds: float) -> dict:
    return {
        "mean": {"psnr": psnr, "ssim": 0.9, "mask_iou": 0.8},
        "per_state": {},
        "train": {"wall_seconds": seconds},
    }


def _table(scenes: dict, **settings) -> dict:
    base = {
        "preset": "default",
        "iterations": None,
        "mip": None,
        "max_gaussians": 60000,
        "synth_args": [],
        "seed": 0,
        "pseudo_every": None,
        "provenance": {"commit": "abc"},
    }
    base.update(settings)
    methods = sorted({m for runs in scenes.values() for m in runs})
    return {**base, "scenes": scenes, "methods": methods}


def test_merge_joins_partial_runs_later_wins_and_checks_settings(tmp_path):
    t1 = _table(
        {"two_blocks": {"a": _run(30.0, 10), "BCP": _run(36.0, 20)}, "five_small": {"a": _run(32.0, 11)}}
    )
    t2 = _table(
        {"two_blocks": {"BCP": _run(37.0, 21)}, "floor_rug": {"a": _run(24.0, 9), "BCP": _run(34.0, 19)}},
        provenance={"commit": "def"},
    )
    p1, p2 = tmp_path / "r1.json", tmp_path / "r2.json"
    p1.write_text(json.dumps(t1))
    p2.write_text(json.dumps(t2))
    out = tmp_path / "merged"
    assert suite_main(["--out", str(out), "--merge", str(p1), str(p2)]) == 0
    m = json.loads((out / "table.json").read_text())
    assert list(m["scenes"]) == ["five_small", "floor_rug", "two_blocks"]  # the default scenes' order
    assert m["methods"] == ["a", "BCP"]
    assert m["scenes"]["two_blocks"]["BCP"]["mean"]["psnr"] == 37.0  # the later run replaced it
    assert m["scenes"]["two_blocks"]["a"]["mean"]["psnr"] == 30.0  # the earlier run's other method is kept
    assert [p["commit"] for p in m["provenance"]] == ["abc", "def"]
    assert m["mean_over_scenes"]["a"]["psnr"] == np.mean([32.0, 24.0, 30.0])
    md = (out / "table.md").read_text()
    assert (
        "(2 of 3 scenes)" in md and "**35.50 / 0.900 / 0.800** (2 of 3 scenes)" in md
    )  # BCP lacks five_small
    # settings that differ do not share a table; nothing is written
    p3 = tmp_path / "r3.json"
    p3.write_text(json.dumps(_table({"two_blocks": {"a": _run(1.0, 1)}}, iterations=2000)))
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p1), str(p3)]) == 2
    p4 = tmp_path / "r4.json"
    p4.write_text(json.dumps(_table({"two_blocks": {"a": _run(1.0, 1)}}, support_weight=0.1)))
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p1), str(p4)]) == 2
    assert not (tmp_path / "bad").exists()
    # dsg-eval --suite is dsg-suite
    assert ev_main(["--suite", "--out", str(tmp_path / "via_eval"), "--merge", str(p1), str(p2)]) == 0
    assert json.loads((tmp_path / "via_eval" / "table.json").read_text())["scenes"] == m["scenes"]
    # training options beside --merge would be ignored: refused instead
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p1), "--scenes", "two_blocks"]) == 2
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p1), "--no-mip"]) == 2
    assert not (tmp_path / "bad").exists()


def _ours(psnr: float, steps: int, joint: int | None) -> dict:
    r = _run(psnr, 1)
    r["train"].update(
        {"iterations": steps} if joint is None else {"iterations": steps, "joint_from_step": joint}
    )
    return r


def test_merge_refuses_ours_rows_of_different_two_state_schedules(tmp_path):
    from train_world.suite.runner import merge_tables, two_state_schedule

    # a table written before schedules were recorded: its rows say 3000 steps and nothing of the joint phase,
    # which then started at half the steps
    old = _table(
        {
            "two_blocks": {"a": _run(29.0, 1), "B": _ours(35.0, 3000, None), "BCP": _ours(35.5, 3000, None)},
            "five_small": {"a": _run(34.0, 1), "BCP": _ours(38.0, 3000, None)},
        }
    )
    new = _table(
        {"two_blocks": {"BCP": _ours(36.0, 4500, 3000)}, "five_small": {"BCP": _ours(38.5, 4500, 3000)}},
        two_state_schedule=[4500, 3000],
    )
    assert merge_tables([old])["two_state_schedule"] == [3000, 1500, 0]
    with pytest.raises(ValueError, match=r"two-state schedules.*\[3000, 1500, 0\]: two_blocks/B"):
        merge_tables([old, new])  # old B beside new B+C+P
    m = merge_tables([old, new], ["a", "BCP"])  # (a) does not depend on it: old (a) rows join new ones
    assert m["methods"] == ["a", "BCP"] and "B" not in m["scenes"]["two_blocks"]
    assert m["two_state_schedule"] == [4500, 3000, 0]
    assert m["scenes"]["two_blocks"]["BCP"]["mean"]["psnr"] == 36.0 and m["scenes"]["five_small"]["a"]
    partial = _table({"two_blocks": {"BCP": _ours(36.0, 4500, 3000)}}, two_state_schedule=[4500, 3000])
    with pytest.raises(ValueError, match="five_small/BCP"):  # five_small's B+C+P would stay the old run's
        merge_tables([old, partial], ["a", "BCP"])
    # the CLI: --methods picks rows, a mixed table is refused and nothing is written
    p_old, p_new = tmp_path / "old.json", tmp_path / "new.json"
    p_old.write_text(json.dumps(old))
    p_new.write_text(json.dumps(new))
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p_old), str(p_new)]) == 2
    assert not (tmp_path / "bad").exists()
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(p_old), "--methods", "a,X"]) == 2
    assert (
        suite_main(["--out", str(tmp_path / "ok"), "--merge", str(p_old), str(p_new), "--methods", "a,BCP"])
        == 0
    )
    assert json.loads((tmp_path / "ok" / "table.json").read_text())["two_state_schedule"] == [4500, 3000, 0]
    # rows refined after merging (a third schedule entry above 0) do not mix with unrefined ones
    refined = _ours(37.5, 4500, 3000)
    refined["train"]["refine_steps"] = 4000
    with pytest.raises(
        ValueError, match=r"\[4500, 3000, 0\]: five_small/BCP; \[4500, 3000, 4000\]: two_blocks/BCP"
    ):
        merge_tables([new, _table({"two_blocks": {"BCP": refined}}, two_state_schedule=[4500, 3000, 4000])])
    # what a suite run records: the schedule dsg-train resolves from the preset and --iterations
    assert two_state_schedule("default", 2000)[0] == 2000
    d = two_state_schedule("default", None)
    assert d[0] > d[1] > 0 and d[2] == 4000
    assert two_state_schedule("default", None, 0) == [d[0], d[1], 0]


def test_merge_refuses_rows_that_held_out_different_views():
    from train_world.suite.runner import merge_tables

    # rows without holdout_every come from trainings that held out every 8th view (the records do not say);
    # newer rows record theirs (0: every view trained)
    old = _table(
        {
            "two_blocks": {"a": _run(29.0, 1), "BCP": _ours(36.0, 4500, 3000)},
            "five_small": {"a": _run(34.0, 1)},
        },
        two_state_schedule=[4500, 3000],
    )
    new_rows = {m: _ours(p, 4500, 3000) for m, p in (("BCP", 36.2), ("a", 29.1))}
    new_rows["a"]["train"] = {"wall_seconds": 1, "holdout_every": 0}
    new_rows["BCP"]["train"]["holdout_every"] = 0
    new = _table({"two_blocks": new_rows}, two_state_schedule=[4500, 3000])
    assert merge_tables([old])["holdout_every"] == 8 and merge_tables([new])["holdout_every"] == 0
    with pytest.raises(ValueError, match=r"held-out views.*0: two_blocks/a, two_blocks/BCP; 8: five_small/a"):
        merge_tables([old, new])  # five_small's (a) would stay the old run's
    m = merge_tables([old, new], ["BCP"])
    assert m["holdout_every"] == 0 and m["scenes"] == {"two_blocks": {"BCP": new_rows["BCP"]}}


@pytest.mark.parametrize(
    "files",
    [
        ("suite/2026-11-24-3224ca5.json", "suite/2026-11-24-a494dde-ablation.json"),  # with refinement
        (
            "suite/2026-11-24-87b82f9-unrefined.json",
            "suite/2026-11-24-5267b3b-ablation-unrefined.json",
            "suite/2026-11-24-a494dde-ablation-unrefined.json",
        ),  # without (README: "Ablations over ...")
    ],
)
def test_committed_ablation_tables_merge_as_the_readme_says(files):
    """The README's commands that rebuild the seven-scene ablation tables from ``benchmarks/results/`` work: the
    files merge (same settings and schedules), cover every scene with B, B+C and B+C+P, and the mean over the
    seven holds the order the README reports."""
    from pathlib import Path

    from train_world.suite.runner import merge_tables

    root = Path(__file__).resolve().parents[1] / "benchmarks" / "results"
    m = merge_tables([json.loads((root / f).read_text()) for f in files], ["B", "BC", "BCP"])
    assert len(m["scenes"]) == 7 and all(set(r) == {"B", "BC", "BCP"} for r in m["scenes"].values())
    psnr = {k: np.mean([r[k]["mean"]["psnr"] for r in m["scenes"].values()]) for k in ("B", "BC", "BCP")}
    assert psnr["B"] < psnr["BC"] < psnr["BCP"], psnr


def test_committed_main_table_merges():
    """``dsg-suite --merge`` of the committed baselines' table and ours (with refinement) gives the seven-scene
    table of (a), (b) and B+C+P, ours ahead of both baselines on the mean."""
    from pathlib import Path

    from train_world.suite.runner import merge_tables

    root = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "suite"
    files = ("2026-11-24-87b82f9-baselines.json", "2026-11-24-3224ca5.json")
    m = merge_tables([json.loads((root / f).read_text()) for f in files], ["a", "b", "BCP"])
    assert len(m["scenes"]) == 7 and all(set(r) == {"a", "b", "BCP"} for r in m["scenes"].values())
    psnr = {k: np.mean([r[k]["mean"]["psnr"] for r in m["scenes"].values()]) for k in ("a", "b", "BCP")}
    assert psnr["BCP"] > max(psnr["a"], psnr["b"]), psnr


def test_world_file_prefers_the_current_extension_and_reuses_older_runs(tmp_path):
    from train_world.suite.runner import world_file

    assert world_file(tmp_path, "BCP") == tmp_path / "BCP.dsgworld"  # nothing there yet: the current name
    (tmp_path / "BCP.dsgw").write_bytes(b"x")
    assert world_file(tmp_path, "BCP") == tmp_path / "BCP.dsgw"  # an older run's world is reused
    (tmp_path / "BCP.dsgworld").write_bytes(b"y")
    assert world_file(tmp_path, "BCP") == tmp_path / "BCP.dsgworld"


def test_ours_train_with_the_preset_s_support_term_and_layers_unless_given(tmp_path):
    from train_world.suite.records import ours_options, two_state_schedule

    full = two_state_schedule("default", None)
    assert ours_options("default", full, None, None) == (0.1, True)
    assert ours_options("default", full, 0, False) == (0.0, False)
    assert ours_options("default", two_state_schedule("default", None, 0), None, None) == (0.1, False)
    assert ours_options("quick", two_state_schedule("quick", None), None, None) == (0.0, False)
    with pytest.raises(ValueError, match="--layers acts in the refinement"):
        ours_options("default", two_state_schedule("default", None, 0), None, True)
    # a table from before they were recorded (support_weight None, no layers) had neither: it merges with
    # a table that says so, and not with one of the default preset's
    legacy = tmp_path / "legacy.json"
    legacy.write_text(json.dumps(_table({"two_blocks": {"a": _run(1.0, 1)}}, support_weight=None)))
    plain = tmp_path / "plain.json"
    plain.write_text(
        json.dumps(_table({"five_small": {"a": _run(2.0, 1)}}, support_weight=0.0, layers=False))
    )
    both = tmp_path / "both.json"
    both.write_text(json.dumps(_table({"five_small": {"a": _run(2.0, 1)}}, support_weight=0.1, layers=True)))
    assert suite_main(["--out", str(tmp_path / "m"), "--merge", str(legacy), str(plain)]) == 0
    merged = json.loads((tmp_path / "m" / "table.json").read_text())
    assert (merged["support_weight"], merged["layers"]) == (0.0, False)
    assert set(merged["scenes"]) == {"two_blocks", "five_small"}
    assert suite_main(["--out", str(tmp_path / "bad"), "--merge", str(legacy), str(both)]) == 2
    assert not (tmp_path / "bad").exists()
