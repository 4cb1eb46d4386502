"""dsg-capture from videos: frames sampled by sharpness, matched as a sequence, checked against ground truth."""

from __future__ import annotations

import json
import os
import shutil

os.environ.setdefault("MUJOCO_GL", "egl")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402  (numpy and Pillow before pycolmap)
import pytest  # noqa: E402
from PIL import Image, ImageFilter  # noqa: E402

av = pytest.importorskip("av", reason="video input needs PyAV (the capture extra)")
pytest.importorskip("pycolmap", reason="dsg-capture needs pycolmap (the capture extra)")

from train_world.capture import load_capture  # noqa: E402
from train_world.capture.compare import compare_captures  # noqa: E402
from train_world.capture.photo_capture import build_capture  # noqa: E402
from train_world.capture.photos import PhotoCaptureError, read_photo_capture  # noqa: E402
from train_world.capture.sfm import sequence_pairs  # noqa: E402
from train_world.capture.video import extract_frames, sharpness  # noqa: E402
from train_world.cli import capture as capture_cli  # noqa: E402
from train_world.cli import synth as synth_cli  # noqa: E402

VIEWS = 24
BLURRED = 2  # blurred copies of each view in the video, around its sharp frame


def _write_video(path: Path, frames: list[np.ndarray], fps: int = 12) -> None:
    with av.open(str(path), "w") as out:
        s = out.add_stream("libx264", rate=fps)
        s.width, s.height, s.pix_fmt = frames[0].shape[1], frames[0].shape[0], "yuv420p"
        s.options = {"crf": "10"}
        for f in frames:
            for pkt in s.encode(av.VideoFrame.from_ndarray(f, format="rgb24")):
                out.mux(pkt)
        for pkt in s.encode():
            out.mux(pkt)


@pytest.fixture(scope="module")
def videos(tmp_path_factory) -> Path:
    """A photo capture (sensor noise, exposure varying by 15 %) turned into one video per state: every view shown
    once sharp between blurred copies."""
    photos = tmp_path_factory.mktemp("photos") / "scene"
    rc = synth_cli.main(["--scene", "four_mixed", "--out", str(photos), "--views", str(VIEWS), "--test-states", "0",
                         "--test-views", "0", "--as-photos", "--photo-noise", "2", "--photo-exposure", "0.15",
                         "--quiet"])  # fmt: skip
    assert rc == 0
    vids = tmp_path_factory.mktemp("videos") / "scene"
    for state in ("state1", "state2"):
        (vids / state).mkdir(parents=True)
        frames = []
        for p in sorted((photos / state / "images").glob("*.jpg")):
            with Image.open(p) as im:
                sharp = im.convert("RGB")
            blur = np.asarray(sharp.filter(ImageFilter.GaussianBlur(2.5)))
            frames += [blur] * (BLURRED // 2) + [np.asarray(sharp)] + [blur] * (BLURRED - BLURRED // 2)
        _write_video(vids / state / "walk.mp4", frames)
        # the masks a segmenter would give for the sampled frames: the photos' masks, renamed
        stems = sorted(p.stem for p in (photos / state / "masks").glob("*.png"))
        (vids / state / "masks").mkdir()
        for i, stem in enumerate(stems):
            shutil.copy(
                photos / state / "masks" / f"{stem}.png", vids / state / "masks" / f"frame_{i:04d}.png"
            )
    shutil.copy(photos / "objects.json", vids / "objects.json")
    gt = vids.parent / "ground_truth"
    shutil.copytree(photos / "ground_truth", gt)
    for state in ("state1", "state2"):  # name the ground truth's views as the extracted frames will be named
        tj = gt / state / "transforms.json"
        doc = json.loads(tj.read_text())
        for i, frame in enumerate(doc["frames"]):
            for key in ("file_path", "mask_path", "depth_path"):
                old = Path(frame[key])
                new = old.with_name(f"frame_{i:04d}{old.suffix}")
                (gt / state / old).rename(gt / state / new)
                frame[key] = str(new)
        tj.write_text(json.dumps(doc))
    return vids


def test_sharpness_prefers_the_sharp_image():
    rng = np.random.default_rng(0)
    img = Image.fromarray(rng.integers(0, 255, (64, 64, 3), dtype=np.uint8))
    assert sharpness(np.asarray(img)) > 4 * sharpness(np.asarray(img.filter(ImageFilter.GaussianBlur(2))))


def test_a_video_state_needs_its_frames_extracted_first(videos, tmp_path):
    src = tmp_path / "v"
    shutil.copytree(videos, src)
    with pytest.raises(PhotoCaptureError, match="extract-frames"):
        read_photo_capture(src)


def test_extract_frames_picks_the_sharp_frames_then_the_capture_matches_ground_truth(
    videos, tmp_path, capsys
):
    src = tmp_path / "v"
    shutil.copytree(videos, src)
    assert capture_cli.main([str(src), "--extract-frames", str(VIEWS), "--quiet"]) == 0
    assert "next:" in capsys.readouterr().out
    for state in ("state1", "state2"):
        doc = json.loads((src / state / "frames.json").read_text())
        assert doc["video"] == "walk.mp4" and doc["frames_in_video"] == VIEWS * (BLURRED + 1)
        # the sharp copy of each view sits at index BLURRED // 2 of its three frames
        assert [f["frame"] for f in doc["frames"]] == [i * (BLURRED + 1) + BLURRED // 2 for i in range(VIEWS)]
        assert len(list((src / state / "images").glob("frame_*.jpg"))) == VIEWS
    cap = read_photo_capture(src)
    assert cap.sequences == frozenset({"state1", "state2"})
    # a second extraction is refused unless asked to replace
    assert capture_cli.main([str(src), "--extract-frames", str(VIEWS), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err

    out = tmp_path / "capture"
    report = build_capture(src, out, progress=False)
    assert all(r["views"] == r["of"] == VIEWS for r in report["registered"].values())
    r = compare_captures(load_capture(out), load_capture(videos.parent / "ground_truth", ["state1", "state2"],
                                                         load_depth=False))  # fmt: skip
    assert r["camera_centre_error_median_percent_of_radius"] < 1.5
    assert r["camera_rotation_error_median_deg"] < 1.0
    for o in r["objects"]:
        assert o["position_error"] < 0.005, o


def test_sequence_pairs_link_neighbours_and_states(videos, tmp_path):
    src = tmp_path / "v"
    shutil.copytree(videos, src)
    extract_frames(src / "state1", VIEWS, progress=False)
    extract_frames(src / "state2", VIEWS, progress=False)
    cap = read_photo_capture(src)
    pairs = set(sequence_pairs(cap, overlap=3, cross_step=4))
    a = [f"state1/frame_{i:04d}.png" for i in range(VIEWS)]
    b = [f"state2/frame_{i:04d}.png" for i in range(VIEWS)]
    assert (a[0], a[1]) in pairs and (a[0], a[3]) in pairs and (a[0], a[4]) not in pairs
    assert (a[0], a[VIEWS - 1]) in pairs  # the walk closes on itself
    assert (
        (a[5], b[0]) in pairs
        and (a[5], b[4]) in pairs
        and (a[5], b[5]) not in pairs
        and (a[4], b[5]) in pairs
    )
    assert len(pairs) < VIEWS * 2 * (VIEWS * 2 - 1) // 2  # fewer than exhaustive


def test_bad_videos(tmp_path, capsys):
    state = tmp_path / "p" / "state1"
    state.mkdir(parents=True)
    with pytest.raises(PhotoCaptureError, match="no video"):
        extract_frames(state, 10, progress=False)
    (state / "walk.mp4").write_bytes(b"\x00not a video" * 100)
    with pytest.raises(PhotoCaptureError, match="cannot decode"):
        extract_frames(state, 10, progress=False)
    assert not (state / "images").exists() and not (state / "frames.json").exists()
    (state / "walk.mp4").unlink()
    _write_video(state / "walk.mp4", [np.zeros((32, 32, 3), np.uint8)] * 5)
    with pytest.raises(PhotoCaptureError, match="fewer than the 10"):
        extract_frames(state, 10, progress=False)
    (state / "other.mov").write_bytes(b"x")
    with pytest.raises(PhotoCaptureError, match="2 videos"):
        extract_frames(state, 3, progress=False)
    with pytest.raises(PhotoCaptureError, match=">= 3"):
        extract_frames(state, 2, progress=False)
    assert capture_cli.main([str(tmp_path / "p"), "--extract-frames", "3", "--quiet"]) == 2
    assert capsys.readouterr().err.strip().startswith("dsg-capture: error: ")


def test_structure_from_motion_runs_every_step_on_one_thread():
    """Extraction, matching and mapping on one thread each: on several, their results follow the threads'
    timing, and a capture would not repeat bit for bit."""
    import pycolmap

    from train_world.capture.sfm import _options

    extraction, matching, verification, mapping = _options(pycolmap)
    assert extraction.num_threads == matching.num_threads == mapping.num_threads == 1
    assert mapping.mapper.num_threads == 1
    assert verification.ransac.random_seed == mapping.random_seed >= 0
