"""Many envs, shared cores, sizes and cameras: ``python -m benchmarks.env_scaling [--out FILE] [--quick]``.

All on the bundled world with ``obs=("rgb", "mask")`` and one random object moved per env step (as
``benchmarks.env_step``), each rate the median over ``--repeats`` runs; one process, nothing else should run.

Every run of a configuration starts from the same reset and takes the same actions, so runs do the same work;
the reset before them is not timed.

* ``vector``: one env (seed 0, as every one-env figure here); one env playing the 16-env vector env's episodes
  one after the other (the same scenes and actions: the reference of ``vector16_over_one_env_same_episodes``,
  since the per-step work differs from scene to scene); ``DSGWorld-v0``'s own vector env with 4 and 16 envs
  (``vectorization_mode="vector_entry_point"``); ``AsyncVectorEnv`` with 2 single-threaded workers; memory per
  extra env of the vector env (``tracemalloc``: the Python and numpy allocations a 16-env vector env holds after
  stepping, minus a 1-env one's, over 15).
* ``shared``: one env idle, beside a busy learner thread in this process (torch matmuls, as an SB3 update) and
  beside a busy second process (a Python loop), for each thread choice of the renderer: ``auto`` (the default:
  :class:`dsg_gym.splat.threads.ThreadChooser`), ``threads`` (always the threaded kernels) and ``serial``; the
  idle and shared runs alternate repeat by repeat.
* ``breakdown``: where an env step's time goes, 128 px, one camera: microseconds per env step of the whole
  step, the transition (action check, physics proxy, task; ``DSGWorldEnv._transition``) and the observation (the
  render), for one env playing the 16-env vector env's episodes and for the 16-env vector env. The vector env over
  one env if its transitions cost nothing (``vector16_over_one_env_without_transitions``) bounds what batching
  the transitions can give.
* ``sizes``: 64, 128 and 256 px with 1, 2 and 4 capture cameras: one env, one env playing the vector env's
  episodes, one env with the exact merge (``render_settings={"tail_stride": 0}``, no background tail tables), the
  16-env vector env, and MuJoCo's own EGL render (RGB + segmentation of the matching synthetic scene, every
  camera) in the same run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
import tracemalloc

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym  # noqa: E402
import numba  # noqa: E402
import numpy as np  # noqa: E402

import dsg_gym  # noqa: E402,F401  registers DSGWorld-v0

from ._results import default_out, machine_info  # noqa: E402
from .env_step import MujocoRun, _one_object_actions, async_rate  # noqa: E402

TARGETS = {
    "vector16_over_one_env": 1.6,
    "vector16_over_async2": 2.0,
    "memory_per_extra_env_mb": 5.0,
    "beside_learner_thread_over_idle": 0.5,
    "beside_busy_process_over_idle": 0.45,
    "one_env_256px_steps_per_s": 700.0,
    "vector16_over_one_env_256px": 1.6,
    "four_cameras_over_one": 0.3,
}


class Stepper:
    """One env or a vector env of ``n`` envs stepped by one-object moves; ``run(steps)`` returns env steps/s.

    ``episodes`` > 1 (one env only): the env plays the episodes of an ``episodes``-env vector env one after the
    other (episode i from ``reset(seed=seed + i)`` with env i's actions), so it does the vector env's work;
    the resets are not timed."""

    def __init__(self, n: int, size: int, cameras: int = 1, threads: str = "auto", seed: int = 0,
                 tail_stride: int | None = None, episodes: int = 1):  # fmt: skip
        kw = {"width": size, "height": size, "obs": ("rgb", "mask"), "max_episode_steps": 10**6,
              "cameras": list(range(cameras)) if cameras > 1 else 0}  # fmt: skip
        if tail_stride is not None:
            kw["render_settings"] = {"tail_stride": tail_stride}
        if n == 1:
            self.env = gym.make("DSGWorld-v0", **kw)
            self.members = [self.env.unwrapped]
        else:
            self.env = gym.make_vec("DSGWorld-v0", num_envs=n, vectorization_mode="vector_entry_point", **kw)
            self.members = self.env.unwrapped.envs
        self.n, self.k = n, self.members[0].K
        self.episodes = episodes if n == 1 else 1
        self.seed, self._acts = seed, {}
        parallel = {"auto": None, "threads": True, "serial": False}[threads]
        self.members[0].renderer.parallel = parallel  # the vector env's batch renderer follows its base
        self.rates: list[float] = []
        self.run(20, keep=False)

    def _actions(self, steps: int) -> np.ndarray:
        if steps not in self._acts:
            rng = np.random.default_rng(self.seed)
            m = max(self.n, self.episodes)
            a = np.stack([_one_object_actions(rng, steps, self.k) for _ in range(m)], axis=1)
            self._acts[steps] = a[:, 0] if m == 1 else a
        return self._acts[steps]

    def run(self, steps: int, keep: bool = True) -> float:
        """``steps`` steps from the same start with the same actions every time (the same work); the reset
        before them is not timed."""
        acts = self._actions(steps)
        if self.episodes > 1:
            took = 0.0
            for i in range(self.episodes):
                self.env.reset(seed=self.seed + i)
                t0 = time.perf_counter()
                for a in acts[:, i]:
                    self.env.step(a)
                took += time.perf_counter() - t0
            rate = steps * self.episodes / took
        else:
            self.env.reset(seed=self.seed)
            t0 = time.perf_counter()
            for a in acts:
                self.env.step(a)
            rate = steps * self.n / (time.perf_counter() - t0)
        if keep:
            self.rates.append(rate)
        return rate

    def median(self) -> float:
        return float(np.median(self.rates))


def _med(r: Stepper) -> dict:
    return {"env_steps_per_s": round(r.median(), 1), "runs": [round(x, 1) for x in r.rates]}


def vector_section(steps: int, repeats: int, breakdown: dict | None = None) -> dict:
    """Steps/s of one env, the 16 episodes one after the other, the 4- and 16-env vector envs and two async
    workers, and the memory per extra env. With ``breakdown`` (a dict), the breakdown section runs on the same
    two steppers it needs before they close, and fills it."""
    runs = {"one_env": Stepper(1, 128), "one_env_same_episodes": Stepper(1, 128, episodes=16),
            "vector4": Stepper(4, 128), "vector16": Stepper(16, 128)}  # fmt: skip
    for _ in range(repeats):
        for name, r in runs.items():
            r.run(steps if name == "one_env" else max(4, steps // max(r.n, r.episodes)))
    out = {name: _med(r) for name, r in runs.items()}
    if breakdown is not None:
        breakdown.update(breakdown_section(steps, repeats, runs["one_env_same_episodes"], runs["vector16"]))
    out["async2"] = async_rate(128, steps // 2, repeats)
    for r in runs.values():
        r.env.close()
    mem = {}
    for n in (1, 16):
        tracemalloc.start()
        r = Stepper(n, 128)
        r.run(10)
        mem[n] = tracemalloc.get_traced_memory()[0]
        tracemalloc.stop()
        r.env.close()
        del r
    out["memory_per_extra_env_mb"] = round((mem[16] - mem[1]) / 15 / 2**20, 3)
    one = out["one_env"]["env_steps_per_s"]
    out["vector16_over_one_env"] = round(out["vector16"]["env_steps_per_s"] / one, 3)
    out["vector16_over_one_env_same_episodes"] = round(
        out["vector16"]["env_steps_per_s"] / out["one_env_same_episodes"]["env_steps_per_s"], 3
    )
    out["vector16_over_async2"] = round(
        out["vector16"]["env_steps_per_s"] / out["async2"]["env_steps_per_s"], 3
    )
    return out


class _Learner:
    """A busy learner thread in this process, with torch's default threads: Adam updates of SB3's NatureCNN-sized
    network (three convolutions and two linear layers) on batches of 64 RGB images of 64x64."""

    def __init__(self):
        import torch

        self.torch, self.stop, self.iters = torch, threading.Event(), 0
        self.thread = threading.Thread(target=self._loop, daemon=True)

    def _loop(self):
        nn, torch = self.torch.nn, self.torch
        net = nn.Sequential(nn.Conv2d(3, 32, 8, 4), nn.ReLU(), nn.Conv2d(32, 64, 4, 2), nn.ReLU(),
                            nn.Conv2d(64, 64, 3, 1), nn.ReLU(), nn.Flatten(), nn.Linear(1024, 512), nn.ReLU(),
                            nn.Linear(512, 8))  # fmt: skip
        opt = torch.optim.Adam(net.parameters(), lr=1e-4)
        x, y = torch.rand(64, 3, 64, 64), torch.randn(64, 8)
        while not self.stop.is_set():
            loss = ((net(x) - y) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            self.iters += 1

    def __enter__(self):
        self.thread.start()
        time.sleep(0.3)
        return self

    def __exit__(self, *exc):
        self.stop.set()
        self.thread.join()


class _BusyProcess:
    def __enter__(self):
        self.p = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        time.sleep(0.3)
        return self

    def __exit__(self, *exc):
        self.p.kill()
        self.p.wait()


def shared_section(steps: int, repeats: int) -> dict:
    out = {}
    for threads in ("auto", "threads", "serial"):
        r = Stepper(1, 128, threads=threads)
        rates = {"idle": [], "learner_thread": [], "busy_process": []}
        for _ in range(repeats):
            rates["idle"].append(r.run(steps, keep=False))
            with _Learner():
                r.run(10, keep=False)  # the chooser sees the new load
                rates["learner_thread"].append(r.run(steps, keep=False))
            with _BusyProcess():
                r.run(10, keep=False)
                rates["busy_process"].append(r.run(steps, keep=False))
        med = {k: round(float(np.median(v)), 1) for k, v in rates.items()}
        out[threads] = {
            **{f"{k}_steps_per_s": v for k, v in med.items()},
            "learner_thread_over_idle": round(med["learner_thread"] / med["idle"], 3),
            "busy_process_over_idle": round(med["busy_process"] / med["idle"], 3),
            "runs": {k: [round(x, 1) for x in v] for k, v in rates.items()},
        }
        r.env.close()
    idle_best = max(out[t]["idle_steps_per_s"] for t in out)
    out["auto_idle_over_best_idle"] = round(out["auto"]["idle_steps_per_s"] / idle_best, 3)
    return out


class _Timed:
    """A method of one object replaced by itself plus a clock (an instance attribute; the class is untouched).
    The clock stops while ``clock["on"]`` is False."""

    def __init__(self, obj, name: str, clock: dict):
        self.obj, self.name = obj, name
        self.f, self.clock, self.seconds = getattr(obj, name), clock, 0.0
        setattr(obj, name, self)

    def remove(self) -> None:
        """The object's own method again."""
        delattr(self.obj, self.name)

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return self.f(*args, **kwargs)
        finally:
            if self.clock["on"]:
                self.seconds += time.perf_counter() - t0


def breakdown_section(
    steps: int, repeats: int, one: Stepper | None = None, vec: Stepper | None = None
) -> dict:
    """Microseconds per env step of the step, the render and the transitions, for ``one`` (one env playing the
    16 episodes) and ``vec`` (the 16-env vector env); each is made here when not given, and closed only then.
    The timing wrappers are instance attributes, removed again afterwards."""
    out = {}
    given = one is not None, vec is not None
    one = one if one is not None else Stepper(1, 128, episodes=16)
    vec = vec if vec is not None else Stepper(16, 128)
    for (name, r), keep in zip((("one_env_same_episodes", one), ("vector16", vec)), given):
        clock = {"on": True}
        timed = [_Timed(r.env.unwrapped, "_observe", clock)]
        timed += [_Timed(m, "_transition", clock) for m in r.members]
        reset = r.env.reset

        def untimed_reset(*args, _reset=reset, _clock=clock, **kwargs):  # Stepper.run's resets are not timed
            _clock["on"] = False
            try:
                return _reset(*args, **kwargs)
            finally:
                _clock["on"] = True

        r.env.reset = untimed_reset
        runs, n = [], max(2, steps // 16) * 16
        for _ in range(repeats):
            for t in timed:
                t.seconds = 0.0
            rate = r.run(n // 16)
            runs.append({"step_us": 1e6 / rate, "observe_us": 1e6 * timed[0].seconds / n,
                         "transition_us": 1e6 * sum(t.seconds for t in timed[1:]) / n})  # fmt: skip
        out[name] = {k: round(float(np.median([x[k] for x in runs])), 1) for k in runs[0]}
        out[name]["runs"] = [{k: round(v, 1) for k, v in x.items()} for x in runs]
        for t in timed:
            t.remove()
        del r.env.reset
        if not keep:
            r.env.close()
    o, v = out["one_env_same_episodes"], out["vector16"]
    out["vector16_over_one_env"] = round(o["step_us"] / v["step_us"], 3)
    out["vector16_over_one_env_without_transitions"] = round(
        o["step_us"] / (v["step_us"] - v["transition_us"]), 3
    )
    return out


def sizes_section(steps: int, repeats: int, sizes, cameras) -> dict:
    rows = []
    for size in sizes:
        for v in cameras:
            one, exact, vec = Stepper(1, size, v), Stepper(1, size, v, tail_stride=0), Stepper(16, size, v)
            same = Stepper(1, size, v, episodes=16)
            mj = MujocoRun(size, cameras=v)
            for _ in range(repeats):
                one.run(steps)
                exact.run(steps)
                same.run(max(2, steps // 16))
                vec.run(max(2, steps // 16))
                mj.run(max(10, steps // 2))
            rows.append({
                "size": size, "cameras": v,
                "one_env_steps_per_s": round(one.median(), 1),
                "one_env_exact_merge_steps_per_s": round(exact.median(), 1),
                "vector16_env_steps_per_s": round(vec.median(), 1),
                "mujoco_steps_per_s": round(float(np.median(mj.rates)), 1),
                "vector16_over_one_env": round(vec.median() / one.median(), 3),
                "one_env_same_episodes_steps_per_s": round(same.median(), 1),
                "vector16_over_one_env_same_episodes": round(vec.median() / same.median(), 3),
            })  # fmt: skip
            one.env.close()
            exact.env.close()
            same.env.close()
            vec.env.close()
            mj.renderer.close()
            print(json.dumps(rows[-1]), flush=True)
    for row in rows:
        base = next(r for r in rows if r["size"] == row["size"] and r["cameras"] == 1)
        row["over_one_camera"] = round(row["one_env_steps_per_s"] / base["one_env_steps_per_s"], 3)
    return {"rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="JSON file (default: benchmarks/results/env_scaling/<date>-<commit>.json)")
    ap.add_argument(
        "--steps", type=int, default=400, help="one-env steps per repeat (vector envs: as many env steps)"
    )
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sections", default="vector,shared,breakdown,sizes", help="comma-separated subset")
    ap.add_argument("--quick", action="store_true", help="a fast smoke run (few steps, 64 px, 1-2 cameras)")
    args = ap.parse_args(argv)
    args.out = args.out or str(default_out("env_scaling"))
    steps, repeats = (40, 1) if args.quick else (args.steps, args.repeats)
    sections = set(args.sections.split(","))
    result: dict = {"benchmark": "env_scaling", "obs": ["rgb", "mask"], "world": "bundled", "steps": steps,
                    "repeats": repeats, "targets": TARGETS}  # fmt: skip
    if "vector" in sections:  # the breakdown, when asked for too, times the vector section's own steppers
        both = {} if "breakdown" in sections else None
        result["vector"] = vector_section(steps, repeats, breakdown=both)
        print(json.dumps(result["vector"]), flush=True)
        if both is not None:
            result["breakdown"] = both
            print(json.dumps(both), flush=True)
    elif "breakdown" in sections:
        result["breakdown"] = breakdown_section(steps, repeats)
        print(json.dumps(result["breakdown"]), flush=True)
    if "shared" in sections:
        result["shared"] = shared_section(steps, repeats)
        print(json.dumps(result["shared"]), flush=True)
    if "sizes" in sections:
        sizes, cams = ((64,), (1, 2)) if args.quick else ((64, 128, 256), (1, 2, 4))
        result["sizes"] = sizes_section(steps, repeats, sizes, cams)
    result["machine"] = machine_info()
    result["numba"] = {"threading_layer": numba.threading_layer(), "threads": numba.get_num_threads()}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=2)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
