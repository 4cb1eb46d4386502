"""Refining an object's motion by its appearance: each photo of one state against the most alike photo of the other.

Features and silhouettes place a small object to about a degree at 128 px; its colours hold more. Under the
true motion, a photo of the second state and the photo of the first state taken from the same side of the
object (the same direction from the object's centre, in the object's own frame) see the same surface points at
the same shading when the light that dominates the capture moves with the camera (a phone's flash,
``dsg-synth``'s camera light) or comes from everywhere (an overcast room), so what differs is only where the
object is. :func:`refine_motion_by_appearance`
pairs the photos that way and minimises, over the object's turn, the colour differences at the points of each
state's visual hull that both photos of a pair see (:func:`visible`: in front, on the object's mask, not hidden
by the hull itself), from blurred photos to sharp ones (a robust loss; a weak pull towards the starting turn
keeps turns the photos do not fix, such as a plain ball's spin, where they started). A hull point off the true
surface still lands on the same surface point in both photos of a pair, because they look at it from nearly
the same direction. On a plain object the colours are shading alone, which shifts between two photos a few
degrees apart; ``dsg-capture`` therefore refines only objects with texture (:mod:`.motions`).

A symmetric shape (a ball, a cylinder, a prism) fits its hulls equally well at many turns, and features may
pick the wrong one; its pattern does not. Given the turns its shape cannot tell apart
(:func:`.silhouettes.symmetric_fits`), the refinement first starts from the one whose colours agree best.

Coordinates are the cameras' (OpenCV world-to-camera ``w2c``); float64 geometry; deterministic.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_erosion, gaussian_filter, map_coordinates, minimum_filter
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from train_world.capture.silhouettes import SilhouetteView, surface_voxels

__all__ = [
    "AppearanceConfig",
    "AppearanceFit",
    "ColourView",
    "colour_score",
    "refine_motion_by_appearance",
    "surface_normals",
    "visible",
]


@dataclass(frozen=True)
class ColourView(SilhouetteView):
    """One photo: a :class:`.silhouettes.SilhouetteView` (object ids ``ids [h,w]`` uint8, 0 = background,
    intrinsics ``K [3,3]`` for that size, OpenCV world-to-camera ``w2c [4,4]``) with its colours
    ``rgb [h,w,3]`` uint8."""

    rgb: np.ndarray


@dataclass(frozen=True)
class AppearanceConfig:
    """Thresholds of :func:`refine_motion_by_appearance`.

    ``blurs``: Gaussian blur of the photos (pixels) at each level, coarse to fine. ``max_pair_angle_deg``: the
    largest angle, seen from the object, between the two photos of a pair. ``loss_scale``: colour difference
    (0..1) beyond which the robust (soft L1) loss discounts a residual. ``prior``: weight of the pull towards
    the starting turn, in colour units per radian, per residual. ``min_points``: fewest hull points seen in
    both photos for a pair to count. ``max_turn_deg``: the largest turn from the start accepted; a larger one
    means the photos disagree with the start, which is then kept."""

    blurs: tuple[float, ...] = (2.0, 1.0, 0.5)
    max_pair_angle_deg: float = 20.0
    loss_scale: float = 0.05
    prior: float = 0.02
    min_points: int = 20
    max_turn_deg: float = 10.0
    choice_blur: float = 1.0


@dataclass(frozen=True)
class AppearanceFit:
    """``transform [4,4]`` (first state to second), photo ``pairs`` used (both directions, sharpest level),
    colour RMS (0..1) of the residuals on the sharpest photos at the given motion (``rms_before``) and at the
    result (``rms_after``), the result's ``turn_deg`` from the given motion and whether it was kept
    (``accepted``; otherwise ``transform`` is the given motion); the number of other ``candidates`` compared
    with the given motion and the turn from it to the one the refinement started from (``chosen_turn_deg``,
    0 when that was the given motion itself)."""

    transform: np.ndarray
    pairs: int
    rms_before: float
    rms_after: float
    turn_deg: float
    accepted: bool
    candidates: int = 0
    chosen_turn_deg: float = 0.0


def surface_normals(points: np.ndarray, hull: np.ndarray, step: float) -> np.ndarray:
    """Outward unit normals ``[N,3]`` of hull surface ``points [N,3]``: away from the mean of the hull's voxels
    within 2.5 voxels (``hull [M,3]``, voxel size ``step``)."""
    tree = cKDTree(hull)
    out = np.zeros_like(points)
    for i, nb in enumerate(tree.query_ball_point(points, 2.5 * step)):
        out[i] = points[i] - hull[nb].mean(axis=0)
    n = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(n > 1e-12, out / np.maximum(n, 1e-300), 0.0)


def _project(v: ColourView, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[N,2]`` (pixel centres at integers) and depth ``[N]`` of ``X [N,3]`` in ``v``."""
    c = X @ v.w2c[:3, :3].T + v.w2c[:3, 3]
    z = c[:, 2]
    zs = np.where(z > 1e-12, z, 1e-12)
    uv = np.stack([v.K[0, 0] * c[:, 0] / zs + v.K[0, 2], v.K[1, 1] * c[:, 1] / zs + v.K[1, 2]], axis=1) - 0.5
    return uv, z


def visible(v: ColourView, obj: int, X: np.ndarray, N: np.ndarray, step: float) -> np.ndarray:
    """Which hull surface points ``X [N,3]`` (normals ``N [N,3]``, voxel size ``step``) photo ``v`` sees on
    object ``obj``: facing the camera, projecting at least a pixel inside the object's mask, and no more than
    two voxels behind the nearest hull point projecting nearby (a 3x3 pixel z-buffer of the points)."""
    uv, z = _project(v, X)
    h, w = v.ids.shape
    facing = np.einsum("ij,ij->i", N, v.centre - X) > 0
    px = np.round(uv).astype(np.int64)
    ok = (z > 1e-12) & (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    inner = binary_erosion(v.ids == obj, border_value=0)
    ok &= inner[np.clip(px[:, 1], 0, h - 1), np.clip(px[:, 0], 0, w - 1)]
    zbuf = np.full((h, w), np.inf)
    np.minimum.at(zbuf, (px[ok, 1], px[ok, 0]), z[ok])
    zbuf = minimum_filter(zbuf, size=3, mode="nearest")
    ok[ok] &= z[ok] <= zbuf[px[ok, 1], px[ok, 0]] + 2.0 * step
    return ok & facing


def _pairs(
    views_a: list[ColourView],
    views_b: list[ColourView],
    T: np.ndarray,
    centre_a: np.ndarray,
    max_angle_deg: float,
) -> list[tuple[int, int]]:
    """For each photo ``b`` of the second state the photo ``a`` of the first whose direction from the object
    (``centre_a`` in the first state, carried by ``T``) is nearest, within ``max_angle_deg``."""
    da = np.array([v.centre - centre_a for v in views_a])
    da /= np.linalg.norm(da, axis=1, keepdims=True)
    cb = T[:3, :3] @ centre_a + T[:3, 3]
    db = np.array([T[:3, :3].T @ (v.centre - cb) for v in views_b])  # in the first state's frame
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    cos = db @ da.T
    out = []
    for b, row in enumerate(cos):
        a = int(np.argmax(row))
        if row[a] >= np.cos(np.radians(max_angle_deg)):
            out.append((a, b))
    return out


class _Terms:
    """The residuals of one direction (points of the first state's hull, photos of the first state against
    their partners in the second) at one blur level."""

    def __init__(self, views_a, views_b, imgs_a, imgs_b, obj, X, N, step, pairs, T, min_points):
        self.imgs_b, self.h = imgs_b, views_b[0].ids.shape[0] if views_b else 0
        pts, ref, vb = [], [], []
        vis_a = {}
        Y = X @ T[:3, :3].T + T[:3, 3]
        NY = N @ T[:3, :3].T
        for a, b in pairs:
            if a not in vis_a:
                vis_a[a] = visible(views_a[a], obj, X, N, step)
            sel = vis_a[a] & visible(views_b[b], obj, Y, NY, step)
            if sel.sum() < min_points:
                continue
            uv, _ = _project(views_a[a], X[sel])
            ref.append(_sample(imgs_a, views_a[a].ids.shape[0], np.full(len(uv), a), uv))
            pts.append(X[sel])
            vb.append(np.full(int(sel.sum()), b))
        self.n_pairs = len(pts)
        self.pts = np.concatenate(pts) if pts else np.zeros((0, 3))
        self.ref = np.concatenate(ref) if ref else np.zeros((0, 3))
        self.vb = np.concatenate(vb) if vb else np.zeros(0, np.int64)
        P = np.stack([v.K @ v.w2c[:3, :4] for v in views_b]) if views_b else np.zeros((0, 3, 4))
        self.P = P[self.vb]  # each point's projection matrix in its partner photo

    def residuals(self, T: np.ndarray) -> np.ndarray:
        """Colour differences ``[3 * points]`` with the first state's points moved by ``T [4,4]``."""
        if not self.n_pairs:
            return np.zeros(0)
        Y = self.pts @ T[:3, :3].T + T[:3, 3]
        p = np.einsum("nij,nj->ni", self.P[:, :, :3], Y) + self.P[:, :, 3]
        z = np.where(p[:, 2:] > 1e-12, p[:, 2:], 1e-12)
        return (_sample(self.imgs_b, self.h, self.vb, p[:, :2] / z - 0.5) - self.ref).ravel()


def _cropped(views: list[ColourView], obj: int, blurs: tuple[float, ...]) -> list[ColourView]:
    """The photos cut to one window size around object ``obj`` (its largest bounding box in any photo, plus a
    margin of a quarter of it and three times the largest blur), intrinsics shifted to match: what the object
    needs of large photos, without holding them whole for every blur level."""
    boxes = []
    for v in views:
        ys, xs = np.nonzero(v.ids == obj)
        boxes.append((ys.min(), ys.max() + 1, xs.min(), xs.max() + 1) if len(xs) else None)
    sizes = np.array([(b[1] - b[0], b[3] - b[2]) for b in boxes if b is not None]).reshape(-1, 2)
    h, w = views[0].ids.shape
    if len(sizes) == 0:
        return views
    pad = int(np.ceil(3 * max(blurs, default=0.0))) + 2
    ch = min(h, int(sizes[:, 0].max() * 1.5) + 2 * pad)
    cw = min(w, int(sizes[:, 1].max() * 1.5) + 2 * pad)
    out = []
    for v, b in zip(views, boxes, strict=True):
        cy, cx = ((b[0] + b[1]) // 2, (b[2] + b[3]) // 2) if b is not None else (h // 2, w // 2)
        y0, x0 = int(np.clip(cy - ch // 2, 0, h - ch)), int(np.clip(cx - cw // 2, 0, w - cw))
        K = v.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        out.append(ColourView(v.ids[y0 : y0 + ch, x0 : x0 + cw], K, v.w2c, v.rgb[y0 : y0 + ch, x0 : x0 + cw]))
    return out


def _stacked(rgb: np.ndarray, blur: float) -> np.ndarray:
    """Photos ``rgb [V,h,w,3]`` blurred by ``blur`` px, as ``[3, V*h, w]`` (one plane per channel, the photos
    one below the other) for :func:`_sample`."""
    out = gaussian_filter(rgb, (0, blur, blur, 0)) if blur > 0 else rgb
    v, h, w, _ = out.shape
    return np.ascontiguousarray(np.moveaxis(out, 3, 0).reshape(3, v * h, w))


def _sample(imgs: np.ndarray, h: int, view: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear colours ``[N,3]`` of stacked photos ``imgs [3, V*h, w]`` (:func:`_stacked`) at photos
    ``view [N]`` and pixels ``uv [N,2]`` (clamped to the photo)."""
    y = np.clip(uv[:, 1], 0.0, h - 1.0) + view * h
    x = np.clip(uv[:, 0], 0.0, imgs.shape[2] - 1.0)
    return np.stack([map_coordinates(c, [y, x], order=1, mode="nearest") for c in imgs], axis=1)


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2))) if len(r) else float("nan")


def _soft_l1(r: np.ndarray, scale: float) -> float:
    """Mean soft-L1 loss of residuals ``r`` (as :func:`scipy.optimize.least_squares` weighs them); inf for none."""
    return float(np.mean(2.0 * (np.sqrt(1.0 + (r / scale) ** 2) - 1.0))) if len(r) else float("inf")


def _angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(A[:3, :3] @ B[:3, :3].T).magnitude()))


def _turned(w: np.ndarray, T: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """``T [4,4]`` followed by the turn ``w [3]`` (rotation vector, radians) about ``pivot [3]``."""
    R = Rotation.from_rotvec(w).as_matrix()
    out = np.eye(4)
    out[:3, :3] = R @ T[:3, :3]
    out[:3, 3] = R @ (T[:3, 3] - pivot) + pivot
    return out


class _Photos:
    """Both states' photos of one object cut to its window (:func:`_cropped`), blurred on demand, with its
    hulls' surface points and normals: what the colour residuals of any motion need."""

    def __init__(self, hull1, hull2, views1, views2, obj: int, cfg: AppearanceConfig):
        (h1, self.s1), (h2, self.s2) = hull1, hull2
        self.obj, self.cfg, self.levels = obj, cfg, {}
        self.X1, self.X2 = surface_voxels(h1, self.s1), surface_voxels(h2, self.s2)
        self.usable = bool(min(len(self.X1), len(self.X2)) >= cfg.min_points and views1 and views2)
        if not self.usable:
            return
        self.N1, self.N2 = surface_normals(self.X1, h1, self.s1), surface_normals(self.X2, h2, self.s2)
        self.c1, self.c2 = h1.mean(axis=0), h2.mean(axis=0)
        self.views1, self.views2 = _cropped(views1, obj, cfg.blurs), _cropped(views2, obj, cfg.blurs)
        self.rgb1 = np.stack([v.rgb for v in self.views1]).astype(np.float32) / 255.0
        self.rgb2 = np.stack([v.rgb for v in self.views2]).astype(np.float32) / 255.0

    def level(self, blur: float) -> tuple[np.ndarray, np.ndarray]:
        if blur not in self.levels:
            self.levels[blur] = (_stacked(self.rgb1, blur), _stacked(self.rgb2, blur))
        return self.levels[blur]

    def terms(self, T: np.ndarray, blur: float) -> tuple[_Terms, _Terms]:
        """Both directions' residual terms of motion ``T [4,4]`` on the photos blurred by ``blur``."""
        cfg, (i1, i2), Ti = self.cfg, self.level(blur), np.linalg.inv(T)
        sides = (
            (self.views1, self.views2, i1, i2, self.X1, self.N1, self.s1, self.c1, T),
            (self.views2, self.views1, i2, i1, self.X2, self.N2, self.s2, self.c2, Ti),
        )
        out = []
        for va, vb, ia, ib, X, N, step, c, M in sides:
            pairs = _pairs(va, vb, M, c, cfg.max_pair_angle_deg)
            out.append(_Terms(va, vb, ia, ib, self.obj, X, N, step, pairs, M, cfg.min_points))
        return out[0], out[1]

    def cost(self, T: np.ndarray) -> float:
        """Mean robust colour difference of motion ``T [4,4]`` on the photos blurred by ``choice_blur``."""
        if not self.usable:
            return float("inf")
        f, b = self.terms(T, self.cfg.choice_blur)
        return _soft_l1(np.concatenate([f.residuals(T), b.residuals(np.linalg.inv(T))]), self.cfg.loss_scale)


def colour_score(
    hull1: tuple[np.ndarray, float],
    hull2: tuple[np.ndarray, float],
    views1: list[ColourView],
    views2: list[ColourView],
    obj: int,
    config: AppearanceConfig | None = None,
) -> Callable[[np.ndarray], float]:
    """A score of motions ``T [4,4]`` of object ``obj`` by its colours (arguments as
    :func:`refine_motion_by_appearance`'s): the mean robust (soft L1) colour difference, at the hull points
    both photos of each pair see, between the photos blurred by ``config.choice_blur`` px; lower is better,
    inf when no pair sees the object. Under light that moves with the camera even a plain object's shading
    agrees best at its true turn, so it breaks ties that shape alone leaves."""
    photos = _Photos(hull1, hull2, views1, views2, obj, config or AppearanceConfig())
    return photos.cost


def refine_motion_by_appearance(
    T0: np.ndarray,
    hull1: tuple[np.ndarray, float],
    hull2: tuple[np.ndarray, float],
    views1: list[ColourView],
    views2: list[ColourView],
    obj: int,
    config: AppearanceConfig | None = None,
    candidates: list[np.ndarray] | None = None,
) -> AppearanceFit:
    """Refine the turn of object ``obj``'s motion ``T0 [4,4]`` (first state to second) by its colours (module
    docstring), about the centre of its first state's hull carried by ``T0``: the translation of that centre
    stays as given (the hulls fix it to about a millimetre; colours of a plain object would pull it).
    ``candidates``: other motions ``[4,4]`` the shape allows as well as ``T0`` (its symmetric turns); the
    refinement starts from whichever of ``T0`` and these agrees best with the photos blurred by
    ``config.choice_blur`` (their translation replaced so that they, too, carry the centre where ``T0`` does).

    ``hull1 = (voxel centres [N,3], voxel size)``: its visual hull in the first state
    (:func:`.silhouettes.visual_hull`), ``views1`` that state's photos (all of one size); likewise for the
    second state. Returns ``T0`` unchanged (``accepted=False``) when no pair of photos sees enough of the
    object in both states, when the refinement would turn more than ``config.max_turn_deg`` from where it
    started or when the result matches the sharpest photos worse than ``T0`` (colour RMS, each judged at the
    points both photos of a pair see under it)."""
    cfg = config or AppearanceConfig()
    T0 = np.asarray(T0, np.float64)
    none = AppearanceFit(T0, 0, float("nan"), float("nan"), 0.0, False)
    photos = _Photos(hull1, hull2, views1, views2, obj, cfg)
    if not photos.usable:
        return none
    pivot = T0[:3, :3] @ photos.c1 + T0[:3, 3]
    fwd, bwd = photos.terms(T0, cfg.blurs[-1])  # the start, on the sharpest photos
    if fwd.n_pairs + bwd.n_pairs == 0:
        return none
    rms_before = _rms(np.concatenate([fwd.residuals(T0), bwd.residuals(np.linalg.inv(T0))]))
    start = T0
    if candidates:  # the start among the shape's equals: the one whose colours agree best (T0 on ties)
        best = photos.cost(T0)
        for C in candidates:
            M = np.eye(4)
            M[:3, :3] = np.asarray(C, np.float64)[:3, :3]
            M[:3, 3] = pivot - M[:3, :3] @ photos.c1
            c = photos.cost(M)
            if c < best:
                start, best = M, c
    T = start
    for blur in cfg.blurs:
        fwd, bwd = photos.terms(T, blur)
        pairs = fwd.n_pairs + bwd.n_pairs
        if pairs == 0:
            return none
        w_prior = cfg.prior * np.sqrt(3.0 * (len(fwd.ref) + len(bwd.ref)))

        def res(w, T_start=T, fwd=fwd, bwd=bwd, w_prior=w_prior):
            M = _turned(w, T_start, pivot)
            return np.concatenate([fwd.residuals(M), bwd.residuals(np.linalg.inv(M)), w_prior * w])

        sol = least_squares(res, np.zeros(3), loss="soft_l1", f_scale=cfg.loss_scale, x_scale=0.01,
                            diff_step=1e-4, max_nfev=100)  # fmt: skip
        T = _turned(sol.x, T, pivot)
    fwd, bwd = photos.terms(T, cfg.blurs[-1])  # the result, judged as the start was
    rms_after = _rms(np.concatenate([fwd.residuals(T), bwd.residuals(np.linalg.inv(T))]))
    turn = _angle_deg(T, start)
    ok = bool(turn <= cfg.max_turn_deg and rms_after <= rms_before and np.all(np.isfinite(T)))
    return AppearanceFit(T if ok else T0, pairs, rms_before, rms_after, _angle_deg(T, T0), ok,
                         len(candidates or []), _angle_deg(start, T0))  # fmt: skip
