import json

import numpy as np

from benchmarks.lighting_ceiling import lighting_ceiling, main


def test_soft_lighting_raises_the_ceiling_and_cli_writes_json(tmp_path):
    soft = lighting_ceiling("two_blocks", "soft", size=32, test_states=1)
    spot = lighting_ceiling("two_blocks", "spot", size=32, test_states=1)
    for r in (soft, spot):
        assert np.isfinite(r["object_psnr"]) and r["object_psnr"] < r["image_psnr"]
    assert soft["object_psnr"] > spot["object_psnr"] + 6.0  # world-fixed lights are what a moved object loses
    for r in (soft, spot):  # the objects' pooled error is a pixel-weighted mean of theirs
        assert list(r["per_object"]) == ["red_box", "blue_cylinder"] and r["seed"] == 0
        assert min(r["per_object"].values()) <= r["object_psnr"] <= max(r["per_object"].values())
    out = tmp_path / "l.json"
    assert main(["--out", str(out), "--lighting", "spot", "--size", "24", "--seed", "1"]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["cameras"] for r in rows] == ["test orbit", "training band"]
    assert all(r["lighting"] == "spot" and r["object_psnr"] > 10 and r["seed"] == 1 for r in rows)
