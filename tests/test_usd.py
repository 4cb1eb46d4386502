"""Tests for dsg_gym.usd: USD export of Gaussian worlds and episodes, and the reader."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdVol

from dsg_gym.cameras import look_at
from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import quat_to_rotmat, rotmat_to_quat
from dsg_gym.usd import (
    Episode,
    EpisodeRecorder,
    UsdCamera,
    UsdObject,
    export_stage,
    read_stage,
    validate_stage,
)
from dsg_gym.usd import stage as stage_mod
from dsg_gym.usd.cameras import K_from_usd_lens, usd_lens_from_K
from dsg_gym.usd.collider import convex_hull_mesh
from dsg_gym.usd.splats import splat_extent

FIELDS = ("means", "quats", "scales", "opacities", "sh", "features", "labels")


# ------------------------------------------------------------------------------------- helpers


def random_set(rng, n, degree=3, n_feat=16, spread=0.05):
    k = (degree + 1) ** 2
    return GaussianSet(
        means=rng.normal(size=(n, 3)) * spread,
        quats=rng.normal(size=(n, 4)),
        scales=rng.uniform(0, 0.01, (n, 3)),
        opacities=rng.uniform(0, 1, n),
        sh=rng.normal(size=(n, k, 3)),
        features=rng.normal(size=(n, n_feat)),
        labels=rng.integers(-3, 7, n),
    )


def random_rotation(rng):
    q = rng.normal(size=4)
    return quat_to_rotmat(q / np.linalg.norm(q))


def random_pose(rng, scale=0.3):
    pose = np.eye(4)
    pose[:3, :3] = random_rotation(rng)
    pose[:3, 3] = rng.normal(size=3) * scale
    return pose


def rot_z(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    pose = np.eye(4)
    pose[:2, :2] = [[c, -s], [s, c]]
    return pose


def make_camera(name="cam", eye=(0.6, -0.4, 0.5), w=160, h=120):
    K = np.array([[150.0, 0.0, 83.25], [0.0, 141.5, 57.5], [0.0, 0.0, 1.0]])
    return UsdCamera(name, look_at(eye, (0.0, 0.0, 0.02)), K, w, h)


def assert_bits_equal(a: GaussianSet, b: GaussianSet):
    assert a.num == b.num
    for f in FIELDS:
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype and x.shape == y.shape, f
        assert x.tobytes() == y.tobytes(), f"{f} differs"


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(7)
    background = random_set(rng, 400, degree=3, n_feat=16, spread=0.3)
    objects = [
        UsdObject("mug", random_set(rng, 120, degree=3, n_feat=16), random_pose(rng), mass=0.25),
        UsdObject("red block #2", random_set(rng, 80, degree=1, n_feat=16), rot_z(90.0), mass=0.05),
        UsdObject("empty", GaussianSet.empty(sh_degree=0, num_features=16), np.eye(4)),
    ]
    cameras = [make_camera("cam0"), make_camera("cam 1", eye=(-0.5, 0.3, 0.7), w=64, h=48)]
    return background, objects, cameras


# ------------------------------------------------------------------------------------- round trip


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_round_trip_exact(tmp_path, world, suffix):
    background, objects, cameras = world
    path = export_stage(
        tmp_path / f"world{suffix}",
        background,
        objects,
        cameras,
        table_bounds=[[-0.5, -0.4, 0.0], [0.5, 0.4, 0.0]],
    )
    assert path == tmp_path / f"world{suffix}" and path.is_file()
    assert sorted(os.listdir(tmp_path)) == [f"world{suffix}"]  # no temporary left
    magic = path.read_bytes()[:8]
    assert magic == (b"PXR-USDC" if suffix == ".usdc" else b"#usda 1.")

    got = read_stage(path)
    assert_bits_equal(got.background, background)
    assert [o.name for o in got.objects] == [o.name for o in objects]
    for o_got, o in zip(got.objects, objects):
        assert_bits_equal(o_got.gaussians, o.gaussians)
        assert np.abs(o_got.pose - o.pose).max() <= 1e-6
        assert o_got.mass == pytest.approx(o.mass, rel=1e-6)
        assert not o_got.kinematic
        assert o_got.collider_triangles.shape[0] >= 4
    assert got.objects[1].prim_path == "/World/Objects/red_block__2"
    assert got.episode is None
    assert got.table_vertices is not None and got.table_vertices[:, 2].max() == pytest.approx(0.0)
    assert [c.name for c in got.cameras] == ["cam0", "cam 1"]
    for c_got, c in zip(got.cameras, cameras):
        assert (c_got.width, c_got.height) == (c.width, c.height)
        np.testing.assert_allclose(c_got.K, c.K, rtol=1e-6)
        np.testing.assert_allclose(c_got.viewmat, c.viewmat, atol=1e-9)


def test_features_absent_and_degree0(tmp_path):
    rng = np.random.default_rng(1)
    bg = random_set(rng, 50, degree=0, n_feat=0)
    path = export_stage(tmp_path / "w.usda", bg, [UsdObject("a", random_set(rng, 10, 2, 0), np.eye(4))])
    got = read_stage(path)
    assert_bits_equal(got.background, bg)
    assert got.background.num_features == 0 and got.objects[0].gaussians.sh_degree == 2
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/World/Background")
    assert not prim.HasAttribute("primvars:dsg:features")
    assert prim.HasAttribute("primvars:dsg:labels")


def test_layout_and_physics(tmp_path, world):
    background, objects, cameras = world
    path = export_stage(tmp_path / "w.usdc", background, objects, cameras)
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/World/Background"))
    scene = UsdPhysics.Scene(stage.GetPrimAtPath("/World/PhysicsScene"))
    assert scene and tuple(scene.GetGravityDirectionAttr().Get()) == (0.0, 0.0, -1.0)
    assert scene.GetGravityMagnitudeAttr().Get() == pytest.approx(9.81)
    obj = stage.GetPrimAtPath("/World/Objects/mug")
    assert obj.HasAPI(UsdPhysics.RigidBodyAPI) and obj.HasAPI(UsdPhysics.MassAPI)
    assert UsdPhysics.MassAPI(obj).GetMassAttr().Get() == pytest.approx(0.25)
    ops = [op.GetOpName() for op in UsdGeom.Xformable(obj).GetOrderedXformOps()]
    assert ops == ["xformOp:translate", "xformOp:orient"]
    coll = stage.GetPrimAtPath("/World/Objects/mug/Collider")
    assert coll.IsA(UsdGeom.Mesh)
    assert coll.HasAPI(UsdPhysics.CollisionAPI) and coll.HasAPI(UsdPhysics.MeshCollisionAPI)
    assert UsdPhysics.MeshCollisionAPI(coll).GetApproximationAttr().Get() == UsdPhysics.Tokens.convexHull
    splats = UsdVol.ParticleField3DGaussianSplat(stage.GetPrimAtPath("/World/Objects/mug/Splats"))
    assert splats.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 3
    assert len(splats.GetRadianceSphericalHarmonicsCoefficientsAttr().Get()) == 120 * 16
    feat = UsdGeom.PrimvarsAPI(splats.GetPrim()).GetPrimvar("dsg:features")
    assert feat.GetElementSize() == 16 and feat.GetInterpolation() == UsdGeom.Tokens.vertex
    # extent bounds every Gaussian centre
    ext = np.array(splats.GetExtentAttr().Get())
    means = objects[0].gaussians.means
    assert (means >= ext[0]).all() and (means <= ext[1]).all()
    # the collider hull contains every splat centre (object frame)
    pts = np.array(UsdGeom.Mesh(coll).GetPointsAttr().Get(), np.float64)
    tris = np.array(UsdGeom.Mesh(coll).GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    _assert_closed_outward_hull(pts, tris, means)


# ------------------------------------------------------------------------------------- quaternions


def test_quaternion_layout_pinned(tmp_path):
    """wxyz in GaussianSet -> Gf.Quatf(real=w, imaginary=(x, y, z)) -> text (w, x, y, z); the
    numpy view of a Vt.QuatfArray is (x, y, z, w). Poses: 90 deg about z maps +x to +y."""
    q = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)  # deliberately unnormalised and asymmetric
    g = GaussianSet(np.zeros((1, 3)), q, np.full((1, 3), 0.01), np.array([0.5]), np.zeros((1, 1, 3)))
    path = export_stage(tmp_path / "q.usda", g, [UsdObject("box", g, rot_z(90.0))])

    text = path.read_text()
    assert "quatf[] orientations = [(0.1, 0.2, 0.3, 0.4)]" in text
    assert (
        "quatd xformOp:orient = (0.7071067811865476, 0, 0, 0.7071067811865476)" in text
        or "quatd xformOp:orient = (0.7071067811865475, 0, 0, 0.7071067811865475)" in text
    )

    stage = Usd.Stage.Open(str(path))
    raw = stage.GetPrimAtPath("/World/Background").GetAttribute("orientations").Get()
    assert isinstance(raw[0], Gf.Quatf)
    assert raw[0].GetReal() == pytest.approx(0.1)
    assert tuple(raw[0].GetImaginary()) == pytest.approx((0.2, 0.3, 0.4))
    np.testing.assert_array_equal(np.array(raw), np.float32([[0.2, 0.3, 0.4, 0.1]]))  # numpy: x, y, z, w
    orient = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Objects/box")).GetOrderedXformOps()[1].Get()
    assert isinstance(orient, Gf.Quatd)
    assert orient.GetReal() == pytest.approx(math.sqrt(0.5))
    assert tuple(orient.GetImaginary()) == pytest.approx((0.0, 0.0, math.sqrt(0.5)))
    m = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Objects/box")).ComputeLocalToWorldTransform(
        Usd.TimeCode.Default()
    )
    assert tuple(m.Transform(Gf.Vec3d(1, 0, 0))) == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)

    got = read_stage(path)
    assert got.background.quats.tobytes() == q.tobytes()
    np.testing.assert_allclose(got.objects[0].pose, rot_z(90.0), atol=1e-12)


def test_rotmat_quat_round_trip():
    rng = np.random.default_rng(3)
    rots = np.stack(
        [random_rotation(rng) for _ in range(200)]
        + [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
    )
    q = rotmat_to_quat(rots)
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(q), rots, atol=1e-12)
    # agrees with Gf (row-vector matrices: transpose)
    gq = Gf.Matrix4d(Gf.Matrix3d(rots[0].T.tolist()), Gf.Vec3d(0.0)).ExtractRotationQuat()
    sign = 1.0 if gq.GetReal() >= 0 else -1.0
    np.testing.assert_allclose(q[0], sign * np.array([gq.GetReal(), *gq.GetImaginary()]), atol=1e-9)


# ------------------------------------------------------------------------------------- validation


@pytest.mark.parametrize("suffix", [".usdc", ".usda"])
def test_validators_report_no_errors(tmp_path, world, suffix):
    background, objects, cameras = world
    rng = np.random.default_rng(5)
    poses = np.stack([[o.pose for o in objects]] * 3)
    poses[1, 0] = random_pose(rng)
    episode = Episode(10.0, poses, rewards=[0.5, 1.0])
    plain = export_stage(tmp_path / f"plain{suffix}", background, objects, cameras)
    full = export_stage(
        tmp_path / f"full{suffix}",
        background,
        objects,
        cameras,
        episode=episode,
        table_bounds=[[-0.5, -0.4, 0.0], [0.5, 0.4, 0.0]],
        meters_per_unit=0.01,
        up_axis="Y",
        kilograms_per_unit=0.001,
    )
    for path in (plain, full):
        issues = validate_stage(path)
        errors = [str(i) for i in issues if i.severity == "Error"]
        assert errors == [], errors


def test_validator_catches_a_broken_stage():
    """The registered validators actually run: a stage without metadata is reported."""
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.Xform.Define(stage, "/World")
    names = {i.name for i in validate_stage(stage) if i.severity == "Error"}
    assert {"MissingMetersPerUnitMetadata", "MissingUpAxisMetadata", "MissingDefaultPrim"} <= names


# ------------------------------------------------------------------------------------- metadata


def test_stage_metadata(tmp_path):
    rng = np.random.default_rng(2)
    obj = UsdObject("a", random_set(rng, 5), np.eye(4))
    path = export_stage(
        tmp_path / "m.usdc",
        random_set(rng, 5),
        [obj],
        meters_per_unit=0.01,
        up_axis="Y",
        kilograms_per_unit=0.001,
    )
    got = read_stage(path)
    md = got.metadata
    assert md["metersPerUnit"] == 0.01 and md["upAxis"] == "Y" and md["kilogramsPerUnit"] == 0.001
    assert md["defaultPrim"] == "/World"
    assert md["customLayerData"]["dsg"]["exporter"] == "dsg-gym"
    stage = Usd.Stage.Open(str(path))
    scene = UsdPhysics.Scene(stage.GetPrimAtPath("/World/PhysicsScene"))
    assert tuple(scene.GetGravityDirectionAttr().Get()) == (0.0, -1.0, 0.0)
    assert scene.GetGravityMagnitudeAttr().Get() == pytest.approx(981.0)


# ------------------------------------------------------------------------------------- episodes


def test_episode_time_samples_play_back(tmp_path, world):
    background, objects, _ = world
    rng = np.random.default_rng(11)
    t_count, k = 7, len(objects)
    rec = EpisodeRecorder(fps=15.0)
    rec.reset([o.pose for o in objects])
    for t in range(1, t_count):
        poses = [random_pose(rng) for _ in range(k)]
        poses[1] = rot_z(170.0 * t) @ poses[1]  # large rotations: hemisphere flips
        rec.step(poses, reward=float(t), action=rng.normal(size=(k, 6)))
    episode = rec.episode()
    assert episode.num_steps == t_count and episode.actions.shape == (t_count - 1, k, 6)
    path = export_stage(tmp_path / "ep.usdc", background, objects, episode=episode)

    stage = Usd.Stage.Open(str(path))
    assert stage.GetTimeCodesPerSecond() == 15.0 and stage.GetFramesPerSecond() == 15.0
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == t_count - 1
    for k_i, o in enumerate(objects):
        prim = stage.GetPrimAtPath(f"/World/Objects/{stage_mod._prim_names('o', [o.name])[0]}")
        assert UsdPhysics.RigidBodyAPI(prim).GetKinematicEnabledAttr().Get() is True
        xf = UsdGeom.Xformable(prim)
        for op in xf.GetOrderedXformOps():
            assert op.GetTimeSamples() == [float(t) for t in range(t_count)]
        for t in range(t_count):
            m = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode(t))).T
            assert np.abs(m - episode.poses[t, k_i]).max() <= 1e-6
        # the untimed default is the object's own pose
        m = np.array(xf.ComputeLocalToWorldTransform(Usd.TimeCode.Default())).T
        assert np.abs(m - o.pose).max() <= 1e-6
        # consecutive quaternions are in the same hemisphere (interpolation takes the short way)
        orient = xf.GetOrderedXformOps()[1]
        qs = [orient.Get(Usd.TimeCode(t)) for t in range(t_count)]
        dots = [Gf.Dot(a, b) for a, b in zip(qs[:-1], qs[1:])]
        assert min(dots) >= 0

    got = read_stage(path)
    assert got.episode is not None and got.episode.fps == 15.0
    assert np.abs(got.episode.poses - episode.poses).max() <= 1e-6
    np.testing.assert_array_equal(got.episode.rewards, episode.rewards)
    np.testing.assert_array_equal(got.episode.actions, episode.actions)
    assert all(o.kinematic for o in got.objects)


def test_episode_single_step_and_no_objects(tmp_path):
    rng = np.random.default_rng(4)
    bg = random_set(rng, 10)
    path = export_stage(tmp_path / "e.usda", bg, [], episode=Episode(30, np.zeros((4, 0, 4, 4))))
    got = read_stage(path)
    assert got.episode.poses.shape == (4, 0, 4, 4) and got.metadata["endTimeCode"] == 3
    obj = UsdObject("a", random_set(rng, 5), np.eye(4))
    path = export_stage(tmp_path / "e1.usda", bg, [obj], episode=Episode(30, np.eye(4)[None, None]))
    got = read_stage(path)
    assert got.episode.poses.shape == (1, 1, 4, 4) and got.episode.rewards is None


# ------------------------------------------------------------------------------------- cameras


def _usd_project(stage: Usd.Stage, prim_path: str, points: np.ndarray, w: int, h: int) -> np.ndarray:
    gf_cam = UsdGeom.Camera(stage.GetPrimAtPath(prim_path)).GetCamera(Usd.TimeCode.Default())
    frustum = gf_cam.frustum
    view = np.array(frustum.ComputeViewMatrix())
    proj = np.array(frustum.ComputeProjectionMatrix())
    hom = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ view @ proj  # row vectors
    ndc = hom[:, :2] / hom[:, 3:4]
    return np.stack([(ndc[:, 0] + 1) / 2 * w, (1 - ndc[:, 1]) / 2 * h], axis=1)


def test_cameras_project_consistently(tmp_path, world):
    background, _, _ = world
    rng = np.random.default_rng(9)
    cams = [
        make_camera("a"),
        UsdCamera(
            "b",
            look_at((0.1, 0.9, 0.3), (0.05, 0.0, 0.1)),
            np.array([[400.0, 0, 300.5], [0, 380.0, 170.25], [0, 0, 1]]),
            640,
            360,
        ),
    ]
    path = export_stage(tmp_path / "c.usdc", background, [], cams)
    stage = Usd.Stage.Open(str(path))
    for cam in cams:
        pts = rng.uniform(-0.15, 0.15, (50, 3))
        cam_pts = (cam.viewmat[:3, :3] @ pts.T + cam.viewmat[:3, 3:4]).T
        assert (cam_pts[:, 2] > 0).all()
        uv_cv = (cam.K @ (cam_pts / cam_pts[:, 2:3]).T).T[:, :2]
        uv_usd = _usd_project(stage, f"/World/Cameras/{cam.name}", pts, cam.width, cam.height)
        np.testing.assert_allclose(uv_usd, uv_cv, atol=1e-3)
        usd_cam = UsdGeom.Camera(stage.GetPrimAtPath(f"/World/Cameras/{cam.name}"))
        assert usd_cam.GetHorizontalApertureAttr().Get() == pytest.approx(20.955)
        assert tuple(usd_cam.GetClippingRangeAttr().Get()) == pytest.approx((0.01, 100.0))


def test_lens_conversion_inverse():
    K = np.array([[321.5, 0, 100.25], [0, 333.0, 77.0], [0, 0, 1]])
    np.testing.assert_allclose(K_from_usd_lens(usd_lens_from_K(K, 211, 149), 211, 149), K, rtol=1e-12)


# ------------------------------------------------------------------------------------- colliders


def _assert_closed_outward_hull(pts, tris, inside, tol=1e-6):
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    normals = np.cross(b - a, c - a)
    assert (np.linalg.norm(normals, axis=1) > 0).all()
    # closed: every directed edge has its reverse
    edges = {(int(i), int(j)) for t in tris for i, j in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert all((j, i) in edges for i, j in edges)
    volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    assert volume > 0  # counter-clockwise seen from outside
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    signed = np.einsum("pfj,fj->pf", inside[:, None, :] - a[None], normals)
    assert (signed <= tol).all()


@pytest.mark.parametrize("case", ["empty", "point", "line", "flat", "tiny", "tilted_flat", "cloud"])
def test_convex_hull_degenerate_sets(case):
    rng = np.random.default_rng(0)
    if case == "empty":
        pts = np.zeros((0, 3))
    elif case == "point":
        pts = np.array([[0.1, 0.2, 0.3]] * 5)
    elif case == "line":
        pts = np.outer(np.linspace(-1, 1, 9), [0.3, 0.1, -0.2])
    elif case == "flat":
        pts = np.c_[rng.uniform(-0.05, 0.05, (50, 2)), np.zeros(50)]
    elif case == "tiny":
        pts = rng.normal(size=(30, 3)) * 1e-6
    elif case == "tilted_flat":
        pts = np.c_[rng.uniform(-0.05, 0.05, (50, 2)), np.zeros(50)] @ random_rotation(rng).T
    else:
        pts = rng.normal(size=(300, 3))
    verts, tris = convex_hull_mesh(pts, min_thickness=2e-3)
    assert verts.shape[1] == 3 and tris.shape[1] == 3 and len(tris) >= 4
    assert tris.dtype == np.int32 and tris.min() >= 0 and tris.max() < len(verts)
    _assert_closed_outward_hull(verts, tris, pts if len(pts) else np.zeros((1, 3)))
    if case != "cloud":  # thickened to min_thickness along the degenerate directions
        extent = np.ptp(verts @ np.linalg.svd(verts - verts.mean(0))[2].T, axis=0)
        assert extent.min() >= 2e-3 - 1e-9
        if case in ("flat", "tilted_flat"):
            assert extent.min() <= 2e-3 + 1e-9


def test_splat_extent_covers_3_sigma():
    rng = np.random.default_rng(6)
    g = random_set(rng, 100)
    lo, hi = splat_extent(g)
    assert (g.means >= lo).all() and (g.means <= hi).all()
    single = GaussianSet(np.zeros((1, 3)), [[1, 0, 0, 0]], [[0.1, 0.2, 0.3]], [1.0], np.zeros((1, 1, 3)))
    lo, hi = splat_extent(single)
    np.testing.assert_allclose(hi, [0.3, 0.6, 0.9], rtol=1e-6)
    np.testing.assert_allclose(lo, [-0.3, -0.6, -0.9], rtol=1e-6)


# ------------------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_value_error(tmp_path, world):
    background, objects, cameras = world
    bad_pose = np.eye(4)
    bad_pose[0, 3] = np.nan
    skew = np.eye(4)
    skew[0, 1] = 0.3
    K_skew = cameras[0].K.copy()
    K_skew[0, 1] = 1.0
    cases = [
        (dict(path=tmp_path / "w.ply"), r"\.usdc .*\.usda"),
        (dict(path=tmp_path / "w.usd"), r"\.usdc .*\.usda"),
        (dict(path=tmp_path / "w.usdz"), r"\.usdc .*\.usda"),
        (dict(objects=[UsdObject("a", background, bad_pose)]), r"'a' pose: contains non-finite"),
        (dict(objects=[UsdObject("a", background, skew)]), r"'a' pose: not a rigid transform"),
        (dict(objects=[UsdObject("a", background, np.eye(3))]), r"pose must be \[4, 4\]"),
        (dict(objects=[UsdObject("a", background, np.eye(4), mass=0.0)]), r"mass"),
        (dict(objects=[UsdObject("a", background, np.eye(4))] * 2), r"same prim name"),
        (
            dict(objects=[UsdObject("a b", background, np.eye(4)), UsdObject("a_b", background, np.eye(4))]),
            r"same prim name",
        ),
        (dict(episode=Episode(10.0, np.stack([np.eye(4)] * 2)[None])), r"episode\.poses .*\[T, 3, 4, 4\]"),
        (dict(cameras=[UsdCamera("c", cameras[0].viewmat, K_skew, 10, 10)]), r"'c'\.K: .*no skew"),
        (dict(cameras=[UsdCamera("c", cameras[0].viewmat, cameras[0].K, 0, 10)]), r"'c'\.width"),
        (dict(up_axis="X"), r"up_axis"),
        (dict(meters_per_unit=float("inf")), r"meters_per_unit"),
        (dict(background="nope"), r"background must be a GaussianSet"),
        (dict(table_bounds=[[0, 0, 0]]), r"table_bounds"),
    ]
    for override, pattern in cases:
        kwargs = dict(path=tmp_path / "w.usdc", background=background, objects=objects, cameras=cameras)
        kwargs.update(override)
        with pytest.raises(ValueError, match=pattern):
            export_stage(**kwargs)
    assert os.listdir(tmp_path) == []


def test_bad_episodes_raise_value_error():
    eye = np.eye(4)[None, None]
    with pytest.raises(ValueError, match=r"Episode\.poses: expected shape"):
        Episode(10.0, np.eye(4))
    with pytest.raises(ValueError, match=r"Episode\.poses: contains non-finite"):
        Episode(10.0, np.full((2, 1, 4, 4), np.inf))
    with pytest.raises(ValueError, match=r"Episode\.fps"):
        Episode(0.0, eye)
    with pytest.raises(ValueError, match=r"Episode\.rewards: expected shape \(1,\)"):
        Episode(10.0, np.concatenate([eye, eye]), rewards=[1.0, 2.0])
    with pytest.raises(ValueError, match=r"Episode\.actions"):
        Episode(10.0, np.concatenate([eye, eye]), actions=np.zeros((3, 2)))
    rec = EpisodeRecorder(10.0)
    with pytest.raises(ValueError, match="reset"):
        rec.step(np.eye(4)[None])


# ------------------------------------------------------------------------------------- atomic writes


def test_write_is_atomic_on_failure_mid_build(tmp_path, world, monkeypatch):
    background, objects, cameras = world
    target = tmp_path / "w.usdc"
    target.write_bytes(b"previous")

    def boom(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(stage_mod, "write_collider", boom)
    with pytest.raises(RuntimeError, match="disk on fire"):
        export_stage(target, background, objects, cameras)
    assert target.read_bytes() == b"previous"
    assert os.listdir(tmp_path) == ["w.usdc"]


def test_write_is_atomic_on_failure_after_temp_written(tmp_path, world, monkeypatch):
    background, objects, cameras = world
    target = tmp_path / "w.usda"
    target.write_bytes(b"previous")
    seen = []

    def failing_replace(src, dst):
        seen.append(Path(src))
        assert Path(src).is_file() and Path(src).suffix == ".usda" and Path(src).parent == tmp_path
        raise OSError("rename failed")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="rename failed"):
        export_stage(target, background, objects, cameras)
    assert seen and not seen[0].exists()
    assert target.read_bytes() == b"previous"
    assert os.listdir(tmp_path) == ["w.usda"]


def test_overwrite_replaces_existing_stage(tmp_path, world):
    background, objects, _ = world
    target = tmp_path / "w.usdc"
    export_stage(target, background, objects)
    export_stage(target, background, objects[:1])
    assert [o.name for o in read_stage(target).objects] == ["mug"]


# ------------------------------------------------------------------------------------- helpers for callers


def test_recorder_accepts_pose7_vectors():
    rec = EpisodeRecorder(fps=10)
    half = math.sqrt(0.5)
    rec.reset([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]])
    rec.step([[0.0, 0.0, 0.0, 2 * half, 0.0, 0.0, 2 * half]], reward=1.0)  # unnormalised: renormalised
    ep = rec.episode()
    np.testing.assert_allclose(ep.poses[0, 0, :3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(ep.poses[1, 0], rot_z(90.0), atol=1e-12)
    with pytest.raises(ValueError, match=r"\[K, 4, 4\] or \[K, 7\]"):
        rec.step(np.zeros((1, 6)))


def test_cameras_from_arrays(tmp_path, world):
    background = world[0]
    cams = [make_camera("x"), make_camera("y", eye=(0.2, 0.7, 0.4))]
    from dsg_gym.usd import cameras_from_arrays

    made = cameras_from_arrays([c.viewmat for c in cams], [c.K for c in cams], 160, 120)
    assert [c.name for c in made] == ["cam_000", "cam_001"]
    got = read_stage(export_stage(tmp_path / "c.usda", background, [], made))
    assert [c.name for c in got.cameras] == ["cam_000", "cam_001"]
    np.testing.assert_allclose(got.cameras[1].viewmat, cams[1].viewmat, atol=1e-9)
    with pytest.raises(ValueError, match="bad shapes"):
        cameras_from_arrays(np.eye(4), np.eye(3), 10, 10)


def test_an_unwritable_place_is_an_os_error_naming_it(tmp_path, world):
    background, objects, _ = world
    if not Path("/proc/self").is_dir():
        pytest.skip("needs /proc, a folder no one can create files in")
    with pytest.raises(OSError, match=r"export_stage: cannot write '/proc/w.usda': Unable to create") as err:
        export_stage("/proc/w.usda", background, objects)
    assert "\n" not in str(err.value) and ".cpp" not in str(err.value)  # USD's reason, without its sources


def test_an_export_removes_what_killed_exports_to_its_path_left(tmp_path, world):
    import subprocess
    import sys
    import textwrap

    background, objects, _ = world
    target = tmp_path / "w.usda"
    code = f"""
        import contextlib, os, signal
        import numpy as np
        import dsg_gym.usd.stage as stage
        from dsg_gym.gaussians import GaussianSet
        real = stage.atomic_path

        @contextlib.contextmanager
        def killed_after_writing(path, **kw):
            with real(path, **kw) as tmp:
                yield tmp
                os.kill(os.getpid(), signal.SIGKILL)  # USD wrote the temporary; it is never renamed

        stage.atomic_path = killed_after_writing
        g = GaussianSet.from_rgb(np.zeros((5, 3)), np.tile([1.0, 0, 0, 0], (5, 1)), np.full((5, 3), 0.01),
                                 np.full(5, 0.5), np.full((5, 3), 0.5))
        stage.export_stage({str(target)!r}, g)
    """
    res = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True)
    assert res.returncode != 0, res.stderr
    left = os.listdir(tmp_path)
    assert len(left) == 1 and left[0].startswith(".w.usda.tmp-") and (tmp_path / left[0]).stat().st_size > 0
    pid, host, rest = left[0][len(".w.usda.tmp-") :].split("-", 2)
    live = f".w.usda.tmp-{os.getppid()}-{host}-{rest}"  # a writer that still runs keeps its temporary
    elsewhere = f".w.usda.tmp-{pid}-{int(host, 16) ^ 1:08x}-{rest}"  # so does one on another machine
    for name in (live, elsewhere):
        (tmp_path / name).write_bytes(b"partial")
    export_stage(target, background, objects)
    assert sorted(os.listdir(tmp_path)) == sorted([live, elsewhere, "w.usda"])
    assert read_stage(target).background.num == background.num
