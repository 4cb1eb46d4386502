"""``dsg-import``: bring a real capture (LLFF or nerfstudio ``transforms.json``) into the capture layout; the
work is :mod:`train_world.capture.importers`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from train_world.capture import importers as _lib
from train_world.capture.importers import import_llff, import_transforms


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-import", description=_lib.__doc__.split("\n\n")[0] + " See docs/captures.md."
    )
    sub = p.add_subparsers(dest="kind", required=True)
    a = sub.add_parser("llff", help="LLFF capture: poses_bounds.npy + images[_F]/ (+ masks[_F]/)")
    a.add_argument("src", type=Path, help="LLFF folder")
    a.add_argument("--out", type=Path, required=True, help="output capture folder")
    a.add_argument(
        "--factor", type=int, default=8, help="use images_F/ and masks_F/ (1: images/, masks/); default 8"
    )
    a.add_argument("--threshold", type=int, default=127, help="mask pixels > threshold are the object")
    a.add_argument("--no-masks", action="store_true", help="ignore masks even if present")
    a.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    b = sub.add_parser("transforms", help="nerfstudio/COLMAP-processed capture with transforms.json")
    b.add_argument("src", type=Path, help="folder holding transforms.json (or the file)")
    b.add_argument("--out", type=Path, required=True, help="output capture folder")
    b.add_argument("--masks", type=Path, default=None, help="folder of masks named like the images")
    b.add_argument("--threshold", type=int, default=127, help="mask pixels > threshold are the object")
    b.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if args.kind == "llff":
            out = import_llff(
                args.src, args.out, args.factor, args.threshold, not args.no_masks, args.overwrite
            )
        else:
            out = import_transforms(args.src, args.out, args.masks, args.threshold, args.overwrite)
    except (ValueError, FileExistsError) as e:
        print(f"dsg-import: error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
