"""Measuring an estimated capture against the ground truth of the same scene (e.g. ``dsg-synth --as-photos``).

The estimated frame differs from the truth by a similarity; :func:`compare_captures` fits it to the camera
centres (Umeyama, views matched by state and file stem), then reports how far the estimated +z and table top
(z = 0) are from the truth's, camera centre errors (truth units and
percent of the scene radius: the median distance of the true camera centres from their mean), camera rotation
errors (degrees) and, per object, the motion error between the first two states: where the estimated motion
puts the object's true centre versus where it really went, and the angle between the rotations, both raw and
modulo the object's shape symmetry when the truth's ``scene.json`` describes its shape (``dsg-synth`` does): a
ball's rotation is then not scored, a cylinder's only by its axis, a box's and a prism's up to the turns that
leave their shape unchanged. A patterned object (``dsg-synth`` maps its pattern onto it through a cube texture
in the object's frame) is also scored modulo only those symmetries that are quarter turns about its axes
(``rotation_error_mod_texture_deg``): a turn of a dotted ball that shows other dots counts, one that shows the
same cube-mapped pattern does not (a lower bound where the pattern itself has fewer symmetries). It also
reports the estimated focal length's error (percent, at the truth's image size).

:func:`with_true_cameras` puts the truth's cameras in place of a structure-from-motion result, so that a capture
built on them shows what the later steps (table frame, object motions) cost by themselves, apart from what the
estimated cameras cost them.
"""

from __future__ import annotations

import numpy as np

from train_world.capture.alignment import rotation_angle_deg, similarity_matrix, umeyama
from train_world.capture.cameras import GL_TO_CV
from train_world.capture.loader import Capture
from train_world.capture.sfm import SfmResult, StateCamera

__all__ = ["compare_captures", "motion_error", "shape_symmetries", "texture_symmetries", "with_true_cameras"]


def _turn(axis: int, deg: float) -> np.ndarray:
    c, s_ = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    i, j = [k for k in range(3) if k != axis]
    m = np.eye(3)
    m[i, i], m[i, j], m[j, i], m[j, j] = c, -s_, s_, c
    return m


def _cube_rotations() -> list[np.ndarray]:
    """The 24 rotations ``[3,3]`` that map the coordinate axes onto themselves (a cube's)."""
    out = []
    for perm in ([0, 1, 2], [0, 2, 1], [1, 0, 2], [1, 2, 0], [2, 0, 1], [2, 1, 0]):
        for signs in np.array(np.meshgrid([1, -1], [1, -1], [1, -1])).T.reshape(-1, 3):
            m = np.zeros((3, 3))
            m[np.arange(3), perm] = signs
            if np.linalg.det(m) > 0:
                out.append(m)
    return out


def shape_symmetries(shape: dict | None) -> str | list[np.ndarray]:
    """Rotations ``[3,3]`` (object frame) that leave a ``dsg-synth`` shape unchanged, or ``"all"`` (sphere) or
    ``"axis"`` (any turn about z, and upside down: cylinder, capsule); ``[I]`` when unknown."""
    if not isinstance(shape, dict):
        return [np.eye(3)]
    kind = shape.get("type")
    if kind == "sphere":
        return "all"
    if kind in ("cylinder", "capsule"):
        return "axis"
    if kind == "box":
        e = np.asarray(shape.get("extents", [1, 2, 3]), np.float64)
        return [m for m in _cube_rotations() if np.allclose(np.abs(m) @ e, e, rtol=1e-6)]
    if kind == "mesh" and shape.get("mesh") in ("prism", "frustum"):
        n = int(shape.get("sides", 1))
        out = [_turn(2, 360.0 * k / n) for k in range(n)]
        if shape.get("mesh") == "prism":
            out += [m @ _turn(0, 180.0) for m in out]
        return out
    return [np.eye(3)]


def texture_symmetries(shape: dict | None, pattern: str | None) -> str | list[np.ndarray]:
    """Rotations ``[3,3]`` (object frame) that leave a ``dsg-synth`` object with ``pattern`` looking the same:
    its :func:`shape_symmetries` that are also quarter turns about its axes (those of its cube texture), or
    exactly :func:`shape_symmetries` when it is plain (``pattern`` None or "solid")."""
    sym = shape_symmetries(shape)
    if pattern in (None, "solid"):
        return sym
    cube = _cube_rotations()
    if isinstance(sym, str):
        return cube if sym == "all" else [m for m in cube if abs(m[2, 2]) == 1]
    return [m for m in sym if any(np.allclose(m, c, atol=1e-9) for c in cube)]


def _symmetric_error(r_est: np.ndarray, r_gt: np.ndarray, q1: np.ndarray, sym) -> float:
    if isinstance(sym, str) and sym == "all":
        return 0.0
    if isinstance(sym, str):
        a = q1[:, 2]
        ang = float(np.degrees(np.arccos(np.clip((r_est @ a) @ (r_gt @ a), -1.0, 1.0))))
        return min(ang, 180.0 - ang)
    return min(float(rotation_angle_deg(r_est.T @ r_gt @ q1 @ m @ q1.T)) for m in sym)


def motion_error(
    T: np.ndarray,
    T_true: np.ndarray,
    P1_true: np.ndarray,
    shape: dict | None = None,
    pattern: str | None = None,
) -> dict:
    """How far a rigid motion ``T`` ``[4,4]`` of one object is from its true motion ``T_true`` (both in the
    truth's frame), the object's true first-state pose being ``P1_true``: ``position_error`` (where the two put
    the object's centre, truth units), ``rotation_error_deg``, ``rotation_error_mod_symmetry_deg`` (modulo
    the symmetries of ``shape``, a ``dsg-synth`` shape description) and ``rotation_error_mod_texture_deg``
    (modulo those that also keep its ``pattern``, :func:`texture_symmetries`; module docstring)."""
    T, T_true, P1 = (np.asarray(a, dtype=np.float64) for a in (T, T_true, P1_true))
    c = P1[:3, 3]
    pos = np.linalg.norm(T[:3, :3] @ c + T[:3, 3] - (T_true[:3, :3] @ c + T_true[:3, 3]))
    return {
        "position_error": float(pos),
        "rotation_error_deg": float(rotation_angle_deg(T[:3, :3].T @ T_true[:3, :3])),
        "rotation_error_mod_symmetry_deg": _symmetric_error(T[:3, :3], T_true[:3, :3], P1[:3, :3],
                                                            shape_symmetries(shape)),
        "rotation_error_mod_texture_deg": _symmetric_error(T[:3, :3], T_true[:3, :3], P1[:3, :3],
                                                           texture_symmetries(shape, pattern)),
    }  # fmt: skip


def _cameras(cap: Capture) -> dict[str, np.ndarray]:
    out = {}
    for s, v in cap.states.items():
        for path, c2w in zip(v.image_paths, v.c2w_opengl):
            out[f"{s}/{path.stem}"] = c2w @ GL_TO_CV
    return out


def _focal_error_percent(estimated: Capture, truth: Capture, keys: list[str]) -> float:
    """Median over the views ``keys`` (``"<state>/<stem>"``) of the estimated focal length's error in percent
    (x and y averaged, the estimate scaled to the truth's image width)."""

    def focals(cap: Capture) -> dict[str, tuple[float, int]]:
        out = {}
        for s, v in cap.states.items():
            Ks = v.Ks.numpy().astype(np.float64)
            for path, K in zip(v.image_paths, Ks, strict=True):
                out[f"{s}/{path.stem}"] = (0.5 * (K[0, 0] + K[1, 1]), v.width)
        return out

    est, gt = focals(estimated), focals(truth)
    errs = [100.0 * (est[k][0] * gt[k][1] / est[k][1] / gt[k][0] - 1.0) for k in keys]
    return float(np.median(errs))


def with_true_cameras(sfm: SfmResult, truth: Capture) -> SfmResult:
    """``sfm`` (:func:`.sfm.run_sfm`'s result on ``truth``'s photos) with every registered view's pose and
    intrinsics replaced by the truth's (a pinhole camera per state; views matched by state and file stem) and
    its points carried into the truth's frame by the similarity fitted to the camera centres (as
    :func:`compare_captures` fits it). Raises ``ValueError`` when a registered view has no true camera or fewer
    than 3 views are shared."""
    gt = _cameras(truth)
    missing = sorted(set(sfm.world_to_camera) - set(gt))
    if missing:
        raise ValueError(
            f"no true camera for registered views {missing[:5]}; pass the photos' own ground truth"
        )
    keys = sorted(sfm.world_to_camera)
    if len(keys) < 3:
        raise ValueError(f"only {len(keys)} registered views; need 3")
    ce = np.array([np.linalg.inv(sfm.world_to_camera[k])[:3, 3] for k in keys])
    s, rot, t = umeyama(ce, np.array([gt[k][:3, 3] for k in keys]))
    cameras = {}
    for state in sfm.cameras:
        v = truth.states[state]
        K = v.Ks[0].numpy().astype(np.float64)
        cameras[state] = StateCamera("PINHOLE", (K[0, 0], K[1, 1], K[0, 2], K[1, 2]), v.width, v.height)
    return SfmResult(
        world_to_camera={k: np.linalg.inv(gt[k]) for k in keys},
        cameras=cameras,
        points=sfm.points @ (s * rot).T + t,
        point_errors=sfm.point_errors,
        mean_reprojection_error=sfm.mean_reprojection_error,
        registered=sfm.registered,
        unregistered=sfm.unregistered,
        timings=sfm.timings,
    )


def compare_captures(estimated: Capture, truth: Capture, src: str = "state1", dst: str = "state2") -> dict:
    """Errors of ``estimated`` against ``truth`` (module docstring) as a JSON-ready dict."""
    est, gt = _cameras(estimated), _cameras(truth)
    keys = sorted(set(est) & set(gt))
    if len(keys) < 3:
        raise ValueError(f"only {len(keys)} views in common between the captures; need 3")
    ce = np.array([est[k][:3, 3] for k in keys])
    cg = np.array([gt[k][:3, 3] for k in keys])
    s, rot, t = umeyama(ce, cg)
    S = similarity_matrix(s, rot, t)
    centre_err = np.linalg.norm(ce @ (s * rot).T + t - cg, axis=1)
    rot_err = np.array([rotation_angle_deg(gt[k][:3, :3].T @ rot @ est[k][:3, :3]) for k in keys])
    radius = float(np.median(np.linalg.norm(cg - cg.mean(axis=0), axis=1)))
    T_est = estimated.relative_transform(src, dst)
    T_gt = truth.relative_transform(src, dst)
    objects = []
    by_name = {o.name: i for i, o in enumerate(truth.objects)}
    described = [o for o in truth.metadata.get("objects", []) if isinstance(o, dict)]
    shapes = {o.get("name"): o.get("shape") for o in described}
    patterns = {o.get("name"): o.get("pattern") for o in described}
    for i, o in enumerate(estimated.objects):
        if o.name not in by_name:
            continue
        j = by_name[o.name]
        P1 = truth.poses[src][j] if src in truth.poses else np.eye(4)
        c = P1[:3, 3]
        objects.append(
            {
                "name": o.name,
                **motion_error(
                    S @ T_est[i] @ np.linalg.inv(S), T_gt[j], P1, shapes.get(o.name), patterns.get(o.name)
                ),
                "true_rotation_deg": float(rotation_angle_deg(T_gt[j][:3, :3])),
                "true_translation": float(np.linalg.norm(T_gt[j][:3, 3] + T_gt[j][:3, :3] @ c - c)),
            }
        )
    up = rot @ np.array([0.0, 0.0, 1.0])
    table = truth.metadata.get("table", {}) if isinstance(truth.metadata.get("table"), dict) else {}
    return {
        "views_compared": len(keys),
        "up_axis_error_deg": float(np.degrees(np.arccos(np.clip(up[2], -1.0, 1.0)))),
        "table_top_error": float(t[2] - float(table.get("top_z", 0.0))),
        "similarity_scale": float(s),
        "scene_radius": radius,
        "camera_centre_error_median": float(np.median(centre_err)),
        "camera_centre_error_max": float(centre_err.max()),
        "camera_centre_error_median_percent_of_radius": float(100 * np.median(centre_err) / radius),
        "camera_rotation_error_median_deg": float(np.median(rot_err)),
        "camera_rotation_error_max_deg": float(rot_err.max()),
        "focal_error_percent": _focal_error_percent(estimated, truth, keys),
        "objects": objects,
    }
