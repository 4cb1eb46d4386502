"""Budget checks of ``dsg-compact`` (:mod:`train_world.compact.compaction`): how much a compacted world's renders drop.

:class:`SelfCheck` needs no ground truth: the compacted world against the original, composited by the runtime
renderer at every state the world stores, from a subset of the plausible cameras; an added mean square error
``d`` per view is turned into a predicted PSNR drop ``10 log10(1 + d / m0)`` for a world whose own MSE
against ground truth is ``m0`` (``--reference-psnr``). :class:`CaptureCheck` adds the measured drop of
``dsg-eval``'s mean PSNR on a capture's test states and takes ``m0`` from the original's measured PSNR.
Both return ``{"ok", "psnr_drop", ...}`` for a candidate ``(background, [objects])``.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import World, WorldObject
from train_world.compact.importance import SceneCameras
from train_world.eval.metrics import psnr_from_mse

__all__ = ["CaptureCheck", "SelfCheck", "psnr", "with_parts"]


class SelfCheck:
    """Compacted vs original world: runtime renders at every stored state from a subset of the plausible
    cameras; predicted drop ``mean 10 log10(1 + mse / m0)`` against ``--reference-psnr``."""

    def __init__(self, world: World, cams: SceneCameras, bg, cfg, reference_psnr: float):
        n_cap = min(cams.num_capture, max(1, cfg.validation_views // 3))
        n_orb = min(len(cams) - cams.num_capture, cfg.validation_views - n_cap)
        idx = np.concatenate(
            [
                np.linspace(0, cams.num_capture - 1, n_cap).round(),
                cams.num_capture + np.linspace(0, len(cams) - cams.num_capture - 1, n_orb).round(),
            ]
        )
        self.idx = np.unique(idx.astype(np.int64))
        self.cams, self.bg = cams, np.asarray(bg, np.float32)
        self.poses = [np.asarray(p, np.float64) for p in world.poses.values()] or [np.zeros((0, 4, 4))]
        self.reference_psnr = float(reference_psnr)
        self.m0 = 10.0 ** (-self.reference_psnr / 10.0)
        self.max_drop = cfg.max_psnr_drop
        self.splat = world.splat_options
        self.compositing = world.compositing
        self.ref = self._render(world.background, [world.objects[i].gaussians for i in world.object_ids])

    def _render(self, bg: GaussianSet, objs: list[GaussianSet]) -> np.ndarray:
        from dsg_gym.scene_renderer import SceneRenderer

        c = self.cams
        r = SceneRenderer(
            bg,
            objs,
            c.viewmats[self.idx],
            c.Ks[self.idx],
            c.width,
            c.height,
            background_color=self.bg,
            compositing=self.compositing,
            **self.splat,
        )
        out = np.empty((len(self.poses), len(self.idx), c.height, c.width, 3), np.float32)
        for s, poses in enumerate(self.poses):
            r.render(poses if len(objs) else np.zeros((0, 4, 4)), rgb=True, mask=False, incremental=False)
            acc, T = r.buffers()
            out[s] = np.clip(acc[..., :3] + T[..., None] * self.bg, 0.0, 1.0)
        return out

    def __call__(self, bg: GaussianSet, objs: list[GaussianSet]) -> dict[str, Any]:
        img = self._render(bg, objs)
        mse = ((img.astype(np.float64) - self.ref) ** 2).mean(axis=(2, 3, 4)).ravel()
        drop = float(np.mean(10.0 * np.log10(1.0 + mse / self.m0)))
        m = float(mse.mean())
        return {
            "ok": drop <= self.max_drop,
            "psnr_drop": drop,
            "predicted_psnr_drop": drop,
            "reference_psnr": self.reference_psnr,
            "self_psnr": psnr(m),
            "worst_view_self_psnr": psnr(float(mse.max())),
        }


class CaptureCheck:
    """Measured and predicted drop. ``dsg-eval``'s mean PSNR on every test state of a capture, original minus
    compacted, averaged over the test states, must be within budget, and so must the self-consistency drop
    over all plausible views with the original's measured test PSNR as the reference (the test cameras alone
    are a narrow sample of the views an env may use)."""

    def __init__(self, world: World, capture: Path, cams: SceneCameras, bg, cfg, tmp: Path):
        from train_world.capture import load_capture

        cap = load_capture(capture, states=[], load_depth=False)
        self.states = [s for s, split in cap.splits.items() if split == "test"]
        if not self.states:
            raise ValueError(f"{capture}: the capture has no test states to measure the PSNR drop on")
        self.capture, self.tmp, self.max_drop, self.world = Path(capture), tmp, cfg.max_psnr_drop, world
        self.n = 0
        self.base = self._psnr(world)
        self.self_check = SelfCheck(world, cams, bg, cfg, float(np.mean(list(self.base.values()))))

    def _psnr(self, w: World) -> dict[str, float]:
        from dsg_gym.world import write_world
        from train_world.eval.evaluate import evaluate

        self.n += 1
        path = write_world(self.tmp / f"candidate_{self.n}.dsgworld", w)
        out = {
            s: float(evaluate(path, self.capture, self.tmp / "eval", state=s)["mean"]["psnr"])
            for s in self.states
        }
        path.unlink()
        return out

    def __call__(self, bg: GaussianSet, objs: list[GaussianSet]) -> dict[str, Any]:
        res = self.self_check(bg, objs)
        res.update(test_psnr_drop=None, test_psnr=None, test_psnr_original=self.base)
        if res["ok"]:  # the cheap check first
            psnr = self._psnr(with_parts(self.world, bg, objs, {}))
            drop = float(np.mean([self.base[s] - psnr[s] for s in self.states]))
            res.update(
                test_psnr_drop=drop,
                test_psnr=psnr,
                ok=drop <= self.max_drop,
                psnr_drop=max(drop, res["predicted_psnr_drop"]),
            )
        return res


def with_parts(world: World, bg: GaussianSet, objs: list[GaussianSet], meta: dict) -> World:
    objects = {oid: WorldObject(world.objects[oid].name, g) for oid, g in zip(world.object_ids, objs)}
    return dataclasses.replace(
        world,
        background=bg,
        objects=MappingProxyType(objects),
        metadata=MappingProxyType({**dict(world.metadata), **meta}),
    )


def psnr(mse: float) -> float:
    """PSNR of ``mse``, at most 100 dB (finite in the JSON report)."""
    return min(psnr_from_mse(mse), 100.0)
