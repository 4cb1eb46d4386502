"""train_world.complete.panorama: a background seen all around from one point, continued where no camera saw."""

from __future__ import annotations

import numpy as np
import pytest

from dsg_gym.cameras import Cameras, look_at
from dsg_gym.gaussians import GaussianSet, rgb_to_sh0
from train_world.complete import panorama as pano


def test_cube_faces_are_rotations_looking_along_the_axes():
    origin = np.array([0.3, -0.2, 0.5])
    vms = pano.cube_viewmats(origin)
    axes = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    for vm, axis in zip(vms, axes):
        R = vm[:3, :3]
        assert np.allclose(R @ R.T, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
        assert np.allclose(R[2], axis)  # the optical axis
        assert np.allclose(vm[:3, :3] @ origin + vm[:3, 3], 0.0)  # the camera sits at the origin
    # a direction is sampled from the face it leaves by, at the pixel it passes through
    size = 8
    values = np.zeros((6, size, size), int)
    values[:] = np.arange(6)[:, None, None]
    assert list(pano.sample_cube(values, np.array(axes, float))) == list(range(6))
    marked = np.zeros((6, size, size))
    marked[0, 0, size - 1] = 1.0  # +x face, top right pixel: towards -y (right) and +z (up)
    d = np.array([[1.0, -0.9, 0.9]])
    assert pano.sample_cube(marked, d / np.linalg.norm(d))[0] == 1.0


def _sphere(radius: float, centre, n: int = 24000) -> GaussianSet:
    """Opaque Gaussians on a sphere: red above the centre's height, blue below."""
    from train_world.complete.shell import fibonacci_directions

    d = fibonacci_directions(n)
    rgb = np.where(d[:, 2:] > 0, [0.9, 0.1, 0.1], [0.1, 0.1, 0.9])
    return GaussianSet(
        means=np.asarray(centre) + radius * d,
        quats=np.tile([1.0, 0, 0, 0], (n, 1)),
        scales=np.full((n, 3), 0.025 * radius),
        opacities=np.full(n, 0.99),
        sh=rgb_to_sh0(rgb)[:, None, :],
    )


def test_render_cube_gives_colour_alpha_and_the_distance_along_each_ray():
    centre = np.array([0.1, 0.2, 0.3])
    colour, alpha, distance = pano.render_cube(_sphere(2.0, centre), centre, 32)
    assert colour.shape == (6, 32, 32, 3) and alpha.shape == distance.shape == (6, 32, 32)
    assert alpha.min() > 0.98
    # the distance is along the ray, not the optical-axis depth (that would be 2 / 1.7 in a face's corner);
    # away from a face's axis the surface's Gaussians are sorted by their centres' depth, so it comes out a
    # little short there (the expected depth of splats)
    assert np.allclose(distance[:, 8:24, 8:24], 2.0, rtol=0.05)
    assert np.allclose(distance, 2.0, rtol=0.1), (distance.min(), distance.max())
    dirs = np.array([[0.3, 0.2, 0.9], [0.2, -0.4, -0.8]])
    got = pano.sample_cube(colour, dirs / np.linalg.norm(dirs, axis=1, keepdims=True))
    assert np.allclose(got, [[0.9, 0.1, 0.1], [0.1, 0.1, 0.9]], atol=0.05)
    with pytest.raises(ValueError, match="size"):
        pano.render_cube(_sphere(2.0, centre), centre, 1)


def test_equirect_cells_hold_their_own_directions():
    grid = pano.equirect_directions(18, 36)
    assert grid.shape == (18, 36, 3) and np.allclose(np.linalg.norm(grid, axis=2), 1.0)
    assert np.all(np.diff(grid[:, 0, 2]) > 0)  # rows go up
    r, c = pano.equirect_cell(grid.reshape(-1, 3), 18, 36)
    assert np.array_equal(r, np.repeat(np.arange(18), 36)) and np.array_equal(c, np.tile(np.arange(36), 18))


def test_seen_by_cameras_needs_the_image_and_the_front():
    K = np.array([[10.0, 0, 8], [0, 10.0, 8], [0, 0, 1.0]])
    cams = Cameras(look_at((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))[None], K[None], 16, 16)
    pts = np.array([[2.0, 0.0, 0.0], [-2.0, 0.0, 0.0], [2.0, 5.0, 0.0], [2.0, 0.0, 0.5]])
    assert list(pano.seen_by_cameras(pts, [cams])) == [True, False, False, True]
    assert not pano.seen_by_cameras(pts, []).any()


def test_continue_columns_takes_the_nearest_known_cell_of_the_column():
    grid = pano.equirect_directions(6, 4)
    known = np.zeros((6, 4), bool)
    known[1:3, 0] = True  # column 0: rows 1 and 2
    known[4, 1] = True  # column 1: row 4
    known[0, 3] = True  # column 3: row 0; column 2: none
    src = pano.continue_columns(known, grid)
    rows, cols = np.divmod(src, 4)
    assert list(rows[:, 0]) == [1, 1, 2, 2, 2, 2] and np.all(cols[:, 0] == 0)
    assert np.all(rows[:, 1] == 4) and np.all(cols[:, 1] == 1)
    assert np.all(rows[:, 3] == 0) and np.all(cols[:, 3] == 3)
    assert np.all(known.reshape(-1)[src[:, 2]])  # column 2 takes known cells nearest in direction
    assert np.all(src.reshape(-1)[known.reshape(-1)] == np.flatnonzero(known))  # known cells keep their own
    with pytest.raises(ValueError, match="no cell is known"):
        pano.continue_columns(np.zeros((6, 4), bool), grid)
