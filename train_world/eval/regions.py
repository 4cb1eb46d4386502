"""Where a rendering's error is: squared error split by image region, from the ground truth's id masks.

Regions of a view, from its ground-truth id mask ``[H, W]`` (0 = table and room, k = object k):

- ``outline``: pixels within ``radius`` pixels (Chebyshev distance) of a pixel of another id: object
  silhouettes and the boundaries between touching objects;
- ``objects``: the other object pixels (object ``name`` alone under ``per_object``);
- ``background``: the other pixels (table and room) that some training view sees;
- ``unseen``: background pixels that no training view sees (:func:`seen_by`; only with depth maps, else
  every background pixel counts as ``background``): what a world can only guess.

Where the ground truth has depth and a table, ``background`` is split further by the surface each pixel shows
(:mod:`.background_parts`: ``table_top``, ``floor``, ``other``), reported under ``background_parts``.

For each region :class:`RegionErrors` accumulates, over views, the pixel count and the sum of squared error
(mean over RGB channels, images in [0, 1], float64) and reports the region's share of the pixels, its PSNR
and its share of the total squared error: a region with a small pixel share and a large error share is where
accuracy is lost. The regions partition every view, so the shares each sum to 1.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy import ndimage

from dsg_gym.cameras import depth_points
from train_world.eval.background_parts import PARTS
from train_world.eval.metrics import psnr_from_mse

if TYPE_CHECKING:
    from train_world.capture.loader import Capture

__all__ = [
    "OUTLINE_RADIUS",
    "REGIONS",
    "SEEN_DEPTH_TOL",
    "RegionErrors",
    "combine",
    "region_masks",
    "seen_by",
]

#: how far from an id change a pixel counts as outline, in pixels
OUTLINE_RADIUS = 1
REGIONS = ("outline", "objects", "background", "unseen")
#: relative depth difference within which a training view's depth map confirms a surface point (not occluded)
SEEN_DEPTH_TOL = 0.02


def seen_by(
    depth: np.ndarray,
    viewmat: np.ndarray,
    K: np.ndarray,
    train_depths: np.ndarray,
    train_viewmats: np.ndarray,
    train_Ks: np.ndarray,
    rel_tol: float = SEEN_DEPTH_TOL,
) -> np.ndarray:
    """Pixels of a view whose surface point some training view sees: bool ``[H, W]``.

    ``depth [H, W]``: the view's depth in metres along the optical axis (0: none, never seen), ``viewmat
    [4, 4]`` world-to-camera and ``K [3, 3]`` (OpenCV, pixel centres at +0.5). A pixel's point is seen by a
    training view (``train_depths [V, h, w]``, ``train_viewmats [V, 4, 4]``, ``train_Ks [V, 3, 3]``) when it
    lies in front of that camera, projects into its image, and that view's depth at the pixel it falls in agrees
    within ``rel_tol`` of the point's depth (nothing in front of it). In float64."""
    d = np.asarray(depth, np.float64)
    H, W = d.shape
    world = depth_points(d, viewmat, K).reshape(-1, 3)
    valid = d.reshape(-1) > 0
    seen = np.zeros(H * W, bool)
    for D, V, Kt in zip(
        np.asarray(train_depths), np.asarray(train_viewmats, np.float64), np.asarray(train_Ks, np.float64)
    ):
        c = world @ V[:3, :3].T + V[:3, 3]
        z = c[:, 2]
        front = valid & (z > 1e-9)
        zs = np.where(front, z, 1.0)
        u = np.floor(Kt[0, 0] * c[:, 0] / zs + Kt[0, 2])
        v = np.floor(Kt[1, 1] * c[:, 1] / zs + Kt[1, 2])
        h, w = D.shape
        inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ui, vi = u[inside].astype(np.int64), v[inside].astype(np.int64)
        dz = D[vi, ui].astype(np.float64)
        ok = (dz > 0) & (np.abs(dz - z[inside]) <= rel_tol * z[inside])
        seen[np.flatnonzero(inside)[ok]] = True
    return seen.reshape(H, W)


def capture_coverage(
    capture: Capture,
    state: str,
    indices: Sequence[int],
    training_states: Sequence[str],
    heldout: Mapping[str, Sequence[int]],
) -> np.ndarray | None:
    """:func:`seen_by` of views ``indices`` of ``state`` of the loaded ``capture`` against its training views
    (every view of ``training_states`` but the ``heldout`` indices of each): bool ``[len(indices), H, W]``;
    None when the capture lacks one of those states or depth maps for them."""
    views = capture.states
    names = list(dict.fromkeys([state, *training_states]))
    if any(n not in views or views[n].depths is None for n in names):
        return None
    td, tv, tk = [], [], []
    for n in training_states:
        keep = [i for i in range(len(views[n])) if i not in set(heldout.get(n, ()))]
        td.append(views[n].depths.numpy()[keep])
        tv.append(views[n].viewmats.numpy()[keep])
        tk.append(views[n].Ks.numpy()[keep])
    train = (np.concatenate(td), np.concatenate(tv), np.concatenate(tk))
    ev = views[state]
    return np.stack(
        [seen_by(ev.depths.numpy()[i], ev.viewmats.numpy()[i], ev.Ks.numpy()[i], *train) for i in indices]
    )


def region_masks(
    classes: np.ndarray, radius: int = OUTLINE_RADIUS, seen: np.ndarray | None = None
) -> dict[str, np.ndarray]:
    """Boolean masks ``[H, W]`` of the regions (module docstring) of an id mask ``classes [H, W]``; they
    partition the image. ``seen``: :func:`seen_by` of the view (None: ``unseen`` stays empty)."""
    cls = np.asarray(classes)
    if cls.ndim != 2:
        raise ValueError(f"classes must be an id mask [H, W], got shape {cls.shape}")
    if radius < 0:
        raise ValueError(f"radius must be >= 0, got {radius}")
    if radius == 0:
        outline = np.zeros(cls.shape, bool)
    else:
        size = 2 * radius + 1
        hi = ndimage.maximum_filter(cls, size=size, mode="nearest")
        lo = ndimage.minimum_filter(cls, size=size, mode="nearest")
        outline = hi != lo
    objects = (cls > 0) & ~outline
    background = ~(outline | objects)
    unseen = np.zeros(cls.shape, bool) if seen is None else background & ~np.asarray(seen, bool)
    return {"outline": outline, "objects": objects, "background": background & ~unseen, "unseen": unseen}


class RegionErrors:
    """Accumulates squared error by region over views; :meth:`report` gives the figures."""

    def __init__(self, object_names: Sequence[str], radius: int = OUTLINE_RADIUS):
        self.names = list(object_names)
        self.radius = int(radius)
        keys = [*REGIONS, *(f"object:{n}" for n in self.names)]
        self.pixels = dict.fromkeys(keys, 0)
        self.sq = dict.fromkeys(keys, 0.0)
        self.views = 0
        self.coverage_views = 0  # views whose unseen pixels were told apart
        self.seen_psnr_sum = 0.0  # over those views: PSNR of the pixels but the unseen ones
        self.parts_views = 0  # views whose background was split into parts
        for part in PARTS:
            self.pixels[f"part:{part}"], self.sq[f"part:{part}"] = 0, 0.0

    def add(
        self,
        ours: np.ndarray,
        truth: np.ndarray,
        classes: np.ndarray,
        seen: np.ndarray | None = None,
        parts: Mapping[str, np.ndarray] | None = None,
    ) -> None:
        """One view: ``ours``, ``truth`` ``[H, W, 3]`` in [0, 1], the ground truth's ids ``[H, W]``, optionally
        which pixels the training views see (:func:`seen_by`) and the view's background parts
        (:func:`.background_parts.background_parts`)."""
        if ours.shape != truth.shape or ours.shape[:2] != classes.shape:
            raise ValueError(
                f"shapes differ: ours {ours.shape}, truth {truth.shape}, classes {classes.shape}"
            )
        err = np.mean((ours.astype(np.float64) - truth.astype(np.float64)) ** 2, axis=-1)
        masks = region_masks(classes, self.radius, seen)
        self.coverage_views += seen is not None
        self.views += 1
        if seen is not None:
            self.seen_psnr_sum += psnr_from_mse(float(err[~masks["unseen"]].mean()))
        for r in REGIONS:
            self.pixels[r] += int(masks[r].sum())
            self.sq[r] += float(err[masks[r]].sum())
        if parts is not None:
            self.parts_views += 1
            for part in PARTS:
                m = masks["background"] & np.asarray(parts[part], bool)
                self.pixels[f"part:{part}"] += int(m.sum())
                self.sq[f"part:{part}"] += float(err[m].sum())
        for k, n in enumerate(self.names, start=1):
            m = masks["objects"] & (classes == k)
            self.pixels[f"object:{n}"] += int(m.sum())
            self.sq[f"object:{n}"] += float(err[m].sum())

    def report(self) -> dict[str, Any]:
        """``{"outline_radius", "regions": {region: entry}, "per_object": {name: entry}}``; an entry holds
        ``pixels``, ``squared_error`` (the sums), ``pixel_share``, ``psnr`` (None without pixels) and
        ``error_share`` (an object's shares are of the whole image). ``mean_psnr_seen``: over the views with
        coverage, the mean PSNR of each view without its unseen pixels (what the views' mean PSNR would be if
        the world rendered unseen background perfectly), None without coverage. ``background_parts``: with
        parts given for every view, ``background`` split by :data:`.background_parts.PARTS` (shares of the
        whole image); None otherwise."""
        total_px = sum(self.pixels[r] for r in REGIONS)
        total_sq = sum(self.sq[r] for r in REGIONS)

        def entry(key: str) -> dict[str, float | None]:
            n = self.pixels[key]
            return {
                "pixels": n,
                "squared_error": self.sq[key],
                "pixel_share": n / total_px if total_px else None,
                "psnr": psnr_from_mse(self.sq[key] / n) if n else None,
                "error_share": self.sq[key] / total_sq if total_sq > 0 else None,
            }

        return {
            "outline_radius": self.radius,
            "views": self.views,
            "coverage_views": self.coverage_views,
            "mean_psnr_seen": self.seen_psnr_sum / self.coverage_views if self.coverage_views else None,
            "regions": {r: entry(r) for r in REGIONS},
            "per_object": {n: entry(f"object:{n}") for n in self.names},
            "background_parts": (
                {part: entry(f"part:{part}") for part in PARTS}
                if self.views and self.parts_views == self.views
                else None
            ),
        }


def combine(reports: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """One :meth:`RegionErrors.report` of the union of the views of several (same objects and radius)."""
    if not reports:
        raise ValueError("combine needs at least one region report")
    first = reports[0]
    if any(
        r["outline_radius"] != first["outline_radius"] or r["per_object"].keys() != first["per_object"].keys()
        for r in reports
    ):
        raise ValueError("region reports of different outline radii or objects cannot be combined")
    acc = RegionErrors(list(first["per_object"]), first["outline_radius"])
    for r in reports:
        acc.views += int(r.get("views", 0))
        acc.coverage_views += int(r.get("coverage_views", 0))
        acc.seen_psnr_sum += (r.get("mean_psnr_seen") or 0.0) * int(r.get("coverage_views", 0))
        parts = r.get("background_parts") or {}
        acc.parts_views += int(r.get("views", 0)) if parts else 0
        for key, e in [
            *r["regions"].items(),
            *((f"object:{n}", e) for n, e in r["per_object"].items()),
            *((f"part:{p}", e) for p, e in parts.items()),
        ]:
            acc.pixels[key] += int(e["pixels"])
            acc.sq[key] += float(e["squared_error"])
    return acc.report()
