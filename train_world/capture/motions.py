"""Per-object rigid motions between the two states, from the objects' features and silhouettes.

Features (:mod:`.features`, :mod:`.tracks`) give candidate motions three ways: the first state's tracks seen by
the second state's views (generalized absolute pose, LO-RANSAC), the reverse, and track-to-track 3D
correspondences (RANSAC on 3-point Kabsch fits, then reweighted least squares). The candidate that explains
most 2D-3D correspondences is refined with the object's points by bundle adjustment (:mod:`.motion_refine`).
The visual hulls (:mod:`.silhouettes`) then refine that rotation locally. When the refined fit is clearly
worse than the best of the hull fits from turns about the table normal, a hull fit is taken instead: the one
that agrees best with the masks (:mod:`.mask_fit`), and among equally good ones the nearest to the features'
turn about the normal (texture still picks among a symmetric shape's equivalent turns). The hulls' centroids,
which the masks fix to about a millimetre, give the translation; when one hull is clearly larger than the other
(another object hid the object from views that would have carved it), the smaller is fitted inside the larger
instead (:func:`.silhouettes.fit_into_larger`). An object without usable features (a plain
ball) gets the hull fit that agrees best with its masks; among equally good ones the one whose colours agree
best when the photos are given (:func:`.appearance.colour_score`: under light that moves with the camera a
plain object's shading still tells its turns apart), else the smallest turn. An object
with texture (features found) then has its turn refined by its colours (:mod:`.appearance`) when the photos
are given, starting from whichever of the turns its hulls cannot tell apart (:func:`.silhouettes.symmetric_fits`:
a ball's every turn, a prism's sides, upside down) its colours agree with best.
Coordinates are those of the cameras (the reconstruction's frame); float64; deterministic (seeded).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from train_world.capture.alignment import umeyama
from train_world.capture.appearance import (
    AppearanceFit,
    ColourView,
    colour_score,
    refine_motion_by_appearance,
)
from train_world.capture.features import ViewFeatures
from train_world.capture.loader import ObjectInfo
from train_world.capture.mask_fit import choose_on_masks
from train_world.capture.photos import PhotoCaptureError
from train_world.capture.silhouettes import (
    SilhouetteView,
    fit_into_larger,
    hull_fits,
    object_centre,
    refine_hull_alignment,
    symmetric_fits,
    visual_hull,
)
from train_world.capture.tracks import match_points_to_views, match_tracks, triangulate_tracks

__all__ = [
    "FeatureMotion",
    "MotionError",
    "ObjectMotion",
    "estimate_feature_motion",
    "estimate_object_motion",
    "fit_motion_to_views",
    "fit_rigid_ransac",
]

#: fewest object points seen in both states for a feature-based motion
MIN_INLIERS = 6
#: fewest voxels in a usable visual hull, and the largest volume ratio between the two states' hulls
MIN_HULL_VOXELS = 50
MAX_HULL_RATIO = 2.0
#: volume ratio of the two states' hulls above which the larger is taken to be inflated (another object hid it
#: from views that would have carved it): the smaller is then placed inside it instead of matching centroids
#: (on the seven default scenes the ratio is at most 1.08, except an occluded cube's 1.36)
HULL_INFLATED = 1.2
#: the features' motion, refined on the hulls, is kept when its hull alignment is within this many voxels of
#: the best silhouette fit from turns about the table normal; otherwise that fit nearest to the features' turn
HULL_AGREEMENT = 0.05


class MotionError(PhotoCaptureError):
    """An object's motion could not be estimated; the message names the object and what to do."""


def _rigid(p: np.ndarray, q: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    _, rot, t = umeyama(p, q, w, with_scale=False)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rot, t
    return m


def fit_rigid_ransac(
    p: np.ndarray, q: np.ndarray, threshold: float, seed: int = 0, max_iters: int = 2000
) -> tuple[np.ndarray, np.ndarray]:
    """Rigid ``T [4,4]`` with ``q ~ R p + t`` for correspondences ``p, q [N,3]`` and the inlier mask ``[N]``.

    RANSAC on 3-point Kabsch fits (scored by truncated squared residuals, ``threshold`` in world units), then
    Cauchy-weighted least squares on the inliers with the inliers' robust spread as scale.
    """
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    n = len(p)
    if n < 3:
        raise ValueError(f"fit_rigid_ransac: need >= 3 correspondences, got {n}")
    rng = np.random.default_rng(seed)
    best, best_cost = np.eye(4), np.inf
    iters, i = max_iters, 0
    while i < iters:
        i += 1
        idx = rng.choice(n, 3, replace=False)
        if np.linalg.norm(np.cross(p[idx[1]] - p[idx[0]], p[idx[2]] - p[idx[0]])) < 1e-12:
            continue
        T = _rigid(p[idx], q[idx])
        r2 = np.sum((p @ T[:3, :3].T + T[:3, 3] - q) ** 2, axis=1)
        cost = np.minimum(r2, threshold**2).sum()
        if cost < best_cost:
            best, best_cost = T, cost
            frac = max(np.mean(r2 < threshold**2), 1e-3)
            iters = min(max_iters, int(np.ceil(np.log(1e-3) / np.log(max(1 - frac**3, 1e-12)))) + 10)
    T = best
    inl = np.sum((p @ T[:3, :3].T + T[:3, 3] - q) ** 2, axis=1) < threshold**2
    if inl.sum() < 3:
        return T, inl
    for _ in range(20):
        res = np.linalg.norm(p @ T[:3, :3].T + T[:3, 3] - q, axis=1)
        sigma = max(1.4826 * np.median(res[inl]), 1e-9 * threshold)
        w = np.where(inl, 1.0 / (1.0 + (res / (2.0 * sigma)) ** 2), 0.0)
        T_new = _rigid(p, q, w)
        done = np.abs(T_new - T).max() < 1e-12 * max(1.0, np.abs(T).max())
        T = T_new
        if done:
            break
    inl = np.linalg.norm(p @ T[:3, :3].T + T[:3, 3] - q, axis=1) < threshold
    return T, inl


def fit_motion_to_views(
    points: np.ndarray,
    xy: np.ndarray,
    view: np.ndarray,
    views: list[ViewFeatures],
    max_error_px: float,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Rigid ``T [4,4]`` moving ``points [M,3]`` (one state) to where the views of the other state see them
    at ``xy [M,2]`` (``view [M]`` indexes ``views``): LO-RANSAC on the generalized absolute pose of the views
    as one rig with known poses, then refinement. Returns ``(T, inlier mask [M])`` or None."""
    import pycolmap

    if len(points) < 4:
        return None
    used = np.unique(view)
    local = np.searchsorted(used, view)
    cams, rigs = [], []
    for k in used:
        K = views[k].K
        cams.append(
            pycolmap.Camera.create_from_model_name(
                int(k) + 1, "PINHOLE", 1.0, int(round(2 * K[0, 2])), int(round(2 * K[1, 2]))
            )
        )
        cams[-1].params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        rigs.append(pycolmap.Rigid3d(views[k].w2c[:3, :4]))
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = float(max_error_px)
    ransac.random_seed = int(seed)
    ransac.min_inlier_ratio = 0.05
    refine = pycolmap.AbsolutePoseRefinementOptions()
    refine.loss_function_scale = float(max_error_px) / 2.0
    out = pycolmap.estimate_and_refine_generalized_absolute_pose(
        np.asarray(xy, np.float64), np.asarray(points, np.float64), local.tolist(), rigs, cams, ransac, refine
    )
    if out is None:
        return None
    T = np.eye(4)
    T[:3, :4] = np.asarray(out["rig_from_world"].matrix(), np.float64)
    return T, np.asarray(out["inlier_mask"], bool)


@dataclass(frozen=True)
class FeatureMotion:
    """A motion from features: ``transform [4,4]`` (first state to second, cameras' frame), points of the
    object seen in both states ``points [N,3]`` (first state's frame), correspondences found (``matches``),
    points kept in both states (``inliers``) and the final RMS reprojection error (pixels)."""

    transform: np.ndarray
    points: np.ndarray
    matches: int
    inliers: int
    rms_px: float


def _correspondence_obs(T, track, points, xy, vi, views, moved, max_err):
    """Observations of 2D-3D correspondences whose points ``points[track]`` mapped by ``T`` land within
    ``max_err`` px of ``xy`` in ``views[vi]``, one per (track, view)."""
    if len(track) == 0:
        return []
    K = np.stack([views[k].K for k in vi])
    w2c = np.stack([views[k].w2c for k in vi])
    Y = points[track] @ T[:3, :3].T + T[:3, 3]
    c = np.einsum("oij,oj->oi", w2c[:, :3, :3], Y) + w2c[:, :3, 3]
    uv = np.einsum("oij,oj->oi", K, c)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = np.where(c[:, 2] > 0, np.linalg.norm(uv[:, :2] / uv[:, 2:3] - xy, axis=1), np.inf)
    order = np.lexsort((err, vi, track))
    first = np.r_[True, (np.diff(track[order]) != 0) | (np.diff(vi[order]) != 0)]
    sel = order[first & (err[order] <= max_err)]
    return [(int(track[o]), moved, K[o], w2c[o], xy[o]) for o in sel]


def _candidate_score(T, tr, corr, views1, views2, max_err) -> int:
    n = len(_correspondence_obs(T, corr[0][0], tr[0].points, corr[0][1], corr[0][2], views2, True, max_err))
    inv = np.linalg.inv(T)
    return n + len(
        _correspondence_obs(inv, corr[1][0], tr[1].points, corr[1][1], corr[1][2], views1, False, max_err)
    )


def estimate_feature_motion(
    views1: list[ViewFeatures],
    views2: list[ViewFeatures],
    obj: int,
    max_error_px: float,
    seed: int = 0,
    min_inliers: int = MIN_INLIERS,
) -> tuple[FeatureMotion | None, int]:
    """The motion of object ``obj`` from its features (module docstring), or None when fewer than
    ``min_inliers`` of its points are kept in both states; also returns the number of 2D-3D correspondences
    found. ``max_error_px``: feature localisation tolerance in pixels."""
    from train_world.capture.motion_refine import Observations, refine_motion, reprojection_errors

    tr = (
        triangulate_tracks(views1, obj, max_error_px, seed),
        triangulate_tracks(views2, obj, max_error_px, seed),
    )
    corr = (match_points_to_views(tr[0], views2, obj), match_points_to_views(tr[1], views1, obj))
    matches = len(corr[0][0]) + len(corr[1][0])
    cands = []
    for d, (track, xy, vi) in enumerate(corr):
        fit = fit_motion_to_views(tr[d].points[track], xy, vi, (views2, views1)[d], 2 * max_error_px, seed)
        if fit is not None:
            cands.append(fit[0] if d == 0 else np.linalg.inv(fit[0]))
    pairs = match_tracks(tr[0], tr[1])
    if len(pairs) >= 3:
        foot = float(np.median(np.r_[tr[0].footprint, tr[1].footprint]))
        T, inl = fit_rigid_ransac(
            tr[0].points[pairs[:, 0]], tr[1].points[pairs[:, 1]], 4 * foot * max_error_px, seed
        )
        if inl.sum() >= 3:
            cands.append(T)
    if not cands:
        return None, matches
    scores = [_candidate_score(T, tr, corr, views1, views2, 2 * max_error_px) for T in cands]
    T0 = cands[int(np.argmax(scores))]
    n1 = len(tr[0])
    X0 = np.concatenate([tr[0].points, (tr[1].points - T0[:3, 3]) @ T0[:3, :3]])
    obs = [
        (int(o), False, views1[v].K, views1[v].w2c, x) for o, v, x in zip(tr[0].owner, tr[0].view, tr[0].xy)
    ]
    obs += [
        (n1 + int(o), True, views2[v].K, views2[v].w2c, x)
        for o, v, x in zip(tr[1].owner, tr[1].view, tr[1].xy)
    ]
    track, xy, vi = corr[0]
    obs += _correspondence_obs(T0, track, tr[0].points, xy, vi, views2, True, 2 * max_error_px)
    track, xy, vi = corr[1]
    obs += [
        (n1 + o[0],) + o[1:]
        for o in _correspondence_obs(
            np.linalg.inv(T0), track, tr[1].points, xy, vi, views1, False, 2 * max_error_px
        )
    ]
    if len(obs) < 2 * min_inliers:
        return None, matches
    ob = Observations(
        np.array([o[0] for o in obs], np.int64),
        np.array([o[1] for o in obs], bool),
        np.stack([o[2] for o in obs]),
        np.stack([o[3] for o in obs]),
        np.stack([o[4] for o in obs]),
    )
    T, X, kept = refine_motion(T0, X0, ob, scale_px=max_error_px / 2, max_error_px=2 * max_error_px)
    both = np.zeros((len(X0), 2), bool)
    both[ob.point[kept], ob.moved[kept].astype(np.int64)] = True
    good = both.all(axis=1)
    if good.sum() < min_inliers:
        return None, matches
    rms = float(np.sqrt(np.mean(np.sum(reprojection_errors(T, X, ob.subset(kept)) ** 2, axis=1))))
    return FeatureMotion(T, X[good], matches, int(good.sum()), rms), matches


@dataclass(frozen=True)
class ObjectMotion:
    """One object's estimate: ``transform [4,4]`` (first state to second), its centre in the first state
    ``centre [3]`` (hull centroid, or the feature points' centroid), ``method`` ("features",
    "features+silhouettes", "silhouettes (features disagreed)" or "silhouettes"; " (hull inflated)" appended
    when one state's hull was fitted inside the other's, "+appearance" when
    the colours refined the turn), feature ``matches`` and ``inliers``, feature RMS reprojection
    error ``rms_px`` (NaN without features), ``views`` seeing the object whole per state, the hulls'
    alignment RMS under the motion ``hull_rms`` (reconstruction units; NaN without usable hulls) and the
    ``appearance`` refinement (None when not tried)."""

    transform: np.ndarray
    centre: np.ndarray
    method: str
    matches: int
    inliers: int
    rms_px: float
    views: tuple[int, int]
    hull_rms: float
    appearance: AppearanceFit | None = None


def _twist(rot: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The rotation about ``axis`` in the swing-twist decomposition of ``rot [3,3]``."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(rot).as_quat()
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    p = (np.array([x, y, z]) @ a) * a
    q = np.array([p[0], p[1], p[2], w])
    if np.linalg.norm(q) < 1e-12:
        return np.eye(3)
    return Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()


def _hull(views: list[SilhouetteView], obj: int, plane) -> tuple[np.ndarray, float, int]:
    centre, radius, n = object_centre(views, obj)
    if n < 2 or not np.isfinite(radius) or radius <= 0:
        return np.zeros((0, 3)), 0.0, n
    hull, step = visual_hull(views, obj, centre, radius, plane)
    return hull, step, n


def estimate_object_motion(
    obj: ObjectInfo,
    features: tuple[list[ViewFeatures], list[ViewFeatures]],
    silhouettes: tuple[list[SilhouetteView], list[SilhouetteView]],
    plane: tuple[np.ndarray, float],
    max_error_px: float,
    seed: int = 0,
    colours: tuple[list[ColourView], list[ColourView]] | None = None,
) -> ObjectMotion:
    """The motion of ``obj`` (module docstring); ``plane = (normal, offset)`` is the table (hulls are cut
    below it); ``colours``: both states' photos, for the appearance refinement (skipped without). Raises
    :class:`MotionError` naming the object when neither its features nor its silhouettes determine the
    motion."""
    label = f"object {obj.id} ({obj.name!r})"
    hulls = [_hull(silhouettes[s], obj.id, plane) for s in (0, 1)]
    for s, (_, _, n) in enumerate(hulls):
        if n < 2:
            raise MotionError(
                f"{label}: seen whole (not cut by the photo's edge) in {n} registered photos of state{s + 1}; "
                "photograph it from more sides, fully in frame"
            )
    (h1, step1, n1), (h2, step2, n2) = hulls
    vols = (len(h1), len(h2))
    volume1, volume2 = vols[0] * step1**3, vols[1] * step2**3
    hull_ok = min(vols) >= MIN_HULL_VOXELS and max(volume1, volume2) <= MAX_HULL_RATIO * min(volume1, volume2)
    fm, matches = estimate_feature_motion(features[0], features[1], obj.id, max_error_px, seed)
    hull_rms = float("nan")
    step, up = max(step1, step2), np.asarray(plane[0], np.float64)
    if fm is not None and hull_ok:
        T_f = fm.transform.copy()
        T_f[:3, 3] = h2.mean(axis=0) - T_f[:3, :3] @ h1.mean(axis=0)
        T, hull_rms = refine_hull_alignment(h1, h2, step, T_f)
        T_t = np.eye(4)  # the features' turn about the table normal alone (objects mostly turn on a table)
        T_t[:3, :3] = _twist(T_f[:3, :3], up)
        T_t[:3, 3] = h2.mean(axis=0) - T_t[:3, :3] @ h1.mean(axis=0)
        fits = hull_fits(h1, h2, step, up, starts=[T_t])
        method = "features+silhouettes"
        if hull_rms > min(c for c, _ in fits) + HULL_AGREEMENT * step:  # features contradict the silhouettes
            i, _ = choose_on_masks(
                [f for _, f in fits], (h1, step1), (h2, step2), *silhouettes, obj.id, prefer=T_t[:3, :3]
            )
            (hull_rms, T), method = fits[i], "silhouettes (features disagreed)"
    elif fm is not None:
        T, method = fm.transform.copy(), "features"
    elif hull_ok:  # no features: the masks choose, and among equally good fits the colours
        fits = hull_fits(h1, h2, step, up)
        rank = colour_score((h1, step1), (h2, step2), *colours, obj.id) if colours is not None else None
        i, _ = choose_on_masks(
            [f for _, f in fits], (h1, step1), (h2, step2), *silhouettes, obj.id, rank=rank
        )
        (hull_rms, T), method = fits[i], "silhouettes"
    else:
        raise MotionError(
            f"{label}: too few feature matches between the states ({matches}; need {MIN_INLIERS} points seen in "
            f"both) and its silhouettes do not agree between the states (hull voxels {vols[0]} vs {vols[1]}); "
            "check that its id marks the same object in both states' masks, give it texture, or take more photos"
        )
    inflated = hull_ok and max(volume1, volume2) > HULL_INFLATED * min(volume1, volume2)
    if inflated:  # one hull is larger than the object: the smaller inside it
        T = fit_into_larger(h1, h2, step, T)
        method += " (hull inflated)"
    elif hull_ok:  # the hulls' centroids fix the translation best (about a millimetre at 128x128)
        T[:3, 3] = h2.mean(axis=0) - T[:3, :3] @ h1.mean(axis=0)
    appearance = None
    if hull_ok and fm is not None and colours is not None:  # texture: colours pin the turn down
        equals = symmetric_fits(h1, h2, step, T, up)
        appearance = refine_motion_by_appearance(
            T, (h1, step1), (h2, step2), *colours, obj.id, candidates=equals
        )
        if appearance.accepted:
            T, method = appearance.transform, method + "+appearance"
    centre = h1.mean(axis=0) if hull_ok else fm.points.mean(axis=0)
    if inflated and volume1 > volume2:  # the second state's hull is the truer shape
        centre = np.linalg.solve(T[:3, :3], h2.mean(axis=0) - T[:3, 3])
    return ObjectMotion(
        transform=T,
        centre=centre,
        method=method,
        matches=int(matches),
        inliers=int(fm.inliers) if fm is not None else 0,
        rms_px=float(fm.rms_px) if fm is not None else float("nan"),
        views=(int(n1), int(n2)),
        hull_rms=hull_rms,
        appearance=appearance,
    )
