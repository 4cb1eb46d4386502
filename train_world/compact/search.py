"""The pruning search of ``dsg-compact`` (steps 4 to 6 of :mod:`train_world.compact.compaction`): the parts
being compacted with their keep masks and scores, rounds of neighbour-aware removal bisected where they break
the budget, and refits of the survivors."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dsg_gym.gaussians import GaussianSet
from train_world.compact.config import CompactConfig
from train_world.compact.importance import SceneCameras, gaussian_importance

__all__ = ["Part", "PruneSearch", "score_part"]


@dataclass
class Part:
    """One part of the world being compacted (the background or an object): its Gaussians, its scoring
    cameras, and which Gaussians are protected (collision-hull vertices) and still kept."""

    name: str
    g: GaussianSet  # SH already truncated
    viewmats: np.ndarray  # scoring cameras
    protected: np.ndarray  # [N] bool
    keep: np.ndarray  # [N] bool
    sh_need: np.ndarray  # [N] int: SH degree each Gaussian still uses

    def kept(self) -> GaussianSet:
        return self.g.subset(self.keep)


def score_part(part: Part, cams: SceneCameras, bg, splat: dict) -> tuple[np.ndarray, np.ndarray]:
    """(weight max [N], removal error per view [N]) of the part's kept Gaussians (NaN where removed), rendered
    with the world's ``splat`` options."""
    imp = gaussian_importance(
        part.kept(),
        part.viewmats,
        cams.Ks[np.zeros(len(part.viewmats), np.int64)],
        cams.width,
        cams.height,
        background=bg,
        **splat,
    )
    w, e = np.full(part.g.num, np.nan), np.full(part.g.num, np.nan)
    w[part.keep] = imp.weight_max
    e[part.keep] = imp.error_sum / max(imp.num_cameras, 1)
    return w, e


def _select(parts: list[Part], errors: list[np.ndarray], n: int, k: int) -> list[tuple[int, int]]:
    """Up to ``n`` (part, index) pairs to remove, smallest removal error first (ties: part, then index), never
    two that are among each other's ``k`` nearest kept neighbours: each score assumes the rest stays, so
    neighbours that cover for each other (a uniformly coloured face) must not go in the same round."""
    from scipy.spatial import cKDTree

    err, pid, idx, neigh = [], [], [], []
    for j, (p, e) in enumerate(zip(parts, errors)):
        kept = np.flatnonzero(p.keep)
        nb = np.full((p.g.num, k), -1, np.int64)
        if len(kept) > 1 and k > 0:
            kk = min(k + 1, len(kept))
            _, q = cKDTree(p.g.means[kept].astype(np.float64)).query(p.g.means[kept].astype(np.float64), k=kk)
            nb[kept, : kk - 1] = kept[q.reshape(len(kept), kk)[:, 1:]]
        neigh.append(nb)
        i = np.flatnonzero(p.keep & ~p.protected)
        err.append(e[i])
        pid.append(np.full(len(i), j))
        idx.append(i)
    err, pid, idx = np.concatenate(err), np.concatenate(pid), np.concatenate(idx)
    locked = [np.zeros(p.g.num, bool) for p in parts]
    out: list[tuple[int, int]] = []
    for t in np.lexsort((idx, pid, err)):
        if len(out) >= n:
            break
        j, i = int(pid[t]), int(idx[t])
        if locked[j][i]:
            continue
        out.append((j, i))
        nb = neigh[j][i]
        locked[j][nb[nb >= 0]] = True
    return out


def _removed(parts: list[Part], base: list[np.ndarray], sel: list[tuple[int, int]]) -> None:
    """Set each part's keep mask to ``base`` minus the selected (part, index) pairs."""
    for p, b in zip(parts, base):
        p.keep = b.copy()
    for j, i in sel:
        parts[j].keep[i] = False


class PruneSearch:
    """The pruning state: parts with their keep masks, the budget check and the log of rounds."""

    def __init__(
        self, parts: list[Part], check, cams: SceneCameras, bg, cfg: CompactConfig, log, splat: dict
    ):
        self.parts, self.check, self.cams, self.bg, self.cfg, self.log = parts, check, cams, bg, cfg, log
        self.splat = splat
        self.rounds: list[dict[str, Any]] = []
        self.res: dict[str, Any] = {}
        self.refits = 0

    def count(self) -> int:
        return int(sum(int(p.keep.sum()) for p in self.parts))

    def run_check(self, what: str | None) -> dict[str, Any]:
        res = self.check(self.parts[0].kept(), [p.kept() for p in self.parts[1:]])
        if what is not None:
            self.rounds.append({"kept": self.count(), "what": what, **_brief(res)})
            self.log(f"{what}: {self.count()} kept; {_fmt(res)}")
        return res

    def errors(self) -> list[np.ndarray]:
        return [score_part(p, self.cams, self.bg, self.splat)[1] for p in self.parts]

    def search(self, errors: list[np.ndarray], floor: int) -> None:
        """Rounds of neighbour-aware removal until the budget breaks (then bisect that round) or ``floor``."""
        cfg = self.cfg
        while self.res["ok"] or cfg.fraction is not None:
            kept = self.count()
            free = int(sum(int((p.keep & ~p.protected).sum()) for p in self.parts))
            n_rm = min(math.ceil(cfg.step * kept), kept - floor, free)
            sel = _select(self.parts, errors, n_rm, cfg.neighbours) if n_rm > 0 else []
            if not sel:
                return
            old = [p.keep for p in self.parts]
            _removed(self.parts, old, sel)
            if cfg.fraction is not None:
                self.rounds.append({"kept": self.count(), "what": "round"})
            else:
                res = self.run_check(None)
                if not res["ok"]:  # bisect the round: the longest prefix (lowest errors first) within budget
                    lo, hi, best = 0, len(sel), self.res
                    for _ in range(cfg.bisect_steps):
                        if hi - lo <= 1:
                            break
                        mid = (lo + hi) // 2
                        _removed(self.parts, old, sel[:mid])
                        r = self.run_check(None)
                        lo, hi, best = (mid, hi, r) if r["ok"] else (lo, mid, best)
                    _removed(self.parts, old, sel[:lo])
                    self.res = best
                    self.rounds.append({"kept": self.count(), "what": "bisected", **_brief(best)})
                    self.log(f"bisected: {self.count()} kept; {_fmt(best)}")
                    return
                self.res = res
                self.rounds.append({"kept": self.count(), "what": "round", **_brief(res)})
                self.log(f"round: {self.count()} kept; {_fmt(res)}")
            if self.count() <= floor:
                return
            errors = self.errors()

    def refit(self, originals: list[GaussianSet]) -> bool:
        """Refit every part's survivors to its original renders; kept only if the check passes and improves.
        Parts are compacted to their survivors (removed rows are dropped for good)."""
        from train_world.compact.refit import refit

        if self.cfg.fraction is not None:  # no budget search: compare with the pruned state
            self.res = self.run_check(None)

        cfg, old = self.cfg, [(p.g, p.protected, p.keep, p.sh_need) for p in self.parts]
        for k, (p, g0) in enumerate(zip(self.parts, originals)):
            sub = p.kept()
            floor = np.where(p.protected[p.keep] & (sub.opacities >= 0.2), 0.2001, 0.0) if k else None
            p.g = refit(
                sub,
                g0,
                p.viewmats,
                self.cams.Ks[np.zeros(len(p.viewmats), np.int64)],
                self.cams.width,
                self.cams.height,
                steps=cfg.refit_steps,
                sh_degrees=p.sh_need[p.keep],
                fit_means=k == 0,
                min_opacity=floor,
                splat_options=self.splat,
                seed=self.refits,
            )
            p.protected, p.sh_need = p.protected[p.keep], p.sh_need[p.keep]
            p.keep = np.ones(p.g.num, bool)
        self.refits += 1
        res = self.run_check(None)
        better = (res["ok"] or self.cfg.fraction is not None) and res["psnr_drop"] < self.res["psnr_drop"]
        self.rounds.append(
            {"kept": self.count(), "what": "refit" if better else "refit (rejected)", **_brief(res)}
        )
        self.log(f"refit{'' if better else ' (rejected)'}: {_fmt(res)}")
        if better:
            self.res = res
        else:
            for p, (g, prot, keep, need) in zip(self.parts, old):
                p.g, p.protected, p.keep, p.sh_need = g, prot, keep, need
        return better


def _brief(res: dict[str, Any]) -> dict[str, Any]:
    return {k: res[k] for k in ("psnr_drop", "test_psnr_drop", "self_psnr") if k in res}


def _fmt(res: dict[str, Any]) -> str:
    s = f"PSNR drop {res['psnr_drop']:.3f} dB (predicted {res['predicted_psnr_drop']:.3f}"
    if res.get("test_psnr_drop") is not None:
        s += f", measured on the test states {res['test_psnr_drop']:.3f}"
    return s + f"), self PSNR {res['self_psnr']:.2f} dB"
