"""Initial Gaussians: back-projected depth where a capture has it, else points placed from what the capture does
know (led by the capture's sparse structure-from-motion points where it has them, :mod:`train_world.capture.points`):
random points carved by silhouettes (NeRF-Blender RGBA data), points on the table and inside each object's visual
hull, then points on background pixels' rays out to the room around the table and random points in the table box
(a tabletop capture with object masks, as ``dsg-capture`` makes from photos; :func:`tabletop_points`), or random
points in the scene bounds.

Also the scene extent (3DGS: 1.1 x the largest camera distance from the cameras' centroid) that scales the
position learning rate and the clone/split threshold.
"""

from __future__ import annotations

import numpy as np
import torch

from dsg_gym.cameras import camera_centres, unproject
from train_world.single_state.field import SegmentedField
from train_world.single_state.losses import knn_indices

__all__ = [
    "carve_silhouettes",
    "initial_field",
    "object_hull_points",
    "points_from_depth",
    "points_in_bounds",
    "room_points",
    "scene_bounds_from_cameras",
    "scene_extent",
    "table_points",
    "tabletop_points",
]

#: :func:`tabletop_points`: the share of the point budget on the table top, and how many candidates per budgeted
#: point are tried against the objects' masks
TABLE_SHARE, HULL_CANDIDATES = 0.1, 6
#: :func:`tabletop_points`: the share of what the table and hulls leave of the budget that goes to
#: :func:`room_points`, and the depths of those (times each camera's distance to the table's centre)
ROOM_SHARE, ROOM_DEPTHS = 0.5, (0.5, 4.0)


def scene_extent(viewmats: torch.Tensor) -> float:
    c = camera_centres(viewmats.detach().numpy())
    return float(1.1 * max(np.linalg.norm(c - c.mean(0), axis=1).max(), 1e-6))


def scene_bounds_from_cameras(viewmats: torch.Tensor, Ks: torch.Tensor, width: int) -> np.ndarray:
    """``[[min], [max]]`` of a cube around the point closest to all optical axes, half-size the image
    half-width at that distance (what every camera sees around its look-at point)."""
    vm = viewmats.detach().double().numpy()
    c = camera_centres(vm)
    d = vm[:, 2, :3]  # optical axes in world (third row of R)
    A = np.zeros((3, 3))
    b = np.zeros(3)
    for ci, di in zip(c, d):
        P = np.eye(3) - np.outer(di, di)
        A += P
        b += P @ ci
    centre = np.linalg.lstsq(A, b, rcond=None)[0]
    dist = float(np.median(np.linalg.norm(c - centre, axis=1)))
    fx = float(np.median(Ks[:, 0, 0].double().numpy()))
    half = dist * (width / 2.0) / fx
    return np.stack([centre - half, centre + half])


def points_from_depth(
    images: torch.Tensor,
    depths: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    masks: torch.Tensor | None,
    max_points: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Back-project pixels with depth > 0 of all views; returns points ``[P,3]`` float64, colours ``[P,3]``
    and mask ids ``[P]`` (0 without masks), a random subset of at most ``max_points``."""
    V, H, W = depths.shape
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    pts, cols, ids = [], [], []
    per_view = max(1, int(np.ceil(4 * max_points / V)))
    for i in range(V):
        z = depths[i].numpy().astype(np.float64)
        valid = np.flatnonzero(z.reshape(-1) > 0)
        if valid.size == 0:
            continue
        if valid.size > per_view:
            valid = np.sort(rng.choice(valid, per_view, replace=False))
        K, vm = Ks[i].double().numpy(), viewmats[i].double().numpy()
        pts.append(unproject(u.reshape(-1)[valid], v.reshape(-1)[valid], z.reshape(-1)[valid], vm, K))
        cols.append(images[i].reshape(-1, 3).numpy()[valid])
        ids.append(masks[i].reshape(-1).numpy()[valid] if masks is not None else np.zeros(valid.size))
    if not pts:
        raise ValueError("points_from_depth: no pixel has depth > 0")
    P, Cc, ids_all = np.concatenate(pts), np.concatenate(cols), np.concatenate(ids).astype(np.int64)
    if len(P) > max_points:
        keep = np.sort(rng.choice(len(P), max_points, replace=False))
        P, Cc, ids_all = P[keep], Cc[keep], ids_all[keep]
    return P, Cc.astype(np.float64), ids_all


def points_in_bounds(
    bounds: np.ndarray, n: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` uniform random points in the box ``bounds`` with random colours (3DGS's synthetic init)."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    P = lo + (hi - lo) * rng.random((n, 3))
    return P, rng.random((n, 3)), np.zeros(n, np.int64)


def _pixels(points: np.ndarray, viewmat: torch.Tensor, K: torch.Tensor, width: int, height: int):
    """The pixel ``(u [P], v [P])`` int64 each point falls in and ``ok [P]``: in front of the camera and inside
    the image."""
    vm, Kd = viewmat.double().numpy(), K.double().numpy()
    cam = points @ vm[:3, :3].T + vm[:3, 3]
    z = cam[:, 2]
    ok = z > 1e-6
    u = np.floor(Kd[0, 0] * cam[:, 0] / np.where(ok, z, 1) + Kd[0, 2]).astype(np.int64)
    v = np.floor(Kd[1, 1] * cam[:, 1] / np.where(ok, z, 1) + Kd[1, 2]).astype(np.int64)
    ok &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return u, v, ok


def _mean_colours(points, images, classes, viewmats, Ks, want) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the mean colour ``[P,3]`` of the pixels it falls in whose class is ``want`` ``[P]``, and how
    many there were ``[P]``."""
    V, H, W = classes.shape
    total = np.zeros((len(points), 3))
    count = np.zeros(len(points), np.int64)
    for i in range(V):
        u, v, ok = _pixels(points, viewmats[i], Ks[i], W, H)
        idx = np.flatnonzero(ok)
        idx = idx[classes[i].numpy()[v[idx], u[idx]] == want[idx]]
        total[idx] += images[i].numpy()[v[idx], u[idx]]
        count[idx] += 1
    return total / np.maximum(count, 1)[:, None], count


def table_points(
    box: np.ndarray, n: int, images, classes, viewmats, Ks, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to ``n`` points uniform on the table top (the plane ``z = box[0, 2]`` over the box's x-y extent), each
    coloured by the mean of the training pixels it falls in where no object covers it (class 0 of ``classes
    [V,H,W]``); points that no view sees uncovered are dropped. Returns points, colours and class ids (0)."""
    lo, hi = np.asarray(box, dtype=np.float64)
    P = np.column_stack([lo[:2] + (hi[:2] - lo[:2]) * rng.random((n, 2)), np.full(n, lo[2])])
    cols, count = _mean_colours(P, images, classes, viewmats, Ks, np.zeros(n, np.int64))
    keep = count > 0
    return P[keep], cols[keep], np.zeros(int(keep.sum()), np.int64)


def object_hull_points(
    box: np.ndarray, candidates: int, images, classes, viewmats, Ks, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points inside the objects' visual hulls: of ``candidates`` uniform in ``box``, those seen in at least 3
    views, on the background in at most a tenth of them and on one object's class in at least half (the rest:
    other objects in front), with that class as id and the mean colour of those pixels."""
    lo, hi = np.asarray(box, dtype=np.float64)
    P = lo + (hi - lo) * rng.random((candidates, 3))
    V, H, W = classes.shape
    num_classes = int(classes.max()) + 1
    if num_classes < 2:  # no object in any view
        return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
    votes = np.zeros((candidates, num_classes), np.int64)
    seen = np.zeros(candidates, np.int64)
    for i in range(V):
        u, v, ok = _pixels(P, viewmats[i], Ks[i], W, H)
        idx = np.flatnonzero(ok)
        seen[idx] += 1
        np.add.at(votes, (idx, classes[i].numpy()[v[idx], u[idx]]), 1)
    k = votes[:, 1:].argmax(axis=1) + 1
    hull = (seen >= 3) & (votes[:, 0] <= 0.1 * seen) & (2 * votes[np.arange(candidates), k] >= seen)
    P, k = P[hull], k[hull]
    cols, count = _mean_colours(P, images, classes, viewmats, Ks, k)
    keep = count > 0
    return P[keep], cols[keep], k[keep]


def room_points(
    box: np.ndarray, n: int, images, classes, viewmats, Ks, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Up to ``n`` points on the rays of random background pixels (class 0 of ``classes [V,H,W]``; any pixel
    when ``classes`` is None) of random training views, each at a depth uniform in inverse depth between
    :data:`ROOM_DEPTHS` times its camera's distance to the centre of ``box``'s bottom face (the table top), and
    coloured like its pixel (``images [V,H,W,3]`` in [0, 1]). Returns points, colours and class ids (0).

    The walls and floor around a table lie beyond any box around it; points there give densification material
    that no box-bound start has. Draws for object pixels are dropped, so fewer than ``n`` may come back."""
    V, H, W = images.shape[:3]
    lo, hi = np.asarray(box, dtype=np.float64)
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    view = rng.integers(0, V, n)
    u, v = rng.random(n) * W, rng.random(n) * H
    row, col = np.minimum(v.astype(np.int64), H - 1), np.minimum(u.astype(np.int64), W - 1)
    keep = np.ones(n, bool) if classes is None else classes.numpy()[view, row, col] == 0
    vm, K = viewmats.detach().double().numpy()[view], Ks.detach().double().numpy()[view]
    dist = np.linalg.norm(camera_centres(viewmats.detach().numpy())[view] - centre, axis=1)
    near, far = ROOM_DEPTHS[0] * dist, ROOM_DEPTHS[1] * dist
    q = rng.random(n)
    z = 1.0 / ((1.0 - q) / near + q / far)
    world = unproject(u, v, z, vm, K)
    cols = images.numpy()[view, row, col].astype(np.float64)
    return world[keep], cols[keep], np.zeros(int(keep.sum()), np.int64)


def tabletop_points(
    box: np.ndarray, n: int, images, classes, viewmats, Ks, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Initial points of a tabletop capture without depth but with object masks (``dsg-capture``'s): a
    :data:`TABLE_SHARE` of the budget ``n`` on the table top (:func:`table_points`), then the objects' visual
    hulls (:func:`object_hull_points`, from ``HULL_CANDIDATES * n`` candidates in ``box``, the table up to half
    its width in height), then what is left of ``n``: a :data:`ROOM_SHARE` of it on background pixels' rays out
    to the room around the table (:func:`room_points`), the rest random points in ``box`` (3DGS's random start:
    raw material that densification moves to what the others miss). ``images [V,H,W,3]``, ``classes [V,H,W]``
    (0: background), ``viewmats``, ``Ks``: the training views."""
    table = table_points(box, int(TABLE_SHARE * n), images, classes, viewmats, Ks, rng)
    hull = object_hull_points(box, HULL_CANDIDATES * n, images, classes, viewmats, Ks, rng)
    rest = max(0, n - len(table[0]) - len(hull[0]))
    room = room_points(box, int(ROOM_SHARE * rest), images, classes, viewmats, Ks, rng)
    parts = (table, hull, room, points_in_bounds(box, rest - len(room[0]), rng))
    return tuple(np.concatenate([p[j] for p in parts]) for j in range(3))


def carve_silhouettes(
    points: np.ndarray,
    silhouettes: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    min_fraction: float = 0.95,
) -> np.ndarray:
    """Boolean ``[P]``: points inside the visual hull, i.e. seen inside the silhouette (alpha > 0.5) in at
    least ``min_fraction`` of the views whose image they project into."""
    V, H, W = silhouettes.shape
    inside = np.zeros(len(points), np.int64)
    seen = np.zeros(len(points), np.int64)
    for i in range(V):
        u, v, ok = _pixels(points, viewmats[i], Ks[i], W, H)
        sil = silhouettes[i].numpy() > 0.5
        seen += ok
        inside[ok] += sil[v[ok], u[ok]]
    return (seen > 0) & (inside >= np.ceil(min_fraction * seen))


def nn_scales(points: np.ndarray) -> np.ndarray:
    """3DGS initial scale: RMS distance to the 3 nearest other points."""
    if len(points) < 2:
        return np.full(len(points), 0.01)
    idx = knn_indices(points, points, min(3, len(points) - 1))
    d2 = ((points[idx] - points[:, None, :]) ** 2).sum(-1)
    return np.sqrt(np.maximum(d2.mean(1), 1e-14))


def initial_field(
    points: np.ndarray,
    colours: np.ndarray,
    class_ids: np.ndarray,
    *,
    num_classes: int,
    sh_degree: int,
    num_features: int,
    opacity: float,
    generator: torch.Generator,
) -> tuple[SegmentedField, torch.Tensor]:
    """A field at ``points`` and a matching initial classifier weight ``[K+1, F]``.

    Each class gets a random unit code vector; Gaussians whose class is known (from a mask) start with their
    class's code as identity feature (others: class 0 with small noise), and the classifier starts as the code
    matrix, so known classes are predicted from the first step.
    """
    codes = torch.randn((num_classes, num_features), generator=generator, dtype=torch.float64)
    codes = codes / codes.norm(dim=-1, keepdim=True)
    noise = 0.05 * torch.randn((len(points), num_features), generator=generator, dtype=torch.float64)
    feats = codes[torch.from_numpy(class_ids)] + noise
    field = SegmentedField.from_points(
        torch.from_numpy(points),
        torch.from_numpy(np.clip(colours, 0.0, 1.0)),
        torch.from_numpy(nn_scales(points)),
        sh_degree=sh_degree,
        num_features=num_features,
        opacity=opacity,
        features=feats.float(),
    )
    return field, codes.float()
