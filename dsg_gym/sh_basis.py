"""Real spherical-harmonics basis (degree 0..3, 3DGS order and signs) in numpy, and SH rotation.

Torch-free so the world-file reader can rotate colours without torch; :mod:`dsg_gym.splat.sh` evaluates the
same basis in torch for rendering and takes its constants from here. Coefficients are ``[..., K, D]`` with
``K = (degree + 1)^2`` (index 0 the constant term, then the 3 linear, 5 quadratic and 7 cubic ones).
"""

from __future__ import annotations

import numpy as np

__all__ = ["C0", "C1", "C2", "C3", "basis_columns", "num_sh_bases", "rotate_sh", "sh_basis", "sh_rotation"]

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of basis functions up to ``degree``: (degree + 1)^2."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"sh degree must be 0..3, got {degree}")
    return (degree + 1) ** 2


def basis_columns(degree: int, x, y, z, ones) -> list:
    """The ``(degree + 1)^2`` basis functions at unit direction components ``x, y, z`` as a list of arrays
    shaped like them (3DGS order and signs). Plain arithmetic only, so numpy arrays and torch tensors
    (:func:`dsg_gym.splat.sh.spherical_harmonics`) share this one definition; ``ones``: ones like ``x``."""
    cols = [ones * C0]
    if degree >= 1:
        cols += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        cols += [C2[0] * xy, C2[1] * yz, C2[2] * (2.0 * zz - xx - yy), C2[3] * xz, C2[4] * (xx - yy)]
    if degree >= 3:
        cols += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * xy * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return cols[: num_sh_bases(degree)]


def sh_basis(degree: int, dirs: np.ndarray) -> np.ndarray:
    """The basis functions ``[M, K]`` (float64) at unit directions ``dirs`` ``[M, 3]``."""
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    return np.stack(basis_columns(degree, x, y, z, np.ones_like(x)), axis=1)


def _sphere_points(n: int) -> np.ndarray:
    """``n`` unit vectors spread over the sphere (Fibonacci lattice), float64 ``[n,3]``."""
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def sh_rotation(R: np.ndarray, degree: int) -> np.ndarray:
    """``D [K,K]`` (float64) such that coefficients ``D @ c`` describe the colour function of ``c`` rotated
    by ``R`` ``[3,3]``: ``f'(d) = f(R^T d)`` for every direction ``d``.

    Use it when a Gaussian is rotated by ``R`` (its view-dependent colour turns with it). Each degree's basis
    spans a rotation-invariant space, so ``D`` is block diagonal with orthogonal blocks; it is found exactly
    (to float64 rounding) by least squares on 64 directions.
    """
    k = num_sh_bases(degree)
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise ValueError(f"sh_rotation: R must be a finite [3,3] rotation, got shape {R.shape}")
    dirs = _sphere_points(64)
    D = np.linalg.lstsq(sh_basis(degree, dirs), sh_basis(degree, dirs @ R), rcond=None)[
        0
    ]  # Y(d) D = Y(R^T d)
    blocks = np.zeros((k, k), dtype=bool)
    for lvl in range(degree + 1):
        blocks[lvl * lvl : (lvl + 1) ** 2, lvl * lvl : (lvl + 1) ** 2] = True
    D = np.where(blocks, D, 0.0)
    D[0, 0] = 1.0  # the constant term is rotation invariant: DC colours stay bit for bit
    return D


def rotate_sh(coeffs: np.ndarray, R: np.ndarray) -> np.ndarray:
    """SH coefficients ``[..., K, D]`` of Gaussians rotated by ``R`` ``[3,3]`` (see :func:`sh_rotation`), in
    the dtype of ``coeffs``. A DC-only set (K = 1) is returned as it is."""
    coeffs = np.asarray(coeffs)
    k = coeffs.shape[-2]
    if k == 1:
        return coeffs
    degree = {4: 1, 9: 2, 16: 3}.get(k)
    if degree is None:
        raise ValueError(f"rotate_sh: {k} bases is not a full degree 0..3 set")
    D = sh_rotation(R, degree)
    return np.einsum("ij,...jd->...id", D, coeffs.astype(np.float64)).astype(coeffs.dtype)
