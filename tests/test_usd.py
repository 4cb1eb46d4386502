"""Tests for dsg_gym.usd: the exported stage (layout, physics, quaternions, metadata, colliders), the exact
round trip through the reader, and the validators."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from _usd_scenes import assert_bits_equal, example_world, random_pose, random_rotation, random_set, rot_z
from pxr import Gf, Sdf, Usd, UsdGeom, UsdPhysics, UsdVol

from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import quat_to_rotmat, rotmat_to_quat
from dsg_gym.usd import Episode, UsdObject, export_stage, read_stage, validate_stage
from dsg_gym.usd.collider import convex_hull_mesh
from dsg_gym.usd.splats import splat_extent


@pytest.fixture(scope="module")
def world():
    return example_world()


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
