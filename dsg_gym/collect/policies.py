"""Policies for data collection: ``random``, a scripted ``expert`` and any ``module:callable``.

A policy maps **one** (unbatched) observation of the env to one action. Policies may also have a
``reset(seed: int)`` method, called at the start of every episode with that episode's seed (the rollout keeps
one instance per vector-env slot for the built-in policies, so their randomness depends only on the episode).

``expert`` solves the default rearrangement task of ``DSGWorld-v0`` (``action_mode="delta"``) without
collisions by moving the objects in *layers*:

1. **lift**: every object rises straight up to its own layer (object ``k`` at layer ``k``; layer 0 floats
   ``clearance`` above the table, every layer starts ``clearance`` above the top of the one below);
2. **travel**: all objects move in x/y and turn (yaw) towards their goals at once; different layers cannot
   touch, and straight x/y paths between two poses that keep the object's footprint circle on the table keep
   it on the table;
3. **lower**: once every object is above its goal, all descend; the task's goals have disjoint footprints.

Steps are clipped to the env's ``max_translation`` / ``max_rotation``; the last step of each leg lands exactly.
The policy is stateless: the phase follows from the poses in the observation (``poses`` must be observed).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

from ..poses import quat_multiply, quat_to_rotmat

__all__ = ["BUILTIN_POLICIES", "ExpertPolicy", "PolicyError", "RandomPolicy", "policy_factory", "policy_name"]

BUILTIN_POLICIES = ("random", "expert")


class PolicyError(ValueError):
    """A policy cannot be made (unknown name, import failure, unsuitable env)."""


class RandomPolicy:
    """Uniform actions in the (bounded) Box action space; seeded per episode by :meth:`reset`."""

    def __init__(self, action_space: gym.Space, seed: int | None = None):
        if not isinstance(action_space, gym.spaces.Box) or not action_space.is_bounded():
            raise PolicyError(f"random policy needs a bounded Box action space, got {action_space}")
        self.space = action_space
        self.rng = np.random.default_rng(seed)

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, obs) -> np.ndarray:
        s = self.space
        return self.rng.uniform(s.low, s.high).astype(s.dtype)


def _yaw_of(q: np.ndarray) -> np.ndarray:
    """Angle about +z of (near-)yaw rotations ``q`` ``[..., 4]`` (w, x, y, z), in ``(-pi, pi]``."""
    a = 2.0 * np.arctan2(q[..., 3], q[..., 0])
    return (a + np.pi) % (2.0 * np.pi) - np.pi


class ExpertPolicy:
    """Scripted, collision-free solver of the ``DSGWorld-v0`` rearrangement task (see the module docstring).

    Args:
        env: a ``DSGWorld-v0`` env (any wrapper); its collision hulls, table and step sizes are read once.
        clearance: metres between the table and layer 0 and between consecutive layers.
        tolerance: metres / radians under which a leg counts as finished.
    """

    def __init__(self, env: gym.Env, clearance: float = 0.01, tolerance: float = 1e-4):
        u = env.unwrapped
        for attr in ("physics", "world", "max_translation", "max_rotation", "action_mode", "obs_keys"):
            if not hasattr(u, attr):
                raise PolicyError(f"expert policy needs a DSGWorld env, got {type(u).__name__}")
        if u.action_mode != "delta":
            raise PolicyError(f"expert policy needs action_mode='delta', got {u.action_mode!r}")
        if "poses" not in u.obs_keys:
            raise PolicyError("expert policy needs 'poses' in the env's obs")
        self.hulls = [np.asarray(h, dtype=np.float64) for h in u.physics.hulls]
        self.table_z = float(u.world.table.z)
        self.max_t, self.max_r = float(u.max_translation), float(u.max_rotation)
        self.k = len(self.hulls)
        self.clearance, self.tol = float(clearance), float(tolerance)
        self.action_space = env.action_space

    def layer_heights(self, poses: np.ndarray) -> np.ndarray:
        """Target origin heights ``[K]`` of the layers for the objects' current orientations."""
        z = np.empty(self.k)
        bottom = self.table_z + self.clearance
        for k in range(self.k):
            hz = (self.hulls[k] @ quat_to_rotmat(poses[k, 3:7]).T)[:, 2]
            z[k] = bottom - hz.min()
            bottom += float(hz.max() - hz.min()) + self.clearance
        return z

    def __call__(self, obs) -> np.ndarray:
        try:
            p = np.asarray(obs["poses"], dtype=np.float64).reshape(self.k, 7)
            g = np.asarray(obs["goal"], dtype=np.float64).reshape(self.k, 7)
        except (KeyError, TypeError, ValueError) as e:
            raise PolicyError(f"expert policy: observation needs 'poses' and 'goal' [K,7] ({e})") from None
        a = np.zeros((self.k, 4))
        dxy = g[:, :2] - p[:, :2]
        dyaw = _yaw_of(quat_multiply(g[:, 3:7], p[:, 3:7] * np.array([1.0, -1.0, -1.0, -1.0])))
        over_goal = (np.abs(dxy).max(axis=1) <= self.tol) & (np.abs(dyaw) <= self.tol)
        layer = self.layer_heights(p)
        if over_goal.all():  # lower
            a[:, 2] = (g[:, 2] - p[:, 2]) / self.max_t
        elif np.any(p[:, 2] < layer - self.tol):  # lift (no horizontal motion until every object is up)
            a[:, 2] = np.maximum(layer - p[:, 2], 0.0) / self.max_t
        else:  # travel at the layer heights
            a[:, :2] = dxy / self.max_t
            a[:, 2] = (layer - p[:, 2]) / self.max_t
            a[:, 3] = dyaw / self.max_r
        a = np.clip(a, -1.0, 1.0)
        a[np.abs(a) < 1e-12] = 0.0  # objects with nothing to do do not move (and are not re-rendered)
        return a.reshape(-1).astype(self.action_space.dtype)


def _load_callable(spec: str) -> Callable:
    mod_name, _, attr = spec.partition(":")
    if not mod_name or not attr:
        raise PolicyError(f"policy must be 'random', 'expert' or 'module:callable', got {spec!r}")
    try:
        obj: Any = importlib.import_module(mod_name)
    except Exception as e:
        raise PolicyError(
            f"policy {spec!r}: cannot import module {mod_name!r}: {type(e).__name__}: {e}"
        ) from e
    for part in attr.split("."):
        try:
            obj = getattr(obj, part)
        except AttributeError:
            raise PolicyError(f"policy {spec!r}: module {mod_name!r} has no attribute {attr!r}") from None
    if not callable(obj):
        raise PolicyError(f"policy {spec!r} is not callable ({type(obj).__name__})")
    return obj


def policy_name(policy) -> str:
    """The name a policy is recorded under: the spec string, or ``module:qualname`` of a callable."""
    if isinstance(policy, str):
        return policy
    f = policy if hasattr(policy, "__qualname__") else type(policy)
    return f"{getattr(f, '__module__', '?')}:{getattr(f, '__qualname__', type(policy).__name__)}"


def policy_factory(policy, env: gym.Env) -> Callable[[], Callable]:
    """A function that makes one policy instance per vector-env slot.

    ``policy``: ``"random"``, ``"expert"``, ``"module:callable"`` (imported) or a callable ``obs -> action``.
    Built-in policies get a fresh instance per slot; a user callable is shared by all slots.
    ``env``: a single env of the kind that is rolled out (spaces; geometry for ``expert``).
    """
    if policy == "random":
        space = env.action_space
        return lambda: RandomPolicy(space)
    if policy == "expert":
        ExpertPolicy(env)  # validate now: a clear error before any env starts
        return lambda: ExpertPolicy(env)
    if isinstance(policy, str):
        obj = _load_callable(policy)
    elif callable(policy):
        obj = policy
    else:
        raise PolicyError(f"policy must be a name or a callable, got {type(policy).__name__}")
    return lambda: obj
