"""``dsg-compact``: compact a world within a PSNR budget; the work is :mod:`train_world.compact.compaction`."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dsg_gym.world import load_world
from train_world.compact import compaction as _lib
from train_world.compact.compaction import CompactConfig, compact_world

# --------------------------------------------------------------------------------------------- CLI
_OPTIONS = (  # (CompactConfig field, type, help); each becomes --field-name
    ("max_psnr_drop", float, "PSNR budget in dB"),
    ("reference_psnr", float, "without --capture: the world's assumed PSNR against ground truth (dB)"),
    ("fraction", float, "keep this fraction of the Gaussians (no budget search)"),
    ("min_weight", float, "invisible below this accumulated weight (pixels) in every plausible view"),
    ("sh_tolerance", float, "largest colour change allowed when dropping SH bands"),
    ("rings", int, "orbit rings of plausible cameras"),
    ("per_ring", int, "cameras per orbit ring"),
    ("object_views", int, "sphere cameras per object"),
    ("step", float, "fraction of the Gaussians removed per round"),
    ("min_fraction", float, "never keep fewer than this fraction"),
    ("neighbours", int, "a removed Gaussian protects this many nearest neighbours for the rest of its round"),
    ("refit_steps", int, "Adam steps of each refit of the survivors to the original renders (0: no refit)"),
    ("refit_cycles", int, "how many times to refit (each followed by more pruning, except the last)"),
    ("validation_views", int, "plausible cameras used for the self-consistency check"),
    ("bisect_steps", int, "bisection steps in the round that breaks the budget"),
)


def _parser() -> argparse.ArgumentParser:
    d = CompactConfig()
    p = argparse.ArgumentParser(
        prog="dsg-compact",
        description=_lib.__doc__.split("\n")[0].split(": ", 1)[1],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("world", type=Path, help="world file to compact")
    p.add_argument("--out", type=Path, required=True, help="compacted world file (written atomically)")
    p.add_argument(
        "--capture", type=Path, help="also measure the drop on this capture's test states (dsg-eval)"
    )
    for name, typ, text in _OPTIONS:
        p.add_argument("--" + name.replace("_", "-"), type=typ, default=getattr(d, name), help=text)
    p.add_argument("--report", type=Path, help="also write the JSON report here")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    return p


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    try:
        cfg = CompactConfig(**{name: getattr(a, name) for name, _, _ in _OPTIONS})
        if not a.world.is_file():
            raise ValueError(f"{a.world}: world file does not exist")
        if a.capture is not None and not (a.capture / "scene.json").is_file():
            raise ValueError(f"{a.capture}: not a capture folder (no scene.json)")
        world = load_world(a.world)
        log = None if a.quiet else (lambda msg: print(f"dsg-compact: {msg}", file=sys.stderr, flush=True))
        out, report = compact_world(world, cfg, capture=a.capture, log=log)
        from dsg_gym.world import write_world

        write_world(a.out, out)
    except (ValueError, OSError) as e:
        print(f"dsg-compact: error: {e}", file=sys.stderr)
        return 2
    report = {
        "input": str(a.world),
        "output": str(a.out),
        "bytes_before": a.world.stat().st_size,
        "bytes_after": a.out.stat().st_size,
        **report,
    }
    text = json.dumps(report, indent=2)
    if a.report is not None:
        from train_world.capture.format import atomic_write_bytes

        atomic_write_bytes(a.report, (text + "\n").encode("utf-8"))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
