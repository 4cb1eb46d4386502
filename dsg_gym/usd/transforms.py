"""USD's layouts of poses and quaternions (the conversions themselves are :mod:`dsg_gym.poses`).

USD uses row vectors: a ``Gf.Matrix4d`` equals the *transpose* of our column-vector matrix
``[[R, t], [0, 1]]`` (``to_gf_matrix`` / ``from_gf_matrix``). ``Vt.QuatfArray`` / ``Vt.QuatdArray`` numpy
buffers are laid out ``x, y, z, w`` (imaginary first, real last), ours ``w, x, y, z``; ``wxyz_to_usd`` /
``usd_to_wxyz`` reorder.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf

__all__ = ["wxyz_to_usd", "usd_to_wxyz", "to_gf_matrix", "from_gf_matrix"]


def wxyz_to_usd(q: np.ndarray) -> np.ndarray:
    """``[..., 4]`` w, x, y, z -> the ``Vt.Quat*Array`` numpy layout x, y, z, w (contiguous copy)."""
    return np.ascontiguousarray(np.asarray(q)[..., [1, 2, 3, 0]])


def usd_to_wxyz(q: np.ndarray) -> np.ndarray:
    """``Vt.Quat*Array`` numpy layout x, y, z, w -> ``[..., 4]`` w, x, y, z (contiguous copy)."""
    return np.ascontiguousarray(np.asarray(q)[..., [3, 0, 1, 2]])


def to_gf_matrix(mat: np.ndarray) -> Gf.Matrix4d:
    """Column-vector 4x4 (ours) -> ``Gf.Matrix4d`` (USD row-vector convention: the transpose)."""
    return Gf.Matrix4d(np.asarray(mat, dtype=np.float64).T.tolist())


def from_gf_matrix(m: Gf.Matrix4d) -> np.ndarray:
    """``Gf.Matrix4d`` (row vectors) -> column-vector float64 ``[4, 4]``."""
    return np.array(m, dtype=np.float64).T.copy()
