"""The similarity between a ground-truth capture's frame and the frame a world was trained in.

A world trained on a ``dsg-capture`` capture lives in the frame estimated from its photos: the table frame
from structure from motion, with an arbitrary scale (or one from a marker). To score it against the ground
truth of the same scene (``dsg-synth --as-photos`` writes it to ``ground_truth/``), :func:`fit_frame_alignment`
fits the similarity ``X_world = s R X_truth + t`` from the cameras the two have in common: the world's stored
training cameras and the truth's cameras of the same states, matched by view name (the world records its
cameras' names in ``metadata["camera_names"]``; for a world without them, the names come from the capture it
was trained on, else the cameras are matched in order).

The rotation maximises ``tr(R^T H)`` with ``H`` the sum of two equally weighted parts: the cross-covariance
of the centred camera centres (Umeyama's, divided by the product of the two point sets' RMS spreads) and the
sum of the per-camera rotations ``R_world,i R_truth,i^T`` (camera-to-world), divided by the camera count, so
centres and orientations both constrain it. Scale and translation then follow from the centres by least
squares. The residuals are reported: camera centre errors in the truth's units and camera rotation errors.

:class:`FrameAlignment` moves the truth's cameras into the world frame (rigid view matrices, the same pinhole
images) and its object poses: an object's motion from the reference state to a test state in the truth's
frame, ``M = P_test inv(P_ref)``, is conjugated by the similarity and applied to the world's reference pose.
A fit within :data:`IDENTITY_TOLERANCE` of the identity is taken as the identity: the frames are one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dsg_gym.world import World
from train_world.capture.alignment import rotation_angle_deg
from train_world.capture.cameras import GL_TO_CV, check_rigid
from train_world.capture.files import CaptureError, read_json
from train_world.dual_state.views import ESTIMATING_GENERATORS, view_names

__all__ = [
    "IDENTITY_TOLERANCE",
    "FrameAlignment",
    "capture_cameras",
    "fit_frame_alignment",
    "fit_similarity",
    "motion_errors",
    "needs_alignment",
    "world_camera_names",
]

#: a fit whose scale, rotation (radians) and translation (relative to the cameras' spread) are all within this
#: of the identity's is the identity
IDENTITY_TOLERANCE = 1e-5


def _project_rotation(H: np.ndarray) -> np.ndarray:
    """The rotation ``R`` maximising ``tr(R^T H)`` (determinant +1)."""
    u, _, vt = np.linalg.svd(H)
    d = np.diag([1.0, 1.0, 1.0 if np.linalg.det(u @ vt) > 0 else -1.0])
    return u @ d @ vt


def fit_similarity(
    centres_truth: np.ndarray, rot_truth: np.ndarray, centres_world: np.ndarray, rot_world: np.ndarray
) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` with ``centres_world ~ s R centres_truth + t`` and ``rot_world ~ R rot_truth`` from camera
    centres ``[N,3]`` and camera-to-world rotations ``[N,3,3]`` (module docstring); ValueError for fewer than 3
    cameras or centres that do not span a plane."""
    cg = np.asarray(centres_truth, dtype=np.float64).reshape(-1, 3)
    cw = np.asarray(centres_world, dtype=np.float64).reshape(-1, 3)
    rg = np.asarray(rot_truth, dtype=np.float64).reshape(-1, 3, 3)
    rw = np.asarray(rot_world, dtype=np.float64).reshape(-1, 3, 3)
    n = len(cg)
    if n < 3 or cw.shape != cg.shape or rg.shape != (n, 3, 3) or rw.shape != (n, 3, 3):
        raise ValueError(f"need at least 3 matched cameras to fit the frames' similarity, got {n}")
    a, b = cg - cg.mean(0), cw - cw.mean(0)
    sa, sb = math.sqrt(float((a * a).sum()) / n), math.sqrt(float((b * b).sum()) / n)
    if np.linalg.matrix_rank(a, tol=1e-9 * max(sa, 1e-300)) < 2 or sb <= 0:
        raise ValueError("the matched camera centres are collinear: the frames' similarity is not determined")
    H = (b.T @ a) / (n * sa * sb) + np.einsum("nij,nkj->ik", rw, rg) / n
    R = _project_rotation(H)
    s = float(np.einsum("ni,ni->", b, a @ R.T) / float((a * a).sum()))
    if not (math.isfinite(s) and s > 0):
        raise ValueError(f"the fitted scale between the frames is {s}: the cameras do not correspond")
    return s, R, cw.mean(0) - s * R @ cg.mean(0)


@dataclass(frozen=True)
class FrameAlignment:
    """The similarity from a ground-truth capture's frame into a world's, ``X_world = s R X_truth + t``, with
    the residuals of its fit: ``centre_rms``/``centre_max`` in the truth's units, ``rotation_rms_deg``.
    ``identity``: the fit is the identity within :data:`IDENTITY_TOLERANCE` (the truth is used as it is)."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    cameras: int
    centre_rms: float
    centre_max: float
    rotation_rms_deg: float
    identity: bool

    @property
    def matrix(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.scale * self.rotation
        m[:3, 3] = self.translation
        return m

    def viewmats(self, viewmats: np.ndarray) -> np.ndarray:
        """The truth's world-to-camera matrices ``[V,4,4]`` as rigid ones of the world frame (camera
        coordinates scaled by ``s``: the same pinhole images)."""
        vm = np.asarray(viewmats, dtype=np.float64)
        if self.identity:
            return vm.copy()
        out = np.tile(np.eye(4), (len(vm), 1, 1))
        out[:, :3, :3] = vm[:, :3, :3] @ self.rotation.T
        out[:, :3, 3] = self.scale * vm[:, :3, 3] - out[:, :3, :3] @ self.translation
        return out

    def motions(self, M: np.ndarray) -> np.ndarray:
        """Rigid motions ``[K,4,4]`` of the truth's frame as motions of the world frame, ``S M inv(S)``."""
        M = np.asarray(M, dtype=np.float64)
        if self.identity:
            return M.copy()
        R, t, s = self.rotation, self.translation, self.scale
        out = np.tile(np.eye(4), (len(M), 1, 1))
        out[:, :3, :3] = R @ M[:, :3, :3] @ R.T
        out[:, :3, 3] = s * M[:, :3, 3] @ R.T + t - out[:, :3, :3] @ t
        return out

    def poses(self, truth_state: np.ndarray, truth_ref: np.ndarray, world_ref: np.ndarray) -> np.ndarray:
        """The world-frame poses ``[K,4,4]`` of the objects at a state whose poses in the truth are
        ``truth_state``: the truth's motion from its reference poses ``truth_ref``, moved into the world
        frame, applied to the world's reference poses ``world_ref``."""
        M = np.asarray(truth_state, dtype=np.float64) @ np.linalg.inv(np.asarray(truth_ref, dtype=np.float64))
        return self.motions(M) @ np.asarray(world_ref, dtype=np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "scale": self.scale,
            "rotation_deg": float(rotation_angle_deg(self.rotation)),
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "cameras": self.cameras,
            "camera_centre_rms": self.centre_rms,
            "camera_centre_max": self.centre_max,
            "camera_rotation_rms_deg": self.rotation_rms_deg,
            "identity": self.identity,
        }


def capture_cameras(path: str | Path, state: str) -> tuple[list[str], np.ndarray]:
    """The view names and OpenCV camera-to-world matrices ``[V,4,4]`` float64 of ``state`` in a capture
    folder (no image is read)."""
    tj = Path(path) / state / "transforms.json"
    names = view_names(path, state)
    frames = read_json(tj)["frames"]
    c2w = []
    for i, fr in enumerate(frames):
        if "transform_matrix" not in fr:
            raise CaptureError(f"{tj}: frames[{i}] has no 'transform_matrix'")
        try:
            m = check_rigid(np.asarray(fr["transform_matrix"], dtype=np.float64), f"{tj}: frames[{i}]")
        except (TypeError, ValueError) as e:
            raise CaptureError(f"{tj}: frames[{i}].transform_matrix: {e}") from e
        c2w.append(m @ GL_TO_CV)
    return names, np.stack(c2w)


def world_camera_names(world: World) -> dict[str, list[str] | None]:
    """Per state with cameras in the world, its cameras' view names: ``metadata["camera_names"]``, else those
    of the capture it was trained on (``metadata.source.path``) when that is readable and has as many views,
    else None (match in order)."""
    stored = world.metadata.get("camera_names")
    src = world.metadata.get("source")
    src_path = Path(src["path"]) if isinstance(src, Mapping) and isinstance(src.get("path"), str) else None
    out: dict[str, list[str] | None] = {}
    for s, cams in world.cameras.items():
        names = stored.get(s) if isinstance(stored, Mapping) else None
        if names is None and src_path is not None:
            try:
                names = view_names(src_path, s)
            except (CaptureError, OSError):
                names = None
        out[s] = list(names) if names is not None and len(names) == len(cams) else None
    return out


_JSON_KINDS = {dict: "an object", list: "an array", str: "a string", bool: "true/false", type(None): "null"}


def _truth_states(truth: Path) -> Mapping[str, Any]:
    """The ``states`` of the ground truth's ``scene.json`` (none when it lists none); CaptureError naming the
    file when it is not a capture's scene description."""
    src = truth / "scene.json"
    meta = read_json(src)
    fix = "give the ground-truth capture folder (dsg-synth --as-photos writes it to ground_truth/)"
    if not isinstance(meta, dict):
        kind = _JSON_KINDS.get(type(meta), "a number")
        raise CaptureError(
            f"{src}: expected a capture's scene description (a JSON object with 'states'), got {kind}; {fix}"
        )
    states = meta.get("states", {})
    if not isinstance(states, dict):
        kind = _JSON_KINDS.get(type(states), "a number")
        raise CaptureError(
            f"{src}: 'states' must be a JSON object mapping state names to their views, got {kind}; {fix}"
        )
    return states


def fit_frame_alignment(world: World, truth: str | Path) -> FrameAlignment:
    """The similarity from the ground-truth capture folder ``truth`` into ``world``'s frame, fitted on the
    cameras of the states both hold (module docstring); ValueError naming the problem when fewer than 3 cameras
    match or ``truth/scene.json`` is not a capture's scene description."""
    names = world_camera_names(world)
    truth = Path(truth)
    splits = _truth_states(truth)
    cg, rg, cw, rw = [], [], [], []
    for s, cams in world.cameras.items():
        if s not in splits:
            continue
        gt_names, gt_c2w = capture_cameras(truth, s)
        w_c2w = np.linalg.inv(np.asarray(cams.viewmats, dtype=np.float64))
        if names[s] is not None:
            index = {n: j for j, n in enumerate(gt_names)}
            pairs = [(i, index[n]) for i, n in enumerate(names[s]) if n in index]
        elif len(gt_names) == len(w_c2w):
            pairs = list(zip(range(len(w_c2w)), range(len(gt_names))))
        else:
            raise ValueError(
                f"{truth}: state {s!r} has {len(gt_names)} views and the world {len(w_c2w)} cameras without "
                "names to match them by; evaluate a world trained by this dsg-train (it records them)"
            )
        for i, j in pairs:
            cw.append(w_c2w[i, :3, 3])
            rw.append(w_c2w[i, :3, :3])
            cg.append(gt_c2w[j, :3, 3])
            rg.append(gt_c2w[j, :3, :3])
    if len(cg) < 3:
        raise ValueError(
            f"{truth}: only {len(cg)} of the world's cameras ({', '.join(world.cameras)}) match views of the "
            "ground truth by state and name; give the ground truth of the capture the world was trained on"
        )
    cg, rg, cw, rw = (np.asarray(x) for x in (cg, rg, cw, rw))
    s, R, t = fit_similarity(cg, rg, cw, rw)
    err = np.linalg.norm(cg @ (s * R).T + t - cw, axis=1) / s
    rot_err = rotation_angle_deg(np.swapaxes(rw, 1, 2) @ R @ rg)
    spread = math.sqrt(float(((cg - cg.mean(0)) ** 2).sum()) / len(cg))
    identity = (
        abs(s - 1.0) <= IDENTITY_TOLERANCE
        and math.radians(float(rotation_angle_deg(R))) <= IDENTITY_TOLERANCE
        and float(np.linalg.norm(t)) <= IDENTITY_TOLERANCE * max(spread, 1e-12)
    )
    if identity:
        s, R, t = 1.0, np.eye(3), np.zeros(3)
    return FrameAlignment(
        scale=float(s),
        rotation=R,
        translation=np.asarray(t, dtype=np.float64),
        cameras=len(cg),
        centre_rms=float(np.sqrt(np.mean(err**2))),
        centre_max=float(err.max()),
        rotation_rms_deg=float(np.sqrt(np.mean(rot_err**2))),
        identity=bool(identity),
    )


def needs_alignment(world: World, capture: str | Path) -> bool:
    """True when ``capture`` is not the capture ``world`` was trained on and that one's frame was estimated
    (made by a generator of :data:`~train_world.dual_state.views.ESTIMATING_GENERATORS`, ``dsg-capture``):
    ``capture`` is then taken to be a ground truth in a frame of its own."""
    src = world.metadata.get("source")
    if not isinstance(src, Mapping):
        return False
    gen = src.get("generator")
    if not (isinstance(gen, Mapping) and gen.get("name") in ESTIMATING_GENERATORS):
        return False
    path = src.get("path")
    return not (isinstance(path, str) and Path(path).resolve() == Path(capture).resolve())


def motion_errors(world: World, truth: str | Path, alignment: FrameAlignment) -> dict[str, Any] | None:
    """How far the world's object motions between its two training states are from the ground truth's, per
    object, for the motions as the world was given them (``estimate_*``, from ``dsg-capture``) and as trained
    (``refined_*``): the world's motions are moved into the truth's frame through ``alignment`` and measured as
    :func:`train_world.capture.compare.motion_error` does (where they put the object's true centre, in the
    truth's units and mm when those are metres; the angle, also modulo the object's shape symmetry when the
    truth describes its shape, and modulo only those that keep its pattern). ``*_px``: what that error means in
    the truth's views of the moved state, at most: (position error + 2 r sin(angle modulo symmetry / 2)) times
    the median over those views of focal length / distance to the object, with r the distance from the true
    centre within which 99 % of the world's Gaussians of the object lie; None when the truth has no cameras
    for that state. None when the world records no motions (``metadata["motions"]``) or the truth lacks either
    state's object poses or has other objects."""
    from train_world.capture import load_capture
    from train_world.capture.compare import motion_error

    rec = world.metadata.get("motions")
    if not isinstance(rec, Mapping) or not world.num_objects:
        return None
    src, dst = rec.get("src"), rec.get("dst")
    cap = load_capture(Path(truth), states=[], load_depth=False)
    if src not in cap.poses or dst not in cap.poses or tuple(cap.object_ids) != tuple(world.object_ids):
        return None
    P1 = np.asarray(cap.poses[src], np.float64)
    true_motion = np.asarray(cap.poses[dst], np.float64) @ np.linalg.inv(P1)
    S, S_inv = alignment.matrix, np.linalg.inv(alignment.matrix)
    described = [o for o in cap.metadata.get("objects", []) if isinstance(o, Mapping)]
    shapes = {o.get("name"): o.get("shape") for o in described}
    patterns = {o.get("name"): o.get("pattern") for o in described}
    centres = np.einsum("kij,kj->ki", true_motion[:, :3, :3], P1[:, :3, 3]) + true_motion[:, :3, 3]
    px_per_unit = _pixels_per_unit(Path(truth) / dst / "transforms.json", centres)
    objects = []
    for k, name in enumerate(world.object_names):
        e: dict[str, Any] = {"name": name}
        oid = world.object_ids[k]
        means = np.asarray(world.objects[oid].gaussians.means, np.float64)
        P = S_inv @ np.asarray(world.poses[src], np.float64)[k]  # object frame -> truth frame, first state
        dist = np.linalg.norm(means @ P[:3, :3].T + P[:3, 3] - P1[k, :3, 3], axis=1)
        radius = float(np.percentile(dist, 99)) if len(dist) else 0.0
        for key, tag in (("initial", "estimate"), ("final", "refined")):
            T = S_inv @ np.asarray(rec[key], dtype=np.float64)[k] @ S
            obj = cap.objects[k].name
            m = motion_error(T, true_motion[k], P1[k], shapes.get(obj), patterns.get(obj))
            bound = m["position_error"] + 2 * radius * math.sin(
                math.radians(m["rotation_error_mod_symmetry_deg"]) / 2
            )
            e[f"{tag}_px"] = None if px_per_unit is None else bound * float(px_per_unit[k])
            e[f"{tag}_translation"] = m["position_error"]
            if cap.units == "metres":
                e[f"{tag}_mm"] = m["position_error"] * 1000.0
            e[f"{tag}_rotation_deg"] = m["rotation_error_deg"]
            e[f"{tag}_rotation_mod_symmetry_deg"] = m["rotation_error_mod_symmetry_deg"]
            e[f"{tag}_rotation_mod_texture_deg"] = m["rotation_error_mod_texture_deg"]
        objects.append(e)
    return {
        "src": src,
        "dst": dst,
        "refined": bool(rec.get("refined")),
        "units": cap.units,
        "objects": objects,
    }


def _pixels_per_unit(transforms_json: Path, centres: np.ndarray) -> np.ndarray | None:
    """Per point of ``centres [K,3]``, the median over the frames of ``transforms_json`` of focal length
    (x and y averaged) over the distance from the camera: pixels per unit of length there. None without the
    file."""
    from train_world.capture.loader import frame_intrinsics, frame_poses

    if not transforms_json.is_file():
        return None
    eyes = frame_poses(transforms_json)[:, :3, 3]
    K = frame_intrinsics(transforms_json)
    focal = (K[:, 0, 0] + K[:, 1, 1]) / 2
    dist = np.linalg.norm(eyes[None] - centres[:, None], axis=2)  # [K,V]
    return np.median(focal[None] / dist, axis=1)
