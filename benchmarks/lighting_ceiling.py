"""What world-fixed lights cost a perfect world model: ``python -m benchmarks.lighting_ceiling [--out FILE]``.

DSG-World moves each object's Gaussians rigidly, so an object keeps the shading it had when it was captured.
MuJoCo's world-fixed lights shade a moved or turned object differently; the camera-carried light does not
(its shading depends only on the surface relative to the camera). This benchmark renders, for every test state
of a synthetic scene, the ground truth and an *ideal* world-model image in which each object keeps its
``--reference`` state's shading: the world-fixed lights are carried along with the object by its rigid motion
from the reference pose to the test pose, and the object's pixels are taken from that render. The PSNR
between the two, over object pixels and over whole images, is the ceiling that no rigid-appearance world model
can pass on that scene and lighting. Both renders share the cameras, so it does not see what MuJoCo's directional
headlight (``--lighting headlight``, generator 1.2's ``soft``) costs: shading along the camera axis, which a
colour that depends on the viewing ray alone cannot follow (see ``train_world.synth.build``).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco
import numpy as np

from dsg_gym.poses import pose7_to_matrix
from train_world.eval.metrics import psnr_from_mse

from ._results import default_out, write_result

__all__ = ["lighting_ceiling", "main"]


def _psnr(sq_err: float, count: int) -> float:
    if count == 0:
        return float("nan")
    return psnr_from_mse(sq_err / count)


def _matrices(poses) -> np.ndarray:
    p = np.asarray(poses, dtype=np.float64)
    return pose7_to_matrix(p) if p.shape[-1] == 7 else p


def lighting_ceiling(
    scene: str = "two_blocks",
    lighting: str = "soft",
    reference: str = "state1",
    size: int = 128,
    test_states: int = 3,
    seed: int = 0,
    band: bool = False,
) -> dict:
    """PSNR (dB) of ideal rigid-appearance renders against the ground truth of ``scene``'s test states.

    ``band``: use 12 cameras of the training orbit instead of the scene's test orbit. Returns a dict with
    ``object_psnr`` (object pixels only), ``per_object`` (``{name: PSNR over that object's pixels}``),
    ``image_psnr`` (whole images) and the settings.
    """
    from train_world.synth import resolve_scene
    from train_world.synth.build import build_scene, set_object_poses
    from train_world.synth.cameras import orbit_c2w
    from train_world.synth.generate import GenerateConfig, rng_for
    from train_world.synth.render import SceneRenderer
    from train_world.synth.states import sample_states

    spec = resolve_scene(scene)
    cfg = GenerateConfig(seed=seed, test_states=test_states, lighting=lighting)
    built = build_scene(spec, size, size, lighting=lighting)
    m = built.model
    data = mujoco.MjData(m)
    states = sample_states(spec, rng_for(cfg.seed, "states"), cfg.test_states)
    if reference not in states:
        raise ValueError(f"reference must be one of {sorted(states)}, got {reference!r}")
    orbit = spec.cameras.train if band else spec.cameras.test
    cams = orbit_c2w(orbit, cfg.test_views, rng_for(cfg.seed, "cameras/test"))
    pos0, dir0 = m.light_pos.copy(), m.light_dir.copy()
    P_ref = _matrices(states[reference])
    err_obj = err_img = 0.0
    n_obj = n_img = 0
    err_k = np.zeros(built.num_objects)
    n_k = np.zeros(built.num_objects, dtype=np.int64)
    with SceneRenderer(built, size, size) as r:
        for t in range(cfg.test_states):
            P_t = _matrices(states[f"test_{t}"])
            set_object_poses(built, data, states[f"test_{t}"])
            for c2w in cams:
                m.light_pos[:], m.light_dir[:] = pos0, dir0
                gt, ids, _ = r.render(data, c2w)
                ideal = gt.copy()
                for k in range(built.num_objects):
                    T = P_t[k] @ np.linalg.inv(P_ref[k])  # the object's rigid motion, reference -> test
                    m.light_pos[:] = pos0 @ T[:3, :3].T + T[:3, 3]
                    m.light_dir[:] = dir0 @ T[:3, :3].T
                    img, _, _ = r.render(data, c2w)
                    sel = ids == k + 1
                    ideal[sel] = img[sel]
                sq = ((gt.astype(np.float64) - ideal.astype(np.float64)) / 255.0) ** 2
                obj = ids > 0
                for k in range(built.num_objects):
                    err_k[k] += float(sq[ids == k + 1].sum())
                    n_k[k] += int((ids == k + 1).sum()) * 3
                err_obj += float(sq[obj].sum())
                err_img += float(sq.sum())
                n_obj += int(obj.sum()) * 3
                n_img += sq.size
    m.light_pos[:], m.light_dir[:] = pos0, dir0
    return {
        "scene": scene,
        "lighting": lighting,
        "reference": reference,
        "size": size,
        "cameras": "training band" if band else "test orbit",
        "test_states": cfg.test_states,
        "views": len(cams),
        "seed": seed,
        "object_psnr": _psnr(err_obj, n_obj),
        "per_object": {o.name: _psnr(float(err_k[k]), int(n_k[k])) for k, o in enumerate(spec.objects)},
        "image_psnr": _psnr(err_img, n_img),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m benchmarks.lighting_ceiling", description=__doc__.split("\n")[0]
    )
    p.add_argument(
        "--out",
        type=Path,
        help="JSON file to write (default: benchmarks/results/lighting_ceiling/<date>-<commit>.json)",
    )
    p.add_argument(
        "--scenes", nargs="+", default=["two_blocks"], help="synthetic scene names (default two_blocks)"
    )
    p.add_argument("--lighting", nargs="+", default=["soft", "spot"], choices=["soft", "spot", "headlight"])
    p.add_argument(
        "--reference", default="state1", help="state whose shading the objects keep (default state1)"
    )
    p.add_argument("--size", type=int, default=128)
    p.add_argument(
        "--seed", type=int, default=0, help="dsg-synth seed: the states and test cameras (default 0)"
    )
    args = p.parse_args(argv)
    args.out = args.out or default_out("lighting_ceiling")
    rows = []
    for scene in args.scenes:
        for lighting in args.lighting:
            for band in (False, True):
                r = lighting_ceiling(scene, lighting, args.reference, args.size, seed=args.seed, band=band)
                rows.append(r)
                print(
                    f"{scene:18s} {lighting:5s} {r['cameras']:13s} objects {r['object_psnr']:6.2f} dB  "
                    f"image {r['image_psnr']:6.2f} dB",
                    file=sys.stderr,
                )
    write_result(Path(args.out), {"benchmark": "lighting_ceiling", "rows": rows})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
