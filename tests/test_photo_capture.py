"""dsg-capture: photos of two states -> camera poses, table frame, object motions, a standard capture.

Measured against the ground truth that ``dsg-synth --as-photos`` writes beside the photos (four_mixed, 128x128,
24 views per state). The tolerances leave about a factor two over what this fixture gives (camera centres
0.64 % of the scene radius, rotations 0.31 degrees; object centres <= 1.8 mm; object rotations modulo their
shape's symmetry <= 2.4 degrees at this low view count; the up axis 0.1 degrees, the table top ~1 mm).
"""

from __future__ import annotations

import json
import os
import shutil

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402  (numpy and Pillow before pycolmap)
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

pytest.importorskip("pycolmap", reason="dsg-capture needs pycolmap (pip install pycolmap==4.2.1)")

from train_world.capture import load_capture  # noqa: E402
from train_world.capture.compare import (  # noqa: E402
    compare_captures,
    shape_symmetries,
    texture_symmetries,
    with_true_cameras,
)
from train_world.capture.files import label_resize  # noqa: E402
from train_world.capture.frame import Plane, table_frame  # noqa: E402
from train_world.capture.motions import MotionError, estimate_object_motion, fit_rigid_ransac  # noqa: E402
from train_world.capture.photo_capture import build_capture  # noqa: E402
from train_world.capture.photos import PhotoCaptureError, read_photo_capture  # noqa: E402
from train_world.capture.sfm import SfmResult, run_sfm  # noqa: E402
from train_world.capture.silhouettes import SilhouetteView  # noqa: E402
from train_world.capture.undistort import Undistorter  # noqa: E402
from train_world.cli import capture as capture_cli  # noqa: E402
from train_world.cli import synth as synth_cli  # noqa: E402

SCENE = "four_mixed"  # a striped box, a dotted cylinder, a plain white ball (no features), a checkered prism
CENTRE_TOL_PERCENT = 1.5  # camera centre median error, % of the scene radius
CAMERA_ROT_TOL_DEG = 1.0
OBJECT_POS_TOL_M = 0.005
OBJECT_ROT_TOL_DEG = 5.0  # modulo the shape's symmetry; 24 views of 128x128 leave few features per object


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("photos") / SCENE
    rc = synth_cli.main(
        [
            "--scene",
            SCENE,
            "--out",
            str(out),
            "--views",
            "24",
            "--test-states",
            "0",
            "--test-views",
            "0",
            "--as-photos",
            "--quiet",
        ]
    )
    assert rc == 0
    return out


@pytest.fixture(scope="module")
def estimated(photos, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("capture") / "estimated"
    report = build_capture(photos, out, progress=False)
    return out, report


def test_as_photos_layout(photos):
    gt = photos / "ground_truth"
    assert (gt / "scene.json").is_file()
    for state in ("state1", "state2"):
        jpgs = sorted((photos / state / "images").glob("*.jpg"))
        masks = sorted((photos / state / "masks").glob("*.png"))
        assert len(jpgs) == len(masks) == 24
        assert [p.stem for p in jpgs] == [p.stem for p in masks]
        with Image.open(jpgs[0]) as im:
            assert im.format == "JPEG" and im.size == (128, 128)
        assert (photos / state / "masks" / masks[0].name).read_bytes() == (
            gt / state / "masks" / masks[0].name
        ).read_bytes()
    names = [o["name"] for o in json.loads((photos / "objects.json").read_text())]
    assert names == [o["name"] for o in json.loads((gt / "scene.json").read_text())["objects"]]


def test_registration_and_report(photos, estimated):
    out, report = estimated
    assert json.loads((out / "report.json").read_text())["registered"] == report["registered"]
    for state in ("state1", "state2"):
        r = report["registered"][state]
        assert r["views"] >= 0.95 * r["of"] and r["of"] == 24
    assert report["mean_reprojection_error_px"] < 1.0
    assert report["units"] == "unknown" and report["scale"]["metres_per_unit"] is None
    assert {o["name"] for o in report["objects"]} == {
        "orange_box",
        "teal_cylinder",
        "white_ball",
        "magenta_prism",
    }
    ball = next(o for o in report["objects"] if o["name"] == "white_ball")
    assert ball["method"] == "silhouettes"  # a plain ball has no features: its masks give the motion
    assert ball["appearance"] is None  # and no texture for its colours to refine the turn by
    textured = [o for o in report["objects"] if o["appearance"] is not None]
    assert {"orange_box", "magenta_prism"} <= {o["name"] for o in textured}
    for o in textured:
        a = o["appearance"]
        assert a["photo_pairs"] > 0 and o["feature_inliers"] > 0
        assert a["kept"] == o["method"].endswith("+appearance")
        assert (
            a["symmetric_candidates"] >= 1
        )  # a box's, a cylinder's, a prism's equal turns, for colours to choose
        assert not a["kept"] or a["colour_rms_after"] <= a["colour_rms_before"] + 1e-6
    assert any(o["appearance"]["kept"] for o in textured)
    assert not any(p.name.startswith(".") for p in out.parent.iterdir())  # no staging or work folders left


def test_capture_loads_and_matches_ground_truth(photos, estimated):
    out, _ = estimated
    cap = load_capture(out)
    truth = load_capture(photos / "ground_truth", ["state1", "state2"], load_depth=False)
    assert cap.train_states == ("state1", "state2") and cap.units == "unknown"
    assert cap.states["state1"].masks is not None and cap.table_bounds is not None
    T = cap.relative_transform("state1", "state2")
    assert np.allclose(T, cap.supplied_transforms[("state1", "state2")], atol=1e-9)
    r = compare_captures(cap, truth)
    print(json.dumps(r, indent=1))
    assert r["camera_centre_error_median_percent_of_radius"] < CENTRE_TOL_PERCENT
    assert r["camera_rotation_error_median_deg"] < CAMERA_ROT_TOL_DEG
    for o in r["objects"]:
        assert o["position_error"] < OBJECT_POS_TOL_M, o
        assert o["rotation_error_mod_symmetry_deg"] < OBJECT_ROT_TOL_DEG, o
        # a patterned cylinder's or prism's turn counts, modulo only what keeps its cube-mapped pattern
        assert o["rotation_error_mod_texture_deg"] < OBJECT_ROT_TOL_DEG, o
    # the frame: +z up and the table top at z = 0, as in the ground truth
    assert r["up_axis_error_deg"] < 0.5 and abs(r["table_top_error"]) < 0.006
    z = np.array([p[2, 3] for p in cap.poses["state1"]])
    assert np.all(z > 0) and np.all(z < 0.2)  # object centres just above the table, in units of ~0.8 m


def test_true_cameras_replace_the_estimate_and_carry_the_points(photos):
    truth = load_capture(photos / "ground_truth", ["state1", "state2"], load_depth=False, load_masks=False)
    assert compare_captures(truth, truth)["focal_error_percent"] == 0.0
    # a reconstruction in another frame: the truth's cameras moved by a similarity S (scale 0.3)
    S = np.eye(4)
    S[:3, :3] = 0.3 * np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    S[:3, 3] = [0.5, -0.2, 1.0]
    w2c, registered = {}, {}
    for state, v in truth.states.items():
        for path, c2w_gl in zip(v.image_paths, v.c2w_opengl, strict=True):
            c2w = c2w_gl @ np.diag([1.0, -1.0, -1.0, 1.0])  # OpenGL -> OpenCV camera axes
            moved = S @ c2w
            moved[:3, :3] /= 0.3
            w2c[f"{state}/{path.stem}"] = np.linalg.inv(moved)
        registered[state] = tuple(p.stem for p in v.image_paths)
    pts = np.random.default_rng(0).normal(size=(50, 3))
    sfm = SfmResult(w2c, {}, pts @ S[:3, :3].T + S[:3, 3], np.zeros(50), 0.2, registered, {})
    exact = with_true_cameras(sfm, truth)
    assert np.allclose(exact.points, pts, atol=1e-6)  # carried back into the truth's frame
    key = next(iter(w2c))
    c2w_true = truth.states["state1"].c2w_opengl[0] @ np.diag([1.0, -1.0, -1.0, 1.0])
    assert np.allclose(np.linalg.inv(exact.world_to_camera[key]), c2w_true, atol=1e-9)
    w2c["state1/not_a_view"] = np.eye(4)
    with pytest.raises(ValueError, match="no true camera for registered views"):
        with_true_cameras(SfmResult(w2c, {}, pts, np.zeros(50), 0.2, registered, {}), truth)


def test_a_capture_on_the_true_cameras_scores_the_motion_step_alone(photos, estimated, tmp_path):
    truth = load_capture(photos / "ground_truth", ["state1", "state2"], load_depth=False, load_masks=False)
    est = compare_captures(load_capture(estimated[0], load_masks=False), truth)
    assert 0.0 < abs(est["focal_error_percent"]) < 3.0  # structure from motion's focal length, a little off

    def reconstruct(capture, work, **kw):
        return with_true_cameras(run_sfm(capture, work, **kw), truth)

    build_capture(photos, tmp_path / "exact", progress=False, reconstruct=reconstruct)
    r = compare_captures(load_capture(tmp_path / "exact", load_masks=False), truth)
    assert r["camera_centre_error_max"] < 1e-4 * r["scene_radius"]
    assert r["camera_rotation_error_max_deg"] < 1e-3 and abs(r["focal_error_percent"]) < 1e-3
    for o in r["objects"]:
        assert o["position_error"] < OBJECT_POS_TOL_M, o
        assert o["rotation_error_mod_symmetry_deg"] < OBJECT_ROT_TOL_DEG, o


def _copy(photos: Path, tmp: Path) -> Path:
    dst = tmp / "photos"
    shutil.copytree(photos, dst, ignore=shutil.ignore_patterns("ground_truth"))
    return dst


def _fails(src: Path, tmp: Path, *needles: str, capsys=None) -> str:
    out = tmp / "out"
    rc = capture_cli.main([str(src), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err if capsys else ""
    assert rc == 2, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("dsg-capture: error: "), line
    for n in needles:
        assert n in line, (n, line)
    assert not out.exists()
    assert not [p for p in tmp.iterdir() if p.name.startswith(".out")]
    return line


def test_bad_input_missing_folders(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    shutil.rmtree(src / "state2" / "masks")
    _fails(src, tmp_path, str(src / "state2" / "masks"), "folder not found", capsys=capsys)
    shutil.rmtree(src / "state2")
    _fails(src, tmp_path, str(src / "state2"), "state1/ and state2/", capsys=capsys)


def test_bad_input_counts_and_stems(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    (src / "state1" / "masks" / "0003.png").unlink()
    _fails(src, tmp_path, "0003.png", "24 images but 23 masks", "same file stem", capsys=capsys)
    (src / "state1" / "masks" / "0003.png").write_bytes(
        (photos / "state1" / "masks" / "0003.png").read_bytes()
    )
    (src / "state1" / "masks" / "0003.png").rename(src / "state1" / "masks" / "x0003.png")
    _fails(src, tmp_path, "0003.png", capsys=capsys)


def test_bad_input_sizes_and_decoding(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    mask = src / "state2" / "masks" / "0005.png"
    Image.fromarray(np.zeros((64, 64), np.uint8)).save(mask)
    _fails(src, tmp_path, str(mask), "64x64", "128x128", capsys=capsys)
    mask.write_bytes((photos / "state2" / "masks" / "0005.png").read_bytes())
    bad = src / "state1" / "images" / "0007.jpg"
    bad.write_bytes(b"not a jpeg at all")
    _fails(src, tmp_path, str(bad), "cannot decode", capsys=capsys)


def test_bad_input_ids_between_states(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    for p in (src / "state2" / "masks").glob("*.png"):
        m = np.asarray(Image.open(p)).copy()
        m[m == 3] = 0  # the ball vanishes from state2
        Image.fromarray(m).save(p)
    _fails(src, tmp_path, "object id 3", "state1", "no mask of state2", capsys=capsys)
    with pytest.raises(PhotoCaptureError, match="object id 3 appears in state1"):
        read_photo_capture(src)


def test_bad_input_objects_json(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    (src / "objects.json").write_text(json.dumps([{"id": 1, "name": "a"}, {"id": 2, "name": "b"}]))
    _fails(src, tmp_path, "objects.json", "no name for object id 3", capsys=capsys)


@pytest.mark.slow
def test_views_that_do_not_register_are_named(photos, tmp_path, capsys):
    src = _copy(photos, tmp_path)
    rng = np.random.default_rng(0)
    blank = np.zeros((128, 128), np.uint8)
    for i in range(3):  # 24 of 27 = 89 % < 95 %
        Image.fromarray(rng.integers(0, 256, (128, 128, 3), dtype=np.uint8)).save(
            src / "state2" / "images" / f"noise{i}.png"
        )
        Image.fromarray(blank).save(src / "state2" / "masks" / f"noise{i}.png")
    line = _fails(src, tmp_path, "did not register", "24 of 27 state2 photos", capsys=capsys)
    assert all(f"noise{i}.png" in line for i in range(3))


def test_too_few_matches_names_the_object(photos, estimated):
    """No features and silhouettes that disagree between the states (e.g. the id marks different objects)."""
    cap = load_capture(estimated[0])
    obj = cap.objects[0]

    def views(state: str, shuffle: bool) -> list[SilhouetteView]:
        v = cap.states[state]
        rng = np.random.default_rng(1)
        out = []
        for m, K, vm in zip(v.masks.numpy(), v.Ks.double().numpy(), v.viewmats.double().numpy()):
            if shuffle:
                m = np.roll(m, tuple(rng.integers(-30, 30, 2)), axis=(0, 1))
            out.append(SilhouetteView(m, K, vm))
        return out

    plane = (np.array([0.0, 0.0, 1.0]), 0.0)
    with pytest.raises(MotionError, match=rf"object {obj.id} \('{obj.name}'\): too few feature matches"):
        estimate_object_motion(obj, ([], []), (views("state1", False), views("state2", True)), plane, 1.5)


def test_rigid_ransac_recovers_motion_with_outliers():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(60, 3)) * 0.05
    ang = np.radians(35.0)
    R = np.array([[np.cos(ang), -np.sin(ang), 0], [np.sin(ang), np.cos(ang), 0], [0, 0, 1]])
    q = p @ R.T + np.array([0.1, -0.2, 0.0]) + rng.normal(size=p.shape) * 1e-4
    q[:15] = rng.normal(size=(15, 3)) * 0.05  # 25 % outliers
    T, inl = fit_rigid_ransac(p, q, threshold=1e-3, seed=0)
    assert np.allclose(T[:3, :3], R, atol=1e-3) and np.allclose(T[:3, 3], [0.1, -0.2, 0.0], atol=1e-3)
    assert inl[15:].all() and not inl[:15].any()


def test_frame_scale_and_orientation():
    rng = np.random.default_rng(0)
    n = np.array([0.0, 0.6, 0.8])
    e1 = np.array([1.0, 0.0, 0.0])
    e2 = np.cross(n, e1)
    pts = rng.uniform(-1, 1, (400, 2)) @ np.stack([e1, e2]) + 0.3 * n
    cams = 2.0 * n + rng.uniform(-1, 1, (20, 3)) @ np.stack([e1, e2, np.zeros(3)]).T
    plane = Plane(n, -0.3, np.ones(len(pts), bool), 0.0)
    f1 = table_frame(plane, pts, np.array([0.3 * n]), cams)
    f2 = table_frame(plane, pts, np.array([0.3 * n]), cams, metres_per_unit=0.5)
    assert f1.units == "unknown" and f2.units == "metres"
    assert np.allclose(f2.world_from_sfm[:3], 0.5 * f1.world_from_sfm[:3])
    assert np.allclose(np.abs(f1.points(pts)[:, 2]), 0.0, atol=1e-9)  # table top at z = 0
    assert np.all(f1.points(cams)[:, 2] > 0)  # +z toward the cameras


def test_undistorter_is_identity_without_distortion():
    und = Undistorter.for_camera("SIMPLE_RADIAL", (100.0, 32.0, 24.0, 0.0), 64, 48)
    img = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    assert (und.width, und.height) == (64, 48) and np.allclose(und.K, [[100, 0, 32], [0, 100, 24], [0, 0, 1]])
    assert np.array_equal(und.rgb(img), img) and np.array_equal(und.ids(img[..., 0]), img[..., 0])
    barrel = Undistorter.for_camera("SIMPLE_RADIAL", (100.0, 32.0, 24.0, -0.05), 64, 48)
    assert barrel.src_x.min() >= 0.5 - 1e-6 and barrel.src_x.max() <= 63.5 + 1e-6  # no blank pixels


def test_texture_symmetries():
    ball = {"type": "sphere", "radius": 1}
    assert texture_symmetries(ball, None) == "all" and len(texture_symmetries(ball, "dots")) == 24
    assert len(texture_symmetries({"type": "cylinder", "radius": 1, "height": 2}, "stripes")) == 8
    assert len(texture_symmetries({"type": "mesh", "mesh": "prism", "sides": 6}, "checker")) == 4
    assert len(texture_symmetries({"type": "mesh", "mesh": "prism", "sides": 8}, "checker")) == 8
    assert len(texture_symmetries({"type": "mesh", "mesh": "frustum", "sides": 7}, "dots")) == 1
    assert len(texture_symmetries({"type": "box", "extents": [1, 1, 3]}, "dots")) == 8
    for m in texture_symmetries({"type": "mesh", "mesh": "prism", "sides": 6}, "dots"):
        assert np.allclose(m @ m.T, np.eye(3)) and np.isclose(np.linalg.det(m), 1.0)
        assert np.allclose(np.abs(m).sum(axis=0), 1.0)  # a quarter-turn rotation: one +-1 per column
    # a dotted ball turned 90 deg about z looks the same, turned 45 deg it does not
    from scipy.spatial.transform import Rotation

    from train_world.capture.compare import motion_error

    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 45.0, degrees=True).as_matrix()
    e = motion_error(turn, np.eye(4), np.eye(4), ball, "dots")
    assert (
        e["rotation_error_mod_symmetry_deg"] == 0.0 and abs(e["rotation_error_mod_texture_deg"] - 45.0) < 1e-6
    )
    turn[:3, :3] = Rotation.from_euler("z", 90.0, degrees=True).as_matrix()
    assert motion_error(turn, np.eye(4), np.eye(4), ball, "dots")["rotation_error_mod_texture_deg"] < 1e-6


def test_shape_symmetries():
    assert shape_symmetries({"type": "sphere", "radius": 1}) == "all"
    assert len(shape_symmetries({"type": "box", "extents": [1, 2, 3]})) == 4
    assert len(shape_symmetries({"type": "box", "extents": [1, 1, 3]})) == 8
    assert len(shape_symmetries({"type": "mesh", "mesh": "prism", "sides": 6})) == 12


def test_the_background_points_are_written_and_start_training(photos, estimated):
    from train_world.capture.points import capture_points
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, get_preset
    from train_world.single_state.trainer import Trainer

    out, report = estimated
    scene = json.loads((out / "scene.json").read_text())
    assert (
        scene["points"]["path"] == "points3d.ply" and scene["points"]["count"] == report["background_points"]
    )
    xyz, rgb = capture_points(out, scene)
    assert len(xyz) == report["background_points"] > 100
    lo, hi = np.asarray(scene["table"]["bounds"])
    on_table = (np.abs(xyz[:, 2]) < 0.02) & np.all((xyz[:, :2] > lo[:2]) & (xyz[:, :2] < hi[:2]), axis=1)
    assert on_table.mean() > 0.4  # most features lie on the table top, at z = 0 of the table frame
    assert rgb.std() > 0.05 and not np.all(rgb == 0.5)  # coloured from the photos, not left grey
    # training on the capture starts from these points, then the table top, the objects' hulls, random points
    cfg = TrainConfig(preset=get_preset("quick"), state="state1", holdout_every=0)
    data = load_training_data(out, cfg)
    np.testing.assert_array_equal(data.points[0], xyz)
    t = Trainer(data, cfg)
    means = t.field.means.detach().double().numpy()
    np.testing.assert_allclose(means[: len(xyz)], xyz, atol=1e-6)
    assert len(means) == t.preset.num_init_points
    rest = means[len(xyz) :]
    assert (rest[:, 2] == 0.0).mean() > 0.05  # the table top of the capture's frame


@pytest.fixture(scope="module")
def stereo(photos, tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("stereo") / "estimated"
    assert capture_cli.main([str(photos), "--out", str(out), "--quiet", "--depth", "stereo"]) == 0
    return out, json.loads((out / "report.json").read_text())


def test_stereo_depth_is_written_and_agrees_with_the_truth(photos, stereo):
    out, report = stereo
    cap = load_capture(out, ["state1"])
    truth = load_capture(photos / "ground_truth", ["state1"])
    est, tru = cap.states["state1"], truth.states["state1"]
    assert est.depths is not None and report["stereo_depth_coverage"]["state1"] > 0.3
    by_stem = {p.stem: i for i, p in enumerate(tru.image_paths)}
    ratios = []
    for i, p in enumerate(est.image_paths):
        d, g = est.depths[i].numpy(), tru.depths[by_stem[p.stem]].numpy()
        ok = (d > 0) & (g > 0)
        ratios.append(d[ok] / g[ok])
    r = np.concatenate(ratios)
    r = r / np.median(r)  # the estimated frame's unit against metres: one scale for every pixel
    assert np.mean(np.abs(r - 1.0) < 0.03) > 0.9


def test_no_depth_maps_unless_asked(estimated):
    out, report = estimated
    assert not (out / "state1" / "depth").exists()
    frames = json.loads((out / "state1" / "transforms.json").read_text())["frames"]
    assert not any("depth_path" in f for f in frames)
    assert report["stereo_depth_coverage"] is None and report["timings_s"]["stereo_depth_s"] < 0.01
    assert report["fitted_depth"] is None and report["timings_s"]["depth_fit_s"] < 0.01


def test_training_on_stereo_depth_starts_in_proportion_to_it(stereo):
    from train_world.single_state.data import load_training_data
    from train_world.single_state.presets import TrainConfig, get_preset
    from train_world.single_state.trainer import Trainer

    out, _ = stereo
    cfg = TrainConfig(preset=get_preset("quick"), state="state1", holdout_every=0)
    data = load_training_data(out, cfg)
    n_sparse = len(data.points[0])
    cover = float((data.depths > 0).double().mean())
    assert 0.2 < cover < 1.0  # bare walls and plain objects have no stereo depth
    means = Trainer(data, cfg).field.means.detach().double().numpy()
    n = get_preset("quick").num_init_points
    assert len(means) == n_sparse + min(round(cover * n), n - n_sparse)
    assert (np.abs(means[n_sparse:, 2]) < 0.01).mean() > 0.2  # much of it on the table top, z = 0


def test_max_size_shrinks_the_views_but_not_the_estimates(photos, estimated, tmp_path):
    """``max_size`` writes the views at half size (images area-averaged, masks by majority, intrinsics halved)
    while the cameras, frame and motions, estimated on the whole photos, are the full-size capture's."""
    full, full_report = estimated
    out = tmp_path / "small"
    report = build_capture(photos, out, progress=False, max_size=64)
    assert report["capture_size"] == [64, 64] and full_report["capture_size"] == [128, 128]
    assert (out / "scene.json").read_bytes() == (full / "scene.json").read_bytes()
    assert report["objects"] == full_report["objects"] and report["cameras"] == full_report["cameras"]
    for s in ("state1", "state2"):
        a = json.loads((full / s / "transforms.json").read_text())
        b = json.loads((out / s / "transforms.json").read_text())
        assert (b["w"], b["h"]) == (64, 64)
        for k in ("fl_x", "fl_y", "cx", "cy"):
            assert b[k] == pytest.approx(a[k] / 2, rel=1e-12)
        assert [f["transform_matrix"] for f in b["frames"]] == [f["transform_matrix"] for f in a["frames"]]
        fr = b["frames"][0]
        big = np.asarray(Image.open(full / s / fr["file_path"]), dtype=np.float64)
        small = np.asarray(Image.open(out / s / fr["file_path"]), dtype=np.float64)
        err = np.abs(small - big.reshape(64, 2, 64, 2, 3).mean(axis=(1, 3)))
        assert err.max() <= 0.5  # the 2x2 means, rounded to 8 bits
        ids = np.asarray(Image.open(out / s / fr["mask_path"]))
        assert ids.shape == (64, 64)
        np.testing.assert_array_equal(
            ids, label_resize(np.asarray(Image.open(full / s / fr["mask_path"])), (64, 64))
        )
