"""``dsg-view``'s server: the world in the browser through viser (the ``viewer`` extra).

The page shows the world's Gaussians with viser's Gaussian splat renderer: the background as one node and each
object as a node under a transform handle at its pose. Dragging a handle moves the object in the
:class:`~dsg_gym.viewer.env_state.ViewerSession`'s ``DSGWorldEnv`` (one absolute-pose step); the panel shows that
env's own observation (RGB, object ids, depth) from the chosen capture camera and the physics verdict, live.
Its buttons reset to ``state1`` / ``state2`` / a random valid configuration, save the configuration (JSON) and
export it as a USD stage, and load an episode file or a Minari dataset episode to play with a time slider.

:class:`Viewer` is the same from Python (``set_object_pose``, ``observation``, ``verdict``, ...); every call
updates the page.
"""

from __future__ import annotations

import re
import threading
from pathlib import Path
from typing import Any

import numpy as np

from .env_state import RANDOM, Verdict, ViewerSession
from .images import panel_image
from .splats import viser_splats

__all__ = ["VIEWER_EXTRA_HINT", "Viewer", "import_viser"]

VIEWER_EXTRA_HINT = "install the viewer extra: pip install 'dsg-gym[viewer]'"
#: size of an object's transform handle, metres
HANDLE_SCALE = 0.12


def import_viser():
    """The ``viser`` module, or ``ModuleNotFoundError`` saying how to install it."""
    try:
        import viser
    except ImportError:
        raise ModuleNotFoundError(f"the viewer needs viser; {VIEWER_EXTRA_HINT}") from None
    return viser


def _node_name(k: int, name: str) -> str:
    return f"/objects/{k}_{re.sub(r'[^A-Za-z0-9_.-]', '_', name)}"


class Viewer:
    """A viser server showing a world and the ``DSGWorldEnv`` behind it (see the module docstring).

    Args:
        world: ``None`` (the bundled world), a world file path or a ``WorldModel``.
        host, port: where the page is served (``127.0.0.1``: this machine only; ``0.0.0.0``: every interface).
        camera: the capture camera of the observation panel (a dropdown changes it).
        size: observation width = height in pixels.
        seed: seed of the first random configuration.
        out_dir: where the buttons save ``configuration.json`` and ``configuration.usdc`` (editable on the page).
        episode, episode_index: an episode file or Minari dataset (and episode) to load for playback.
    """

    def __init__(
        self,
        world=None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        camera: int = 0,
        size: int = 256,
        seed: int = 0,
        out_dir: str | Path = "out/viewer",
        episode: str | Path | None = None,
        episode_index: int = 0,
        verbose: bool = False,
    ):
        viser = import_viser()
        self.session = ViewerSession(world, camera=camera, size=size, seed=seed)
        if episode is not None:
            self.session.load_episode(episode, episode_index)
        self.server = viser.ViserServer(host=host, port=int(port), verbose=verbose)
        self._closed = threading.Event()
        self._playing = threading.Event()
        try:
            self._build_scene()
            self._build_gui(out_dir, episode, episode_index)
            self._refresh()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ page
    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}"

    def _build_scene(self) -> None:
        scene, world = self.server.scene, self.session.world
        scene.set_up_direction("+z")
        scene.add_gaussian_splats("/world/background", **viser_splats(world.background))
        poses = self.session.poses()
        self._handles = []
        for k, (name, obj) in enumerate(zip(world.object_names, world.objects)):
            node = _node_name(k, name)
            h = scene.add_transform_controls(
                node, scale=HANDLE_SCALE, position=poses[k, :3], wxyz=poses[k, 3:]
            )
            scene.add_gaussian_splats(f"{node}/splats", **viser_splats(obj))
            h.on_update(lambda event, k=k: self._dragged(k, event.target))
            self._handles.append(h)
        self._aim_initial_camera(self.session.camera)

    def _aim_initial_camera(self, camera: int) -> None:
        """New pages open looking from capture camera ``camera`` at the table's centre."""
        w = self.session.world
        vm = w.cameras.viewmats[camera]
        t = w.table
        cam = self.server.initial_camera
        cam.position = tuple(float(v) for v in -(vm[:3, :3].T @ vm[:3, 3]))
        cam.look_at = (0.5 * (t.xmin + t.xmax), 0.5 * (t.ymin + t.ymax), float(t.z))
        cam.up = (0.0, 0.0, 1.0)

    def _build_gui(self, out_dir, episode, episode_index: int) -> None:
        gui, s = self.server.gui, self.session
        gui.configure_theme(control_width="large", show_share_button=False)
        obs = s.observation()
        with gui.add_folder("Observation"):
            self._camera = gui.add_dropdown(
                "Camera", [str(i) for i in range(s.num_cameras)], initial_value=str(s.camera)
            )
            self._camera.on_update(lambda _: self._guarded(self._camera_changed))
            self._image = gui.add_image(panel_image(obs), label="RGB | object ids | depth", format="png")
            self._verdict = gui.add_markdown("")
        with gui.add_folder("Configuration"):
            for state in ("state1", "state2"):
                if state in s.world.states:
                    b = gui.add_button(f"Reset to {state}")
                    b.on_click(lambda _, state=state: self._guarded(self.reset, state))
            gui.add_button("Random configuration").on_click(lambda _: self._guarded(self.reset, RANDOM))
            self._out_dir = gui.add_text("Output folder", initial_value=str(out_dir))
            gui.add_button("Save configuration (JSON)").on_click(
                lambda _: self._guarded(self.save_configuration)
            )
            gui.add_button("Export USD stage").on_click(lambda _: self._guarded(self.export_usd))
        with gui.add_folder("Playback"):
            self._source = gui.add_text(
                "Episode or dataset", initial_value="" if episode is None else str(episode)
            )
            self._index = gui.add_number("Dataset episode", initial_value=int(episode_index), min=0, step=1)
            gui.add_button("Load episode").on_click(lambda _: self._guarded(self._load_clicked))
            n = len(s.playback) if s.playback is not None else 1
            self._slider = gui.add_slider(
                "Step", min=0, max=max(n - 1, 1), step=1, initial_value=0, disabled=s.playback is None
            )
            self._slider.on_update(lambda _: self._guarded(self._slider_moved))
            self._play = gui.add_button("Play", disabled=s.playback is None)
            self._play.on_click(lambda _: self._guarded(self._play_clicked))
        self._status = gui.add_markdown("")

    def _guarded(self, fn, *args) -> Any:
        """Run a button's action; a ``ValueError`` shows on the page instead of stopping the callback."""
        try:
            return fn(*args)
        except (ValueError, OSError) as e:
            self._status.content = f"**Error:** {e}"
            return None

    def _refresh(self, dragged: int | None = None) -> None:
        """Show the session's state: handles (the dragged one only where the env clipped it), panel images
        and verdict."""
        s = self.session
        poses = s.poses()
        for k, h in enumerate(self._handles):
            now = np.concatenate([np.asarray(h.position, np.float64), np.asarray(h.wxyz, np.float64)])
            if k != dragged or np.abs(now - poses[k]).max() > 1e-6:
                h.position, h.wxyz = tuple(poses[k, :3]), tuple(poses[k, 3:])
        self._image.image = panel_image(s.observation())
        info = s.info()
        reached = "reached" if info.get("success", False) else "not reached"
        errors = ", ".join(f"{e * 100:.1f} cm" for e in np.asarray(info.get("position_errors", [])))
        self._verdict.content = f"**Physics:** {s.verdict().text}  \n**Goal:** {reached} ({errors})"

    # ------------------------------------------------------------------ page callbacks
    def _dragged(self, k: int, handle) -> None:
        pose = np.concatenate([np.asarray(handle.position, np.float64), np.asarray(handle.wxyz, np.float64)])
        if self._guarded(self.session.set_object_pose, k, pose) is not None:
            self._refresh(dragged=k)

    def _camera_changed(self) -> None:
        camera = int(self._camera.value)
        if camera != self.session.camera:
            self.session.set_camera(camera)
            self._refresh()

    def _load_clicked(self) -> None:
        source = self._source.value.strip()
        if not source:
            raise ValueError("give an episode file (.npz) or a Minari dataset (folder or id) to load")
        self.load_episode(source, int(self._index.value))

    def _slider_moved(self) -> None:
        if self.session.playback is not None:
            self.session.show_step(int(self._slider.value))
            self._refresh()

    def _play_clicked(self) -> None:
        if self._playing.is_set() or self.session.playback is None:
            self._playing.clear()
            return
        self._playing.set()
        threading.Thread(target=self._play_loop, name="dsg-view-play", daemon=True).start()

    def _play_loop(self) -> None:
        pb = self.session.playback
        t = int(self._slider.value)
        start = 0 if t >= len(pb) - 1 else t
        for t in range(start, len(pb)):
            if not self._playing.is_set() or self._closed.is_set() or self.session.playback is not pb:
                break
            self._slider.value = t  # moves the objects (the slider's callback)
            self._closed.wait(1.0 / pb.fps)
        self._playing.clear()

    # ------------------------------------------------------------------ API
    def poses(self) -> np.ndarray:
        """The objects' poses ``[K, 7]`` in the env."""
        return self.session.poses()

    def goal(self) -> np.ndarray:
        """The env's goal poses ``[K, 7]``."""
        return self.session.goal()

    def observation(self) -> dict[str, np.ndarray]:
        """The env's latest observation (``rgb``, ``mask``, ``depth``, ``poses``, ``goal``)."""
        return self.session.observation()

    def verdict(self) -> Verdict:
        """The physics verdict on the current configuration."""
        return self.session.verdict()

    def set_object_pose(self, name_or_index, pose7) -> Verdict:
        """Move one object (name or index) to ``pose7`` (``x y z qw qx qy qz``, absolute); the verdict."""
        v = self.session.set_object_pose(name_or_index, pose7)
        self._refresh()
        return v

    def set_poses(self, poses) -> Verdict:
        """Move every object (``[K, 7]`` or ``[K, 4, 4]``); the verdict."""
        v = self.session.set_poses(poses)
        self._refresh()
        return v

    def reset(self, start: str = "state1") -> Verdict:
        """Start over at a captured state or (``"random"``) at a random valid configuration."""
        v = self.session.reset(start)
        self._refresh()
        self._status.content = f"reset to {start}"
        return v

    def set_camera(self, camera: int) -> None:
        """Show the observation of capture camera ``camera``."""
        self.session.set_camera(camera)
        self._camera.value = str(self.session.camera)
        self._refresh()

    def _out_path(self, path, name: str) -> Path:
        return Path(self._out_dir.value.strip() or ".") / name if path is None else Path(path)

    def save_configuration(self, path=None) -> Path:
        """Save the poses as JSON (default ``OUT/configuration.json``, OUT the page's output folder)."""
        p = self.session.save_configuration(self._out_path(path, "configuration.json"))
        self._status.content = f"saved {p}"
        return p

    def export_usd(self, path=None) -> Path:
        """Export the world at the current poses as a USD stage (default ``OUT/configuration.usdc``)."""
        p = self.session.export_usd(self._out_path(path, "configuration.usdc"))
        self._status.content = f"exported {p}"
        return p

    def load_configuration(self, path) -> Verdict:
        """Move the objects to the poses of a poses file (``.json``, ``.npy``, ``.npz``)."""
        v = self.session.load_configuration(path)
        self._refresh()
        return v

    def load_episode(self, source, index: int = 0) -> int:
        """Load an episode file or a Minari dataset episode for the time slider; its number of steps."""
        self._playing.clear()
        n = self.session.load_episode(source, index)
        self._slider.max = max(n - 1, 1)
        self._slider.disabled = self._play.disabled = False
        self._slider.value = 0
        self._refresh()
        self._status.content = f"loaded {self.session.playback.source}: {n} steps"
        return n

    def show_step(self, t: int) -> Verdict:
        """Show step ``t`` of the loaded episode (moves the slider too)."""
        v = self.session.show_step(t)
        self._slider.value = int(t)
        self._refresh()
        return v

    def serve_forever(self) -> None:
        """Block until :meth:`close` (or Ctrl-C, which closes)."""
        try:
            while not self._closed.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
        finally:
            self.close()

    def close(self) -> None:
        """Stop the server and the env."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._playing.clear()
        self.server.stop()
        self.session.close()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
