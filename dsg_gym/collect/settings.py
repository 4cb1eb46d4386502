"""The settings of a collection run, checked before anything is written: the argument values, the dataset id,
the output folder, and one env and the policy built from them. Every failure is a
:class:`~dsg_gym.collect.rollout.CollectSettingsError` with a one-line message."""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from .policies import PolicyError, policy_factory, policy_name
from .rollout import VECTORIZATIONS, CollectSettingsError, make_env
from .writer import IMAGE_ENCODINGS

__all__ = [
    "RUN_FORMAT",
    "RUN_VERSION",
    "check_env_and_policy",
    "check_settings",
    "default_dataset_id",
    "positive",
]

RUN_FORMAT = "dsg-collect-run"
RUN_VERSION = 1
BACKENDS = ("local", "ray")


def _slug(s: str) -> str:
    return re.sub(r"[^-_\w]+", "_", s).strip("_") or "x"


def default_dataset_id(env_id: str, policy: str) -> str:
    """``<env name>/<policy>-v0``, e.g. ``dsgworld/expert-v0`` (lower case, Minari's id syntax)."""
    env = env_id.split(":")[-1].split("/")[-1]
    env = re.sub(r"-v\d+$", "", env).lower()
    pol = policy.split(":")[-1].split(".")[-1] if ":" in policy else policy
    return f"{_slug(env)}/{_slug(pol).lower()}-v0"


def positive(name: str, v) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
        raise CollectSettingsError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


def _one_line(e: BaseException) -> str:
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
    return lines[0] if lines else type(e).__name__


def check_settings(
    out,
    *,
    env_id: str,
    env_kwargs: Mapping[str, Any] | None,
    policy: str | Callable,
    episodes,
    seed,
    dataset_id: str | None,
    max_episode_steps,
    image_encoding: str,
    data_format: str,
    num_envs,
    vectorization: str,
    shard_episodes,
    backend: str,
) -> dict[str, Any]:
    """The run's recorded settings (``run.json``: JSON-safe, ``policy`` as its name, ``seed`` may be ``None``)
    after checking every value; raises :class:`CollectSettingsError` naming the first bad one."""
    episodes = positive("episodes", episodes)
    positive("num_envs", num_envs)
    positive("shard_episodes", shard_episodes)
    if vectorization not in VECTORIZATIONS:
        raise CollectSettingsError(f"vectorization must be one of {VECTORIZATIONS}, got {vectorization!r}")
    if max_episode_steps is not None:
        max_episode_steps = positive("max_episode_steps", max_episode_steps)
    if image_encoding not in IMAGE_ENCODINGS:
        raise CollectSettingsError(f"image_encoding must be one of {IMAGE_ENCODINGS}, got {image_encoding!r}")
    if backend not in BACKENDS:
        raise CollectSettingsError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
        raise CollectSettingsError(f"seed must be an integer >= 0, got {seed!r}")
    if not isinstance(env_kwargs, (Mapping, type(None))):
        raise CollectSettingsError(f"env_kwargs must be a mapping, got {type(env_kwargs).__name__}")
    try:  # JSON-safe: it is recorded and compared on resume
        env_kwargs = json.loads(json.dumps(dict(env_kwargs or {}), allow_nan=False))
    except (TypeError, ValueError) as e:
        raise CollectSettingsError(f"env_kwargs must be JSON-serialisable: {e}") from None
    pname = policy_name(policy)
    dataset_id = dataset_id or default_dataset_id(env_id, pname)
    from minari.dataset.minari_dataset import parse_dataset_id

    try:
        parse_dataset_id(dataset_id)
    except ValueError as e:
        raise CollectSettingsError(f"dataset id {dataset_id!r}: {_one_line(e)}") from None
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CollectSettingsError(f"--out {out} is a file; give a folder (a Minari datasets root)")
    return {
        "format": RUN_FORMAT, "format_version": RUN_VERSION, "env_id": env_id, "env_kwargs": env_kwargs,
        "policy": pname, "seed": None if seed is None else int(seed), "episodes": episodes,
        "max_episode_steps": max_episode_steps, "image_encoding": image_encoding, "data_format": data_format,
        "dataset_id": dataset_id,
    }  # fmt: skip


def check_env_and_policy(env_id: str, env_kwargs: Mapping[str, Any], max_episode_steps, policy) -> None:
    """Build one env from the settings, reset it once and build the policy for it, so that a bad env setting
    (a corrupt world file, a negative size, an unknown kwarg) or an unusable policy is reported before any
    run state exists. Any exception of the env's constructor or reset counts as a bad setting."""
    shown = json.dumps(dict(env_kwargs))
    try:
        env = make_env(env_id, env_kwargs, max_episode_steps)
    except Exception as e:
        raise CollectSettingsError(
            f"cannot make {env_id} with env kwargs {shown}: {_one_line(e)}; fix --env / --env-kwargs"
        ) from e
    try:
        if not isinstance(env.action_space, gym.spaces.Box):
            raise CollectSettingsError(
                f"{env_id}: only Box action spaces can be collected, got {env.action_space}"
            )
        try:
            env.reset(seed=0)
        except Exception as e:
            raise CollectSettingsError(
                f"{env_id} with env kwargs {shown} fails on reset: {_one_line(e)}; fix --env / --env-kwargs"
            ) from e
        try:
            policy_factory(policy, env)
        except PolicyError as e:
            raise CollectSettingsError(_one_line(e)) from e
    finally:
        env.close()
