"""Camera poses of a real capture from its images alone against the poses it ships with:
``python -m benchmarks.capture_poses --llff DIR [--factor 8] [--features object] [--out FILE]``.

The LLFF capture is imported (``dsg-import llff``), its one state reconstructed by the same structure from motion
as ``dsg-capture`` (:mod:`train_world.capture.pose_check`), and the two pose sets compared after a similarity fit.
For ``../shared/external/ethiopian_head_llff`` (a bronze head on a turntable: the room stays, the head turns) pass
``--features object``.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from ._results import default_out, write_result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--llff", type=Path, required=True, help="LLFF capture folder (poses_bounds.npy, images_N/)"
    )
    ap.add_argument("--factor", type=int, default=8)
    ap.add_argument("--features", default="all", choices=("all", "object", "background"))
    ap.add_argument(
        "--out", help="JSON file (default: benchmarks/results/capture_poses/<date>-<commit>.json)"
    )
    args = ap.parse_args(argv)
    from train_world.capture.importers import import_llff
    from train_world.capture.pose_check import compare_poses, estimate_state_poses

    out = args.out or str(default_out("capture_poses"))
    with tempfile.TemporaryDirectory() as tmp:
        cap = import_llff(args.llff, Path(tmp) / "capture", factor=args.factor)
        est = estimate_state_poses(cap, "state1", Path(tmp) / "work", features=args.features)
        result = {"benchmark": "capture_poses", "capture": args.llff.name, "factor": args.factor,
                  "features": args.features, **compare_poses(est)}  # fmt: skip
    write_result(Path(out), result)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
