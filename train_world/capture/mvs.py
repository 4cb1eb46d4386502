"""Dense depth maps from calibrated photos: plane-sweep stereo, then a consistency check between views.

For each reference view, depth hypotheses are swept as fronto-parallel planes (evenly in inverse depth between
``near`` and ``far``); each neighbour view is warped onto the reference by the plane's homography and compared
by zero-mean normalised cross-correlation over a ``window x window`` patch of grey values (robust to exposure
differences). A pixel's cost at a depth is ``1 - NCC`` averaged over its best ``best_of`` neighbours, which
tolerates occlusion in the others; its depth is the best hypothesis refined by a parabola through the costs
beside it. A depth is kept when it is confident (cost below ``max_cost``, patch not flat) and when at least
``min_consistent`` neighbours' own depth maps agree with it: the point reprojected into the neighbour and its
depth there carried back land within ``reproj_px`` pixels and ``rel_depth`` of the original. Everything else
is 0 ("no depth"), which is what textureless walls and occluded borders get. With ``average``, a kept depth is
the mean of its own and the confirming neighbours' depths, which averages out part of the matching noise.

Conventions: ``w2c [V,4,4]`` world-to-camera in OpenCV axes (x right, y down, z forward), ``Ks [V,3,3]`` pinhole
intrinsics with pixel centres at integer + 0.5, depths along the optical axis in world units. Deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = [
    "MvsConfig",
    "consistent_depths",
    "plane_sweep_depth",
    "select_neighbours",
    "stereo_depths",
]


@dataclass(frozen=True)
class MvsConfig:
    """Thresholds of :func:`stereo_depths`."""

    neighbours: int = 6  # views compared with each reference view
    best_of: int = 3  # a pixel's cost: the mean of its best this-many neighbours
    planes: int = 128  # depth hypotheses, even in inverse depth
    window: int = 5  # NCC patch side (pixels)
    min_angle_deg: float = 3.0  # neighbours see the scene centre from at least this angle apart ...
    max_angle_deg: float = 45.0  # ... and at most this
    preferred_angle_deg: float = 15.0  # the neighbours nearest this angle first
    max_cost: float = 0.5  # 1 - NCC above this: no depth
    min_std: float = 2.0 / 255.0  # grey-value standard deviation of a patch below this: flat, no depth
    min_consistent: int = 2  # neighbours whose depth maps must agree
    average: bool = False  # a kept depth: the mean of its own and the agreeing neighbours' (carried back)
    reproj_px: float = 1.5
    rel_depth: float = 0.02
    range_margin: tuple[float, float] = (0.8, 1.25)  # the depth range: SfM depths' 1st-99th percentile, times
    max_size: int = 256  # photos are reduced to this longest side for stereo (cost grows with pixels)

    def __post_init__(self) -> None:
        if not 1 <= self.best_of <= self.neighbours:
            raise ValueError(
                f"MvsConfig: need 1 <= best_of <= neighbours, got {self.best_of}, {self.neighbours}"
            )
        if self.planes < 3 or self.window < 3 or self.window % 2 == 0:
            raise ValueError("MvsConfig: planes >= 3 and an odd window >= 3 are needed")


def select_neighbours(w2c: np.ndarray, centre: np.ndarray, config: MvsConfig) -> list[np.ndarray]:
    """Per view, the indices of up to ``config.neighbours`` other views whose directions to ``centre [3]``
    differ by an angle in ``[min_angle_deg, max_angle_deg]``, the ones nearest ``preferred_angle_deg`` first."""
    c = np.array([-w[:3, :3].T @ w[:3, 3] for w in w2c])
    d = np.asarray(centre, np.float64)[None] - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(d @ d.T, -1.0, 1.0)))
    out = []
    for i in range(len(w2c)):
        ok = np.flatnonzero((ang[i] >= config.min_angle_deg) & (ang[i] <= config.max_angle_deg))
        ok = ok[np.argsort(np.abs(ang[i, ok] - config.preferred_angle_deg), kind="stable")]
        out.append(ok[: config.neighbours])
    return out


def _box(a: np.ndarray, w: int) -> np.ndarray:
    return cv2.boxFilter(a, -1, (w, w), normalize=True, borderType=cv2.BORDER_REFLECT)


def plane_sweep_depth(
    grey: np.ndarray,
    Ks: np.ndarray,
    w2c: np.ndarray,
    ref: int,
    neighbours: np.ndarray,
    near: float,
    far: float,
    config: MvsConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth ``[H,W]`` float32 of view ``ref`` and its cost (``1 - NCC``, inf where no neighbour sees it)
    from ``grey [V,H,W]`` float32 images, before any confidence or consistency check."""
    V, H, W = grey.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64) + 0.5, np.arange(H, dtype=np.float64) + 0.5)
    rays = np.linalg.inv(Ks[ref]) @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])  # [3,HW], z = 1
    inv = np.linspace(1.0 / near, 1.0 / far, config.planes)
    w = config.window
    r = grey[ref].astype(np.float32)
    mr = _box(r, w)
    sr = np.sqrt(np.maximum(_box(r * r, w) - mr * mr, 0.0))
    costs = np.full((len(neighbours), config.planes, H, W), np.inf, np.float32)
    ref_c2w = np.linalg.inv(w2c[ref])
    for k, n in enumerate(neighbours):
        rel = w2c[n] @ ref_c2w  # reference camera -> neighbour camera
        A = Ks[n] @ rel[:3, :3] @ rays  # [3,HW]
        b = Ks[n] @ rel[:3, 3]
        img = grey[n].astype(np.float32)
        for j, q in enumerate(inv):
            p = A / q + b[:, None]
            with np.errstate(divide="ignore", invalid="ignore"):
                mx = (p[0] / p[2] - 0.5).reshape(H, W).astype(np.float32)
                my = (p[1] / p[2] - 0.5).reshape(H, W).astype(np.float32)
            inside = (p[2].reshape(H, W) > 0) & (mx >= 0) & (mx <= W - 1) & (my >= 0) & (my <= H - 1)
            mx[~inside], my[~inside] = -10.0, -10.0
            warped = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            mw = _box(warped, w)
            sw = np.sqrt(np.maximum(_box(warped * warped, w) - mw * mw, 0.0))
            cov = _box(r * warped, w) - mr * mw
            ncc = cov / np.maximum(sr * sw, 1e-6)
            c = 1.0 - np.clip(ncc, -1.0, 1.0)
            seen = _box(inside.astype(np.float32), w) > 0.999
            costs[k, j] = np.where(seen, c, np.inf)
    best = np.sort(costs, axis=0)[: config.best_of]
    with np.errstate(invalid="ignore"):
        cost = np.where(np.isfinite(best).all(0), best.mean(0), np.inf)  # [D,H,W]
    idx = np.argmin(cost, axis=0)
    cb = np.take_along_axis(cost, idx[None], 0)[0]
    lo = np.take_along_axis(cost, np.clip(idx - 1, 0, config.planes - 1)[None], 0)[0]
    hi = np.take_along_axis(cost, np.clip(idx + 1, 0, config.planes - 1)[None], 0)[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = lo - 2.0 * cb + hi
        off = np.where(np.isfinite(denom) & (denom > 1e-9), 0.5 * (lo - hi) / denom, 0.0)
    off = np.clip(np.where((idx > 0) & (idx < config.planes - 1), off, 0.0), -0.5, 0.5)
    step = inv[1] - inv[0]
    q = inv[0] + (idx + off) * step
    depth = (1.0 / q).astype(np.float32)
    cb = np.where(sr < config.min_std, np.inf, cb).astype(np.float32)
    return depth, cb


def consistent_depths(
    depths: np.ndarray, Ks: np.ndarray, w2c: np.ndarray, neighbours: list[np.ndarray], config: MvsConfig
) -> np.ndarray:
    """``depths [V,H,W]`` (0 = none) with every depth that fewer than ``config.min_consistent`` neighbours
    confirm set to 0 (module docstring); with ``config.average``, each kept depth is the mean of its own and
    the confirming neighbours' depths carried back into its view."""
    V, H, W = depths.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float64) + 0.5, np.arange(H, dtype=np.float64) + 0.5)
    pix = np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    out = np.zeros_like(depths)
    for i in range(V):
        z = depths[i].ravel().astype(np.float64)
        cam = (np.linalg.inv(Ks[i]) @ pix) * z
        world = np.linalg.inv(w2c[i]) @ np.vstack([cam, np.ones(z.size)])
        votes = np.zeros(z.size, np.int64)
        total = z.copy()
        for n in neighbours[i]:
            pn = w2c[n] @ world
            zn = pn[2]
            with np.errstate(divide="ignore", invalid="ignore"):
                uvn = Ks[n] @ (pn[:3] / zn)
            xi, yi = np.floor(uvn[0]), np.floor(uvn[1])
            ok = (z > 0) & (zn > 0) & (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H)
            dn = np.zeros(z.size)
            dn[ok] = depths[n][yi[ok].astype(np.int64), xi[ok].astype(np.int64)]
            ok &= dn > 0
            # the neighbour's depth at that pixel, carried back into view i
            back_cam = (np.linalg.inv(Ks[n]) @ np.vstack([uvn[0], uvn[1], np.ones(z.size)])) * dn
            back = w2c[i] @ np.linalg.inv(w2c[n]) @ np.vstack([back_cam, np.ones(z.size)])
            with np.errstate(divide="ignore", invalid="ignore"):
                bp = Ks[i] @ (back[:3] / back[2])
                err = np.hypot(bp[0] - pix[0], bp[1] - pix[1])
                rel = np.abs(back[2] - z) / z
            agree = ok & (err <= config.reproj_px) & (rel <= config.rel_depth)
            votes += agree
            total += np.where(agree, back[2], 0.0)
        keep = votes >= config.min_consistent
        kept = total / (1 + votes) if config.average else z
        out[i] = np.where(keep, kept, 0.0).reshape(H, W)
    return out


def _stereo_depths(images, Ks, w2c, points, config: MvsConfig, progress) -> np.ndarray:
    """:func:`stereo_depths` at the images' own size."""
    V = len(images)
    grey = np.stack([cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) for im in images]).astype(np.float32) / 255.0
    raw = np.zeros(grey.shape, np.float32)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) < 10:  # no depth range to sweep
        if progress is not None:
            for _ in range(V):
                progress()
        return raw
    nbrs = select_neighbours(w2c, np.median(points, axis=0), config)
    for i in range(V):
        zs = (points @ w2c[i][:3, :3].T + w2c[i][:3, 3])[:, 2]
        zs = zs[zs > 0]
        if len(nbrs[i]) >= config.best_of and zs.size >= 10:
            near = max(config.range_margin[0] * np.percentile(zs, 1), 1e-6)
            far = config.range_margin[1] * np.percentile(zs, 99)
            d, c = plane_sweep_depth(grey, Ks, w2c, i, nbrs[i], near, far, config)
            raw[i] = np.where(c <= config.max_cost, d, 0.0)
        if progress is not None:
            progress()
    return consistent_depths(raw, Ks, w2c, nbrs, config)


def stereo_depths(
    images: np.ndarray,
    Ks: np.ndarray,
    w2c: np.ndarray,
    points: np.ndarray,
    config: MvsConfig | None = None,
    progress=None,
) -> np.ndarray:
    """Depth maps ``[V,H,W]`` float32 (0 = no depth) of calibrated views, at the images' size.

    ``images [V,H,W,3]`` uint8 RGB; ``Ks [V,3,3]``; ``w2c [V,4,4]`` OpenCV world-to-camera; ``points [P,3]``:
    sparse scene points (structure from motion) that bound each view's depth range (its 1st-99th
    percentile, times ``config.range_margin``) and place the scene centre. Images larger than
    ``config.max_size`` on their longest side are reduced (area average) for the sweep and each depth is
    copied to the pixels it covers. ``progress``: called once per view."""
    config = config or MvsConfig()
    images = np.asarray(images)
    if len(images) < 2:
        raise ValueError(f"stereo depth needs at least two views of a state, got {len(images)}")
    V, H, W = images.shape[:3]
    s = min(1.0, config.max_size / max(H, W))
    if s >= 1.0:
        return _stereo_depths(images, Ks, w2c, points, config, progress)
    w, h = max(1, round(W * s)), max(1, round(H * s))
    small = np.stack([cv2.resize(im, (w, h), interpolation=cv2.INTER_AREA) for im in images])
    Ks_small = np.array(Ks, np.float64)
    Ks_small[:, 0] *= w / W
    Ks_small[:, 1] *= h / H
    d = _stereo_depths(small, Ks_small, w2c, points, config, progress)
    return np.stack([cv2.resize(x, (W, H), interpolation=cv2.INTER_NEAREST) for x in d])
