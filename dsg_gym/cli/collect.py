"""``dsg-collect``: roll a policy out in vector envs and write a Minari dataset (see ``dsg-collect --help``;
the work is done by :func:`dsg_gym.collect.collect`)."""

from __future__ import annotations

import argparse
import json
import os
import sys

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="dsg-collect",
        description="Roll a policy out in vectorised envs and write a Minari dataset to OUT/<dataset-id> "
        "(OUT is a Minari datasets root: MINARI_DATASETS_PATH=OUT, then minari.load_dataset(ID)). "
        "Nothing is uploaded.",
    )
    p.add_argument("--env", default="DSGWorld-v0", help="Gymnasium env id (default DSGWorld-v0)")
    p.add_argument(
        "--env-kwargs", default="{}", metavar="JSON", help="env kwargs as JSON, e.g. '{\"width\": 64}'"
    )
    p.add_argument("--policy", default="random", help="random | expert | module:callable (obs -> action)")
    p.add_argument("--episodes", type=int, required=True)
    p.add_argument("--num-envs", type=int, default=1, help="envs in the vector env (default 1)")
    p.add_argument(
        "--vectorization",
        choices=("auto", "own", "async"),
        default="auto",
        help="for --num-envs > 1: the env's own vector env in this process when it has one (auto, own: "
        "DSGWorld-v0's batch renderer) or an AsyncVectorEnv of worker processes (async); the same episodes",
    )
    p.add_argument("--out", required=True, help="output root (a Minari datasets folder)")
    p.add_argument("--seed", type=int, default=None, help="base seed (default: random, recorded)")
    p.add_argument("--dataset-id", default=None, help="Minari dataset id (default <env>/<policy>-v0)")
    p.add_argument("--max-episode-steps", type=int, default=None, help="time limit (default: the env's, 200)")
    p.add_argument(
        "--image-encoding",
        choices=("raw", "jpeg"),
        default="raw",
        help="raw: lossless uint8 RGB (default); jpeg: Minari's lossy JPEG frames (smaller)",
    )
    p.add_argument("--resume", action="store_true", help="continue an interrupted run with the same settings")
    p.add_argument("--overwrite", action="store_true", help="discard an unfinished run / replace the dataset")
    p.add_argument("--shard-episodes", type=int, default=16, help="finished episodes per shard (default 16)")
    p.add_argument("--backend", choices=("local", "ray"), default="local")
    p.add_argument("--ray-workers", type=int, default=None, help="Ray tasks (default: CPUs / num-envs)")
    p.add_argument(
        "--ray-address", default=None, help="Ray cluster address (default: start a local instance)"
    )
    p.add_argument("--keep-shards", action="store_true", help="keep the shard datasets after combining")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from dsg_gym.collect.policies import policy_name
    from dsg_gym.collect.rollout import CollectError
    from dsg_gym.collect.run import WORK_DIR, CollectSettingsError, collect, default_dataset_id

    try:
        env_kwargs = json.loads(args.env_kwargs)
    except json.JSONDecodeError as e:
        print(f"dsg-collect: error: --env-kwargs is not valid JSON ({e})", file=sys.stderr)
        return 2
    if not isinstance(env_kwargs, dict):
        print(
            "dsg-collect: error: --env-kwargs must be a JSON object, e.g. '{\"width\": 64}'", file=sys.stderr
        )
        return 2
    dataset_id = args.dataset_id or default_dataset_id(args.env, policy_name(args.policy))
    try:
        res = collect(
            args.out, env_id=args.env, env_kwargs=env_kwargs, policy=args.policy, episodes=args.episodes,
            num_envs=args.num_envs, vectorization=args.vectorization, seed=args.seed, dataset_id=dataset_id,
            max_episode_steps=args.max_episode_steps,
            image_encoding=args.image_encoding, resume=args.resume, overwrite=args.overwrite,
            shard_episodes=args.shard_episodes, backend=args.backend, ray_workers=args.ray_workers,
            ray_address=args.ray_address, keep_shards=args.keep_shards, progress=not args.no_progress,
        )  # fmt: skip
    except CollectSettingsError as e:  # nothing was written
        print(f"dsg-collect: error: {e}", file=sys.stderr)
        return 2
    except CollectError as e:
        print(f"dsg-collect: error: {e}", file=sys.stderr)
        print(f"dsg-collect: finished episodes are kept under {args.out}/{WORK_DIR}/; fix the cause and re-run "
              "with --resume", file=sys.stderr)  # fmt: skip
        return 1
    except KeyboardInterrupt:
        print(f"\ndsg-collect: interrupted; finished episodes are kept under {args.out}/{WORK_DIR}/; re-run "
              "the same command with --resume to continue", file=sys.stderr)  # fmt: skip
        return 130
    print(
        f"dataset {res.dataset_id}: {res.episodes} episodes, {res.transitions} transitions, success rate "
        f"{res.success_rate:.1%}; this run: {res.new_episodes} episodes, {res.new_transitions} transitions in "
        f"{res.seconds:.1f} s ({res.transitions_per_second:.0f} transitions/s overall: env start-up and dataset "
        "writing included)\n"
        f'written to {res.path}\nload: MINARI_DATASETS_PATH={args.out} python -c "import minari; '
        f"print(minari.load_dataset('{res.dataset_id}'))\""
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
