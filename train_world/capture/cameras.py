"""Camera conventions for captures on disk and for the renderer (numpy, float64).

On disk (``transforms.json``, NeRF-Blender / nerfstudio style) each frame has a ``transform_matrix``: a 4x4
camera-to-world matrix in **OpenGL camera axes** (x right, y up, the camera looks down -z).

The renderer (``dsg_gym.splat``) takes **OpenCV** cameras: x right, y down, z forward; ``viewmats`` are
world-to-camera ``[V,4,4]`` and ``Ks`` are ``[V,3,3]`` pinhole intrinsics whose principal point is in
continuous pixel coordinates where pixel ``(u, v)`` covers ``[u, u+1) x [v, v+1)`` (centre at ``(u+0.5,
v+0.5)``). With a symmetric frustum ``cx = w/2, cy = h/2``. MuJoCo's offscreen renderer follows exactly this
convention (checked by ``tests/test_synth.py`` reprojecting depth maps), with ``fx = fy = 0.5 * h / tan(fovy /
2)``.

Going from one to the other flips the camera's y and z axes: ``c2w_cv = c2w_gl @ diag(1, -1, -1, 1)``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "GL_TO_CV",
    "check_rigid",
    "focal_from_fov",
    "intrinsics_matrix",
    "opengl_c2w_to_viewmat",
    "viewmat_to_opengl_c2w",
]

#  Right-multiplying an OpenGL camera-to-world matrix by this gives the OpenCV camera-to-world matrix (and
# back).
GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def focal_from_fov(fov_rad: float, size_px: float) -> float:
    """Focal length in pixels for a full field of view ``fov_rad`` spanning ``size_px`` pixels."""
    return 0.5 * float(size_px) / float(np.tan(0.5 * float(fov_rad)))


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 pinhole matrix (float64); ``cx, cy`` in the pixel-centre-at-+0.5 convention of the module
    docstring."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def rigidity_error(mat: np.ndarray) -> float:
    """How far a 4x4 (or [...,4,4]) matrix is from a rigid transform (max abs deviation, inf if
    non-finite)."""
    m = np.asarray(mat, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        return float("inf")
    rot = m[..., :3, :3]
    ortho = np.abs(np.swapaxes(rot, -1, -2) @ rot - np.eye(3)).max(initial=0.0)
    det = np.abs(np.linalg.det(rot) - 1.0).max(initial=0.0)
    bottom = np.abs(m[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(initial=0.0)
    return float(max(ortho, det, bottom))


def check_rigid(mat: np.ndarray, what: str, tol: float = 1e-4) -> np.ndarray:
    """Return ``mat`` as float64 [...,4,4] or raise ``ValueError`` naming ``what`` if it is not a rigid
    transform.

    Rigid means finite, rotation block orthonormal with determinant +1 (within ``tol``) and last row ``0 0 0
    1``.
    """
    m = np.asarray(mat, dtype=np.float64)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"{what}: expected a 4x4 matrix, got shape {tuple(m.shape)}")
    if not np.all(np.isfinite(m)):
        raise ValueError(f"{what}: matrix has non-finite entries")
    err = rigidity_error(m)
    if err > tol:
        raise ValueError(
            f"{what}: not a rigid transform (rotation not orthonormal with det +1, or last row not "
            f"0 0 0 1; deviation {err:.3g} > {tol:g})"
        )
    return m


def opengl_c2w_to_viewmat(c2w_gl: np.ndarray) -> np.ndarray:
    """OpenGL camera-to-world [...,4,4] -> OpenCV world-to-camera ``viewmats`` [...,4,4] (float64)."""
    c2w_cv = np.asarray(c2w_gl, dtype=np.float64) @ GL_TO_CV
    rot = c2w_cv[..., :3, :3]
    t = c2w_cv[..., :3, 3:]
    out = np.zeros(c2w_cv.shape, dtype=np.float64)
    rt = np.swapaxes(rot, -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3:] = -rt @ t
    out[..., 3, 3] = 1.0
    return out


def viewmat_to_opengl_c2w(viewmat: np.ndarray) -> np.ndarray:
    """Inverse of :func:`opengl_c2w_to_viewmat`."""
    v = np.asarray(viewmat, dtype=np.float64)
    rot = v[..., :3, :3]
    t = v[..., :3, 3:]
    c2w_cv = np.zeros(v.shape, dtype=np.float64)
    rt = np.swapaxes(rot, -1, -2)
    c2w_cv[..., :3, :3] = rt
    c2w_cv[..., :3, 3:] = -rt @ t
    c2w_cv[..., 3, 3] = 1.0
    return c2w_cv @ GL_TO_CV
