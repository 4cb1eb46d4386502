"""Environment step throughput: ``python -m benchmarks.env_step [--out FILE]``.

Single ``DSGWorld-v0`` on the bundled world (or ``--world FILE``, e.g. a ``dsg-compact`` output) at 128x128
with ``obs=("rgb", "mask")``, random moves of one object per step (``collision="reject"``), with
incremental and with full rendering (``--env-only``: just these two); MuJoCo's own EGL render
(RGB + segmentation) of the matching synthetic scene at the same size with one object moved per frame; and
an ``AsyncVectorEnv`` (shared memory) with 2 workers. All in one run; rates are medians over repeats
(``--repeats`` of ``--steps`` each; the full-render env takes a quarter of the steps). The incremental env
and MuJoCo alternate repeat by repeat, so their ratio compares runs under the same machine load.
"""

from __future__ import annotations

import argparse
import json
import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

import dsg_gym  # noqa: E402,F401  registers DSGWorld-v0

from ._results import default_out, machine_info  # noqa: E402

TARGET_STEPS = 500.0
TARGET_RATIO = 3.0


def _one_object_actions(rng: np.random.Generator, n: int, k: int, per: int = 4) -> np.ndarray:
    a = np.zeros((n, k * per), np.float32)
    obj = rng.integers(k, size=n)
    for i, o in enumerate(obj):
        a[i, o * per : (o + 1) * per] = rng.uniform(-1, 1, per)
    return a


class EnvRun:
    """A single env stepped by random one-object moves; ``run(steps)`` returns steps/s of one repeat."""

    def __init__(self, incremental: bool, size: int, seed: int = 0, world: str | None = None):
        self.env = gym.make(
            "DSGWorld-v0", world=world, width=size, height=size, obs=("rgb", "mask"), incremental=incremental
        )
        self.k = self.env.unwrapped.K
        self.env.reset(seed=seed)
        self.rng = np.random.default_rng(seed)
        self.rates, self.tiles, self.rejected = [], [], 0
        for a in _one_object_actions(self.rng, 30, self.k):  # warm-up (numba load, caches)
            self.env.step(a)

    def run(self, steps: int) -> float:
        env = self.env
        acts = _one_object_actions(self.rng, steps, self.k)
        t0 = time.perf_counter()
        for a in acts:
            _, _, term, trunc, info = env.step(a)
            self.rejected += int(info["rejected"].any())
            self.tiles.append(env.unwrapped.renderer.last_dirty_tiles)
            if term or trunc:
                env.reset()
        self.rates.append(steps / (time.perf_counter() - t0))
        return self.rates[-1]

    def result(self) -> dict:
        self.env.close()
        return {
            "steps_per_s": float(np.median(self.rates)),
            "runs": [round(r, 1) for r in self.rates],
            "mean_tiles_recomposited": float(np.mean(self.tiles)),
            "rejected_fraction": self.rejected / len(self.tiles),
        }


def env_rate(
    incremental: bool, size: int, steps: int, repeats: int, seed: int = 0, world: str | None = None
) -> dict:
    r = EnvRun(incremental, size, seed, world)
    for _ in range(repeats):
        r.run(steps)
    return r.result()


class MujocoRun:
    """MuJoCo's own EGL render (RGB + segmentation) of the matching synthetic scene from ``cameras`` capture
    cameras, one random object moved by up to 2 cm per frame; ``run(frames)`` returns frames/s of one repeat
    (a frame: every camera rendered once)."""

    def __init__(self, size: int, seed: int = 0, cameras: int = 1):
        import mujoco

        from train_world.synth import resolve_scene
        from train_world.synth.build import build_scene
        from train_world.synth.generate import rng_for
        from train_world.synth.geom_world import capture_cameras
        from train_world.synth.render import SceneRenderer
        from train_world.synth.states import sample_states

        spec = resolve_scene("two_blocks")
        self.built = build_scene(spec, size, size)
        self.data = mujoco.MjData(self.built.model)
        self.poses = sample_states(spec, rng_for(0, "states"), 3)["state1"]
        self.cams = list(capture_cameras(spec, 0, "state1", cameras, size, size)[0])
        self.rng = np.random.default_rng(seed)
        self.renderer = SceneRenderer(self.built, size, size)
        self.rates = []
        for _ in range(10):
            for cam in self.cams:
                self.renderer.render(self.data, cam, rgb=True, seg=True, depth=False)

    def run(self, frames: int) -> float:
        from train_world.synth.build import set_object_poses

        t0 = time.perf_counter()
        for _ in range(frames):
            p = self.poses.copy()
            k = self.rng.integers(len(p))
            p[k, :2, 3] += self.rng.uniform(-0.02, 0.02, 2)
            set_object_poses(self.built, self.data, p)
            for cam in self.cams:
                self.renderer.render(self.data, cam, rgb=True, seg=True, depth=False)
        self.rates.append(frames / (time.perf_counter() - t0))
        return self.rates[-1]

    def result(self) -> dict:
        self.renderer.close()
        return {"frames_per_s": float(np.median(self.rates)), "runs": [round(r, 1) for r in self.rates]}


def async_rate(size: int, steps: int, repeats: int, workers: int = 2, world: str | None = None) -> dict:
    envs = gym.make_vec(
        "DSGWorld-v0",
        world=world,
        num_envs=workers,
        vectorization_mode="async",
        vector_kwargs={"shared_memory": True},
        width=size,
        height=size,
        obs=("rgb", "mask"),
    )
    envs.reset(seed=list(range(workers)))
    k = envs.get_attr("K")[0]
    rng = np.random.default_rng(0)

    def batch():
        return np.stack([_one_object_actions(rng, 1, k)[0] for _ in range(workers)])

    for _ in range(20):
        envs.step(batch())
    rates = []
    for _ in range(repeats):
        acts = [batch() for _ in range(steps)]
        t0 = time.perf_counter()
        for a in acts:
            envs.step(a)
        rates.append(workers * steps / (time.perf_counter() - t0))
    envs.close()
    return {
        "workers": workers,
        "env_steps_per_s": float(np.median(rates)),
        "runs": [round(r, 1) for r in rates],
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", help="JSON file to write (default: benchmarks/results/env_step/<date>-<commit>.json)"
    )
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--steps", type=int, default=600, help="steps (frames) per repeat")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--world", help="world file (default: the bundled world)")
    ap.add_argument("--env-only", action="store_true", help="only the single-env rates (no MuJoCo, no async)")
    args = ap.parse_args(argv)
    args.out = args.out or str(default_out("env_step"))
    # the incremental env and MuJoCo take turns repeat by repeat, so that a change in the machine's load
    # reaches both rates alike
    runs = [EnvRun(True, args.size, world=args.world)] + ([] if args.env_only else [MujocoRun(args.size)])
    for _ in range(args.repeats):
        for r in runs:
            r.run(args.steps)
    inc = runs[0].result()
    mj = runs[1].result() if len(runs) > 1 else None
    full = env_rate(False, args.size, max(1, args.steps // 4), args.repeats, world=args.world)
    vec = None if args.env_only else async_rate(args.size, args.steps // 2, args.repeats, world=args.world)
    ratio = inc["steps_per_s"] / mj["frames_per_s"] if mj else None
    result = {
        "benchmark": "env_step",
        "size": [args.size, args.size],
        "obs": ["rgb", "mask"],
        "world": args.world or "bundled (assets/worlds/two_blocks_dsg.dsgworld)",
        "incremental": inc,
        "full": full,
        "mujoco_egl_rgb_seg": mj,
        "async_vector_env": vec,
        "incremental_over_full": inc["steps_per_s"] / full["steps_per_s"],
        "incremental_over_mujoco": ratio,
        "targets": {
            "incremental_steps_per_s": TARGET_STEPS,
            "incremental_over_mujoco": TARGET_RATIO,
            "met_steps": inc["steps_per_s"] >= TARGET_STEPS,
            "met_ratio": None if ratio is None else ratio >= TARGET_RATIO,
        },
        "machine": machine_info(),
        # the runtime's kernels run on numba's own choice of layer (dsg_gym.splat.threads)
        "numba": {"threading_layer": numba.threading_layer(), "threads": numba.get_num_threads()},
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
