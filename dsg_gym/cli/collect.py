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
        "Nothing is uploaded. One run per dataset at a time (a file lock beside it).",
        epilog="Rates (progress bar and summary): 'rollout N env steps/s' is env steps per second of rollout "
        "time (resets, policy and env steps; start-up and dataset writes excluded); 'overall N episodes/s' is "
        "episodes finished per second since the command started (env start-up and dataset writes included), "
        "the speed at which the dataset grows. Errors: one line 'dsg-collect: error: ...'; exit status 2 when "
        "the run is refused before it starts (nothing changed), 1 when it stops on an error (finished "
        "episodes kept, --resume continues), 130 on Ctrl-C.",
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
    p.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run, or add episodes to a finished dataset (a larger --episodes); the "
        "same settings, and the same episodes as one uninterrupted run",
    )
    p.add_argument("--overwrite", action="store_true", help="discard an unfinished run / replace the dataset")
    p.add_argument("--shard-episodes", type=int, default=16, help="finished episodes per shard (default 16)")
    p.add_argument("--backend", choices=("local", "ray"), default="local")
    p.add_argument("--ray-workers", type=int, default=None, help="Ray tasks (default: CPUs / num-envs)")
    p.add_argument(
        "--ray-address", default=None, help="Ray cluster address (default: start a local instance)"
    )
    p.add_argument("--keep-shards", action="store_true", help="keep the shard datasets after combining")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--video",
        type=int,
        default=0,
        metavar="N",
        help="also write the first N episodes as videos in DATASET/videos/ (MP4 with the video extra, else GIF; "
        "the env's render() frames with the goal drawn as a ghost; needs 'poses' observed)",
    )
    return p


def _error(msg: object) -> None:
    """One line on stderr, argparse's style."""
    print(f"dsg-collect: error: {' '.join(str(msg).split())}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Exit status: 0 done; 2 refused before starting (bad arguments or settings, an existing dataset or
    unfinished run, the dataset locked by another run; nothing changed); 1 stopped by an error after starting
    (finished episodes kept, ``--resume`` continues); 130 Ctrl-C (finished episodes kept)."""
    args = build_parser().parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "egl")
    from dsg_gym.collect.policies import policy_name
    from dsg_gym.collect.rollout import CollectError, CollectSettingsError
    from dsg_gym.collect.run import WORK_DIR, collect
    from dsg_gym.collect.settings import default_dataset_id

    if args.video < 0 or args.video > args.episodes:
        _error(f"--video must be between 0 and --episodes ({args.episodes}), got {args.video}")
        return 2
    try:
        env_kwargs = json.loads(args.env_kwargs)
    except json.JSONDecodeError as e:
        _error(f"--env-kwargs is not valid JSON ({e}); give an object, e.g. '{{\"width\": 64}}'")
        return 2
    if not isinstance(env_kwargs, dict):
        _error("--env-kwargs must be a JSON object, e.g. '{\"width\": 64}'")
        return 2
    dataset_id = args.dataset_id or default_dataset_id(args.env, policy_name(args.policy))
    kept = f"finished episodes are kept under {args.out}/{WORK_DIR}/"
    try:
        res = collect(
            args.out, env_id=args.env, env_kwargs=env_kwargs, policy=args.policy, episodes=args.episodes,
            num_envs=args.num_envs, vectorization=args.vectorization, seed=args.seed, dataset_id=dataset_id,
            max_episode_steps=args.max_episode_steps,
            image_encoding=args.image_encoding, resume=args.resume, overwrite=args.overwrite,
            shard_episodes=args.shard_episodes, backend=args.backend, ray_workers=args.ray_workers,
            ray_address=args.ray_address, keep_shards=args.keep_shards, progress=not args.no_progress,
        )  # fmt: skip
    except CollectSettingsError as e:  # refused before starting: nothing changed
        _error(e)
        return 2
    except CollectError as e:
        _error(f"{e} ({kept}; fix the cause and re-run with --resume)")
        return 1
    except KeyboardInterrupt:
        _error(f"interrupted ({kept}; re-run the same command with --resume to continue)")
        return 130
    except OSError as e:
        _error(f"{e} ({kept}; fix the cause and re-run with --resume)")
        return 1
    except Exception as e:  # anything else still ends in one line
        _error(f"{type(e).__name__}: {e} ({kept}; re-run with --resume)")
        return 1
    print(f"dataset {res.dataset_id}: {res.episodes} episodes, {res.transitions} transitions, success rate "
          f"{res.success_rate:.1%}")  # fmt: skip
    if res.new_episodes:
        print(
            f"this run: {res.new_episodes} episodes, {res.new_transitions} transitions in {res.seconds:.1f} s; "
            f"rollout {res.rollout_steps_per_second:.0f} env steps/s (resets, policy and env steps only); "
            f"overall {res.episodes_per_second:.2f} episodes/s (env start-up and dataset writes included)"
        )
    else:
        print(f"this run: nothing to collect, the dataset already holds all {res.episodes} episodes")
    print(
        f'written to {res.path}\nload: MINARI_DATASETS_PATH={args.out} python -c "import minari; '
        f"print(minari.load_dataset('{res.dataset_id}'))\""
    )
    if args.video:
        from dsg_gym.episode_video import write_dataset_videos

        try:
            paths = write_dataset_videos(res.path, episodes=args.video)
        except (ValueError, OSError, ModuleNotFoundError) as e:
            _error(f"videos: {e} (the dataset is complete)")
            return 1
        print(f"videos: {len(paths)} in {paths[0].parent}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
