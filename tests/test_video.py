"""Video and pictures: Gymnasium's ``RecordVideo`` on ``DSGWorld-v0`` (the video extra), ``dsg_gym.video``'s
GIF and MP4 writers, the demo's GIF, and the labels of ``dsg-eval``'s grid."""

from __future__ import annotations

import importlib.util
import os

os.environ.setdefault("MUJOCO_GL", "egl")

import gymnasium as gym
import numpy as np
import pytest
from PIL import Image, ImageSequence

import dsg_gym  # noqa: F401  (registers DSGWorld-v0)
from dsg_gym.video import views_side_by_side, write_gif, write_mp4


def _frames(n: int, h: int, w: int) -> list[np.ndarray]:
    """A colour gradient with a square that moves 3 px per frame."""
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([255 * x / w, 255 * y / h, np.full((h, w), 128.0)], axis=-1).astype(np.uint8)
    out = []
    for i in range(n):
        f = base.copy()
        f[4:12, 3 * i : 3 * i + 8] = (250, 250, 40)
        out.append(f)
    return out


def _decode(path) -> list[np.ndarray]:
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg", reason="the video extra is not installed")
    reader = imageio_ffmpeg.read_frames(str(path))
    meta = next(reader)
    w, h = meta["size"]
    return [np.frombuffer(f, np.uint8).reshape(h, w, 3) for f in reader]


def test_record_video_writes_every_frame_of_an_episode(tmp_path):
    pytest.importorskip("moviepy", reason="the video extra (moviepy) is not installed")
    from gymnasium.wrappers import RecordVideo

    env = gym.make(
        "DSGWorld-v0", width=16, height=16, obs=("poses",), render_mode="rgb_array", render_width=64,
        render_height=48, max_episode_steps=12,
    )  # fmt: skip
    env = RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda e: e == 0, disable_logger=True)
    env.action_space.seed(0)
    env.reset(seed=0)
    steps, done = 0, False
    while not done:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps += 1
        done = terminated or truncated
    env.close()
    videos = sorted((tmp_path / "videos").glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0
    frames = _decode(videos[0])
    assert len(frames) == steps + 1  # the reset frame and one per step
    assert frames[0].shape == (48, 64, 3)
    assert max(float(np.abs(f.astype(int) - frames[0]).mean()) for f in frames) > 0  # objects move


def test_write_mp4_decodes_pads_and_repeats_bytes(tmp_path):
    pytest.importorskip("imageio_ffmpeg", reason="the video extra is not installed")
    frames = _frames(7, 33, 47)
    a = write_mp4(frames, tmp_path / "a.mp4", fps=5)
    b = write_mp4(np.stack(frames), tmp_path / "sub" / "b.mp4", fps=5)
    assert a.read_bytes() == b.read_bytes()  # same frames, same bytes
    decoded = _decode(a)
    assert len(decoded) == 7
    assert decoded[0].shape == (34, 48, 3)  # padded to even sizes
    assert np.abs(decoded[3][:33, :47].astype(int) - frames[3]).mean() < 8  # lossy but the same picture
    assert not list(tmp_path.glob(".*tmp*"))  # no temporaries left


@pytest.mark.parametrize(
    "frames, match",
    [
        ([], "no frames"),
        ([np.zeros((8, 8, 3), np.float32)], "must be a uint8"),
        ([np.zeros((8, 8, 3), np.uint8), np.zeros((8, 6, 3), np.uint8)], "frames must match"),
    ],
)
def test_writers_reject_bad_frames(tmp_path, frames, match):
    with pytest.raises(ValueError, match=match):
        write_gif(frames, tmp_path / "x.gif")
    assert not (tmp_path / "x.gif").exists()
    if frames:
        with pytest.raises(ValueError, match=match):
            write_mp4(frames, tmp_path / "x.mp4")
    with pytest.raises(ValueError, match="fps"):
        write_gif(_frames(2, 8, 8), tmp_path / "y.gif", fps=0)


def test_write_gif_frames_timing_and_bytes(tmp_path):
    frames = _frames(5, 20, 30)
    a = write_gif(frames, tmp_path / "a.gif", fps=4)
    b = write_gif(frames, tmp_path / "b.gif", fps=4)
    assert a.read_bytes() == b.read_bytes()
    with Image.open(a) as im:
        assert im.n_frames == 5 and im.size == (30, 20)
        assert im.info["duration"] == 250 and im.info["loop"] == 0
        got = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(im)]
    assert np.abs(got[2].astype(int) - frames[2]).mean() < 8  # 256 colours for the whole clip
    assert not np.array_equal(got[0], got[1])


def test_demo_writes_a_gif_of_its_episode(tmp_path, capsys):
    from dsg_gym.demo import run_env_demo

    png = run_env_demo(tmp_path / "demo.png", size=32, seed=0)
    out = capsys.readouterr().out
    gif = tmp_path / "demo.gif"
    assert png.exists() and gif.exists()
    with Image.open(gif) as im:
        n = im.n_frames
        assert im.size == (32, 32)
    steps = int(out.split(" expert steps")[0].split()[-1])
    assert n == steps + 1  # the reset frame and one per step
    assert f"({n} frames)" in out
    mp4 = tmp_path / "demo.mp4"
    try:
        import imageio_ffmpeg  # noqa: F401
    except ImportError:
        assert not mp4.exists() and "no MP4" in out
    else:
        assert len(_decode(mp4)) == n


def test_eval_grid_has_column_and_row_labels():
    pytest.importorskip("torch")
    from train_world.eval.report_files import grid as _grid

    rows = [[np.full((32, 32, 3), 90 + 40 * j, np.uint8) for j in range(3)] for _ in range(2)]
    plain = _grid(rows)
    labelled = _grid(rows, ["ground truth", "ours", "error"], ["state1\nview 0", "state1\nview 4"])
    assert labelled.shape[0] > plain.shape[0] and labelled.shape[1] > plain.shape[1]
    # the labels are dark text on the white margins: above the first row and left of the first column
    dark = labelled.min(axis=-1) < 80
    tiles = np.isin(labelled.reshape(-1, 3)[:, 0], [90, 130, 170]).reshape(labelled.shape[:2])
    ys, xs = np.nonzero(tiles)
    assert dark[: ys.min()].any() and dark[:, : xs.min()].any()
    assert not dark[tiles].any()
    # without labels the grid keeps its plain layout: tiles and 2 px white borders only
    assert set(np.unique(plain)) <= {90, 130, 170, 255}


def test_views_side_by_side_for_multi_camera_episodes():
    rgb = np.stack(
        [np.stack(_frames(3, 6, 5)), np.stack(_frames(3, 6, 5))[:, ::-1]], axis=1
    )  # [T, V, H, W, 3]
    tiled = views_side_by_side(rgb)
    assert tiled.shape == (3, 6, 10, 3)
    assert np.array_equal(tiled[1, :, :5], rgb[1, 0]) and np.array_equal(tiled[1, :, 5:], rgb[1, 1])
    assert views_side_by_side(rgb[:, 0]).shape == (3, 6, 5, 3)
    with pytest.raises(ValueError, match="expected"):
        views_side_by_side(rgb[0, 0])


def test_episode_frames_are_the_frames_render_gave(tmp_path):
    from dsg_gym.episode_video import episode_frames

    kw = {"width": 8, "height": 8, "render_width": 40, "render_height": 32, "cameras": [0, 3]}
    env = gym.make("DSGWorld-v0", **kw, obs=("poses",), render_mode="rgb_array", render_goal=True)
    env.action_space.seed(4)
    obs, _ = env.reset(seed=4)
    live, poses = [env.render()], [obs["poses"]]
    for _ in range(5):
        obs, *_ = env.step(env.action_space.sample())
        live.append(env.render())
        poses.append(obs["poses"])
    goal = env.unwrapped.goal
    env.close()
    frames = episode_frames(np.stack(poses), goal, env_kwargs=kw)
    assert frames.shape == (6, 32, 80, 3)
    assert np.array_equal(frames, np.stack(live))  # the same bits
    plain = episode_frames(np.stack(poses), env_kwargs=kw)  # no goal: no ghost
    assert not np.array_equal(plain, frames)
    with pytest.raises(ValueError, match="render_goal needs the goal"):
        episode_frames(np.stack(poses), env_kwargs=kw, render_goal=True)
    with pytest.raises(ValueError, match=r"poses must be \[T, K, 7\]"):
        episode_frames(np.zeros((2, 7)), env_kwargs=kw)


def test_write_dataset_videos_renders_the_first_episodes(tmp_path):
    from dsg_gym.collect import collect, load
    from dsg_gym.episode_video import write_dataset_videos

    res = collect(
        tmp_path / "datasets", policy="random", episodes=3, seed=0, max_episode_steps=4,
        env_kwargs={"width": 8, "height": 8, "obs": ["poses"], "render_width": 24, "render_height": 16},
    )  # fmt: skip
    gifs = write_dataset_videos(res.path, episodes=2, fmt="gif", fps=5)
    assert [p.name for p in gifs] == ["episode_0000.gif", "episode_0001.gif"]
    assert gifs[0].parent == res.path / "videos"
    ds = load(res.path)
    for i, p in enumerate(gifs):
        with Image.open(p) as im:
            assert im.n_frames == len(ds[i].observations["poses"]) and im.size == (24, 16)
            assert im.info["duration"] == 200
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        write_dataset_videos(res.path, episodes=0)
    with pytest.raises(ValueError, match="fmt must be one of"):
        write_dataset_videos(res.path, fmt="avi")
    with pytest.raises(ValueError, match="not a readable Minari dataset"):
        write_dataset_videos(tmp_path / "nothing", out_dir=tmp_path / "v")
    assert not (tmp_path / "v").exists()
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        (mp4,) = write_dataset_videos(res.path, episodes=1, out_dir=tmp_path / "mp4")
        assert mp4.suffix == ".mp4" and len(_decode(mp4)) == len(ds[0].observations["poses"])
