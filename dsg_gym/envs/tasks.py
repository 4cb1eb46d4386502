"""The default task of ``DSGWorld-v0``: goal-conditioned rearrangement.

* Configurations are sampled on the table: every object keeps the tilt of its captured orientation (so it
  rests the way it was seen), gets a uniformly random yaw and a uniformly random x/y position where its
  horizontal bounding circle stays inside the table bounds (minus ``margin``) and at least ``gap`` away from
  the other objects' circles; its height is the resting height of its collision hull. The physics proxy
  verifies the result (no interpenetration, inside the bounds).
* Errors per object: position error ``|p - g|`` (metres) and rotation error, the angle of the relative
  rotation (radians).
* Reward (dense): ``-(mean position error + rotation_weight * mean rotation error)``, plus ``success_bonus``
  on success and minus ``collision_penalty`` on a step whose move was rejected or resolved by physics.
* Success: every object within ``position_tolerance`` and ``rotation_tolerance`` of its goal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..physics import PhysicsProxy
from ..poses import quat_multiply, quat_normalize, quat_to_rotmat, yaw_to_quat

__all__ = ["RearrangementTask", "TaskParams"]


@dataclass(frozen=True)
class TaskParams:
    """Tolerances and reward weights (metres, radians)."""

    position_tolerance: float = 0.02
    rotation_tolerance: float = float(np.deg2rad(15.0))
    rotation_weight: float = 0.1
    success_bonus: float = 1.0
    collision_penalty: float = 0.1
    margin: float = 0.02
    gap: float = 0.01
    max_tries: int = 200

    def __post_init__(self) -> None:
        for k, v in self.__dict__.items():
            if not np.isfinite(v) or v < 0:
                raise ValueError(f"TaskParams.{k} must be a finite number >= 0, got {v!r}")
        if self.position_tolerance <= 0 or self.rotation_tolerance <= 0:
            raise ValueError("TaskParams: tolerances must be > 0")


class RearrangementTask:
    """Sampling, errors, reward and success for a world with a :class:`PhysicsProxy` (see module docstring).

    ``reference_quats`` ``[K,4]``: the orientations whose tilt sampled configurations keep (e.g. a captured
    state's).
    """

    def __init__(self, physics: PhysicsProxy, reference_quats: np.ndarray, params: TaskParams | None = None):
        self.physics = physics
        self.params = TaskParams() if params is None else params
        self.k = physics.num_objects
        self.reference_quats = quat_normalize(
            np.asarray(reference_quats, dtype=np.float64).reshape(self.k, 4)
        )
        self._goal_key: bytes | None = None  # cache of errors(): the last goal's bytes and unit quaternions
        self._goal_unit = np.zeros((self.k, 4))

    # ------------------------------------------------------------------ sampling
    def _radius_z(self, k: int, q: np.ndarray) -> tuple[float, float]:
        h = self.physics.hulls[k] @ quat_to_rotmat(q).T
        return float(np.linalg.norm(h[:, :2], axis=1).max()), float(-h[:, 2].min())

    def sample_configuration(self, rng: np.random.Generator) -> np.ndarray:
        """A valid random configuration ``[K,7]`` float64 (ValueError if none is found in ``max_tries``)."""
        p, t = self.params, self.physics.world.table
        for _ in range(p.max_tries):
            out = np.zeros((self.k, 7))
            placed: list[tuple[float, float, float]] = []
            ok = True
            for k in rng.permutation(self.k):
                q = quat_normalize(
                    quat_multiply(yaw_to_quat(rng.uniform(-np.pi, np.pi)), self.reference_quats[k])
                )
                r, dz = self._radius_z(k, q)
                lo_x, hi_x = t.xmin + p.margin + r, t.xmax - p.margin - r
                lo_y, hi_y = t.ymin + p.margin + r, t.ymax - p.margin - r
                if lo_x > hi_x or lo_y > hi_y:
                    raise ValueError(f"object {k} does not fit on the table")
                for _ in range(p.max_tries):
                    x, y = rng.uniform(lo_x, hi_x), rng.uniform(lo_y, hi_y)
                    if all(np.hypot(x - a, y - b) >= r + c + p.gap for a, b, c in placed):
                        break
                else:
                    ok = False
                    break
                placed.append((x, y, r))
                out[k] = (x, y, t.z + dz, *q)
            if ok and self.physics.check(out).ok:
                return out
        raise ValueError(f"could not sample a valid configuration in {p.max_tries} tries")

    def sample_goal(self, rng: np.random.Generator, start: np.ndarray) -> np.ndarray:
        """A configuration that is not already solved from ``start``."""
        for _ in range(self.params.max_tries):
            goal = self.sample_configuration(rng)
            if not self.success(start, goal):
                return goal
        raise ValueError("could not sample a goal that differs from the start")

    # ------------------------------------------------------------------ evaluation
    def errors(self, poses: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per object position error (m) and rotation error (rad), each ``[K]`` float64.

        The same numbers as ``norm(poses[:, :3] - goal[:, :3], axis=1)`` and ``quat_angle(poses[:, 3:7],
        goal[:, 3:7])``; the goal's unit quaternions are cached (a goal stays fixed for an episode)."""
        goal = np.asarray(goal, dtype=np.float64)
        key = goal.tobytes()
        if key != self._goal_key:
            self._goal_unit, self._goal_key = quat_normalize(goal[:, 3:7]), key
        d = poses[:, :3] - goal[:, :3]
        pe = np.sqrt(np.add.reduce(d * d, axis=1))  # np.linalg.norm(d, axis=1), the same reduction
        c = np.abs(np.add.reduce(quat_normalize(poses[:, 3:7]) * self._goal_unit, axis=-1))
        return pe, 2.0 * np.arccos(np.clip(c, 0.0, 1.0))  # quat_angle

    def success(self, poses: np.ndarray, goal: np.ndarray) -> bool:
        pe, re = self.errors(poses, goal)
        return bool(
            np.all(pe <= self.params.position_tolerance) and np.all(re <= self.params.rotation_tolerance)
        )

    def reward(
        self,
        poses: np.ndarray,
        goal: np.ndarray,
        collided: bool,
        errors: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[float, bool]:
        """``(reward, success)`` of a step that ended at ``poses`` (``errors``: ``self.errors(poses, goal)``
        when the caller has it already)."""
        p = self.params
        pe, re = self.errors(poses, goal) if errors is None else errors
        success = bool(np.all(pe <= p.position_tolerance) and np.all(re <= p.rotation_tolerance))
        r = -(float(pe.mean()) + p.rotation_weight * float(re.mean()))
        if success:
            r += p.success_bonus
        if collided:
            r -= p.collision_penalty
        return r, success
