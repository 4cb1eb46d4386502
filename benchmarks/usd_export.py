"""USD export speed: a 50k-Gaussian world to .usdc and .usda.

    python -m benchmarks.usd_export [--repeats 5] [--quick] [--out FILE]

World: 40k background Gaussians + 5 objects x 2k (SH degree 3, 16 identity features, labels),
4 cameras, a table collider; each export also writes a 200-step episode in a second variant.
Writes a JSON list of records ``{format, gaussians, episode_steps, export_s (median), export_s_all,
read_s (median), bytes}``; the target is ``.usdc`` export under 2 s on this 2-core CPU. A last record
(``"world": "bundled"``) exports the bundled world through ``dsg_gym.export.export_world_usd`` (world already
loaded; ``load_s`` is the world file load, ``path_export_s`` load + export from the path as ``dsg-export`` does).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.usd import Episode, UsdCamera, UsdObject, export_stage, read_stage

from ._results import default_out

BACKGROUND = 40_000
OBJECTS = 5
PER_OBJECT = 2_000
SH_DEGREE = 3
FEATURES = 16
EPISODE_STEPS = 200


def _gaussians(rng: np.random.Generator, n: int, spread: float) -> GaussianSet:
    k = (SH_DEGREE + 1) ** 2
    return GaussianSet(
        means=rng.normal(size=(n, 3)) * spread,
        quats=rng.normal(size=(n, 4)),
        scales=rng.uniform(1e-4, 1e-2, (n, 3)),
        opacities=rng.uniform(0, 1, n),
        sh=rng.normal(size=(n, k, 3)) * 0.3,
        features=rng.normal(size=(n, FEATURES)),
        labels=rng.integers(0, OBJECTS + 1, n),
    )


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    pose[:3, 3] = [x, y, 0.04]
    return pose


def make_world(seed: int = 0):
    rng = np.random.default_rng(seed)
    background = _gaussians(rng, BACKGROUND, 0.5)
    objects = [
        UsdObject(f"object_{i + 1}", _gaussians(rng, PER_OBJECT, 0.03), _pose(0.1 * i - 0.2, 0.05, 0.4 * i))
        for i in range(OBJECTS)
    ]
    cameras = []
    for i in range(4):
        a = 2 * np.pi * i / 4
        eye = np.array([0.8 * np.cos(a), 0.8 * np.sin(a), 0.5])
        z = -eye / np.linalg.norm(eye)
        x = np.cross(z, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        r = np.stack([x, np.cross(z, x), z])
        view = np.eye(4)
        view[:3, :3], view[:3, 3] = r, -r @ eye
        K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])  # noqa: N806
        cameras.append(UsdCamera(f"cam_{i}", view, K, 320, 240))
    t = np.linspace(0, 1, EPISODE_STEPS)
    poses = np.stack(
        [[_pose(0.1 * i - 0.2 + 0.1 * tt, 0.05, 0.4 * i + 3 * tt) for i in range(OBJECTS)] for tt in t]
    )
    episode = Episode(30.0, poses, rewards=np.zeros(EPISODE_STEPS - 1))
    return background, objects, cameras, episode


def run(repeats: int) -> list[dict]:
    background, objects, cameras, episode = make_world()
    n = background.num + sum(o.gaussians.num for o in objects)
    table = [[-0.6, -0.6, 0.0], [0.6, 0.6, 0.0]]
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for suffix in (".usdc", ".usda"):
            for ep in (None, episode):
                path = Path(tmp) / f"world{suffix}"
                reps = repeats if suffix == ".usdc" else max(1, repeats // 2)
                times, read_times = [], []
                for _ in range(reps):
                    t0 = time.perf_counter()
                    export_stage(path, background, objects, cameras, episode=ep, table_bounds=table)
                    times.append(time.perf_counter() - t0)
                    t0 = time.perf_counter()
                    read_stage(path)
                    read_times.append(time.perf_counter() - t0)
                records.append(
                    {
                        "format": suffix[1:],
                        "gaussians": n,
                        "objects": len(objects),
                        "sh_degree": SH_DEGREE,
                        "features": FEATURES,
                        "episode_steps": 0 if ep is None else ep.num_steps,
                        "export_s": round(statistics.median(times), 4),
                        "export_s_all": [round(t, 4) for t in times],
                        "read_s": round(statistics.median(read_times), 4),
                        "bytes": os.path.getsize(path),
                    }
                )
                print(json.dumps(records[-1]), flush=True)
    return records


def run_bundled(repeats: int) -> dict:
    """The bundled world exported with ``export_world_usd`` (objects at state1, cameras, table)."""
    from dsg_gym.envs.dsg_world import DEFAULT_WORLD
    from dsg_gym.export import export_world_usd
    from dsg_gym.world_model import WorldModel

    t0 = time.perf_counter()
    wm = WorldModel.load(DEFAULT_WORLD)
    load_s = time.perf_counter() - t0
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "bundled.usdc"
        times, path_times = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            export_world_usd(wm, path)
            times.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            export_world_usd(DEFAULT_WORLD, path)
            path_times.append(time.perf_counter() - t0)
        record = {
            "world": "bundled",
            "format": "usdc",
            "gaussians": wm.num_gaussians,
            "objects": wm.num_objects,
            "cameras": len(wm.cameras),
            "episode_steps": 0,
            "export_s": round(statistics.median(times), 4),
            "export_s_all": [round(t, 4) for t in times],
            "load_s": round(load_s, 4),
            "path_export_s": round(statistics.median(path_times), 4),
            "bytes": os.path.getsize(path),
        }
    print(json.dumps(record), flush=True)
    return record


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/usd_export/<date>-<commit>.json)",
    )
    parser.add_argument("--repeats", type=int, default=5, help="exports per configuration (median)")
    parser.add_argument("--quick", action="store_true", help="one repeat each")
    args = parser.parse_args(argv)
    args.out = args.out or default_out("usd_export")
    records = run(1 if args.quick else args.repeats)
    records.append(run_bundled(1 if args.quick else args.repeats))
    usdc = [r for r in records if r["format"] == "usdc"]
    summary = {"target_usdc_s": 2.0, "usdc_under_target": all(r["export_s"] < 2.0 for r in usdc)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"records": records, "summary": summary}, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
