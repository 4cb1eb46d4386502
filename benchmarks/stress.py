"""Numerical stress benchmark: ``python -m benchmarks.stress [--quick] [--out FILE]``.

The long versions of ``tests/stress`` (whose helpers it shares: ``tests/stress/_stress_ref.py``,
``tests/_worlds.py``, ``tests/_captures.py``), each section with pass/fail against the stated bounds:

* ``pose_chains``: 1e6 composed random float64 pose increments (4 chains in lockstep) through unrenormalised
  quaternion products (``dsg_gym.poses``), numpy 4x4 products, torch ``dsg_gym.geometry`` quaternions and
  ``se3_compose``; compared with the same increments composed in ``np.longdouble``. Bounds: quaternion norm
  error, orthonormality and error against the reference <= 1e-9.
* ``env_pose_drift``: 1e5 small steps of ``DSGWorld-v0`` (``se3`` and ``delta``; ``collision="ignore"``;
  poses only, nothing rendered) against the exact composition of the same increments. Bound 1e-9.
* ``env_long_run``: 1e5 random valid steps (rgb + mask + depth + poses, ``collision="reject"``, a reset every
  200 steps) on the two-box test world at 48x48, plus a shorter run on the bundled world at 64x64: non-finite
  values counted (bound 0), resident memory (``/proc/self/statm``) before and after. Bound: growth < 64 MiB.
* ``render_extremes``: every extreme renderer case over many seeds: numba float32 vs torch float64 (tolerances
  in ``tolerances``), numba float64 vs torch float64, finiteness of outputs and gradients.
* ``training_faults``: a tiny single-state run with NaN gradients injected at random steps, each stopping with
  ``TrainingDiverged`` and resumed from the last checkpoint; the final world must equal a fault-free run's
  byte for byte. Truncated checkpoints must all be refused.

The JSON (written atomically: :mod:`dsg_gym.io.atomic`) holds the figures, the counts run, timings and
``all_passed``; the exit status is 1 when a check failed. ``--quick`` divides every count by about 100.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
# one threading layer for rendering and training in one process (as the tests do; see tests/conftest.py)
os.environ.setdefault("NUMBA_THREADING_LAYER", "workqueue")

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "tests" / "stress"), str(ROOT / "tests")]

import numpy as np
import torch
from _stress_ref import (
    ALPHA_TOL,
    CASES,
    COLOR_TOL,
    DEPTH_REL_TOL,
    EXTENDED,
    F64_TOL,
    LD,
    env_reference,
    extreme_scene,
    increment_blocks,
    ld_matrices,
    non_finite_entries,
    quat_error,
    random_action,
    render_case,
    render_errors,
    rss_bytes,
)
from tqdm import tqdm

from dsg_gym import geometry as G
from dsg_gym import poses as P

from ._results import default_out, machine_info
from .stress_training import training_faults

POSE_TOL = 1e-9
MEMORY_BOUND_MIB = 64
MIB = 1 << 20
FULL = {
    "chain_steps": 1_000_000,
    "chains": 4,
    "drift_steps": 100_000,
    "env_steps": 100_000,
    "bundled_steps": 10_000,
    "render_seeds": 40,
    "train_steps": 60,
    "train_faults": 3,
}


def _bar(total: int, desc: str, progress: bool):
    return tqdm(
        total=total, desc=desc, disable=not progress, dynamic_ncols=True, mininterval=1.0, leave=False
    )


# ------------------------------------------------------------------------------------------------ pose chains


def _chain(route: str, n: int, chains: int, progress: bool, snapshots=()) -> tuple[object, float, dict]:
    """Compose ``n`` increments per chain along one route; ``(final state, seconds, {step: state})``."""
    eye4 = np.tile(np.eye(4), (chains, 1, 1))
    state = {
        "quat_numpy": np.tile([1.0, 0.0, 0.0, 0.0], (chains, 1)),
        "matrix_numpy": eye4,
        "quat_torch": torch.tensor([[1.0, 0.0, 0.0, 0.0]] * chains, dtype=torch.float64),
        "matrix_torch": torch.from_numpy(eye4.copy()),
        "reference": eye4.astype(LD),
    }[route]
    kept, step = {}, 0
    bar = _bar(n, route, progress)
    t0 = time.perf_counter()
    for dq, dt in increment_blocks(n, chains, seed=0):
        if route == "quat_numpy":
            for d in dq:
                state = P.quat_multiply(d, state)
                step += 1
                if step in snapshots:
                    kept[step] = state
        elif route == "matrix_numpy":
            for d in P.pose7_to_matrix(np.concatenate([dt, dq], -1)):
                state = d @ state
        elif route == "quat_torch":
            for d in torch.from_numpy(dq).unbind(0):
                state = G.quat_multiply(d, state)
        elif route == "matrix_torch":
            for d in G.pose7_to_matrix(torch.from_numpy(np.concatenate([dt, dq], -1))).unbind(0):
                state = G.se3_compose(d, state)
        else:
            for d in ld_matrices(dq, dt):
                state = d @ state
        bar.update(len(dq))
    seconds = time.perf_counter() - t0
    bar.close()
    return state, seconds, kept


def pose_chains(n: int, chains: int, progress: bool) -> dict:
    snaps = {10**k for k in range(2, 8) if 10**k < n}
    ref, t_ref, _ = _chain("reference", n, chains, progress)
    ref = ref.astype(np.float64)
    scale = max(1.0, float(np.abs(ref[:, :3, 3]).max()))
    q, t_q, kept = _chain("quat_numpy", n, chains, progress, snaps)
    m, t_m, _ = _chain("matrix_numpy", n, chains, progress)
    qt, t_qt, _ = _chain("quat_torch", n, chains, progress)
    mt, t_mt, _ = _chain("matrix_torch", n, chains, progress)
    qt, mt = qt.numpy(), mt.numpy()

    def norm_err(x):
        return float(np.abs(np.linalg.norm(x, axis=-1) - 1).max())

    def rigid(x):
        r = x[:, :3, :3]
        return {
            "orthonormality_error": float(np.abs(r.transpose(0, 2, 1) @ r - np.eye(3)).max()),
            "det_error": float(np.abs(np.linalg.det(r) - 1).max()),
            "rotation_vs_reference": float(np.abs(r - ref[:, :3, :3]).max()),
            "translation_vs_reference": float(np.abs(x[:, :3, 3] - ref[:, :3, 3]).max()),
        }

    out = {
        "increments_per_chain": n,
        "chains": chains,
        "translation_scale_m": scale,
        "reference": {"dtype": str(np.dtype(LD)), "extended": EXTENDED, "seconds": t_ref},
        "quat_numpy": {
            "norm_error": norm_err(q),
            "norm_error_at": {str(k): norm_err(v) for k, v in sorted(kept.items())},
            "rotation_vs_reference": float(np.abs(P.quat_to_rotmat(q) - ref[:, :3, :3]).max()),
            "seconds": t_q,
            "us_per_step": 1e6 * t_q / n,
        },
        "matrix_numpy": {**rigid(m), "seconds": t_m, "us_per_step": 1e6 * t_m / n},
        "quat_torch": {
            "norm_error": norm_err(qt),
            "rotation_vs_reference": float(
                np.abs(G.quat_to_rotmat(torch.from_numpy(qt)).numpy() - ref[:, :3, :3]).max()
            ),
            "vs_quat_numpy": quat_error(qt, q),
            "seconds": t_qt,
            "us_per_step": 1e6 * t_qt / n,
        },
        "matrix_torch": {**rigid(mt), "seconds": t_mt, "us_per_step": 1e6 * t_mt / n},
    }
    figures = [out["quat_numpy"]["norm_error"], out["quat_torch"]["norm_error"]]
    figures += [out[r][k] for r in ("quat_numpy", "quat_torch") for k in ("rotation_vs_reference",)]
    for r in ("matrix_numpy", "matrix_torch"):
        figures += [out[r]["orthonormality_error"], out[r]["det_error"], out[r]["rotation_vs_reference"]]
        figures.append(out[r]["translation_vs_reference"] / scale)
    out["max_error"] = max(figures)
    out["bound"] = POSE_TOL
    out["passed"] = bool(EXTENDED and out["max_error"] <= POSE_TOL)
    return out


# ------------------------------------------------------------------------------------------------ env


def _two_box_env(**kw):
    from _worlds import two_box_world

    from dsg_gym.envs.dsg_world import DSGWorldEnv

    return DSGWorldEnv(world=two_box_world(), **kw)


def env_pose_drift(steps: int, progress: bool) -> dict:
    out = {}
    for mode in ("se3", "delta"):
        env = _two_box_env(obs=("poses",), collision="ignore", action_mode=mode)
        env.reset(seed=3)
        rng = np.random.default_rng(4)
        start = env.poses
        ref = (start[:, :3].astype(LD), start[:, 3:].astype(LD))
        at, chunk = {}, max(1, min(1000, steps // 10))
        worst_norm, env_seconds = 0.0, 0.0
        bar = _bar(steps, f"env drift {mode}", progress)
        done = 0
        while done < steps:
            m = min(chunk, steps - done)
            acts = rng.uniform(-1, 1, (m,) + env.action_space.shape).astype(np.float32)
            t0 = time.perf_counter()
            for a in acts:
                env.step(a)
            env_seconds += time.perf_counter() - t0
            ref = env_reference(env, acts, start=ref)
            done += m
            got = env.poses
            worst_norm = max(worst_norm, float(np.abs(np.linalg.norm(got[:, 3:], axis=1) - 1).max()))
            if done in {10**k for k in range(2, 8)} or done == steps:
                at[str(done)] = {
                    "position_error_m": float(np.abs(got[:, :3] - ref[0]).max()),
                    "quaternion_error": quat_error(got[:, 3:], ref[1]),
                }
            bar.update(m)
        bar.close()
        travelled = float(np.abs(env.poses[:, :3] - start[:, :3]).max())
        env.close()
        out[mode] = {
            **at[str(steps)],
            "at": at,
            "quaternion_norm_error": worst_norm,
            "distance_travelled_m": travelled,
            "steps": steps,
            "env_steps_per_s": steps / env_seconds,
        }
    out["max_error"] = max(
        max(out[m]["position_error_m"], out[m]["quaternion_error"]) for m in ("se3", "delta")
    )
    out["bound"] = POSE_TOL
    out["passed"] = bool(EXTENDED and out["max_error"] <= POSE_TOL)
    return out


def env_long_run(steps: int, world: str, progress: bool, warmup: int = 500) -> dict:
    obs_keys = ("rgb", "mask", "depth", "poses")
    if world == "boxes":
        env, size = _two_box_env(width=48, height=48, obs=obs_keys, collision="reject", action_mode="se3"), 48
    else:
        from dsg_gym.envs.dsg_world import DSGWorldEnv

        env, size = DSGWorldEnv(width=64, height=64, obs=obs_keys, collision="reject", action_mode="se3"), 64
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    for _ in range(min(warmup, steps)):
        env.step(random_action(env, rng))
    gc.collect()
    before = rss_bytes()
    samples, bad, first_bad = [], 0, []
    counts = {"resets": 0, "rejected_steps": 0, "successes": 0, "space_checks": 0}
    obs, info = env.reset(seed=1)
    bar = _bar(steps, f"env run {world}", progress)
    t0 = time.perf_counter()
    for i in range(steps):
        obs, reward, terminated, truncated, info = env.step(random_action(env, rng))
        wrong = non_finite_entries(obs, reward, info)
        if i % 1000 == 0:
            counts["space_checks"] += 1
            if obs not in env.observation_space:
                wrong.append("observation outside its space")
        if wrong:
            bad += 1
            if len(first_bad) < 5:
                first_bad.append({"step": i, "entries": wrong})
        counts["rejected_steps"] += int(info["rejected"].any())
        counts["successes"] += int(terminated)
        if terminated or truncated or (i + 1) % 200 == 0:
            obs, info = env.reset(seed=int(rng.integers(1 << 31)))
            counts["resets"] += 1
            if non_finite_entries(obs, 0.0, info):
                bad += 1
        if (i + 1) % max(1, steps // 10) == 0:
            samples.append({"step": i + 1, "rss_mib": rss_bytes() / MIB})
        bar.update(1)
    seconds = time.perf_counter() - t0
    bar.close()
    gc.collect()
    after = rss_bytes()
    env.close()
    growth = (after - before) / MIB
    return {
        "world": "two-box test world (tests/_worlds.py)"
        if world == "boxes"
        else "bundled world (dsg_gym.envs.dsg_world.DEFAULT_WORLD)",
        "size": [size, size],
        "obs": list(obs_keys),
        "steps": steps,
        "warmup_steps": min(warmup, steps),
        "steps_with_non_finite": bad,
        "first_problems": first_bad,
        **counts,
        "rss_before_mib": before / MIB,
        "rss_after_mib": after / MIB,
        "rss_growth_mib": growth,
        "rss_samples": samples,
        "memory_bound_mib": MEMORY_BOUND_MIB,
        "steps_per_s": steps / seconds,
        "seconds": seconds,
        "passed": bool(bad == 0 and growth < MEMORY_BOUND_MIB),
    }


# ------------------------------------------------------------------------------------------------ renderer


def render_extremes(seeds: int, progress: bool) -> dict:
    out, failures = {}, []
    bar = _bar(seeds * len(CASES), "render extremes", progress)
    t0 = time.perf_counter()
    for case in CASES:
        worst32 = {"color": 0.0, "alpha": 0.0, "depth_rel": 0.0}
        worst64 = dict(worst32)
        finite = True
        for seed in range(seeds):
            scene = extreme_scene(case, seed)
            got = render_case(scene, "numba", torch.float32, grad=True)
            ref = render_case(scene, "torch", torch.float64)
            e32 = render_errors(got, ref)
            e64 = render_errors(render_case(scene, "numba", torch.float64), ref)
            ok = bool(torch.isfinite(got[0]).all() and torch.isfinite(got[1]).all())
            ok = ok and all(bool(torch.isfinite(g).all()) for g in got[3].values())
            ok = ok and bool(((got[1] >= 0) & (got[1] <= 1)).all()) and bool((got[0][..., :3] >= 0).all())
            finite = finite and ok
            worst32 = {k: max(v, e32[k]) for k, v in worst32.items()}
            worst64 = {k: max(v, e64[k]) for k, v in worst64.items()}
            within = (
                e32["color"] <= COLOR_TOL and e32["alpha"] <= ALPHA_TOL and e32["depth_rel"] <= DEPTH_REL_TOL
            )
            if not (ok and within and max(e64.values()) <= F64_TOL):
                failures.append({"case": case, "seed": seed, "float32": e32, "float64": e64, "finite": ok})
            bar.update(1)
        out[case] = {"numba_f32_vs_torch_f64": worst32, "numba_f64_vs_torch_f64": worst64, "finite": finite}
    bar.close()
    return {
        "seeds_per_case": seeds,
        "image_size": [40, 32],
        "cases": out,
        "failures": failures[:10],
        "failure_count": len(failures),
        "seconds": time.perf_counter() - t0,
        "passed": not failures,
    }


# ------------------------------------------------------------------------------------------------ training


SECTIONS = ("pose_chains", "env_pose_drift", "env_long_run", "render_extremes", "training_faults")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m benchmarks.stress",
        description="Numerical stress benchmark: long pose compositions, long env runs (NaN/Inf, "
        "memory), extreme renders (float32 vs float64), training under injected faults.",
    )
    ap.add_argument("--out", type=Path, help="JSON file to write (default: "
                                             "benchmarks/results/stress/<date>-<commit>.json)")
    ap.add_argument("--quick", action="store_true", help="about 1/100 of every count (a smoke run)")
    ap.add_argument(
        "--sections", default=",".join(SECTIONS), help=f"comma-separated subset of {','.join(SECTIONS)}"
    )
    for key, value in FULL.items():
        ap.add_argument(f"--{key.replace('_', '-')}", type=int, default=None, help=f"(default {value})")
    ap.add_argument("--no-progress", action="store_true", help="no tqdm progress bars")
    args = ap.parse_args(argv)
    args.out = args.out or default_out("stress")
    sections = [s for s in args.sections.split(",") if s]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        ap.error(f"unknown sections {unknown}; choose from {SECTIONS}")
    counts = {}
    for key, value in FULL.items():
        given = getattr(args, key)
        quick = {"chains": value, "render_seeds": 3, "train_steps": 24, "train_faults": 2}.get(
            key, max(1, value // 100)
        )
        counts[key] = given if given is not None else (quick if args.quick else value)
    progress = not args.no_progress
    result: dict = {
        "benchmark": "stress",
        "quick": args.quick,
        "counts": counts,
        "tolerances": {
            "pose": POSE_TOL,
            "render_numba_f32_vs_torch_f64": {
                "color_abs": COLOR_TOL,
                "alpha_abs": ALPHA_TOL,
                "expected_depth_rel_where_alpha_gt_0.05": DEPTH_REL_TOL,
            },
            "render_numba_f64_vs_torch_f64": F64_TOL,
            "env_memory_growth_mib": MEMORY_BOUND_MIB,
        },
    }
    runs = {
        "pose_chains": lambda: pose_chains(counts["chain_steps"], counts["chains"], progress),
        "env_pose_drift": lambda: env_pose_drift(counts["drift_steps"], progress),
        "env_long_run": lambda: {
            "boxes": env_long_run(counts["env_steps"], "boxes", progress),
            "bundled": env_long_run(counts["bundled_steps"], "bundled", progress),
        },
        "render_extremes": lambda: render_extremes(counts["render_seeds"], progress),
        "training_faults": lambda: training_faults(counts["train_steps"], counts["train_faults"], progress),
    }
    seconds, passed = {}, {}
    for name in sections:
        t0 = time.perf_counter()
        result[name] = runs[name]()
        seconds[name] = time.perf_counter() - t0
        r = result[name]
        passed[name] = bool(r["passed"]) if "passed" in r else all(bool(v["passed"]) for v in r.values())
        print(
            f"stress: {name}: {'passed' if passed[name] else 'FAILED'} in {seconds[name]:.1f} s",
            file=sys.stderr,
        )
    result["passed"] = passed
    result["all_passed"] = all(passed.values())
    result["seconds"] = seconds
    result["machine"] = {
        **machine_info(),
        "torch": torch.__version__,
        "numba_threading_layer": os.environ.get("NUMBA_THREADING_LAYER"),
        "load_average": list(os.getloadavg()),
    }
    from dsg_gym.io.atomic import atomic_write_bytes

    atomic_write_bytes(args.out, (json.dumps(result, indent=2) + "\n").encode())
    print(f"stress: wrote {args.out}; all passed: {result['all_passed']}", file=sys.stderr)
    return 0 if result["all_passed"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
