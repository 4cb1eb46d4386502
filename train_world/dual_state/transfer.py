"""Object-aware state transfer ``T`` (DSG-World, "Object-Aware Transformation Modeling").

Every Gaussian belongs to the class the shared classifier gives its identity feature (argmax over K+1
classes; 0 = background). Background Gaussians stay, the Gaussians of object ``k`` move by that object's rigid
transform between two configurations, ``T_a->b[k] = P_b[k] @ inv(P_a[k])`` with ``P`` the world-from-object
poses ``[K,4,4]``. The result is a per-Gaussian ``[N,4,4]`` matrix that ``SegmentedField.render(transform=)``
applies to centres and rotations (gradients flow to the Gaussians, not through the labels).
"""

from __future__ import annotations

import numpy as np
import torch

from dsg_gym.geometry import quat_multiply, rotmat_to_quat

__all__ = ["ObjectTransfer", "gaussian_transforms", "object_labels", "relative_transforms"]


def relative_transforms(
    poses_src: np.ndarray | torch.Tensor, poses_dst: np.ndarray | torch.Tensor
) -> torch.Tensor:
    """``[K,4,4]`` float32 ``P_dst[k] @ inv(P_src[k])`` (world-frame motion of each object)."""
    a = torch.tensor(np.asarray(poses_src), dtype=torch.float64)
    b = torch.tensor(np.asarray(poses_dst), dtype=torch.float64)
    if a.shape != b.shape or a.shape[-2:] != (4, 4):
        raise ValueError(
            f"relative_transforms: poses must both be [K,4,4], got {tuple(a.shape)}, {tuple(b.shape)}"
        )
    return (b @ torch.linalg.inv(a)).float()


@torch.no_grad()
def object_labels(features: torch.Tensor, classifier: torch.nn.Module) -> torch.Tensor:
    """Class per Gaussian ``[N]`` int64: argmax of the shared classifier on its identity feature."""
    if features.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64)
    return classifier(features.detach()).argmax(dim=-1)


def gaussian_transforms(labels: torch.Tensor, object_T: torch.Tensor) -> torch.Tensor:
    """Per-Gaussian rigid transforms ``[N,4,4]``: identity for class 0, ``object_T[c-1]`` for class ``c``.

    ``object_T``: ``[K,4,4]`` (e.g. :func:`relative_transforms`). Labels outside ``0..K`` raise ValueError.
    """
    object_T = torch.as_tensor(object_T, dtype=torch.float32)
    k = object_T.shape[0]
    if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) > k):
        raise ValueError(
            f"gaussian_transforms: labels must be in 0..{k}, got {int(labels.min())}..{int(labels.max())}"
        )
    table = torch.cat([torch.eye(4)[None], object_T], dim=0)  # [K+1,4,4]
    return table[labels.long()]


class ObjectTransfer:
    """``T`` as a callable ``(means, quats) -> (means, quats)`` for ``SegmentedField.render(transform=)``:
    the same result as :func:`gaussian_transforms` but with one rotation matrix and quaternion per class,
    gathered by label, and only the object Gaussians touched (background rows pass through as they are:
    cheaper than ``N`` matrices and ``N`` matrix-to-quaternion conversions)."""

    def __init__(self, labels: torch.Tensor, object_T: torch.Tensor):
        object_T = torch.as_tensor(object_T, dtype=torch.float32)
        table = torch.cat([torch.eye(4)[None], object_T], dim=0)
        R = table[:, :3, :3]
        self._setup(labels, R, table[:, :3, 3], rotmat_to_quat(R))

    @classmethod
    def from_parts(
        cls, labels: torch.Tensor, rotations: torch.Tensor, translations: torch.Tensor, quats: torch.Tensor
    ) -> ObjectTransfer:
        """``T`` from per-object rotations ``[K,3,3]``, translations ``[K,3]`` and the rotations' unit
        quaternions ``[K,4]`` (gradients flow to them: the motion refinement of :mod:`.motions`)."""
        self = cls.__new__(cls)
        eye = torch.eye(3, dtype=rotations.dtype)[None]
        self._setup(
            labels,
            torch.cat([eye, rotations], dim=0),
            torch.cat([torch.zeros(1, 3, dtype=translations.dtype), translations], dim=0),
            torch.cat([torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=quats.dtype), quats], dim=0),
        )
        return self

    def _setup(self, labels: torch.Tensor, R: torch.Tensor, t: torch.Tensor, q: torch.Tensor) -> None:
        """Rows ``[K+1, ...]``: row 0 is the background's identity."""
        k = R.shape[0] - 1
        if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) > k):
            raise ValueError(f"ObjectTransfer: labels must be in 0..{k}")
        self.labels = labels.long()
        self.R, self.t, self.q = R, t, q
        self.moved = torch.nonzero(self.labels > 0).squeeze(1)  # rows of object Gaussians
        self._moved_labels = self.labels[self.moved]

    def rotations(self) -> torch.Tensor:
        """Each Gaussian's rotation ``[N,3,3]`` (for turning its SH colour with it)."""
        return self.R[self.labels]

    def rotate_dirs(self, dirs: torch.Tensor) -> torch.Tensor:
        """View directions ``[C,N,3]`` into each Gaussian's unmoved frame, ``R^T d`` (what
        ``SegmentedField.render`` does with :meth:`rotations`, on the object rows only)."""
        if self.moved.numel() == 0:
            return dirs
        turned = torch.einsum("cnj,nji->cni", dirs[:, self.moved], self.R[self._moved_labels])
        return dirs.index_copy(1, self.moved, turned)

    def __call__(self, means: torch.Tensor, quats: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        idx = self.moved
        if idx.numel() == 0:
            return means, quats
        lab = self._moved_labels
        m = torch.einsum("nij,nj->ni", self.R[lab], means[idx]) + self.t[lab]
        return means.index_copy(0, idx, m), quats.index_copy(0, idx, quat_multiply(self.q[lab], quats[idx]))
