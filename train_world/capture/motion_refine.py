"""Refining one object's rigid motion together with its 3D points (a small bundle adjustment, cameras fixed).

Points ``X [P,3]`` live in the first state's frame; an observation of point ``i`` in a view of the first
state projects ``X_i``, one in a view of the second state projects ``R X_i + t``. :func:`refine_motion`
minimises the reprojection errors (pixels, Cauchy loss) over the motion and the points, drops observations
that stay far off, and solves again. Float64 throughout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["Observations", "refine_motion"]


@dataclass(frozen=True)
class Observations:
    """``point [O]`` (index into the points), ``moved [O]`` bool (seen in the second state), ``K [O,3,3]``,
    OpenCV world-to-camera ``w2c [O,4,4]`` and pixel positions ``xy [O,2]``."""

    point: np.ndarray
    moved: np.ndarray
    K: np.ndarray
    w2c: np.ndarray
    xy: np.ndarray

    def subset(self, keep: np.ndarray) -> Observations:
        return Observations(self.point[keep], self.moved[keep], self.K[keep], self.w2c[keep], self.xy[keep])


def reprojection_errors(T: np.ndarray, X: np.ndarray, obs: Observations) -> np.ndarray:
    """Residuals ``[O,2]`` (pixels) of ``obs`` for motion ``T [4,4]`` and points ``X [P,3]``."""
    Y = X[obs.point]
    Y = np.where(obs.moved[:, None], Y @ T[:3, :3].T + T[:3, 3], Y)
    c = np.einsum("oij,oj->oi", obs.w2c[:, :3, :3], Y) + obs.w2c[:, :3, 3]
    uv = np.einsum("oij,oj->oi", obs.K, c)
    z = np.where(np.abs(uv[:, 2:3]) > 1e-12, uv[:, 2:3], 1e-12)
    return uv[:, :2] / z - obs.xy


def _skew(v: np.ndarray) -> np.ndarray:
    """``[N,3]`` -> ``[N,3,3]`` cross-product matrices."""
    z = np.zeros(len(v))
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], 1),
            np.stack([v[:, 2], z, -v[:, 0]], 1),
            np.stack([-v[:, 1], v[:, 0], z], 1),
        ],
        1,
    )


def _solve(
    T: np.ndarray, X: np.ndarray, obs: Observations, scale_px: float, iters: int = 50
) -> tuple[np.ndarray, np.ndarray]:
    """Levenberg-Marquardt with Cauchy weights (IRLS) on the motion (left-multiplied rotation increment and
    translation) and the points; analytic Jacobians, normal equations reduced to the motion's 6 unknowns by
    the Schur complement of the points' 3x3 blocks."""
    T, X = T.copy(), X.copy()
    n_pts, n_obs = len(X), len(obs.point)
    moved = obs.moved

    def cost(T_, X_) -> float:
        r2 = np.sum(reprojection_errors(T_, X_, obs) ** 2, axis=1)
        return float(np.sum(np.log1p(r2 / scale_px**2)))

    lam, current = 1e-3, cost(T, X)
    for _ in range(iters):
        RX = X[obs.point] @ T[:3, :3].T
        Y = np.where(moved[:, None], RX + T[:3, 3], X[obs.point])
        c = np.einsum("oij,oj->oi", obs.w2c[:, :3, :3], Y) + obs.w2c[:, :3, 3]
        z = c[:, 2]
        fx, fy = obs.K[:, 0, 0], obs.K[:, 1, 1]
        r = np.stack([fx * c[:, 0] / z + obs.K[:, 0, 2], fy * c[:, 1] / z + obs.K[:, 1, 2]], 1) - obs.xy
        jc = np.zeros((n_obs, 2, 3))
        jc[:, 0, 0], jc[:, 0, 2] = fx / z, -fx * c[:, 0] / z**2
        jc[:, 1, 1], jc[:, 1, 2] = fy / z, -fy * c[:, 1] / z**2
        jy = jc @ obs.w2c[:, :3, :3]  # d r / d Y  [O,2,3]
        jx = np.where(moved[:, None, None], jy @ T[:3, :3], jy)  # d r / d X
        jm = np.zeros((n_obs, 2, 6))
        jm[:, :, :3] = -jy @ _skew(RX)  # rotation increment exp([w]) R
        jm[:, :, 3:] = jy
        jm[~moved] = 0.0
        w = 1.0 / (1.0 + np.sum(r**2, axis=1) / scale_px**2)
        # normal equations in blocks: motion (6) and one 3x3 block per point, solved by the Schur complement
        wjm = jm * w[:, None, None]
        wjx = jx * w[:, None, None]
        A = np.einsum("oki,okj->ij", wjm, jm)
        g_m = np.einsum("oki,ok->i", wjm, r)
        C = np.zeros((n_pts, 3, 3))
        B = np.zeros((n_pts, 6, 3))
        g_x = np.zeros((n_pts, 3))
        np.add.at(C, obs.point, np.einsum("oki,okj->oij", wjx, jx))
        np.add.at(B, obs.point, np.einsum("oki,okj->oij", wjm, jx))
        np.add.at(g_x, obs.point, np.einsum("oki,ok->oi", wjx, r))
        improved = False
        for _ in range(10):
            Ad = A + lam * np.diag(np.maximum(np.diag(A), 1e-12))
            Cd = C + lam * np.eye(3) * np.maximum(np.diagonal(C, axis1=1, axis2=2), 1e-12)[:, None, :]
            try:
                Ci = np.linalg.inv(Cd)
                BCi = B @ Ci  # [P,6,3]
                S_ = Ad - np.einsum("pij,pkj->ik", BCi, B)
                dm = -np.linalg.solve(S_, g_m - np.einsum("pij,pj->i", BCi, g_x))
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            dx = -np.einsum("pij,pj->pi", Ci, g_x + np.einsum("pji,j->pi", B, dm))
            step = np.concatenate([dm, dx.ravel()])
            T_new = np.eye(4)
            T_new[:3, :3] = Rotation.from_rotvec(step[:3]).as_matrix() @ T[:3, :3]
            T_new[:3, 3] = T[:3, 3] + step[3:6]
            X_new = X + step[6:].reshape(n_pts, 3)
            new = cost(T_new, X_new)
            if new < current:
                T, X, lam, improved = T_new, X_new, max(lam / 10, 1e-9), True
                done = current - new < 1e-10 * max(current, 1e-12)
                current = new
                break
            lam *= 10
        if not improved or done:
            break
    return T, X


def refine_motion(
    T0: np.ndarray, X0: np.ndarray, obs: Observations, scale_px: float = 1.0, max_error_px: float = 3.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refined ``(T [4,4], X [P,3], kept [O] bool)``: solve, drop observations off by more than
    ``max_error_px``, solve again. Points left with observations in one state only do not constrain the
    motion (they are kept but ignored by the caller's counts)."""
    T0 = np.asarray(T0, np.float64)
    X0 = np.asarray(X0, np.float64).reshape(-1, 3)
    T, X = _solve(T0, X0, obs, scale_px)
    kept = np.linalg.norm(reprojection_errors(T, X, obs), axis=1) <= max_error_px
    if kept.sum() >= 6 and not kept.all():
        T, X = _solve(T, X, obs.subset(kept), scale_px)
        kept = np.linalg.norm(reprojection_errors(T, X, obs), axis=1) <= max_error_px
    u, _, vt = np.linalg.svd(T[:3, :3])
    T[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return T, X, kept
