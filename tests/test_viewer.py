"""``dsg-view``: the env-side session (no server), the viser server's API, and the page in a real headless
browser (Debian's chromium) showing the splats."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess

os.environ.setdefault("MUJOCO_GL", "egl")

import numpy as np
import pytest

from dsg_gym.export import load_poses_file
from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import matrix_to_pose7
from dsg_gym.viewer.env_state import RANDOM, TABLE_NAME, ViewerSession
from dsg_gym.viewer.images import depth_image, mask_image, panel_image
from dsg_gym.viewer.splats import viser_splats

SIZE = 48


@pytest.fixture(scope="module")
def session():
    s = ViewerSession(size=SIZE)
    yield s
    s.close()


def _stacked(s: ViewerSession) -> tuple[np.ndarray, np.ndarray]:
    """Poses for a collision: the second object placed on the first's x/y (its height kept)."""
    poses = s.poses()
    moved = poses[1].copy()
    moved[:2] = poses[0, :2]
    return poses, moved


# ----------------------------------------------------------------------------------------------- session
def test_moving_an_object_moves_it_in_the_env(session):
    session.reset("state1")
    before = session.observation()
    pose = session.poses()[0]
    pose[:2] += (-0.06, 0.05)  # away from the other object
    verdict = session.set_object_pose(session.names[0], pose)
    after = session.observation()
    assert verdict.free and verdict.status == "free"
    assert np.allclose(session.poses()[0], pose, atol=1e-12)
    assert np.allclose(session.poses()[1], before["poses"][1], atol=1e-12)  # the other one stays
    assert not np.array_equal(after["rgb"], before["rgb"]) and not np.array_equal(
        after["mask"], before["mask"]
    )
    assert after["rgb"].shape == (SIZE, SIZE, 3) and after["depth"].shape == (SIZE, SIZE)
    # by index, with a yaw: the quaternion comes back normalised
    q = np.array([np.cos(0.3), 0, 0, np.sin(0.3)])
    session.set_object_pose(1, np.r_[session.poses()[1, :3], 2 * q])
    assert np.allclose(session.poses()[1, 3:], q, atol=1e-12)


def test_verdict_names_collisions_and_leaving_the_workspace(session):
    session.reset("state1")
    poses, moved = _stacked(session)
    v = session.set_object_pose(1, moved)
    assert not v.free and v.colliding and "colliding" in v.status
    assert (session.names[0], session.names[1]) in v.colliding or (
        session.names[1],
        session.names[0],
    ) in v.colliding
    assert np.allclose(session.poses()[1], moved, atol=1e-12)  # the env keeps an interpenetrating move
    session.reset("state1")
    away = session.poses()[0]
    away[0] = session.world.table.xmax + 0.5  # past the table's edge
    v = session.set_object_pose(0, away)
    assert v.out_of_workspace == (session.names[0],) and "out of the workspace" in v.text
    assert np.allclose(session.poses(), poses, atol=1e-12)  # the env undid that move
    sunk = session.poses()[1]
    sunk[2] = session.world.table.z + 0.005  # into the table top
    v = session.set_object_pose(1, sunk)
    assert (session.names[1], TABLE_NAME) in v.colliding


def test_bad_input_names_the_problem_and_changes_nothing(session):
    session.reset("state1")
    poses, obs = session.poses(), session.observation()
    with pytest.raises(ValueError, match="unknown object 'mug'"):
        session.set_object_pose("mug", poses[0])
    with pytest.raises(ValueError, match="index below"):
        session.set_object_pose(len(session.names), poses[0])
    with pytest.raises(ValueError, match="NaN or Inf"):
        session.set_object_pose(0, np.full(7, np.nan))
    with pytest.raises(ValueError, match="quaternion is zero"):
        session.set_object_pose(0, np.r_[poses[0, :3], 0, 0, 0, 0])
    with pytest.raises(ValueError, match="state of this world"):
        session.reset("state9")
    with pytest.raises(ValueError, match="out of range"):
        session.set_camera(10_000)
    fresh = ViewerSession(size=16)
    with pytest.raises(ValueError, match="no episode loaded"):
        fresh.show_step(0)
    fresh.close()
    assert np.array_equal(session.poses(), poses)
    assert np.array_equal(session.observation()["rgb"], obs["rgb"])


def test_resets_go_to_captured_states_and_seeded_random_ones(session):
    session.reset("state2")
    assert np.allclose(session.poses(), matrix_to_pose7(session.world.states["state2"]), atol=1e-12)
    assert np.allclose(session.goal(), matrix_to_pose7(session.world.states["state1"]), atol=1e-12)
    assert session.verdict().free
    other = ViewerSession(size=16, seed=7)
    again = ViewerSession(size=16, seed=7)
    a1, b1 = other.reset(RANDOM), again.reset(RANDOM)
    assert a1.free and b1.free
    assert np.array_equal(other.poses(), again.poses())  # same seed, same configuration
    other.reset(RANDOM)
    assert not np.allclose(other.poses(), again.poses())  # the next seed, another configuration
    other.close()
    again.close()


def test_camera_change_keeps_the_configuration(session):
    session.reset("state1")
    poses, rgb = session.poses(), session.observation()["rgb"]
    session.set_camera(5)
    assert session.camera == 5 and np.array_equal(session.poses(), poses)
    assert not np.array_equal(session.observation()["rgb"], rgb)
    session.set_camera(0)
    assert np.array_equal(session.observation()["rgb"], rgb)  # same camera, same pixels


def test_save_load_configuration_and_export_usd(session, tmp_path):
    session.reset("state1")
    pose = session.poses()[0]
    pose[1] += 0.05
    session.set_object_pose(0, pose)
    path = session.save_configuration(tmp_path / "cfg" / "configuration.json")
    doc = json.loads(path.read_text())
    assert doc["objects"] == list(session.names) and len(doc["poses"]) == len(session.names)
    assert np.allclose(
        matrix_to_pose7(load_poses_file(path, len(session.names))), session.poses(), atol=1e-12
    )
    with pytest.raises(ValueError, match="must end in .json"):
        session.save_configuration(tmp_path / "configuration.txt")
    saved = session.poses()
    session.reset("state2")
    session.load_configuration(path)
    assert np.allclose(session.poses(), saved, atol=1e-9)
    stage = session.export_usd(tmp_path / "configuration.usda")
    text = stage.read_text()
    assert stage.suffix == ".usda" and all(n in text for n in session.names)


def _episode_file(path, steps: int):
    """Record ``steps`` random steps of ``DSGWorld-v0`` as an episode file."""
    import gymnasium as gym

    import dsg_gym  # noqa: F401
    from dsg_gym.envs.recording import RecordEpisode

    env = RecordEpisode(gym.make("DSGWorld-v0", width=8, height=8, obs=("poses",)))
    env.reset(seed=2)
    env.action_space.seed(2)
    for _ in range(steps):
        env.step(env.action_space.sample())
    return env.save(path)


def test_plays_an_episode_file(session, tmp_path):
    from dsg_gym.envs.recording import load_episode

    path = _episode_file(tmp_path / "ep.npz", steps=6)
    recorded = np.stack([matrix_to_pose7(m) for m in load_episode(path).poses])
    n = session.load_episode(path)
    assert n == 7 and np.allclose(session.poses(), recorded[0], atol=1e-9)
    session.show_step(4)
    assert np.allclose(session.poses(), recorded[4], atol=1e-9)
    with pytest.raises(ValueError, match=r"step must be an integer in \[0, 7\)"):
        session.show_step(7)
    with pytest.raises(ValueError, match="does not exist"):
        session.load_episode(tmp_path / "missing.npz")
    assert np.allclose(session.poses(), recorded[4], atol=1e-9)


def test_plays_a_minari_dataset_episode(session, tmp_path):
    from dsg_gym.collect import collect

    res = collect(
        tmp_path / "datasets", policy="random", episodes=2, seed=0, max_episode_steps=5,
        env_kwargs={"width": 8, "height": 8, "obs": ["poses"]},
    )  # fmt: skip
    n = session.load_episode(res.path, index=1)
    from dsg_gym.collect import load

    ep = load(res.path)[1]
    assert n == len(ep.observations["poses"])
    assert np.allclose(session.goal(), ep.observations["goal"][0], atol=1e-12)
    session.show_step(n - 1)
    assert np.allclose(session.poses(), ep.observations["poses"][n - 1], atol=1e-9)
    with pytest.raises(ValueError, match="episode index 2 out of range: the dataset has 2 episodes"):
        session.load_episode(res.path, index=2)


def test_panel_pictures():
    mask = np.array([[0, 1], [2, 1]], np.uint8)
    m = mask_image(mask)
    assert m.shape == (2, 2, 3) and m.dtype == np.uint8
    assert np.array_equal(m[0, 1], m[1, 1]) and not np.array_equal(m[0, 1], m[1, 0])
    assert not np.array_equal(m[0, 0], m[0, 1])
    d = depth_image(np.array([[0.0, 1.0], [2.0, 3.0]], np.float32))
    assert d[0, 0].max() == 0 and d[0, 1, 0] > d[1, 0, 0] > d[1, 1, 0] > 0  # near is bright, no hit black
    obs = {"rgb": np.zeros((4, 5, 3), np.uint8), "mask": np.zeros((4, 5), np.uint8), "depth": np.ones((4, 5))}
    assert panel_image(obs).shape == (4, 3 * 5 + 4, 3)


def test_splat_arrays_for_viser():
    q = np.array([[np.cos(0.4), 0, 0, np.sin(0.4)], [2.0, 0, 0, 0]], np.float32)  # a yaw; an unnormalised one
    scales = np.array([[0.01, 0.02, 0.03], [0.05, 0.05, 0.05]], np.float32)
    sh = np.zeros((2, 1, 3), np.float32)
    sh[0, 0] = 10.0  # clipped to white
    g = GaussianSet(np.zeros((2, 3)), q, scales, np.array([0.5, 1.0]), sh)
    a = viser_splats(g)
    assert a["centers"].shape == (2, 3) and a["opacities"].shape == (2, 1)
    assert np.allclose(
        np.linalg.eigvalsh(a["covariances"][0].astype(np.float64)), np.sort(scales[0] ** 2), rtol=1e-5
    )
    assert np.allclose(a["covariances"][1], np.diag(scales[1] ** 2), rtol=1e-5)
    assert np.allclose(a["rgbs"], [[1, 1, 1], [0.5, 0.5, 0.5]])


def test_cli_refuses_bad_input_with_one_line(tmp_path, capsys):
    from dsg_gym.cli.view import main

    with pytest.raises(SystemExit) as e:
        main(["--port", "0"])
    assert e.value.code == 2 and "give a port in 1..65535" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.dsgworld")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("dsg-view: ") and "\n" not in err
    if importlib.util.find_spec("viser") is None:
        assert "install the viewer extra" in err
        return
    assert "missing.dsgworld" in err
    assert main(["--camera", "999"]) == 1
    assert "out of range" in capsys.readouterr().err


# ----------------------------------------------------------------------------------------------- server
def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def viewer(tmp_path):
    pytest.importorskip("viser", reason="the viewer extra (viser) is not installed")
    from dsg_gym.viewer.server import Viewer

    v = Viewer(host="127.0.0.1", port=_free_port(), size=SIZE, out_dir=tmp_path / "out")
    yield v
    v.close()


def test_viewer_api_drives_the_env_and_the_page(viewer, tmp_path):
    assert viewer.url.startswith("http://127.0.0.1:")
    before = viewer.observation()
    assert np.array_equal(viewer._image.image, panel_image(before))
    pose = viewer.poses()[1]
    pose[:2] += (0.05, -0.05)  # away from the box
    assert viewer.set_object_pose("blue_cylinder", pose).free
    after = viewer.observation()
    assert not np.array_equal(after["rgb"], before["rgb"])
    assert np.array_equal(viewer._image.image, panel_image(after))  # the panel shows the env's observation
    assert np.allclose(viewer._handles[1].position, pose[:3])
    assert "free" in viewer._verdict.content
    _, moved = _stacked(viewer.session)
    assert not viewer.set_object_pose(1, moved).free
    assert "colliding" in viewer._verdict.content
    # the page's handle drag: the handle's pose goes to the env
    h = viewer._handles[0]
    h.position = tuple(viewer.poses()[0, :3] + (0.03, 0.0, 0.0))
    viewer._dragged(0, h)
    assert np.allclose(viewer.poses()[0, :3], h.position)
    assert viewer.save_configuration().parent == tmp_path / "out"
    assert viewer.export_usd().suffix == ".usdc"
    viewer.reset("state2")
    assert np.allclose(viewer.poses(), matrix_to_pose7(viewer.session.world.states["state2"]), atol=1e-12)
    viewer.set_camera(3)
    assert viewer._camera.value == "3" and viewer.session.camera == 3
    # an episode file on the time slider, then played to its end
    path = _episode_file(tmp_path / "ep.npz", steps=4)
    assert viewer.load_episode(path) == 5
    assert viewer._slider.max == 4 and not viewer._slider.disabled and "5 steps" in viewer._status.content
    frames = viewer.session.playback.poses
    viewer._slider.value = 2  # the page's slider moves the objects
    assert np.allclose(viewer.poses(), frames[2], atol=1e-9)
    viewer.show_step(1)
    assert viewer._slider.value == 1 and np.allclose(viewer.poses(), frames[1], atol=1e-9)
    viewer._play_clicked()
    assert viewer._playing.is_set()
    for _ in range(100):  # 4 frames at 10 fps; bounded wait
        if not viewer._playing.is_set():
            break
        viewer._closed.wait(0.1)
    assert not viewer._playing.is_set() and viewer._slider.value == 4
    assert np.allclose(viewer.poses(), frames[4], atol=1e-9)
    # a bad page input shows an error and changes nothing
    viewer.session.playback = None
    viewer._source.value = str(tmp_path / "nothing.npz")
    viewer._guarded(viewer._load_clicked)
    assert "Error" in viewer._status.content and viewer.session.playback is None


def _screenshot(url: str, out, profile, timeout: float = 150.0) -> None:
    """Load ``url`` in headless chromium (software WebGL) and save a screenshot; the browser and its children
    are killed when it overruns ``timeout``."""
    cmd = [
        shutil.which("chromium"), "--headless", "--no-sandbox", "--no-first-run", "--disable-dev-shm-usage",
        "--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", f"--user-data-dir={profile}",
        "--window-size=1280,800", "--virtual-time-budget=15000", f"--screenshot={out}", url,
    ]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def test_page_in_headless_chromium_shows_the_splats(viewer, tmp_path):
    if shutil.which("chromium") is None:
        pytest.skip("chromium is not installed (apt-get install chromium; .ci/run installs it)")
    from PIL import Image

    shot = tmp_path / "page.png"
    _screenshot(viewer.url, shot, tmp_path / "profile")
    assert shot.exists(), "chromium wrote no screenshot"
    img = np.asarray(Image.open(shot).convert("RGB")).astype(np.float64)
    assert img.shape[:2] == (800, 1280)
    canvas = img[:, : int(img.shape[1] * 0.6)]  # the 3D view, left of the panel
    drawn = np.abs(canvas - 255.0).max(axis=-1) > 30  # viser's empty canvas is white
    assert drawn.mean() > 0.5, f"only {drawn.mean():.0%} of the canvas is drawn: no splats?"
    assert canvas.std() > 20
    # the page's server still drives the env
    rgb = viewer.observation()["rgb"]
    pose = viewer.poses()[0]
    pose[0] += 0.05
    viewer.set_object_pose(0, pose)
    assert not np.array_equal(viewer.observation()["rgb"], rgb)
