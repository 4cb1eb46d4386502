"""Evaluating a world against a ground truth in another frame: the similarity fitted from the cameras, the
cameras and object poses moved through it, the same scores as in one frame, and the identity case giving
exactly the evaluation without alignment."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from _captures import tiny_capture
from PIL import Image

from dsg_gym.cameras import Cameras, look_at
from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import World, load_world, write_world
from train_world.capture import load_capture
from train_world.cli import train as train_cli
from train_world.cli.eval import main as eval_main
from train_world.eval.evaluate import evaluate, evaluate_test_states
from train_world.eval.frames import (
    FrameAlignment,
    fit_frame_alignment,
    fit_similarity,
    motion_errors,
    needs_alignment,
)


def _rot(axis, deg):
    a = math.radians(deg)
    axis = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


# the similarity applied to the capture (truth -> transformed truth): scale 0.5, 30 degrees, a shift
SCALE, ROT, SHIFT = 0.5, _rot([0.2, -0.4, 1.0], 30.0), np.array([0.3, -0.1, 0.25])


def _similar(x: np.ndarray) -> np.ndarray:
    return SCALE * x @ ROT.T + SHIFT


# ----------------------------------------------------------------------------------- the fit
def test_fit_recovers_a_similarity_from_cameras_and_refuses_degenerate_ones():
    rng = np.random.default_rng(0)
    c = rng.normal(size=(12, 3))
    r = np.stack([_rot(rng.normal(size=3), rng.uniform(0, 180)) for _ in range(12)])
    s, R, t = fit_similarity(c, r, _similar(c), ROT @ r)
    assert s == pytest.approx(SCALE, rel=1e-12) and np.allclose(R, ROT, atol=1e-12)
    assert np.allclose(t, SHIFT, atol=1e-12)
    with pytest.raises(ValueError, match="at least 3"):
        fit_similarity(c[:2], r[:2], c[:2], r[:2])
    line = np.outer(np.arange(5.0), [1.0, 2.0, 0.5])
    with pytest.raises(ValueError, match="collinear"):
        fit_similarity(line, r[:5], line, r[:5])


def test_moved_cameras_see_moved_points_at_the_same_pixels():
    al = FrameAlignment(SCALE, ROT, SHIFT, 3, 0.0, 0.0, 0.0, False)
    rng = np.random.default_rng(1)
    vm = np.tile(np.eye(4), (3, 1, 1))
    for i in range(3):
        vm[i, :3, :3] = _rot(rng.normal(size=3), 40.0 * i + 10)
        vm[i, :3, 3] = [0.1 * i, -0.05, 2.0]
    pts = rng.normal(scale=0.3, size=(20, 3))
    moved = al.viewmats(vm)
    assert np.allclose(moved[:, :3, :3] @ np.transpose(moved[:, :3, :3], (0, 2, 1)), np.eye(3), atol=1e-12)

    def pixels(v, p):
        x = p @ v[:3, :3].T + v[:3, 3]
        return x[:, :2] / x[:, 2:], x[:, 2]

    for i in range(3):
        (a, za), (b, zb) = pixels(vm[i], pts), pixels(moved[i], _similar(pts))
        assert np.allclose(a, b, atol=1e-12) and np.allclose(zb, SCALE * za, atol=1e-12)
    # an object's motion in the truth's frame, carried into the world's, moves the object the same way
    M = np.eye(4)
    M[:3, :3] = _rot([0, 0, 1], 25)
    M[:3, 3] = [0.1, -0.2, 0.0]
    Mw = al.motions(M[None])[0]
    assert np.allclose(_similar(pts @ M[:3, :3].T + M[:3, 3]), _similar(pts) @ Mw[:3, :3].T + Mw[:3, 3])


def test_a_ground_truth_whose_scene_json_is_no_scene_description_is_a_one_line_error(tmp_path):
    vm = np.stack([look_at([0.6 * math.cos(a), 0.6 * math.sin(a), 0.4], [0.0, 0.0, 0.0]) for a in (0, 2, 4)])
    K = np.tile(np.array([[50.0, 0.0, 16.0], [0.0, 50.0, 16.0], [0.0, 0.0, 1.0]]), (3, 1, 1))
    world = World(
        GaussianSet.empty(), {}, {}, {"state1": Cameras(vm, K, 32, 32)}, np.zeros((1, 1)), np.zeros(1)
    )
    scene = tmp_path / "scene.json"
    for content, problem in (
        ([], "expected a capture's scene description .* got an array"),
        ("state1", "expected a capture's scene description .* got a string"),
        ({"states": ["state1"]}, "'states' must be a JSON object .* got an array"),
    ):
        scene.write_text(json.dumps(content))
        with pytest.raises(
            ValueError, match=f"^{re.escape(str(scene))}: {problem}; give the ground-truth"
        ) as e:
            fit_frame_alignment(world, tmp_path)
        assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------------- end to end
def _transformed_capture(src: Path, dst: Path) -> Path:
    """``src`` with every camera and object pose moved by the similarity (the images stay valid: a similarity of
    the whole scene and its cameras leaves pinhole images unchanged)."""
    shutil.copytree(src, dst)
    scene = json.loads((dst / "scene.json").read_text())
    for st in scene["states"].values():
        for p in st["object_poses"]:
            P = np.array(p["pose"])
            P[:3, :3] = ROT @ P[:3, :3]
            P[:3, 3] = _similar(P[:3, 3])
            p["pose"] = P.tolist()
    (dst / "scene.json").write_text(json.dumps(scene))
    for tj in dst.glob("*/transforms.json"):
        doc = json.loads(tj.read_text())
        for fr in doc["frames"]:
            m = np.array(fr["transform_matrix"])
            m[:3, :3] = ROT @ m[:3, :3]
            m[:3, 3] = _similar(m[:3, 3])
            fr["transform_matrix"] = m.tolist()
        tj.write_text(json.dumps(doc))
    return dst


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval_gt")
    cap = tiny_capture(root, test_views=3, test_states=2)
    world = root / "w.dsgworld"
    args = [str(cap), "--out", str(world), "--preset", "quick", "--iterations", "60", "--quiet"]
    assert train_cli.main_two_state(args) == 0
    return cap, world, _transformed_capture(cap, root / "moved")


def test_scores_through_the_fitted_similarity_equal_those_in_one_frame(trained, tmp_path, capsys):
    cap, world, moved = trained
    assert load_world(world).metadata["camera_names"]["state1"][:2] == ["0000", "0001"]
    plain = evaluate_test_states(world, cap, tmp_path / "plain")
    assert eval_main([str(world), str(moved), "--out", str(tmp_path / "gt"), "--align-frames"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rep = json.loads((tmp_path / "gt" / "report.json").read_text())
    al = rep["frame_alignment"]
    assert al == {**printed["frame_alignment"], "rotation": al["rotation"], "identity": False}
    # truth -> world is the inverse of the similarity applied to the capture
    assert al["scale"] == pytest.approx(1 / SCALE, rel=1e-5)
    assert al["rotation_deg"] == pytest.approx(30.0, abs=1e-4)
    assert np.allclose(np.array(al["rotation"]), ROT.T, atol=1e-5)
    assert np.allclose(al["translation"], -ROT.T @ SHIFT / SCALE, atol=1e-5)
    assert al["camera_centre_rms"] < 1e-5 and al["camera_rotation_rms_deg"] < 0.02 and al["cameras"] == 32
    assert list(rep["states"]) == list(plain["states"]) and rep["views"] == plain["views"] == 6
    for s, v in plain["states"].items():
        got = rep["states"][s]["mean"]
        assert got["psnr"] == pytest.approx(v["mean"]["psnr"], abs=1e-4)
        assert got["ssim"] == pytest.approx(v["mean"]["ssim"], abs=1e-5)
        assert got["mask_iou"] == pytest.approx(v["mean"]["mask_iou"], abs=1e-2)
    # without the similarity the moved truth scores far worse: the alignment is what made them equal
    assert eval_main([str(world), str(moved), "--out", str(tmp_path / "raw"), "--same-frame"]) == 0
    raw = json.loads((tmp_path / "raw" / "report.json").read_text())
    assert raw["mean"]["mask_iou"] < plain["mean"]["mask_iou"] - 0.3 and "frame_alignment" not in raw
    assert raw["mean"]["psnr"] < plain["mean"]["psnr"] and raw["mean"]["ssim"] < plain["mean"]["ssim"]


def test_one_frame_gives_exactly_the_evaluation_without_alignment(trained, tmp_path):
    cap, world, _ = trained
    plain = evaluate_test_states(world, cap, tmp_path / "plain")
    w = load_world(world)
    al = fit_frame_alignment(w, cap)
    assert al.identity and al.scale == 1.0 and np.array_equal(al.rotation, np.eye(3))
    aligned = evaluate_test_states(world, cap, tmp_path / "aligned", alignment=al)
    assert aligned["mean"] == plain["mean"] and aligned["frame_alignment"]["identity"]
    for s in plain["states"]:
        a = json.loads((tmp_path / "aligned" / s / "report.json").read_text())
        b = json.loads((tmp_path / "plain" / s / "report.json").read_text())
        assert a["per_view"] == b["per_view"]
    # a world without camera names is matched through the capture it was trained on
    unnamed = dataclasses.replace(w, metadata={k: v for k, v in w.metadata.items() if k != "camera_names"})
    assert fit_frame_alignment(unnamed, cap).identity
    # the training views are scored in the world's own frame only
    with pytest.raises(ValueError, match="another frame"):
        evaluate(world, cap, tmp_path / "fit", state="state1", alignment=al, training_views=True)
    assert not (tmp_path / "fit").exists()


def test_when_the_frames_are_aligned_and_when_cameras_do_not_match(trained, tmp_path, capsys):
    cap, world, moved = trained
    w = load_world(world)
    assert not needs_alignment(w, moved)  # a synthetic world shares its capture's frame
    src = dict(w.metadata["source"])
    est = dataclasses.replace(
        w, metadata={**w.metadata, "source": {**src, "generator": {"name": "dsg-capture", "version": "1.0"}}}
    )
    assert needs_alignment(est, moved) and not needs_alignment(est, src["path"])
    renamed = dataclasses.replace(
        w,
        metadata={
            **w.metadata,
            "camera_names": {s: [f"x{n}" for n in v] for s, v in w.metadata["camera_names"].items()},
        },
    )
    with pytest.raises(ValueError, match="only 0 of the world's cameras"):
        fit_frame_alignment(renamed, moved)
    # a ground truth in another frame without test states is refused unless a state is named
    bare = tmp_path / "bare"
    shutil.copytree(moved, bare)
    scene = json.loads((bare / "scene.json").read_text())
    scene["states"] = {k: v for k, v in scene["states"].items() if v.get("split") == "train"}
    (bare / "scene.json").write_text(json.dumps(scene))
    assert eval_main([str(world), str(bare), "--out", str(tmp_path / "e"), "--align-frames"]) == 2
    assert "no test states" in capsys.readouterr().err
    assert (
        eval_main(
            [str(world), str(bare), "--out", str(tmp_path / "e"), "--align-frames", "--state", "state2"]
        )
        == 0
    )
    rep = json.loads((tmp_path / "e" / "report.json").read_text())
    assert rep["views"] == 16 and rep["frame_alignment"]["scale"] == pytest.approx(2.0, rel=1e-5)


def _enlarged_capture(src: Path, dst: Path, k: int) -> Path:
    """``src`` with every view ``k`` times as wide and high: each pixel of its images, masks and depth repeated
    ``k x k`` times and the intrinsics scaled, so that downscaling by ``k`` gives back the views of ``src``."""
    shutil.copytree(src, dst)
    for tj in dst.glob("*/transforms.json"):
        doc = json.loads(tj.read_text())
        for d in (doc, *doc["frames"]):
            for key in ("fl_x", "fl_y", "cx", "cy", "w", "h"):
                if key in d:
                    d[key] *= k
            for key in ("file_path", "mask_path", "depth_path"):
                if key in d:
                    with Image.open(tj.parent / d[key]) as img:
                        big = img.resize((img.width * k, img.height * k), Image.Resampling.NEAREST)
                    big.save(tj.parent / d[key])
        tj.write_text(json.dumps(doc))
    return dst


def test_a_world_is_scored_at_the_size_it_was_trained_at(trained, tmp_path):
    cap, world, moved = trained
    w = load_world(world)
    size = list(w.metadata["image_size"])
    al = fit_frame_alignment(w, moved)
    same = evaluate_test_states(world, moved, tmp_path / "same", alignment=al)
    # a ground truth twice the world's size is brought down to it: the same views, the same scores
    big = _enlarged_capture(moved, tmp_path / "big", 2)
    with Image.open(big / "test_0" / "images" / "0000.png") as img:
        assert img.size == (2 * size[0], 2 * size[1])
    rep = evaluate_test_states(world, big, tmp_path / "big_eval", alignment=fit_frame_alignment(w, big))
    assert rep["mean"] == same["mean"]
    for s in rep["states"]:
        r = json.loads((tmp_path / "big_eval" / s / "report.json").read_text())
        assert (
            r["image_size"] == size
            and r["per_view"] == json.loads((tmp_path / "same" / s / "report.json").read_text())["per_view"]
        )
    # a world trained on its capture downscaled (photos larger than the world) is scored at its own size too,
    # not at the ground truth's size divided by its training downscale
    src = {**w.metadata["source"], "downscale": 2}
    halved = write_world(
        tmp_path / "halved.dsgworld", dataclasses.replace(w, metadata={**w.metadata, "source": src})
    )
    rep = evaluate_test_states(halved, moved, tmp_path / "halved_eval", alignment=al)
    assert rep["mean"] == same["mean"] and rep["image_size"] == size
    assert all(v["image_size"] == size for v in rep["states"].values())
    assert json.loads((tmp_path / "halved_eval" / "test_0" / "report.json").read_text())["image_size"] == size
    # a ground truth of another size is refused, naming both sizes, and nothing is written
    odd = write_world(
        tmp_path / "odd.dsgworld",
        dataclasses.replace(w, metadata={**w.metadata, "image_size": [size[0] - 8, size[1] - 8]}),
    )
    with pytest.raises(ValueError, match=rf"views are {size[0]}x{size[1]}, the world was trained at") as e:
        evaluate_test_states(odd, moved, tmp_path / "odd_eval", alignment=al)
    assert "\n" not in str(e.value) and "integer multiple" in str(e.value)
    assert not (tmp_path / "odd_eval").exists()
    # one rule in one frame as well: the world's own capture enlarged 2x scores as the capture itself
    own = evaluate_test_states(world, cap, tmp_path / "own")
    own_big = evaluate_test_states(
        world, _enlarged_capture(cap, tmp_path / "own_big", 2), tmp_path / "own_big_e"
    )
    assert own_big["mean"] == own["mean"] and own_big["image_size"] == size
    with pytest.raises(ValueError, match=rf"views are {size[0]}x{size[1]}, the world was trained at") as e:
        evaluate_test_states(odd, cap, tmp_path / "odd_own")
    assert "\n" not in str(e.value) and not (tmp_path / "odd_own").exists()


def test_aligning_each_view_recovers_what_camera_errors_cost(trained, tmp_path, capsys):
    cap, world, moved = trained
    plain = evaluate_test_states(world, cap, tmp_path / "plain")
    # the truth's test cameras turned by 0.5 degrees about their centres (the training cameras, and so the
    # fitted similarity, stay): what a structure-from-motion error does to an evaluation
    shaken = tmp_path / "shaken"
    shutil.copytree(moved, shaken)
    scene = json.loads((shaken / "scene.json").read_text())
    for s, st in scene["states"].items():
        if st.get("split") != "test":
            continue
        tj = shaken / s / "transforms.json"
        doc = json.loads(tj.read_text())
        for i, fr in enumerate(doc["frames"]):
            m = np.array(fr["transform_matrix"])
            m[:3, :3] = m[:3, :3] @ _rot([1.0, 0.5 * (-1) ** i, 0.2], 0.5)
            fr["transform_matrix"] = m.tolist()
        tj.write_text(json.dumps(doc))
    out = tmp_path / "off"
    assert eval_main([str(world), str(shaken), "--out", str(out), "--align-frames"]) == 0
    off = json.loads((out / "report.json").read_text())
    assert off["mean"]["psnr"] != plain["mean"]["psnr"] and "mean_unaligned" not in off
    out = tmp_path / "aligned"
    assert eval_main([str(world), str(shaken), "--out", str(out), "--align-frames", "--align-views"]) == 0
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    rep = json.loads((out / "report.json").read_text())
    assert printed["mean_unaligned"] == rep["mean_unaligned"]
    assert rep["mean_unaligned"]["psnr"] == pytest.approx(off["mean"]["psnr"], abs=1e-4)
    # (how much comes back is test_view_align's: this quick world is too coarse to tell)
    assert rep["mean"]["psnr"] >= off["mean"]["psnr"]
    for s in rep["states"]:
        r = json.loads((out / s / "report.json").read_text())
        va = r["view_alignment"]
        assert len(va["per_view"]) == r["views"] == 3 and va["settings"]["steps"] == 60
        assert 0 <= va["kept"] <= 3 and math.isfinite(va["rotation_deg_rms"])
        assert [v["kept"] for v in va["per_view"]].count(True) == va["kept"]
        assert all(v["psnr"] >= v["psnr_unaligned"] - 1e-9 for v in r["per_view"])
        assert "unaligned mean PSNR" in (out / s / "report.md").read_text()
    assert eval_main([str(world), str(shaken), "--out", str(out), "--align-views", "0"]) == 2
    assert "steps must be an integer >= 1" in capsys.readouterr().err


def test_motion_errors_against_the_ground_truth(trained, tmp_path):
    cap, world, moved = trained
    w = load_world(world)
    al = fit_frame_alignment(w, moved)
    exact = motion_errors(w, moved, al)
    assert exact["src"] == "state1" and exact["dst"] == "state2" and not exact["refined"]
    assert [o["name"] for o in exact["objects"]] == list(w.object_names)
    for o in exact["objects"]:  # the synthetic world was given the true motions: nothing to find
        assert o["estimate_translation"] < 1e-6 and o["refined_rotation_deg"] < 1e-3
    # a world whose given motion puts the first object 4 mm off (world units = metres) and turned by 1 degree
    rec = json.loads(json.dumps(w.metadata["motions"]))
    T = np.array(rec["initial"])
    o2 = T[0, :3, :3] @ np.asarray(w.poses["state1"])[0, :3, 3] + T[0, :3, 3]  # its origin in state 2
    X = np.eye(4)  # a turn about that origin, then a shift
    X[:3, :3] = _rot([0, 0, 1.0], 1.0)
    X[:3, 3] = o2 - X[:3, :3] @ o2 + [0.004, 0, 0]
    T[0] = X @ T[0]
    rec["initial"] = T.tolist()
    off = dataclasses.replace(w, metadata={**w.metadata, "motions": rec})
    e = motion_errors(off, moved, al)["objects"]
    assert e[0]["estimate_translation"] == pytest.approx(0.004 * SCALE, rel=1e-4)  # in the truth's units
    assert e[0]["estimate_rotation_deg"] == pytest.approx(1.0, abs=1e-6)
    assert e[1]["estimate_translation"] < 1e-6 and e[0]["refined_translation"] < 1e-6
    # in pixels of the truth's second-state views: (offset + 2 r sin(angle / 2)) x median(focal / distance),
    # with the cameras read here from the loaded views and r from the object's Gaussians in the truth's frame
    views = load_capture(moved, ["state2"], load_depth=False).states["state2"]
    eyes = np.stack([-vm[:3, :3].T @ vm[:3, 3] for vm in views.viewmats.double().numpy()])
    Ks = views.Ks.double().numpy()
    P1, P2 = (np.asarray(load_capture(moved, []).poses[s])[0] for s in ("state1", "state2"))
    ppu = np.median((Ks[:, 0, 0] + Ks[:, 1, 1]) / 2 / np.linalg.norm(eyes - P2[:3, 3], axis=1))
    g = w.gaussians("state1")
    pts = _similar(g.means[g.labels == w.object_ids[0]].astype(np.float64))  # world -> truth
    r = np.percentile(np.linalg.norm(pts - P1[:3, 3], axis=1), 99)
    turn = 2 * r * math.sin(math.radians(e[0]["estimate_rotation_mod_symmetry_deg"]) / 2)
    assert e[0]["estimate_px"] == pytest.approx((0.004 * SCALE + turn) * ppu, rel=1e-4)
    assert 0.004 * SCALE * ppu <= e[0]["estimate_px"] and e[1]["estimate_px"] < 1e-3 < e[0]["estimate_px"]
    assert all(o["refined_px"] < 1e-3 for o in e)
    # the dsg-eval report carries them
    assert eval_main([str(world), str(moved), "--out", str(tmp_path / "e"), "--align-frames"]) == 0
    rep = json.loads((tmp_path / "e" / "report.json").read_text())
    assert rep["motion_errors"]["objects"] == exact["objects"]
    assert "Object motions state1 -> state2" in (tmp_path / "e" / "report.md").read_text()
    # without motions in the world there is nothing to compare
    bare = dataclasses.replace(w, metadata={k: v for k, v in w.metadata.items() if k != "motions"})
    assert motion_errors(bare, moved, al) is None
