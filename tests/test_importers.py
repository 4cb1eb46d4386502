"""dsg-import: LLFF and transforms.json captures into our layout (one state, one object)."""

from __future__ import annotations

import json
import os
import shutil

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PIL import Image  # noqa: E402

from train_world.capture import CaptureError, load_capture  # noqa: E402
from train_world.capture.importers import import_llff, import_transforms, llff_to_opengl_c2w  # noqa: E402
from train_world.cli import importer as importer_cli  # noqa: E402
from train_world.synth.generate import GenerateConfig, generate_scene  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "external"
HEAD = SHARED / "ethiopian_head_llff"
N_HEAD = 8
SIZE = 50


@pytest.fixture(scope="session")
def synth(tmp_path_factory) -> Path:
    cfg = GenerateConfig(seed=2, width=40, height=30, views=5, test_views=1, test_states=1, progress=False)
    return generate_scene("two_blocks", tmp_path_factory.mktemp("imp") / "synth", cfg)


@pytest.fixture(scope="session")
def small_head(tmp_path_factory) -> Path:
    """The first images of the real LLFF capture, downscaled 500 -> 50 px, with their rows of poses_bounds."""
    if not (HEAD / "poses_bounds.npy").is_file():
        pytest.skip("shared/external/ethiopian_head_llff is not available")
    out = tmp_path_factory.mktemp("head") / "head"
    (out / "images_8").mkdir(parents=True)
    (out / "masks_8").mkdir()
    names = sorted(p.name for p in (HEAD / "images_8").iterdir())[:N_HEAD]
    for n in names:
        stem = Path(n).stem
        Image.open(HEAD / "images_8" / n).resize((SIZE, SIZE), Image.Resampling.BOX).save(
            out / "images_8" / n, quality=95
        )
        Image.open(HEAD / "masks_8" / f"{stem}.png").resize((SIZE, SIZE), Image.Resampling.BILINEAR).save(
            out / "masks_8" / f"{stem}.png"
        )
    np.save(out / "poses_bounds.npy", np.load(HEAD / "poses_bounds.npy")[:N_HEAD])
    return out


def _to_llff(c2w_gl: np.ndarray, h: float, w: float, f: float) -> np.ndarray:
    """Inverse of llff_to_opengl_c2w, as poses_bounds rows."""
    rows = []
    for m in c2w_gl:
        r = np.column_stack([-m[:3, 1], m[:3, 0], m[:3, 2], m[:3, 3], [h, w, f]])
        rows.append(np.concatenate([r.ravel(), [0.1, 5.0]]))
    return np.asarray(rows)


@pytest.fixture
def synth_llff(synth, tmp_path) -> Path:
    """state1 of the synthetic capture written as an LLFF capture whose poses claim twice the resolution."""
    tj = json.loads((synth / "state1" / "transforms.json").read_text())
    src = tmp_path / "llff"
    (src / "images").mkdir(parents=True)
    (src / "masks").mkdir()
    for fr in tj["frames"]:
        name = Path(fr["file_path"]).name
        shutil.copy(synth / "state1" / fr["file_path"], src / "images" / name)
        ids = np.asarray(Image.open(synth / "state1" / fr["mask_path"]))
        Image.fromarray(((ids > 0) * 255).astype(np.uint8)).save(src / "masks" / name)
    c2w = np.array([fr["transform_matrix"] for fr in tj["frames"]])
    np.save(src / "poses_bounds.npy", _to_llff(c2w, 2 * tj["h"], 2 * tj["w"], 2 * tj["fl_x"]))
    return src


def test_llff_axes():
    # LLFF camera axes are [down, right, back]; OpenGL's are [right, up, back]
    p = np.zeros((1, 3, 5))
    p[0, :, 0] = [0, 0, -1]  # down  = world -z
    p[0, :, 1] = [1, 0, 0]  # right = world +x
    p[0, :, 2] = [0, -1, 0]  # back  = world -y (the camera looks along +y)
    p[0, :, 3] = [1, 2, 3]
    m = llff_to_opengl_c2w(p)[0]
    np.testing.assert_array_equal(m[:3, 0], [1, 0, 0])
    np.testing.assert_array_equal(m[:3, 1], [0, 0, 1])
    np.testing.assert_array_equal(m[:3, 2], [0, -1, 0])
    np.testing.assert_array_equal(m[:3, 3], [1, 2, 3])


def test_llff_round_trip_reproduces_cameras(synth, synth_llff, tmp_path):
    out = import_llff(synth_llff, tmp_path / "out", factor=1)
    got = load_capture(out)
    want = load_capture(synth, states=["state1"]).states["state1"]
    v = got.states["state1"]
    assert got.object_ids == (1,) and list(got.states) == ["state1"]
    np.testing.assert_allclose(v.viewmats.numpy(), want.viewmats.numpy(), atol=1e-6)
    np.testing.assert_allclose(v.Ks.numpy(), want.Ks.numpy(), rtol=1e-6)  # focal scaled by 40 / 80
    np.testing.assert_array_equal(v.images.numpy(), want.images.numpy())
    np.testing.assert_array_equal(v.masks.numpy(), (want.masks.numpy() > 0).astype(np.uint8))
    np.testing.assert_array_equal(got.poses["state1"][0], np.eye(4))


def test_real_llff_capture(small_head, tmp_path):
    out = tmp_path / "head_out"
    assert importer_cli.main(["llff", str(small_head), "--out", str(out), "--factor", "8"]) == 0
    cap = load_capture(out)
    v = cap.states["state1"]
    pb = np.load(small_head / "poses_bounds.npy")
    assert len(v) == N_HEAD and (v.width, v.height) == (SIZE, SIZE)
    np.testing.assert_allclose(v.Ks[:, 0, 0].numpy(), pb[0, 14] * SIZE / pb[0, 9], rtol=1e-6)
    assert set(np.unique(v.masks.numpy())) == {0, 1}
    # triangulate the object from the mask centroids: its projection lies in every mask, in front of the
    # camera
    vm, K, m = v.viewmats.double().numpy(), v.Ks.double().numpy(), v.masks.numpy()
    A, b = np.zeros((3, 3)), np.zeros(3)
    for i in range(len(v)):
        ys, xs = np.nonzero(m[i])
        d = vm[i, :3, :3].T @ np.linalg.solve(K[i], [xs.mean() + 0.5, ys.mean() + 0.5, 1.0])
        d /= np.linalg.norm(d)
        o = -vm[i, :3, :3].T @ vm[i, :3, 3]
        P = np.eye(3) - np.outer(d, d)
        A, b = A + P, b + P @ o
    X = np.linalg.solve(A, b)
    for i in range(len(v)):
        p = vm[i, :3, :3] @ X + vm[i, :3, 3]
        uv = (K[i] @ p)[:2] / p[2]
        assert p[2] > 0 and m[i, int(uv[1]), int(uv[0])] == 1
    assert importer_cli.main(["llff", str(small_head), "--out", str(out)]) == 2  # exists: refuses


def test_llff_errors(synth_llff, tmp_path):
    sorted((synth_llff / "images").iterdir())[-1].unlink()
    with pytest.raises(CaptureError, match=r"poses_bounds\.npy: camera count mismatch: 5 poses but 4 images"):
        import_llff(synth_llff, tmp_path / "a", factor=1)
    assert not (tmp_path / "a").exists()


def test_llff_mask_errors(synth_llff, tmp_path):
    first = sorted((synth_llff / "masks").iterdir())[0]
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(first)
    with pytest.raises(CaptureError, match=rf"{first.name}: mask is 10x10 but image {first.name} is 40x30"):
        import_llff(synth_llff, tmp_path / "a", factor=1)
    first.unlink()
    with pytest.raises(CaptureError, match="no mask for image '0000'"):
        import_llff(synth_llff, tmp_path / "a", factor=1)
    import_llff(synth_llff, tmp_path / "a", factor=1, masks=False)
    assert load_capture(tmp_path / "a").states["state1"].masks is None


def test_llff_missing_poses(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(CaptureError, match=r"poses_bounds\.npy: file not found"):
        import_llff(tmp_path, tmp_path / "out", factor=1)


def test_import_transforms(synth, tmp_path):
    out = tmp_path / "t"
    assert (
        importer_cli.main(["transforms", str(synth / "state1"), "--out", str(out), "--threshold", "0"]) == 0
    )
    got = load_capture(out).states["state1"]
    want = load_capture(synth, states=["state1"]).states["state1"]
    np.testing.assert_allclose(got.viewmats.numpy(), want.viewmats.numpy(), atol=1e-6)
    np.testing.assert_allclose(got.Ks.numpy(), want.Ks.numpy())
    np.testing.assert_array_equal(got.masks.numpy(), (want.masks.numpy() > 0).astype(np.uint8))
    assert got.depths is None


def test_import_transforms_rejects_bad_pose(synth, tmp_path):
    src = Path(shutil.copytree(synth / "state1", tmp_path / "src"))
    d = json.loads((src / "transforms.json").read_text())
    d["frames"][0]["transform_matrix"][0][0] = 3.0
    (src / "transforms.json").write_text(json.dumps(d))
    with pytest.raises(CaptureError, match=r"transforms\.json: frames\[0\]\.transform_matrix: not a rigid"):
        import_transforms(src, tmp_path / "out")
