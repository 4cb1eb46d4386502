"""Renderer speed: numba kernels against the PyTorch reference, in the same run.

    python -m benchmarks.render [--quick] [--out FILE]

Writes a JSON list of records ``{backend, n, width, height, channels, forward_ms,
forward_backward_ms, peak_rss_mb}`` (medians over repeats); numba records also carry their
speed-up over the torch record of the same configuration. Each (n, size) runs in its own subprocess so
that peak RSS belongs to that configuration: numba is measured first, then torch in the same
process (torch's peak includes numba's, which is far smaller).

Scene: N Gaussians filling a 60-degree view at depths 2..6 (``benchmarks.splat_scenes``),
19 channels (RGB + 16 identity features), loss = random projection of colours and alphas.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks._results import default_out, write_result

SIZES = (128, 256)
COUNTS = (5_000, 20_000, 100_000)
CHANNELS = 19


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _measure(n: int, size: int, backend: str, repeats: int) -> dict:
    import torch

    from benchmarks.splat_scenes import random_scene
    from dsg_gym.splat import rasterize

    scene = random_scene(n, width=size, height=size, channels=CHANNELS, seed=0)
    g = torch.Generator().manual_seed(1)
    w_out = torch.randn(1, size, size, CHANNELS, generator=g)
    w_alpha = torch.randn(1, size, size, 1, generator=g)

    def forward():
        with torch.no_grad():
            rasterize(**scene, backend=backend)

    def forward_backward():
        leaves = {
            k: scene[k].clone().requires_grad_(True)
            for k in ("means", "quats", "scales", "opacities", "colors")
        }
        out, alpha, _ = rasterize(**{**scene, **leaves}, backend=backend)
        ((out * w_out).sum() + (alpha * w_alpha).sum()).backward()

    def timed(fn):
        fn()  # warm-up (numba compile / caches)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
        return statistics.median(times)

    fwd = timed(forward)
    fwd_bwd = timed(forward_backward)
    return {
        "backend": backend,
        "n": n,
        "width": size,
        "height": size,
        "channels": CHANNELS,
        "forward_ms": round(fwd, 3),
        "forward_backward_ms": round(fwd_bwd, 3),
        "peak_rss_mb": round(_peak_rss_mb(), 1),
        "repeats": repeats,
        "threads": {"torch": torch.get_num_threads(), "numba": _numba_threads()},
        "threading_layer": _threading_layer(),
    }


def _threading_layer() -> str:
    import numba

    return numba.threading_layer()


def _numba_threads() -> int:
    import numba

    return numba.get_num_threads()


def _child(n: int, size: int, repeats_numba: int, repeats_torch: int, out: str) -> None:
    records = [_measure(n, size, "numba", repeats_numba)]
    if repeats_torch > 0:
        records.append(_measure(n, size, "torch", repeats_torch))
    Path(out).write_text(json.dumps(records))


def _torch_repeats(n: int, size: int, quick: bool) -> int:
    work = n * size * size
    if work >= 100_000 * 256 * 256:
        return 1 if not quick else 0
    return 2 if quick else (3 if work >= 100_000 * 128 * 128 else 5)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--out", help="JSON file to write (default: benchmarks/results/render/<date>-<commit>.json)"
    )
    ap.add_argument("--quick", action="store_true", help="fewer repeats, skip torch at the largest size")
    ap.add_argument("--repeats", type=int, default=None, help="numba repeats (default 20, quick 5)")
    ap.add_argument(
        "--threading-layer",
        default="omp",
        choices=["omp", "workqueue"],
        help="numba threading layer (omp: training's; workqueue: the runtime default)",
    )
    args = ap.parse_args(argv)
    args.out = args.out or str(default_out("render"))
    repeats = args.repeats or (5 if args.quick else 20)
    records = []
    for size in SIZES:
        for n in COUNTS:
            with tempfile.TemporaryDirectory() as tmp:
                out = os.path.join(tmp, "r.json")
                cmd = [
                    sys.executable,
                    "-m",
                    "benchmarks.render",
                    "--child",
                    str(n),
                    str(size),
                    str(repeats),
                    str(_torch_repeats(n, size, args.quick)),
                    out,
                ]
                env = {**os.environ, "NUMBA_THREADING_LAYER": args.threading_layer}
                subprocess.run(cmd, check=True, env=env)
                recs = json.loads(Path(out).read_text())
            for r in recs:
                print(
                    f"{r['backend']:6s} n={n:7d} {size}x{size}  fwd {r['forward_ms']:9.2f} ms  "
                    f"fwd+bwd {r['forward_backward_ms']:9.2f} ms  peak {r['peak_rss_mb']:7.1f} MB",
                    flush=True,
                )
            records.extend(recs)
    by = {(r["backend"], r["n"], r["width"]): r for r in records}
    for r in records:
        ref = by.get(("torch", r["n"], r["width"]))
        if r["backend"] == "numba" and ref:
            r["speedup_vs_torch_forward"] = round(ref["forward_ms"] / r["forward_ms"], 2)
            r["speedup_vs_torch_forward_backward"] = round(
                ref["forward_backward_ms"] / r["forward_backward_ms"], 2
            )
    config = {"sizes": list(SIZES), "counts": list(COUNTS), "repeats": repeats, "quick": bool(args.quick),
              "threading_layer": args.threading_layer}  # fmt: skip
    write_result(Path(args.out), {"benchmark": "render", "config": config, "records": records})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        _child(int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5]), sys.argv[6])
    else:
        raise SystemExit(main())
