"""Generate one synthetic dual-state capture on disk (the layout of :mod:`train_world.capture.format`).

Determinism: every random choice comes from ``numpy.random.Generator`` streams derived from ``(seed, label)``
(labels such as ``"states"`` or ``"cameras/state1"``), PNGs are encoded without timestamps and JSON keeps a
fixed key order, so the same seed (and MuJoCo/Pillow versions, GL driver) gives the same bytes.
"""

from __future__ import annotations

import os
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from train_world.capture.format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    atomic_write_json,
    depth_to_png_units,
    encode_png,
    matrix_to_list,
    staged_directory,
    write_state_views,
)
from train_world.synth.build import LIGHTING, build_scene, set_object_poses  # noqa: E402
from train_world.synth.cameras import orbit_c2w  # noqa: E402
from train_world.synth.render import SceneRenderer  # noqa: E402
from train_world.synth.spec import SceneSpec, resolve_scene  # noqa: E402
from train_world.synth.states import sample_states, verify_with_mujoco  # noqa: E402

__all__ = ["GENERATOR_VERSION", "GenerateConfig", "generate_scene", "rng_for"]

# 1.1: "soft" lighting and test cameras in the training band by default
# 1.2: RGB supersampled 4x4 per pixel by default (area-integrated like a camera sensor, no texture aliasing)
# 1.3: the camera light of "soft" and "spot" is a point light at the camera centre, not MuJoCo's directional
#      headlight (1.2's "soft" is now "headlight"; see train_world.synth.build)
GENERATOR_VERSION = "1.3"


@dataclass(frozen=True)
class GenerateConfig:
    """What to generate: image size, training views per training state, held-out test cameras shared by the
    ``test_states`` test states, whether lights cast shadows, the lighting preset (``"soft"``, ``"spot"`` or
    ``"headlight"``,
    :data:`~train_world.synth.build.LIGHTING`) and the RGB supersampling factor per axis (``supersample``:
    each pixel is the mean of ``supersample**2`` point samples; 1 = point-sampled, generator 1.1's look)."""

    seed: int = 0
    width: int = 128
    height: int = 128
    views: int = 48
    test_views: int = 12
    test_states: int = 3
    shadows: bool = False
    lighting: str = "soft"
    supersample: int = 4
    #: side of an ArUco marker (``DICT_4X4_50`` id 0, black square edge, metres) lying on the table; 0: none
    marker: float = 0.0
    progress: bool = True

    def __post_init__(self) -> None:
        for k in ("width", "height", "views"):
            if int(getattr(self, k)) < 1:
                raise ValueError(f"GenerateConfig.{k} must be >= 1, got {getattr(self, k)}")
        if self.test_views < 0 or self.test_states < 0:
            raise ValueError("GenerateConfig.test_views and test_states must be >= 0")
        if int(self.supersample) != self.supersample or not 1 <= self.supersample <= 16:
            raise ValueError(
                f"GenerateConfig.supersample must be an integer in 1..16, got {self.supersample!r}"
            )
        if self.lighting not in LIGHTING:
            raise ValueError(
                f"GenerateConfig.lighting must be one of {sorted(LIGHTING)}, got {self.lighting!r}"
            )
        if not (0.0 <= float(self.marker) <= 0.3):
            raise ValueError(
                f"GenerateConfig.marker must be a side in metres in [0, 0.3], got {self.marker!r}"
            )
        if (self.test_states > 0) != (self.test_views > 0):
            raise ValueError("test states need test views (and vice versa): set both > 0 or both 0")


def rng_for(seed: int, label: str) -> np.random.Generator:
    """Independent, reproducible random stream for one purpose."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, zlib.crc32(label.encode())]))


def _shape_dict(shape) -> dict:
    d = {k: v for k, v in asdict(shape).items() if v not in (0, 0.0, "", (0.0, 0.0, 0.0))}
    d["type"] = shape.type
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def _scene_json(
    scene: SceneSpec,
    cfg: GenerateConfig,
    states: dict[str, np.ndarray],
    splits: dict[str, str],
    counts: dict[str, int],
) -> dict:
    (x0, x1), (y0, y1) = scene.table_bounds
    return {
        "format": FORMAT_NAME,
        "format_version": FORMAT_VERSION,
        "name": scene.name,
        "description": scene.description,
        "units": "metres",
        "up_axis": "+z",
        "generator": {
            "name": "dsg-synth",
            "version": GENERATOR_VERSION,
            "seed": int(cfg.seed),
            "scene_spec": Path(scene.source).name if scene.source else scene.name,
            "width": cfg.width,
            "height": cfg.height,
            "views": cfg.views,
            "test_views": cfg.test_views,
            "test_states": cfg.test_states,
            "shadows": bool(cfg.shadows),
            "lighting": cfg.lighting,
            "supersample": int(cfg.supersample),
            **(
                {"marker": {"dictionary": "DICT_4X4_50", "id": 0, "size_m": float(cfg.marker)}}
                if cfg.marker
                else {}
            ),
            "mujoco_version": mujoco.__version__,
        },
        "objects": [
            {
                "id": i + 1,
                "name": o.name,
                "shape": _shape_dict(o.shape),
                "rest": o.rest,
                "pattern": o.appearance.pattern,
            }
            for i, o in enumerate(scene.objects)
        ],
        "table": {"bounds": [[x0, y0, 0.0], [x1, y1, 0.0]], "top_z": 0.0, "kind": scene.surface.kind},
        "states": {
            name: {
                "split": splits[name],
                "num_views": counts[name],
                "object_poses": [{"id": k + 1, "pose": matrix_to_list(p)} for k, p in enumerate(poses)],
            }
            for name, poses in states.items()
        },
    }


def generate_scene(
    scene: SceneSpec | str,
    out: str | os.PathLike,
    config: GenerateConfig | None = None,
    overwrite: bool = False,
) -> Path:
    """Generate ``scene`` (a spec or a default scene name / JSON path) into the folder ``out``.

    Refuses (``FileExistsError``) if ``out`` exists and is not empty unless ``overwrite``. The capture is
    staged in a hidden sibling folder and renamed into place only when complete.
    """
    if isinstance(scene, str):
        scene = resolve_scene(scene)
    cfg = GenerateConfig() if config is None else config
    out = Path(out)
    with staged_directory(out, overwrite=overwrite) as stage:
        ss = int(cfg.supersample)
        built = build_scene(
            scene, cfg.width * ss, cfg.height * ss, cfg.shadows, cfg.lighting, marker=cfg.marker
        )
        data = mujoco.MjData(built.model)
        states = sample_states(scene, rng_for(cfg.seed, "states"), cfg.test_states)
        for name, poses in states.items():
            verify_with_mujoco(built, data, poses, name)
        cams: dict[str, np.ndarray] = {}
        splits: dict[str, str] = {}
        for name in ("state1", "state2"):
            cams[name] = orbit_c2w(
                scene.cameras.train,
                cfg.views,
                rng_for(cfg.seed, f"cameras/{name}"),
                azimuth_phase_deg=rng_for(cfg.seed, f"phase/{name}").uniform(0, 360),
            )
            splits[name] = "train"
        if cfg.test_states:
            test_cams = orbit_c2w(scene.cameras.test, cfg.test_views, rng_for(cfg.seed, "cameras/test"))
            for t in range(cfg.test_states):
                cams[f"test_{t}"] = test_cams
                splits[f"test_{t}"] = "test"
        total = sum(len(c) for c in cams.values())
        with (
            SceneRenderer(built, cfg.width, cfg.height, supersample=ss) as renderer,
            tqdm(total=total, desc=f"dsg-synth {scene.name}", unit="view", disable=not cfg.progress) as bar,
        ):
            fx, fy, cx, cy = renderer.intrinsics()
            for name, c2ws in cams.items():
                set_object_poses(built, data, states[name])
                images, masks, depths = [], [], []
                for c2w in c2ws:
                    rgb, ids, depth = renderer.render(data, c2w)
                    images.append(encode_png(rgb))
                    masks.append(encode_png(ids))
                    depths.append(encode_png(depth_to_png_units(depth)))
                    bar.update(1)
                write_state_views(
                    stage / name, list(c2ws), cfg.width, cfg.height, fx, fy, cx, cy, images, masks, depths
                )
        atomic_write_json(
            stage / "scene.json",
            _scene_json(scene, cfg, states, splits, {k: len(v) for k, v in cams.items()}),
        )
    return out
