"""``dsg-suite`` end to end on one tiny scene: baselines, two ablations sharing one reconstruction phase, the
table files and the per-scene grid."""

from __future__ import annotations

import json

import numpy as np

from dsg_gym.world import load_world
from train_world.suite import main as suite_main


def test_suite_runs_baselines_and_shared_phase_ablations(tmp_path):
    out = tmp_path / "suite"
    rc = suite_main(["--out", str(out), "--scenes", "two_blocks", "--methods", "a,b,BC,BCP", "--preset", "quick",
                     "--iterations", "40", "--width", "24", "--height", "24", "--views", "8", "--test-views", "2",
                     "--test-states", "1", "--max-gaussians", "4000", "--mip"])
    assert rc == 0
    table = json.loads((out / "table.json").read_text())
    runs = table["scenes"]["two_blocks"]
    assert set(runs) == {"a", "b", "BC", "BCP"}
    for m, r in runs.items():
        assert np.isfinite(r["mean"]["psnr"]) and 0 < r["mean"]["ssim"] <= 1, (m, r)
        assert set(r["per_state"]) == {"test_0"}
    wdir = out / "worlds" / "two_blocks"
    assert table["mip"] is True  # every world trained (or derived) with the Mip-Splatting filters
    assert all(load_world(wdir / f"{m}.dsgw").splat_options == {"rasterize_mode": "antialiased", "eps2d": 0.1}
               for m in runs)
    # one shared reconstruction phase, recorded in both ablations' training figures
    recon = json.loads((wdir / "recon.json").read_text())
    assert recon["step"] == 20
    for m in ("BC", "BCP"):
        info = runs[m]["train"]
        assert info["recon_phase_seconds"] == recon["wall_seconds"] and info["wall_seconds"] > recon["wall_seconds"]
        assert info["ablation"] == {"BC": "B+C", "BCP": "B+C+P"}[m]
    md = (out / "table.md").read_text()
    assert "ours: B+C+P" in md and "(a) single-state" in md and "**mean**" in md
    assert (out / "grids" / "two_blocks.png").stat().st_size > 0
    # rerunning finds every world and trains nothing: same table
    before = {m: (wdir / f"{m}.dsgw").stat().st_mtime_ns for m in runs}
    assert suite_main(["--out", str(out), "--scenes", "two_blocks", "--methods", "a,b,BC,BCP", "--preset",
                       "quick", "--iterations", "40"]) == 0
    assert {m: (wdir / f"{m}.dsgw").stat().st_mtime_ns for m in runs} == before
    # a training killed after its last checkpoint continues from it: nothing is retrained, same world
    for m in ("a", "BCP"):
        assert (wdir / f"{m}.dsgw.ckpt").is_file()
        data = (wdir / f"{m}.dsgw").read_bytes()
        trained = json.loads((wdir / f"{m}.json").read_text())["train_seconds"]
        (wdir / f"{m}.dsgw").unlink()
        (wdir / f"{m}.json").unlink()
        assert suite_main(["--out", str(out), "--scenes", "two_blocks", "--methods", m, "--preset", "quick",
                           "--iterations", "40", "--max-gaussians", "4000", "--mip"]) == 0
        assert (wdir / f"{m}.dsgw").read_bytes() == data, m
        assert json.loads((wdir / f"{m}.json").read_text())["train_seconds"] == trained, m
