"""Object motions as parameters of the joint phase (not part of DSG-World, which takes the motions as known).

A capture gives each object's rigid motion between the two training states, ``T_1->2[k] = P2[k] inv(P1[k])``.
A synthetic capture knows them exactly; ``dsg-capture`` estimates them from the photos, a few millimetres and
under a degree off. With motion refinement on, every object gets a rigid correction, a rotation vector
``w_k`` and a translation ``u_k``, both zero at the start, applied about the object's estimated state-2 origin
``o_k = P2[k][:3, 3]``::

    T'_1->2[k](x) = exp(w_k) (T_1->2[k] x - o_k) + o_k + u_k          T'_2->1[k] = inv(T'_1->2[k])

so ``u_k`` is how far the object's origin moves in state 2 and ``|w_k|`` the angle it turns. Everything is
composed in float64 from the estimate's unit quaternion and the correction's (renormalised after the
product); ``T'_2->1`` is the exact inverse (transposed rotation, conjugate quaternion), and the float32
copies the renderer takes are made last. The corrections receive gradients through the bidirectional
alignment loss ``L_align`` (the transferred Gaussians, :class:`~.transfer.ObjectTransfer`) and have their own
Adam (:meth:`ObjectMotions.make_optimizer`); the trainer (:mod:`.trainer`) steps it in the joint phase only.
State 1 is the reference: its poses stay, the refined state-2 poses are ``T'_1->2 P1``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from dsg_gym.geometry import (
    axis_angle_to_quat,
    quat_conjugate,
    quat_multiply,
    quat_normalize,
    quat_to_rotmat,
    rotmat_to_quat,
)
from train_world.capture.alignment import rotation_angle_deg
from train_world.dual_state.transfer import ObjectTransfer

__all__ = [
    "ObjectMotions",
    "motion_correction",
    "motion_error",
    "motions_record",
]


def motion_error(T: np.ndarray, T_ref: np.ndarray, P1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per object, the distance ``[K]`` between where ``T`` and ``T_ref`` put the object's state-1 origin
    (``P1[k][:3, 3]``), in scene units, and the angle ``[K]`` in degrees between their rotations."""
    T, T_ref, P1 = (np.asarray(a, dtype=np.float64) for a in (T, T_ref, P1))
    o = P1[:, :3, 3]
    a = np.einsum("kij,kj->ki", T[:, :3, :3], o) + T[:, :3, 3]
    b = np.einsum("kij,kj->ki", T_ref[:, :3, :3], o) + T_ref[:, :3, 3]
    ang = rotation_angle_deg(np.swapaxes(T[:, :3, :3], 1, 2) @ T_ref[:, :3, :3])
    return np.linalg.norm(a - b, axis=1), ang


def motion_correction(
    initial: np.ndarray, refined: np.ndarray, P1: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """How far refinement moved each object in state 2 (scene units) and turned it (degrees):
    :func:`motion_error` of the refined motions against the initial ones."""
    return motion_error(refined, initial, P1)


class ObjectMotions:
    """The per-object corrections of the module docstring for poses ``P1``, ``P2`` ``[K,4,4]``.

    ``rotvec`` and ``translation`` ``[K,3]`` float64 are the parameters (zero: the capture's motions)."""

    def __init__(self, P1: np.ndarray, P2: np.ndarray):
        P1 = np.asarray(P1, dtype=np.float64)
        P2 = np.asarray(P2, dtype=np.float64)
        if P1.shape != P2.shape or P1.ndim != 3 or P1.shape[1:] != (4, 4):
            raise ValueError(f"ObjectMotions: poses must both be [K,4,4], got {P1.shape} and {P2.shape}")
        self.P1 = P1
        self.initial = P2 @ np.linalg.inv(P1)  # T_1->2 as given
        T = torch.from_numpy(self.initial.copy())
        self._q0 = quat_normalize(rotmat_to_quat(T[:, :3, :3]))
        self._t0 = T[:, :3, 3].clone()
        self._pivot = torch.from_numpy(P2[:, :3, 3].copy())
        k = len(P1)
        self.rotvec = torch.zeros(k, 3, dtype=torch.float64, requires_grad=True)
        self.translation = torch.zeros(k, 3, dtype=torch.float64, requires_grad=True)

    def __len__(self) -> int:
        return len(self.P1)

    def named_parameters(self) -> list[tuple[str, torch.Tensor]]:
        return [("motions.rotvec", self.rotvec), ("motions.translation", self.translation)]

    def make_optimizer(self, lr_translation: float, lr_rotation: float) -> torch.optim.Adam:
        """One Adam with two groups: ``[rotvec]`` at ``lr_rotation`` (radians), ``[translation]`` at
        ``lr_translation`` (scene units)."""
        return torch.optim.Adam(
            [
                {"params": [self.rotvec], "lr": lr_rotation},
                {"params": [self.translation], "lr": lr_translation},
            ],
            eps=1e-15,
        )

    # ------------------------------------------------------------------ the refined motions
    def parts(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``T'_1->2`` as rotations ``[K,3,3]``, translations ``[K,3]`` and unit quaternions ``[K,4]``, float64
        and differentiable in the parameters."""
        qc = axis_angle_to_quat(self.rotvec)
        q = quat_normalize(quat_multiply(qc, self._q0))
        Rc = quat_to_rotmat(qc)
        t = torch.einsum("kij,kj->ki", Rc, self._t0 - self._pivot) + self._pivot + self.translation
        return quat_to_rotmat(q), t, q

    def transfers(
        self, labels_1: torch.Tensor, labels_2: torch.Tensor
    ) -> tuple[ObjectTransfer, ObjectTransfer]:
        """``T'_1->2`` for field 1's Gaussians and its exact inverse ``T'_2->1`` for field 2's (float32 for the
        renderer, with gradients to the parameters)."""
        R, t, q = self.parts()
        Ri = R.transpose(1, 2)
        ti = -torch.einsum("kij,kj->ki", Ri, t)
        return (
            ObjectTransfer.from_parts(labels_1, R.float(), t.float(), q.float()),
            ObjectTransfer.from_parts(labels_2, Ri.float(), ti.float(), quat_conjugate(q).float()),
        )

    @torch.no_grad()
    def T12(self) -> np.ndarray:
        """``T'_1->2`` ``[K,4,4]`` float64 (rigid: its rotation is the quaternion's)."""
        R, t, _ = self.parts()
        out = np.tile(np.eye(4), (len(self), 1, 1))
        out[:, :3, :3] = R.numpy()
        out[:, :3, 3] = t.numpy()
        return out

    def T21(self) -> np.ndarray:
        """The exact inverse of :meth:`T12` ``[K,4,4]`` float64."""
        T = self.T12()
        out = np.tile(np.eye(4), (len(self), 1, 1))
        out[:, :3, :3] = np.transpose(T[:, :3, :3], (0, 2, 1))
        out[:, :3, 3] = -np.einsum("kij,kj->ki", out[:, :3, :3], T[:, :3, 3])
        return out

    def P2(self) -> np.ndarray:
        """The refined state-2 poses ``T'_1->2 P1`` ``[K,4,4]`` float64."""
        return self.T12() @ self.P1

    # ------------------------------------------------------------------ checkpoints
    def state_tensors(self) -> dict[str, torch.Tensor]:
        return {"motions/rotvec": self.rotvec.detach(), "motions/translation": self.translation.detach()}

    @torch.no_grad()
    def load_state_tensors(self, tensors: dict[str, torch.Tensor]) -> None:
        for key, p in (("motions/rotvec", self.rotvec), ("motions/translation", self.translation)):
            v = tensors[key]
            if tuple(v.shape) != tuple(p.shape):
                raise ValueError(f"checkpoint {key}: shape {tuple(v.shape)}, expected {tuple(p.shape)}")
            p.copy_(v)


def motions_record(
    initial: np.ndarray,
    final: np.ndarray,
    P1: np.ndarray,
    object_ids: tuple[int, ...],
    object_names: tuple[str, ...],
    units: str,
    refined: bool,
    states: tuple[str, str],
) -> dict[str, Any]:
    """The world's ``metadata["motions"]``: the motions ``states[0] -> states[1]`` as given and as trained
    (``[K,4,4]`` lists, world-from-world), whether they were refined, and per object the correction (the
    distance its state-2 origin moved, in scene units and in mm when the units are metres, and the angle)."""
    dist, ang = motion_correction(initial, final, P1)
    metric = units == "metres"
    objects = []
    for k, (oid, name) in enumerate(zip(object_ids, object_names)):
        entry: dict[str, Any] = {
            "id": int(oid),
            "name": name,
            "correction_translation": float(dist[k]),
            "correction_rotation_deg": float(ang[k]),
        }
        if metric:
            entry["correction_mm"] = float(dist[k] * 1000.0)
        objects.append(entry)
    return {
        "src": states[0],
        "dst": states[1],
        "refined": bool(refined),
        "initial": np.asarray(initial, dtype=np.float64).tolist(),
        "final": np.asarray(final, dtype=np.float64).tolist(),
        "objects": objects,
    }
