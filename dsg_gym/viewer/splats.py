"""A :class:`~dsg_gym.gaussians.GaussianSet` as the arrays of viser's Gaussian splat API.

viser draws each Gaussian from its centre, its 3D covariance ``R S S R^T`` (``R`` the rotation of its
quaternion, ``S`` its standard deviations), an RGB colour and an opacity. Colours are the view-independent
(DC) part of the spherical harmonics, ``0.5 + SH_C0 * sh[:, 0]`` clipped to [0, 1]: the browser shows no
view-dependent shading. The env's own renders (the panel's observation) do.
"""

from __future__ import annotations

import numpy as np

from ..gaussians import SH_C0, GaussianSet
from ..poses import quat_to_rotmat

__all__ = ["viser_splats"]


def viser_splats(g: GaussianSet) -> dict[str, np.ndarray]:
    """``{"centers" [N,3], "covariances" [N,3,3], "rgbs" [N,3], "opacities" [N,1]}`` float32 arrays of
    ``g`` for ``viser``'s ``scene.add_gaussian_splats`` (in ``g``'s own frame)."""
    q = np.asarray(g.quats, np.float64)
    norm = np.linalg.norm(q, axis=1, keepdims=True)
    q = np.where(norm > 0, q / np.where(norm > 0, norm, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    m = quat_to_rotmat(q) * np.asarray(g.scales, np.float64)[:, None, :]
    cov = m @ np.swapaxes(m, 1, 2)
    rgb = np.clip(0.5 + SH_C0 * np.asarray(g.sh[:, 0], np.float64), 0.0, 1.0)
    return {
        "centers": np.ascontiguousarray(g.means, np.float32),
        "covariances": cov.astype(np.float32),
        "rgbs": rgb.astype(np.float32),
        "opacities": np.clip(np.asarray(g.opacities, np.float32), 0.0, 1.0)[:, None],
    }
