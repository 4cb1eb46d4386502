"""Triangulated feature tracks of one object in one state, and matching them to the other state.

:func:`triangulate_tracks` links guided matches between every pair of a state's views and splits each linked
group into 3D points by robust triangulation; :func:`match_tracks` (track to track) and
:func:`match_points_to_views` (track to the other state's 2D features) find correspondences between the
states by descriptor votes and ratio tests. Float64; deterministic for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from train_world.capture.features import RATIO, ViewFeatures, fundamental, mutual_ratio_matches, sampson

__all__ = ["MIN_TRIANGULATION_DEG", "Tracks", "match_points_to_views", "match_tracks", "triangulate_tracks"]

#: smallest angle (degrees) between two rays of a triangulated track
MIN_TRIANGULATION_DEG = 2.0


@dataclass(frozen=True)
class Tracks:
    """Triangulated tracks of one object in one state: ``points [T,3]``, per-track reprojection error
    ``errors [T]`` (pixels), depth over focal length ``footprint [T]`` (world units per pixel), and the
    members: descriptors ``desc [M,128]``, ``owner [M]`` (track index, non-decreasing), ``view [M]`` (index
    of the view in the state's list) and ``xy [M,2]`` (pixels)."""

    points: np.ndarray
    errors: np.ndarray
    footprint: np.ndarray
    desc: np.ndarray
    owner: np.ndarray
    view: np.ndarray
    xy: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])


def _find(parent: np.ndarray, i: int) -> int:
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


def _triangulate(P: np.ndarray, n: np.ndarray) -> np.ndarray:
    """DLT point from projection matrices ``P [k,3,4]`` (world-to-camera) and normalised image points
    ``n [k,2]``."""
    rows = np.concatenate([n[:, :1] * P[:, 2] - P[:, 0], n[:, 1:2] * P[:, 2] - P[:, 1]])
    _, _, vt = np.linalg.svd(rows)
    X = vt[-1]
    return X[:3] / X[3] if abs(X[3]) > 1e-300 else np.full(3, np.nan)


def _errors(X: np.ndarray, P: np.ndarray, K: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Reprojection errors (pixels; inf behind a camera) of ``X [3]`` in members ``P [k,3,4]``, ``K [k,3,3]``,
    ``xy [k,2]``."""
    c = P[:, :, :3] @ X + P[:, :, 3]
    uv = np.einsum("kij,kj->ki", K, c)
    with np.errstate(divide="ignore", invalid="ignore"):
        e = np.linalg.norm(uv[:, :2] / uv[:, 2:3] - xy, axis=1)
    return np.where(c[:, 2] > 0, e, np.inf)


def _best_per_view(err: np.ndarray, view: np.ndarray, max_err: float) -> np.ndarray:
    """Inlier mask keeping at most one member per view (the one with the smallest error)."""
    ok = err <= max_err
    order = np.lexsort((err, view))
    first = np.r_[True, view[order][1:] != view[order][:-1]]
    keep = np.zeros(len(err), bool)
    keep[order[first]] = True
    return ok & keep


def _triangulate_pairs(P: np.ndarray, n: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Two-view DLT points ``[H,3]`` for member ``pairs [H,2]`` (NaN when at infinity)."""
    i, j = pairs[:, 0], pairs[:, 1]
    rows = np.stack(
        [
            n[i, :1] * P[i, 2] - P[i, 0],
            n[i, 1:2] * P[i, 2] - P[i, 1],
            n[j, :1] * P[j, 2] - P[j, 0],
            n[j, 1:2] * P[j, 2] - P[j, 1],
        ],
        axis=1,
    )
    _, _, vt = np.linalg.svd(rows)
    X = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(X[:, 3:]) > 1e-300, X[:, :3] / X[:, 3:], np.nan)


def _split_component(
    P: np.ndarray, K: np.ndarray, n: np.ndarray, xy: np.ndarray, view: np.ndarray, max_err: float, rng
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Robust triangulation of linked observations: repeatedly the two-view hypothesis that explains most
    members (one per view) becomes a track, refined on its inliers; returns ``[(X [3], member mask)]``."""
    left = np.ones(len(view), bool)
    out = []
    centres = -np.einsum("kji,kj->ki", P[:, :, :3], P[:, :, 3])
    while left.sum() >= 2 and len(np.unique(view[left])) >= 2:
        idx = np.flatnonzero(left)
        ii, jj = np.triu_indices(len(idx), 1)
        ok = view[idx[ii]] != view[idx[jj]]
        pairs = np.stack([idx[ii[ok]], idx[jj[ok]]], axis=1)
        if len(pairs) > 200:
            pairs = pairs[np.sort(rng.choice(len(pairs), 200, replace=False))]
        X = _triangulate_pairs(P, n, pairs)  # [H,3]
        c = np.einsum("kij,hj->hki", P[idx, :, :3], X) + P[idx, :, 3][None]  # [H,m,3]
        uv = np.einsum("kij,hkj->hki", K[idx], c)
        with np.errstate(divide="ignore", invalid="ignore"):
            err = np.linalg.norm(uv[..., :2] / uv[..., 2:3] - xy[idx][None], axis=2)
        err = np.where((c[..., 2] > 0) & np.isfinite(err), err, np.inf)
        counts = np.array([_best_per_view(e, view[idx], max_err).sum() for e in err])
        score = counts * ((len(idx) + 1) * max_err) - np.minimum(err, max_err).sum(axis=1)
        h = int(np.argmax(score))
        if counts[h] < 2:
            break
        members = idx[_best_per_view(err[h], view[idx], max_err)]
        X = _triangulate(P[members], n[members])
        inl = _best_per_view(_errors(X, P[idx], K[idx], xy[idx]), view[idx], max_err)
        members = idx[inl] if inl.sum() >= 2 else members
        X = _triangulate(P[members], n[members])
        rays = X - centres[members]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        left[members] = False
        if (
            np.all(np.isfinite(X))
            and np.degrees(np.arccos(np.clip((rays @ rays.T).min(), -1, 1))) >= MIN_TRIANGULATION_DEG
        ):
            mask = np.zeros(len(view), bool)
            mask[members] = True
            out.append((X, mask))
    return out


def triangulate_tracks(views: list[ViewFeatures], obj: int, max_error_px: float, seed: int = 0) -> Tracks:
    """Tracks of object ``obj`` over ``views`` (one state): guided mutual matches between every pair of views
    (Sampson distance <= ``max_error_px``) are linked, and each linked group is split into points by robust
    triangulation (reprojection error <= ``max_error_px``, one observation per view, >= 2 views whose rays are
    >= 2 degrees apart)."""
    feats = [(v, np.flatnonzero(v.label == obj)) for v in views]
    offsets = np.cumsum([0] + [len(f) for _, f in feats])
    parent = np.arange(offsets[-1])
    for a in range(len(feats)):
        va, ia = feats[a]
        if len(ia) == 0:
            continue
        for b in range(a + 1, len(feats)):
            vb, ib = feats[b]
            if len(ib) == 0:
                continue
            sim = va.desc[ia] @ vb.desc[ib].T
            sim = np.where(sampson(fundamental(va, vb), va.xy[ia], vb.xy[ib]) <= max_error_px, sim, -np.inf)
            for i, j in mutual_ratio_matches(sim, RATIO):
                ra, rb = _find(parent, offsets[a] + i), _find(parent, offsets[b] + j)
                if ra != rb:
                    parent[max(ra, rb)] = min(ra, rb)
    roots = np.array([_find(parent, i) for i in range(len(parent))], dtype=np.int64)
    view_of = np.repeat(np.arange(len(feats)), np.diff(offsets))
    feat_of = np.concatenate([f for _, f in feats]) if len(parent) else np.zeros(0, np.int64)
    rng = np.random.default_rng(seed)
    points, errors, foot, descs, owners, mview, mxy = [], [], [], [], [], [], []
    for root in np.unique(roots):
        m = np.flatnonzero(roots == root)
        if len(m) < 2:
            continue
        vs = [feats[view_of[i]][0] for i in m]
        P = np.stack([v.w2c[:3, :4] for v in vs])
        K = np.stack([v.K for v in vs])
        xy = np.stack([v.xy[f] for v, f in zip(vs, feat_of[m])])
        n = (xy - K[:, :2, 2]) / np.stack([K[:, 0, 0], K[:, 1, 1]], axis=1)
        for X, mask in _split_component(P, K, n, xy, view_of[m], max_error_px, rng):
            c = P[mask, :, :3] @ X + P[mask, :, 3]
            t = len(points)
            points.append(X)
            errors.append(float(np.mean(_errors(X, P[mask], K[mask], xy[mask]))))
            foot.append(float(np.median(c[:, 2] / K[mask, 0, 0])))
            for i in np.flatnonzero(mask):
                descs.append(vs[i].desc[feat_of[m][i]])
                owners.append(t)
                mview.append(view_of[m][i])
                mxy.append(xy[i])
    return Tracks(
        points=np.asarray(points, np.float64).reshape(-1, 3),
        errors=np.asarray(errors, np.float64),
        footprint=np.asarray(foot, np.float64),
        desc=np.asarray(descs, np.float32).reshape(-1, 128),
        owner=np.asarray(owners, np.int64),
        view=np.asarray(mview, np.int64),
        xy=np.asarray(mxy, np.float64).reshape(-1, 2),
    )


def match_tracks(a: Tracks, b: Tracks, ratio: float = RATIO) -> np.ndarray:
    """Track correspondences ``[M,2]`` (index in ``a``, index in ``b``): every member of a track of ``b``
    votes for the track of ``a`` holding its nearest descriptor (if it passes the ratio test against the
    next-best track); pairs that are each other's most voted are kept."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros((0, 2), np.int64)
    dist = np.sqrt(np.maximum(2.0 - 2.0 * (b.desc @ a.desc.T).astype(np.float64), 0.0))  # [Mb, Ma]
    starts = np.flatnonzero(np.r_[True, np.diff(a.owner) != 0])
    per_track = np.minimum.reduceat(dist, starts, axis=1)  # [Mb, Ta]
    track_ids = a.owner[starts]
    votes = np.zeros((len(b), len(a)), np.int64)
    order = np.argsort(per_track, axis=1)
    best = order[:, 0]
    d1 = per_track[np.arange(len(best)), best]
    d2 = (
        per_track[np.arange(len(best)), order[:, 1]] if per_track.shape[1] > 1 else np.full(len(best), np.inf)
    )
    ok = d1 < ratio * d2
    np.add.at(votes, (b.owner[ok], track_ids[best[ok]]), 1)
    pairs = []
    for tb in range(len(b)):
        ta = int(np.argmax(votes[tb]))
        if votes[tb, ta] > 0 and int(np.argmax(votes[:, ta])) == tb:
            pairs.append((ta, tb))
    return np.asarray(pairs, np.int64).reshape(-1, 2)


def match_points_to_views(
    tracks: Tracks, views: list[ViewFeatures], obj: int, ratio: float = RATIO
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D-3D correspondences between the tracks of one state and the object's features in the views of the
    other: each feature's nearest track (by its closest member descriptor) if it passes the ratio test
    against the next-best track. Returns ``track [M]`` (index in ``tracks``), ``xy [M,2]`` and ``view [M]``
    (index in ``views``)."""
    pts, xys, vids = [], [], []
    if len(tracks) >= 2:
        starts = np.flatnonzero(np.r_[True, np.diff(tracks.owner) != 0])
        ids = tracks.owner[starts]
        for k, v in enumerate(views):
            f = np.flatnonzero(v.label == obj)
            if len(f) == 0:
                continue
            dist = np.sqrt(np.maximum(2.0 - 2.0 * (v.desc[f] @ tracks.desc.T).astype(np.float64), 0.0))
            per = np.minimum.reduceat(dist, starts, axis=1)
            order = np.argsort(per, axis=1)[:, :2]
            d1 = per[np.arange(len(f)), order[:, 0]]
            d2 = per[np.arange(len(f)), order[:, 1]]
            ok = d1 < ratio * d2
            pts.append(ids[order[ok, 0]])
            xys.append(v.xy[f[ok]])
            vids.append(np.full(int(ok.sum()), k))
    if not pts:
        return np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0, np.int64)
    return np.concatenate(pts), np.concatenate(xys), np.concatenate(vids)
