"""Data collection throughput: ``python -m benchmarks.collect [--out FILE]``.

``dsg_gym.collect.collect`` on the bundled world (128x128, ``obs`` rgb + mask + poses, lossless RGB) with the
``random`` policy and 1 and 2 envs (sync / async with shared memory): rollout rate (transitions/s from the
first step to the last, shards written on the way) and end-to-end rate (including env start-up and the final
combination of the shards). Then the ``expert`` policy on fresh episodes: success rate, episodes without a
single rejected (colliding) move, mean episode length.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np

from dsg_gym.collect import collect
from dsg_gym.collect.episodes import collect_episodes

from ._results import default_out, machine_info


def _settings(policy: str, size: int, steps: int, seed: int) -> dict:
    return {"env_id": "DSGWorld-v0", "env_kwargs": {"width": size, "height": size}, "policy": policy,
            "seed": seed, "max_episode_steps": steps, "dataset_id": "bench/x-v0", "data_format": "hdf5"}  # fmt: skip


def rollout_rate(policy: str, num_envs: int, episodes: int, size: int, steps: int, seed: int = 0) -> dict:
    """Transitions/s from the start of the rollout to its last vector step (env start-up excluded), shards
    written."""
    marks: list[float] = []
    recs: list = []
    with tempfile.TemporaryDirectory() as d:
        stats = collect_episodes(
            _settings(policy, size, steps, seed), range(episodes), Path(d), num_envs=num_envs,
            on_steps=lambda n: marks.append(time.perf_counter()), on_episode=recs.append,
        )  # fmt: skip
    dt = marks[-1] - marks[0]
    # marks[0] is collect_episodes' on_steps(0) at the start of the rollout: every transition is after it
    return {
        "num_envs": num_envs,
        "episodes": stats["episodes"],
        "transitions": stats["transitions"],
        "transitions_per_s": stats["transitions"] / dt if dt > 0 else float("nan"),
        "success_rate": float(np.mean([r.success for r in recs])),
        "collision_free_rate": float(np.mean([not r.infos["collision"].any() for r in recs])),
        "mean_length": float(np.mean([len(r) for r in recs])),
    }


def end_to_end(num_envs: int, episodes: int, size: int, steps: int) -> dict:
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        res = collect(d, env_kwargs={"width": size, "height": size}, policy="random", episodes=episodes,
                      num_envs=num_envs, seed=0, max_episode_steps=steps)  # fmt: skip
        dt = time.perf_counter() - t0
        size_mb = sum(f.stat().st_size for f in Path(res.path).rglob("*") if f.is_file()) / 1e6
    return {"num_envs": num_envs, "transitions": res.transitions, "seconds": dt,
            "transitions_per_s": res.transitions / dt, "dataset_mb": size_mb}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", help="JSON file to write (default: benchmarks/results/collect/<date>-<commit>.json)"
    )
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--episodes", type=int, default=12, help="random-policy episodes per configuration")
    ap.add_argument("--steps", type=int, default=100, help="time limit of the random episodes")
    ap.add_argument("--expert-episodes", type=int, default=100)
    args = ap.parse_args(argv)
    args.out = args.out or str(default_out("collect"))

    result: dict = {
        "machine": machine_info(),
        "config": vars(args),
        "random": [],
        "end_to_end": [],
    }
    for n in (1, 2):
        r = rollout_rate("random", n, args.episodes, args.size, args.steps)
        result["random"].append(r)
        print(f"random, {n} env(s): {r['transitions_per_s']:.0f} transitions/s (rollout + shard writes)")
    for n in (1, 2):
        r = end_to_end(n, args.episodes, args.size, args.steps)
        result["end_to_end"].append(r)
        print(f"end to end, {n} env(s): {r['transitions_per_s']:.0f} transitions/s, {r['dataset_mb']:.1f} MB")
    e = rollout_rate("expert", 2, args.expert_episodes, args.size, 200, seed=1)
    result["expert"] = e
    print(
        f"expert: success {e['success_rate']:.1%}, collision-free {e['collision_free_rate']:.1%}, "
        f"mean length {e['mean_length']:.1f} steps, {e['transitions_per_s']:.0f} transitions/s (2 envs)"
    )
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
