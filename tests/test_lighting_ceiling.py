import json

import numpy as np

from benchmarks.lighting_ceiling import lighting_ceiling, main


def test_soft_lighting_raises_the_ceiling_and_cli_writes_json(tmp_path):
    soft = lighting_ceiling("two_blocks", "soft", size=32, test_states=1)
    spot = lighting_ceiling("two_blocks", "spot", size=32, test_states=1)
    for r in (soft, spot):
        assert np.isfinite(r["object_psnr"]) and r["object_psnr"] < r["image_psnr"]
    assert soft["object_psnr"] > spot["object_psnr"] + 6.0  # world-fixed lights are what a moved object loses
    out = tmp_path / "l.json"
    assert main(["--out", str(out), "--lighting", "spot", "--size", "24"]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [r["cameras"] for r in rows] == ["test orbit", "training band"]
    assert all(r["lighting"] == "spot" and r["object_psnr"] > 10 for r in rows)
