"""dsg_gym.cameras: the camera set type, look-at views, orbits and unprojection (OpenCV convention)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from dsg_gym.cameras import (
    Cameras,
    camera_centres,
    depth_points,
    intrinsics_from_fov,
    look_at,
    orbit_eyes,
    unproject,
)


def _to_camera(vm: np.ndarray, p) -> np.ndarray:
    return vm[:3, :3] @ np.asarray(p, np.float64) + vm[:3, 3]


def test_look_at_convention_and_errors():
    eye, target = np.array([0.6, -0.4, 0.5]), np.array([0.05, 0.1, 0.02])
    vm = look_at(eye, target)
    r = vm[:3, :3]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0) and np.array_equal(vm[3], [0, 0, 0, 1])
    np.testing.assert_allclose(_to_camera(vm, eye), 0.0, atol=1e-12)
    t = _to_camera(vm, target)  # on the optical axis (+z) at its distance
    np.testing.assert_allclose(t[:2], 0.0, atol=1e-12)
    assert t[2] == pytest.approx(np.linalg.norm(target - eye))
    above = _to_camera(vm, target + [0.0, 0.0, 0.1])
    assert above[1] < 0 and abs(above[0]) < 1e-12  # world up is image up (-y)
    with pytest.raises(ValueError, match="eye equals target"):
        look_at(eye, eye)
    with pytest.raises(ValueError, match="parallel"):
        look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0))


def test_orbit_rings_the_centre():
    centre, up = np.array([0.1, -0.2, 0.3]), np.array([0.2, 0.1, 1.0])
    elev = (math.radians(20.0), math.radians(45.0))
    eyes = orbit_eyes(centre, up, 1.5, elev, 8)
    assert eyes.shape == (8, 3)
    np.testing.assert_allclose(np.linalg.norm(eyes - centre, axis=1), 1.5, rtol=1e-12)
    u = up / np.linalg.norm(up)
    heights = (eyes - centre) @ u / 1.5
    np.testing.assert_allclose(heights, np.sin(np.resize(elev, 8)), atol=1e-12)
    horizontal = (eyes - centre) - np.outer(heights * 1.5, u)
    np.testing.assert_allclose(horizontal.sum(axis=0), 0.0, atol=1e-12)  # evenly around the ring
    for e in eyes:
        np.testing.assert_allclose(_to_camera(look_at(e, centre, u), centre)[:2], 0.0, atol=1e-12)
    # azimuth0 turns the ring: view 0 with azimuth0 = 2 pi / 8 is view 1 without
    np.testing.assert_allclose(
        orbit_eyes(centre, up, 1.5, (0.3,), 8, 2 * math.pi / 8)[0],
        orbit_eyes(centre, up, 1.5, (0.3,), 8)[1],
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="at least one view"):
        orbit_eyes(centre, up, 1.5, elev, 0)


def test_cameras_type():
    k = intrinsics_from_fov(60.0, 64, 48)
    assert k[0, 0] == k[1, 1] == pytest.approx(24.0 / math.tan(math.radians(30.0)))
    assert (k[0, 2], k[1, 2]) == (32.0, 24.0)
    vm32 = look_at((1.0, 0.5, 0.8), (0.0, 0.0, 0.0)).astype(np.float32)[None]
    c = Cameras(vm32, k[None].astype(np.float32), 64, 48)
    assert len(c) == 1 and c.viewmats.dtype == np.float64 and c.Ks.dtype == np.float64
    assert np.array_equal(c.viewmats.astype(np.float32), vm32)  # float32 storage converts back exactly
    r = c.resized(128, 96)
    assert (r.width, r.height) == (128, 96) and r.Ks[0, 0, 2] == 64.0 and r.Ks[0, 1, 1] == 2 * c.Ks[0, 1, 1]
    for bad in (
        dict(viewmats=np.zeros((0, 4, 4)), Ks=np.zeros((0, 3, 3))),
        dict(viewmats=np.eye(4)[None], Ks=np.eye(3)[None] * np.nan),
        dict(viewmats=np.eye(4)[None], Ks=np.eye(3)[None], width=0),
    ):
        with pytest.raises(ValueError, match="Cameras"):
            Cameras(**{"width": 8, "height": 8, **bad})


def test_unproject_inverts_the_projection():
    rng = np.random.default_rng(3)
    K = intrinsics_from_fov(55.0, 96, 64)
    vms = np.stack(
        [look_at(e, [0.1, -0.2, 0.0]) for e in ([1.0, 0.5, 0.8], [-0.7, 1.1, 0.4], [0.2, -1.3, 1.5])]
    )
    pts = rng.uniform(-0.3, 0.3, (3, 50, 3))
    cams = np.einsum("vij,vnj->vni", vms[:, :3, :3], pts) + vms[:, None, :3, 3]
    pix = np.einsum("ij,vnj->vni", K, cams)
    u, v, z = pix[..., 0] / pix[..., 2], pix[..., 1] / pix[..., 2], cams[..., 2]
    for i in range(3):  # one camera for all points
        np.testing.assert_allclose(unproject(u[i], v[i], z[i], vms[i], K), pts[i], atol=1e-12)
    per_point = unproject(u.ravel(), v.ravel(), z.ravel(), np.repeat(vms, 50, 0), np.repeat(K[None], 150, 0))
    np.testing.assert_allclose(per_point, pts.reshape(-1, 3), atol=1e-12)
    # the principal point at depth d lies on the optical axis, d in front of the camera centre
    centre = -vms[0, :3, :3].T @ vms[0, :3, 3]
    p = unproject([K[0, 2]], [K[1, 2]], [2.0], vms[0], K)[0]
    np.testing.assert_allclose(p, centre + 2.0 * vms[0, 2, :3], atol=1e-12)


def test_camera_centres_and_depth_points():
    eyes = np.array([[1.0, 0.5, 0.8], [-0.7, 1.1, 0.4], [0.2, -1.3, 1.5]])
    vms = np.stack([look_at(e, [0.1, -0.2, 0.0]) for e in eyes])
    np.testing.assert_allclose(camera_centres(vms), eyes, atol=1e-12)
    np.testing.assert_allclose(camera_centres(vms[1]), eyes[1], atol=1e-12)  # one camera
    np.testing.assert_allclose(camera_centres(vms.reshape(3, 1, 4, 4)), eyes[:, None], atol=1e-12)
    K = intrinsics_from_fov(55.0, 6, 4)
    depth = np.arange(1.0, 25.0).reshape(4, 6) / 10
    depth[2, 3] = 0.0
    p = depth_points(depth, vms[0], K)
    assert p.shape == (4, 6, 3) and p.dtype == np.float64
    # every pixel centre back in its pixel at its depth; a pixel without depth on the camera centre
    cam = p @ vms[0, :3, :3].T + vms[0, :3, 3]
    np.testing.assert_allclose(cam[..., 2], depth, atol=1e-12)
    ok = depth > 0
    u = K[0, 0] * cam[..., 0][ok] / cam[..., 2][ok] + K[0, 2]
    v = K[1, 1] * cam[..., 1][ok] / cam[..., 2][ok] + K[1, 2]
    np.testing.assert_allclose(u, (np.nonzero(ok)[1] + 0.5), atol=1e-9)
    np.testing.assert_allclose(v, (np.nonzero(ok)[0] + 0.5), atol=1e-9)
    np.testing.assert_allclose(p[2, 3], eyes[0], atol=1e-12)
    with pytest.raises(ValueError, match="depth must be a map"):
        depth_points(depth[None], vms[0], K)
