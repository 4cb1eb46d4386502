"""train_world.capture.mask_fit: an object's motion chosen by how well it agrees with the masks."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_closing, binary_fill_holes
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from train_world.capture.alignment import rotation_angle_deg
from train_world.capture.mask_fit import MASK_TIE, choose_on_masks, mask_cost
from train_world.capture.silhouettes import SilhouetteView, hull_fits, object_centre, visual_hull

SIZE = 64
K = np.array([[70.0, 0.0, SIZE / 2], [0.0, 70.0, SIZE / 2], [0.0, 0.0, 1.0]])
UP = np.array([0.0, 0.0, 1.0])


def _look_at(eye: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera of a camera at ``eye`` looking at the origin."""
    f = -eye / np.linalg.norm(eye)
    r = np.cross(f, UP)
    r /= np.linalg.norm(r)
    w2c = np.eye(4)
    w2c[:3, :3] = np.stack([r, np.cross(f, r), f])
    w2c[:3, 3] = -w2c[:3, :3] @ eye
    return w2c


def _views(points: np.ndarray, cams: list[np.ndarray]) -> list[SilhouetteView]:
    out = []
    for w2c in cams:
        c = points @ w2c[:3, :3].T + w2c[:3, 3]
        uv = (c @ K.T)[:, :2] / c[:, 2:]
        ids = np.zeros((SIZE, SIZE), bool)
        ids[uv[:, 1].astype(int).clip(0, SIZE - 1), uv[:, 0].astype(int).clip(0, SIZE - 1)] = True
        ids = binary_fill_holes(binary_closing(ids, iterations=2))
        out.append(SilhouetteView(ids.astype(np.uint8), K, w2c))
    return out


def _scene():
    """An irregular convex object on the table (z = 0) seen by 16 cameras, and the same object turned 80
    degrees about the vertical and moved: the two states' photos and the true motion."""
    rng = np.random.default_rng(3)
    corners = rng.normal(size=(14, 3)) * np.array([0.05, 0.03, 0.025])
    corners[:, 2] -= corners[:, 2].min()
    box = rng.uniform(corners.min(axis=0), corners.max(axis=0), (60000, 3))
    body = box[Delaunay(corners).find_simplex(box) >= 0]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 80.0, degrees=True).as_matrix()
    T[:3, 3] = [0.04, -0.03, 0.0]
    angles = np.radians(np.arange(16) * 22.5)
    cams = [_look_at(np.array([0.45 * np.cos(a), 0.45 * np.sin(a), 0.3])) for a in angles]
    moved = body @ T[:3, :3].T + T[:3, 3]
    return _views(body, cams), _views(moved, cams), T


def _hull(views):
    centre, radius, _ = object_centre(views, 1)
    return visual_hull(views, 1, centre, radius, (UP, 0.0))


def test_the_masks_pick_the_true_turn_among_hull_fits():
    v1, v2, T_true = _scene()
    h1, h2 = _hull(v1), _hull(v2)
    fits = hull_fits(h1[0], h2[0], max(h1[1], h2[1]), UP)
    candidates = [f for _, f in fits]
    i, cost = choose_on_masks(candidates, h1, h2, v1, v2, 1)
    err = float(rotation_angle_deg(candidates[i][:3, :3].T @ T_true[:3, :3]))
    assert err < 4.0, err
    assert np.linalg.norm(candidates[i][:3, 3] - T_true[:3, 3]) < 0.01
    # the true motion agrees with the masks to a pixel or so, a turn of 40 degrees more does not
    wrong = T_true.copy()
    wrong[:3, :3] = Rotation.from_euler("z", 40.0, degrees=True).as_matrix() @ T_true[:3, :3]
    wrong[:3, 3] = T_true[:3, :3] @ np.zeros(3) + T_true[:3, 3]
    true_cost = mask_cost(h1, h2, v1, v2, 1, T_true)
    assert true_cost < 1.5 and mask_cost(h1, h2, v1, v2, 1, wrong) > 2 * true_cost
    assert cost == mask_cost(h1, h2, v1, v2, 1, candidates[i])  # the reported cost is the candidate's


def test_equally_good_candidates_go_to_the_preferred_turn():
    v1, v2, T_true = _scene()
    h1, h2 = _hull(v1), _hull(v2)
    # the same motion twice: a tie; the candidate nearer the preferred rotation wins, else the first
    near = T_true.copy()
    near[:3, :3] = Rotation.from_euler("z", 0.01, degrees=True).as_matrix() @ T_true[:3, :3]
    assert choose_on_masks([T_true, near], h1, h2, v1, v2, 1, prefer=near[:3, :3])[0] == 1
    assert choose_on_masks([T_true, near], h1, h2, v1, v2, 1, prefer=T_true[:3, :3])[0] == 0
    # a clearly worse candidate is not taken for being nearer the preferred rotation
    far = np.eye(4)
    far[:3, 3] = T_true[:3, 3]
    i, _ = choose_on_masks([T_true, far], h1, h2, v1, v2, 1, prefer=np.eye(3))
    assert i == 0 and mask_cost(h1, h2, v1, v2, 1, far) > (1 + MASK_TIE) * mask_cost(
        h1, h2, v1, v2, 1, T_true
    )
    # no photos to score by: every candidate is as good, the preferred rotation decides
    i, cost = choose_on_masks([far, T_true], h1, h2, [], [], 1, prefer=T_true[:3, :3])
    assert i == 1 and cost == float("inf")


def test_a_rank_decides_among_equally_good_candidates_only():
    v1, v2, T_true = _scene()
    h1, h2 = _hull(v1), _hull(v2)
    near = T_true.copy()
    near[:3, :3] = Rotation.from_euler("z", 0.01, degrees=True).as_matrix() @ T_true[:3, :3]
    far = np.eye(4)
    far[:3, 3] = T_true[:3, 3]
    calls = []

    def rank(T):  # prefers the candidate turned 0.01 deg, and the far one most of all
        calls.append(T)
        return 0.0 if np.allclose(T, far) else (1.0 if np.allclose(T, near) else 2.0)

    i, cost = choose_on_masks([T_true, near, far], h1, h2, v1, v2, 1, prefer=T_true[:3, :3], rank=rank)
    assert i == 1 and cost == mask_cost(h1, h2, v1, v2, 1, near)  # over the preferred rotation
    assert len(calls) == 2  # the far candidate is no tie: never ranked, never taken
    # equal ranks: the preferred rotation decides, as without a rank
    assert (
        choose_on_masks([T_true, near], h1, h2, v1, v2, 1, prefer=T_true[:3, :3], rank=lambda T: 0.0)[0] == 0
    )


def test_outline_is_the_objects_edge_and_not_the_photos():
    from train_world.capture.mask_fit import _Views

    ids = np.zeros((8, 8), np.uint8)
    ids[2:5, 2:6] = 1  # a 3x4 block inside the photo: its 10 edge pixels are the outline
    ids[5:, 0:3] = 2  # another object cut by the photo's bottom-left corner
    v = SilhouetteView(ids, K, np.eye(4))
    inside = {(int(x), int(y)) for x, y in _Views([v], 1).outline[0]}
    assert inside == {(x, y) for y in range(2, 5) for x in range(2, 6)} - {(3, 3), (4, 3)}
    cut = {(int(x), int(y)) for x, y in _Views([v], 2).outline[0]}
    # only the pixels next to the background are outline; those on the photo's edge alone are not
    assert cut == {(0, 5), (1, 5), (2, 5), (2, 6), (2, 7)}
    # the distance map to the nearest object pixel is computed once and shared by every object
    assert v.object_distance is v.object_distance
    assert v.object_distance[3, 3] == 0.0 and v.object_distance[0, 0] == np.hypot(2, 2)
