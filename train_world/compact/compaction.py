"""``dsg-compact``: fewer Gaussians and SH bands in a world file, within a PSNR budget.

    dsg-compact WORLD --out WORLD2 [--max-psnr-drop 0.3] [--capture CAPTURE] [--report FILE]

Steps (the per-Gaussian scores come from :mod:`train_world.compact.importance`):

1. **SH bands.** For real orthonormal SH, ``sum_m Y_lm(d)^2 = (2l+1) / 4pi`` for every direction ``d``, so
   dropping the bands above ``L`` changes a colour channel by at most ``sqrt(sum_{l>L} (2l+1)/4pi) *
   ||c_{l>L}||`` over the whole sphere (Cauchy-Schwarz; the clamp at 0 can only shrink the change). Each
   Gaussian keeps the lowest degree whose bound is ``<= --sh-tolerance`` (its higher bands are zeroed) and a
   part (background, each object) is stored with the highest degree any of its Gaussians still needs, so a
   world whose colours are view-independent drops to degree 0 and the renderer skips the SH evaluation.
2. **Plausible cameras.** The background is scored *without the objects* (they move and reveal what is
   under them) from the capture cameras plus an orbit around the point they look at: ``--rings`` rings of
   ``--per-ring`` look-at cameras at the capture cameras' median distance, spanning their elevations
   widened by 10 degrees below and 20 above (a test orbit is often higher). Each object is scored *alone*
   in its own frame (occlusion by other objects never counts) from ``--object-views`` cameras on a sphere at
   that distance: every side it can show in any orientation.
3. **Invisible Gaussians.** Those whose accumulated blending weight is below ``--min-weight`` (1/255 px) in
   every plausible view: removing one moves no pixel of those views by more than 1/255.
4. **Redundant Gaussians.** In rounds, up to ``--step`` of the remaining Gaussians with the smallest
   removal error (what the images lose without each one alone, mean per view; pooled over all parts) are
   removed, skipping any of the ``--neighbours`` nearest kept neighbours of one already taken in the round
   (each score assumes the others stay: the discs of a uniformly coloured face all look redundant, but not
   at once); then the scores are recomputed. Vertices of an object's collision hull (the convex hull of its
   means with opacity >= 0.2, what :class:`dsg_gym.physics.PhysicsProxy` builds) are never removed.
5. **Budget.** Every round is checked (:mod:`train_world.compact.checks`) and the round that breaks the
   budget is bisected. Without ``--capture`` the check is self-consistency: the compacted world against the
   original, composited by the runtime renderer at every state the world stores (captured and test poses)
   from ``--validation-views`` of the plausible cameras. An added error of mean square ``d`` in a view
   raises the error of a world whose own PSNR against ground truth is ``--reference-psnr`` (MSE ``m0``) to
   about ``m0 + d`` (compaction errors are not correlated with the reconstruction error): a drop of
   ``10 log10(1 + d / m0)`` dB, whose mean over views must stay ``<= --max-psnr-drop``. With ``--capture``
   the reference is the original's measured mean PSNR on the capture's test states, and the measured drop
   there (``dsg-eval``, original minus compacted, mean over test states) must be within budget too.
6. **Refit.** ``--refit-cycles`` times: the survivors' colours, opacities, shrinking scales and (background
   only) means are fitted to the original part's renders (:mod:`train_world.compact.refit`, ``--refit-steps`` Adam
   steps; kept only if the check improves), then pruning resumes from the refitted world (except after the
   last refit). Object means and hull-vertex opacities stay, so the physics proxy is unchanged.

``--fraction F`` skips the budget (no checks until the end) and keeps ``F`` of the Gaussians.
The result keeps everything else (poses, cameras, classifier, identity features, encodings of the kept
Gaussians); ``metadata.compacted`` records the options and figures, and table bounds derived from the
geometry are stored so pruning cannot move them. A far shell's recorded count (``metadata.background_shell``)
follows its kept Gaussians. Identity features stay in the file (``dsg-eval`` classifies rendered features for
its mask IoU); the runtime does not need them (env masks come from object labels), so
``DSGWorld-v0`` drops them when it loads a world file. Output is written atomically; the report (counts, PSNR,
times) is printed as JSON and, with ``--report``, written to a file.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.world import World
from train_world.compact.checks import CaptureCheck, SelfCheck, with_parts
from train_world.compact.config import CompactConfig
from train_world.compact.importance import SceneCameras, scene_cameras, sphere_cameras
from train_world.compact.search import Part, PruneSearch, score_part

__all__ = ["CompactConfig", "compact_world", "hull_vertices", "sh_change_bound", "truncate_sh"]

_BAND_NORM2 = np.array([(2 * b + 1) / (4 * math.pi) for b in range(4)])  # sum_m Y_lm^2 per band


# --------------------------------------------------------------------------------------------- SH bands
def sh_change_bound(sh: np.ndarray, degree: int) -> np.ndarray:
    """``[N]`` float64: the largest change of any colour channel, over all view directions, when the bands
    above ``degree`` of ``sh [N,K,3]`` are dropped (0 when there are none)."""
    sh = np.asarray(sh, np.float64)
    k0 = (degree + 1) ** 2
    if sh.shape[1] <= k0:
        return np.zeros(sh.shape[0])
    d_max = round(math.sqrt(sh.shape[1])) - 1
    scale = math.sqrt(float(_BAND_NORM2[degree + 1 : d_max + 1].sum()))
    return scale * np.sqrt((sh[:, k0:] ** 2).sum(1)).max(1)


def truncate_sh(g: GaussianSet, tolerance: float) -> tuple[GaussianSet, np.ndarray]:
    """``g`` with each Gaussian's SH cut to the lowest degree whose :func:`sh_change_bound` is
    ``<= tolerance`` (higher bands zeroed) and the array cut to the highest degree still used; also
    returns the per-Gaussian degrees ``[N]`` int."""
    d = g.sh_degree
    need = np.full(g.num, d, np.int64)
    for L in range(d - 1, -1, -1):  # from the top: a Gaussian needs L if its bands above L are small
        ok = sh_change_bound(g.sh, L) <= tolerance
        need[ok] = L
    new_d = int(need.max()) if g.num else 0
    sh = np.ascontiguousarray(g.sh[:, : (new_d + 1) ** 2]).copy()
    for L in range(new_d):
        sh[need == L, (L + 1) ** 2 :] = 0.0
    return dataclasses.replace(g, sh=sh), need


# --------------------------------------------------------------------------------------------- parts
def hull_vertices(g: GaussianSet) -> np.ndarray:
    """``[N]`` bool: the vertices of the convex hull of the means with opacity >= 0.2 (all of them when
    fewer than 4 or the hull is degenerate), the points :class:`dsg_gym.physics.PhysicsProxy` builds the
    collision hull from."""
    idx = np.flatnonzero(g.opacities >= 0.2)
    if len(idx) < 4:
        idx = np.arange(g.num)
    out = np.zeros(g.num, bool)
    from scipy.spatial import ConvexHull, QhullError

    try:
        out[idx[ConvexHull(g.means[idx].astype(np.float64)).vertices]] = True
    except (QhullError, ValueError):  # flat or tiny sets: keep them all
        out[idx] = True
    return out


def _capture_cameras(world: World) -> tuple[np.ndarray, np.ndarray, int, int]:
    """The world's capture cameras of the reference state's image size, reference state first."""
    if not world.cameras:
        raise ValueError("the world has no capture cameras to derive plausible cameras from")
    ref = world.metadata.get("reference_state")
    order = sorted(world.cameras, key=lambda s: (s != ref, str(s)))
    first = world.cameras[order[0]]
    same = [
        world.cameras[s]
        for s in order
        if (world.cameras[s].width, world.cameras[s].height) == (first.width, first.height)
    ]
    vm = np.concatenate([np.asarray(c.viewmats, np.float64) for c in same])
    Ks = np.concatenate([np.asarray(c.Ks, np.float64) for c in same])
    return vm, Ks, first.width, first.height


def _parts(
    world: World, gsets: list[tuple[GaussianSet, np.ndarray]], cams: SceneCameras, cfg: CompactConfig
) -> list[Part]:
    """Background and objects (``gsets``: (SH-cut set, per-Gaussian degrees)) with their scoring cameras."""
    (g, need), rest = gsets[0], gsets[1:]
    parts = [Part("background", g, cams.viewmats, np.zeros(g.num, bool), np.ones(g.num, bool), need)]
    for oid, (g, need) in zip(world.object_ids, rest):
        if g.num:
            lo, hi = g.means.min(0).astype(np.float64), g.means.max(0).astype(np.float64)
        else:
            lo = hi = np.zeros(3)
        vm = sphere_cameras(0.5 * (lo + hi), cams.radius, cfg.object_views, up=cams.up)
        parts.append(Part(f"object_{oid}", g, vm, hull_vertices(g), np.ones(g.num, bool), need))
    return parts


def _table_meta(world: World) -> dict:
    """``{"table": ...}`` when the world has no table bounds in its metadata but the runtime can derive them
    from the geometry (stored so that pruning cannot move them); else ``{}``."""
    if "table" in world.metadata or not world.num_objects:
        return {}
    from dsg_gym.world_model import WorldModel

    try:
        t = WorldModel.from_world(world).table
    except ValueError:
        return {}
    return {"table": {"bounds": [[t.xmin, t.ymin, t.z], [t.xmax, t.ymax, t.z]], "top_z": t.z}}


def _shell_meta(world: World, keep: np.ndarray) -> dict:
    """``{"background_shell": ...}`` counting the far shell's kept rows (the last ones of the background,
    :mod:`train_world.complete.shell`), so that the shell can still be told apart; else ``{}``."""
    rec = world.metadata.get("background_shell")
    if rec is None:
        return {}
    n = int(rec["gaussians"])
    return {"background_shell": {**dict(rec), "gaussians": int(keep[len(keep) - n :].sum()) if n else 0}}


def _background_color(world: World) -> tuple[float, float, float]:
    bg = world.metadata.get("background", (0.0, 0.0, 0.0))
    try:
        out = tuple(float(v) for v in bg)
    except (TypeError, ValueError):
        out = ()
    if len(out) != 3 or not all(math.isfinite(v) for v in out):
        raise ValueError(f"world metadata 'background' must be an RGB triple, got {bg!r}")
    return out  # type: ignore[return-value]


def compact_world(
    world: World,
    cfg: CompactConfig | None = None,
    *,
    capture: str | Path | None = None,
    log: Callable[[str], None] | None = None,
) -> tuple[World, dict[str, Any]]:
    """The compacted world and a report (module docstring). ``capture``: also measure the PSNR drop on its
    test states with ``dsg-eval`` (and use the original's measured PSNR as the reference)."""
    cfg = cfg or CompactConfig()
    log = log or (lambda _msg: None)
    t_start = time.perf_counter()
    bg_color = _background_color(world)
    vm, Ks, W, H = _capture_cameras(world)
    fallback = np.median(world.background.means, 0) if world.background.num else None
    cams = scene_cameras(vm, Ks, W, H, rings=cfg.rings, per_ring=cfg.per_ring, fallback_target=fallback)
    originals = [world.background] + [world.objects[i].gaussians for i in world.object_ids]
    total0 = sum(g.num for g in originals)
    timings: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="dsg-compact-") as tmp:
        t = time.perf_counter()
        check = (
            CaptureCheck(world, Path(capture), cams, bg_color, cfg, Path(tmp))
            if capture is not None
            else SelfCheck(world, cams, bg_color, cfg, cfg.reference_psnr)
        )
        timings["reference_s"] = time.perf_counter() - t
        t = time.perf_counter()
        parts = _parts(world, [truncate_sh(g, cfg.sh_tolerance) for g in originals], cams, cfg)
        scores = [score_part(p, cams, bg_color, world.splat_options) for p in parts]
        for p, (w, _) in zip(parts, scores):
            p.keep = (w >= cfg.min_weight) | p.protected
        timings["scoring_s"] = time.perf_counter() - t
        s = PruneSearch(parts, check, cams, bg_color, cfg, log, world.splat_options)
        s.res = s.run_check("sh+invisible")
        sh_truncated = True
        if not (s.res["ok"] or cfg.fraction is not None):  # the SH cut alone breaks the budget: keep SH
            sh_truncated = False
            for p, g in zip(parts, originals):
                p.g, p.sh_need = g, np.full(g.num, g.sh_degree)
            s.res = s.run_check("invisible (all SH bands)")
            if not s.res["ok"]:
                for p in parts:
                    p.keep[:] = True
                s.res = s.run_check("nothing removed")
        floor = math.ceil((cfg.fraction if cfg.fraction is not None else cfg.min_fraction) * total0)
        t = time.perf_counter()
        s.search([e for _, e in scores], floor)
        for cycle in range(cfg.refit_cycles if cfg.refit_steps > 0 else 0):
            if not s.refit(originals) or cycle == cfg.refit_cycles - 1 or not s.res["ok"]:
                break
            s.search(s.errors(), floor)
        if cfg.fraction is not None:
            s.res = s.run_check("final")
        timings["search_s"] = time.perf_counter() - t
    res = s.res
    bg_new, objs_new = parts[0].kept(), [p.kept() for p in parts[1:]]
    total1 = bg_new.num + sum(g.num for g in objs_new)
    summary = {
        "gaussians_before": total0,
        "gaussians_after": total1,
        "reduction": total0 / max(total1, 1),
        "mode": "capture" if capture is not None else "self",
        "psnr_drop": res["psnr_drop"],
        "sh_truncated": sh_truncated,
        "refits": s.refits,
        "options": dataclasses.asdict(cfg),
    }
    meta = {"compacted": summary, **_table_meta(world), **_shell_meta(world, parts[0].keep)}
    if "num_gaussians" in world.metadata:
        meta["num_gaussians"] = total1
    report = {
        **{k: v for k, v in summary.items() if k != "options"},
        "parts": {
            p.name: {
                "before": int(g.num),
                "after": int(p.keep.sum()),
                "protected": int(p.protected.sum()),
                "sh_degree_before": int(g.sh_degree),
                "sh_degree_after": int(p.g.sh_degree),
            }
            for p, g in zip(parts, originals)
        },
        "check": {k: v for k, v in res.items() if k != "ok"},
        "within_budget": bool(res["ok"]),
        "rounds": s.rounds,
        "cameras": {
            "capture": cams.num_capture,
            "orbit": len(cams) - cams.num_capture,
            "radius": cams.radius,
            "elevations_deg": list(cams.elevations_deg),
            "object_views": cfg.object_views,
            "validation_views": len(getattr(check, "self_check", check).idx),
            "image_size": [cams.width, cams.height],
        },
        "options": dataclasses.asdict(cfg),
        "time_s": {**timings, "total_s": time.perf_counter() - t_start},
    }
    return with_parts(world, bg_new, objs_new, meta), report
