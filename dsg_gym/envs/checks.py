"""Input checks of ``DSGWorld-v0``: camera and size kwargs, actions, and start / goal configurations against the
workspace and the collision mode. Every check raises a ``ValueError`` naming the problem before the env changes."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from ..cameras import Cameras, intrinsics_from_fov, look_at
from ..physics import SETTLE_TOLERANCE, TABLE, CollisionReport, PhysicsProxy

__all__ = [
    "check_action",
    "check_goal",
    "check_start",
    "positive_int",
    "real_array",
    "resolve_cameras",
    "settle_checked",
]


def _look_at(spec: Mapping[str, Any], width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """``(viewmat, K)`` of a look-at camera spec ``{eye, target[, up][, fovy_deg]}`` (checked)."""
    unknown = set(spec) - {"eye", "target", "up", "fovy_deg"}
    if unknown or "eye" not in spec or "target" not in spec:
        raise ValueError(
            f"look-at camera spec needs 'eye' and 'target' (optional 'up', 'fovy_deg'); got {spec}"
        )
    eye = real_array(spec["eye"], "look-at camera: eye")
    target = real_array(spec["target"], "look-at camera: target")
    up = real_array(spec.get("up", (0.0, 0.0, 1.0)), "look-at camera: up")
    fovy = real_array(spec.get("fovy_deg", 50.0), "look-at camera: fovy_deg")
    if eye.shape != (3,) or target.shape != (3,) or up.shape != (3,) or fovy.shape != ():
        raise ValueError("look-at camera: eye, target and up must be 3-vectors, fovy_deg a number")
    fovy = float(fovy)
    if not (np.all(np.isfinite(eye)) and np.all(np.isfinite(target)) and np.all(np.isfinite(up))):
        raise ValueError("look-at camera: non-finite eye/target/up")
    if not 0.0 < fovy < 180.0:
        raise ValueError(f"look-at camera: fovy_deg must lie in (0, 180), got {fovy}")
    return look_at(eye, target, up), intrinsics_from_fov(fovy, width, height)


def resolve_cameras(cameras, capture: Cameras, width: int, height: int) -> tuple[Cameras, bool]:
    """The ``cameras`` kwarg as ``(Cameras, multi)``: capture camera indices of ``capture`` and look-at dicts,
    checked; ``multi`` is False for a single camera given as an int, a dict or ``None``."""
    cap = capture.resized(width, height)
    multi = isinstance(cameras, (list, tuple))
    items = list(cameras) if multi else [0 if cameras is None else cameras]
    if not items:
        raise ValueError("cameras: empty list")
    vms, ks = [], []
    for c in items:
        if isinstance(c, (int, np.integer)) and not isinstance(c, bool):
            if not 0 <= int(c) < len(cap):
                raise ValueError(f"cameras: capture camera index {c} out of range [0, {len(cap)})")
            vms.append(cap.viewmats[int(c)])
            ks.append(cap.Ks[int(c)])
        elif isinstance(c, Mapping):
            vm, k = _look_at(c, width, height)
            vms.append(vm)
            ks.append(k)
        else:
            raise ValueError(f"cameras: expected a capture camera index or a look-at dict, got {c!r}")
    return Cameras(np.stack(vms), np.stack(ks), width, height), multi


def positive_int(name: str, v) -> int:
    """``v`` as an int >= 1; ``ValueError`` naming ``name`` otherwise (booleans included)."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < 1:
        raise ValueError(f"{name} must be a positive integer, got {v!r}")
    return int(v)


def real_array(value, what: str) -> np.ndarray:
    """``value`` as a float64 array; ``ValueError`` naming the dtype unless it holds booleans, integers or
    floats (complex numbers, objects such as ``None``, strings, dates are refused, never cast)."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):  # ragged nesting
        raise ValueError(f"{what} must be a real numeric array, got {type(value).__name__}") from None
    if a.dtype.kind not in "biuf":
        raise ValueError(f"{what} must be a real numeric array, got dtype {a.dtype}")
    return a.astype(np.float64)


def check_action(action, shape: tuple[int, ...], k: int, n: int) -> np.ndarray:
    """The action as ``[k, n]`` float64 clipped to [-1, 1]; ``ValueError`` for a non-real dtype, a wrong shape,
    NaN or Inf."""
    a = real_array(action, "action")
    if a.shape != shape:
        raise ValueError(f"action has shape {a.shape}, expected {shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("action contains NaN or Inf")
    return np.clip(a, -1.0, 1.0).reshape(k, n)


def _object(physics: PhysicsProxy, k: int) -> str:
    return f"object {k} ({physics.world.object_names[k]!r})"


def _in_workspace(physics: PhysicsProxy, poses: np.ndarray, what: str) -> None:
    problems = physics.workspace_problems(poses)
    if problems:
        k, why = next(iter(problems.items()))
        raise ValueError(f"{what}: {_object(physics, k)}: {why}")


def _overlap(physics: PhysicsProxy, report: CollisionReport) -> str:
    (a, b), depth = report.penetrating[0], report.depths[0]
    other = "the table" if b == TABLE else _object(physics, b)
    return f"{_object(physics, a)} and {other} interpenetrate by {depth * 1000:.1f} mm"


def _check(physics: PhysicsProxy, poses: np.ndarray, collision: str) -> CollisionReport:
    """The collision report with the mode's penetration tolerance (settle: :data:`SETTLE_TOLERANCE`)."""
    if collision == "settle":
        return physics.check(poses, tol=SETTLE_TOLERANCE, distance=False)
    return physics.check(poses, distance=False)


def check_start(
    physics: PhysicsProxy, poses: np.ndarray, collision: str, what: str = "options['start']"
) -> tuple[np.ndarray, CollisionReport, bool]:
    """``(start, report, settled)`` for start poses ``[K,7]`` given to ``reset``.

    Outside the workspace: ``ValueError`` naming the object and the bound. Interpenetrating: ``reject`` refuses,
    ``settle`` lets physics bring the objects to rest (refused when they do not come to rest inside the
    workspace without penetrating deeper than :data:`~dsg_gym.physics.SETTLE_TOLERANCE`), ``ignore`` accepts."""
    _in_workspace(physics, poses, what)
    report = _check(physics, poses, collision)
    if not report.penetrating or collision == "ignore":
        return poses, report, False
    if collision == "reject":
        raise ValueError(
            f"{what}: {_overlap(physics, report)}; collision='reject' refuses an interpenetrating start "
            "(collision='settle' settles it, collision='ignore' accepts it)"
        )
    rest = settle_checked(physics, poses)
    if rest is None:
        raise ValueError(
            f"{what}: {_overlap(physics, report)} and do not come to rest inside the workspace without "
            "interpenetrating; give a start without overlaps"
        )
    return rest[0], rest[1], True


def check_goal(
    physics: PhysicsProxy, poses: np.ndarray, collision: str, what: str = "options['goal']"
) -> None:
    """``ValueError`` for goal poses ``[K,7]`` outside the workspace (naming the object and the bound) or, with
    ``collision`` ``reject`` or ``settle``, interpenetrating (such a goal cannot be reached)."""
    _in_workspace(physics, poses, what)
    if collision == "ignore":
        return
    report = _check(physics, poses, collision)
    if report.penetrating:
        raise ValueError(
            f"{what}: {_overlap(physics, report)}; collision={collision!r} cannot reach an interpenetrating goal"
        )


def settle_checked(physics: PhysicsProxy, poses: np.ndarray) -> tuple[np.ndarray, CollisionReport] | None:
    """``(resting poses, their report)`` from ``physics.settle(poses)`` when the objects come to rest inside
    the workspace interpenetrating by at most :data:`~dsg_gym.physics.SETTLE_TOLERANCE`; ``None`` otherwise (or
    when the simulation diverges)."""
    try:
        rest = physics.settle(poses)
    except RuntimeError:
        return None
    report = physics.check(rest, tol=SETTLE_TOLERANCE, distance=False)
    return (rest, report) if report.ok else None
