"""Building blocks of ``benchmarks.pareto``: settings points, world variants, error and step-time measurement,
the Pareto front and the recommended-point rule.

Everything here is deterministic except the step times (wall clock).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import pose7_to_matrix
from dsg_gym.scene_renderer import RenderSettings, SceneRenderer
from dsg_gym.splat.numba_raster import ALPHA_MIN, T_MIN
from dsg_gym.world_model import WorldModel

DEFAULT_SIZE = 128  # the env's default observation size
# the sweep's reference ("default" point): the 3DGS thresholds of the training renderer; the env's default
# RenderSettings() is the point this benchmark recommends (pareto.json says whether they still agree)
DEFAULT_ALPHA_MIN = ALPHA_MIN
DEFAULT_T_MIN = T_MIN
STORAGES = ("float32", "float16", "float16_all")
RENDER_AXES = ("alpha_min", "t_min", "sh_degree")


# ----------------------------------------------------------------------------------------------- points
@dataclass(frozen=True)
class Point:
    """One setting: the renderer's knobs (``alpha_min``, ``t_min``, ``sh_degree``; ``None`` = all the world
    carries), the observation ``size`` (square), the Gaussian ``fraction`` kept (importance pruning, no refit)
    and the ``storage`` of colours/opacities (``float16``: SH and opacities rounded to float16;
    ``float16_all``: every Gaussian attribute rounded); ``world``: another world file to render instead (e.g.
    the bundled world before compaction). ``axis`` names the sweep it belongs to."""

    name: str
    axis: str
    size: int = DEFAULT_SIZE
    alpha_min: float = DEFAULT_ALPHA_MIN
    t_min: float = DEFAULT_T_MIN
    sh_degree: int | None = None
    fraction: float = 1.0
    storage: str = "float32"
    world: str | None = None

    def __post_init__(self) -> None:
        RenderSettings(self.alpha_min, self.t_min, self.sh_degree)  # validates
        if not 0.0 < self.fraction <= 1.0:
            raise ValueError(f"fraction must lie in (0, 1], got {self.fraction}")
        if self.storage not in STORAGES:
            raise ValueError(f"storage must be one of {STORAGES}, got {self.storage!r}")
        if int(self.size) < 16:
            raise ValueError(f"size must be >= 16, got {self.size}")

    @property
    def render_settings(self) -> RenderSettings:
        return RenderSettings(self.alpha_min, self.t_min, self.sh_degree)

    @property
    def world_key(self) -> tuple:
        """What the world itself depends on (points sharing it share one world variant)."""
        return (self.world, self.fraction, self.storage)

    @property
    def env_settable(self) -> bool:
        """Only the renderer settings change (full world, float32): a possible env default."""
        return self.fraction == 1.0 and self.storage == "float32" and self.world is None

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def sweep_points(quick: bool = False) -> list[Point]:
    """The one-axis-at-a-time sweep around the default (``quick``: a few points per axis)."""
    pts = [Point("default", "default")]
    sizes = (64,) if quick else (64, 96)
    shs = (0,) if quick else (0, 1, 2)
    alphas = (4,) if quick else (0.5, 2, 3, 4, 8, 16)
    tmins = (1e-2,) if quick else (1e-5, 1e-3, 3e-3, 1e-2, 3e-2)
    fracs = (0.5,) if quick else (0.7, 0.5, 0.3)
    storages = ("float16",) if quick else ("float16", "float16_all")
    pts += [Point(f"size {s}", "resolution", size=s) for s in sizes]
    pts += [Point(f"sh_degree {d}", "sh_degree", sh_degree=d) for d in shs]
    pts += [Point(f"alpha_min {a:g}/255", "alpha_min", alpha_min=a / 255) for a in alphas]
    pts += [Point(f"t_min {t:g}", "t_min", t_min=t) for t in tmins]
    pts += [Point(f"budget {round(f * 100)}%", "budget", fraction=f) for f in fracs]
    pts += [Point(f"storage {s}", "storage", storage=s) for s in storages]
    return pts


def combined_points(points: list[Point], psnr: dict[str, float], tolerances=(0.1, 0.5)) -> list[Point]:
    """For each tolerance: one point combining, per renderer axis (``alpha_min``, ``t_min``, ``sh_degree``),
    the cheapest swept value whose PSNR is within the tolerance of the default's (cheapest: largest
    threshold, lowest SH degree). Axes with no such value keep the default. Duplicates are dropped."""
    base = psnr["default"]
    out: list[Point] = []
    for tol in tolerances:
        kw: dict = {}
        for axis in RENDER_AXES:
            ok = [p for p in points if p.axis == axis and psnr[p.name] >= base - tol]
            if not ok:
                continue
            if axis == "sh_degree":
                best = min(ok, key=lambda p: p.sh_degree)
            else:
                best = max(ok, key=lambda p: getattr(p, axis))
                if getattr(best, axis) <= getattr(Point("d", "d"), axis):
                    continue  # only values that are cheaper than the default count
            kw[axis] = getattr(best, axis)
        if not kw:
            continue
        p = Point(f"combined {tol:g} dB", "combined", **kw)
        if all(dataclasses.replace(q, name=p.name, axis=p.axis) != p for q in points + out):
            out.append(p)
    return out


# ------------------------------------------------------------------------------------------ world variants
def round_float16(a: np.ndarray) -> np.ndarray:
    """``a`` stored as float16 and read back as float32 (round to nearest even; overflow becomes inf)."""
    with np.errstate(over="ignore"):
        return np.asarray(a, np.float32).astype(np.float16).astype(np.float32)


def _round_set(g: GaussianSet, fields: tuple[str, ...]) -> GaussianSet:
    out = dataclasses.replace(g.without_encodings(), **{f: round_float16(getattr(g, f)) for f in fields})
    return out


def float16_world(world: WorldModel, all_fields: bool = False) -> WorldModel:
    """``world`` with its SH colours and opacities (``all_fields``: also means, quats and scales) rounded to
    float16 and back: the error float16 storage would cost (the renderer itself computes in float32)."""
    fields = ("sh", "opacities") + (("means", "quats", "scales") if all_fields else ())
    return dataclasses.replace(
        world,
        background=_round_set(world.background, fields),
        objects=tuple(_round_set(o, fields) for o in world.objects),
    )


def keep_top(scores: np.ndarray, fraction: float, protected: np.ndarray | None = None) -> np.ndarray:
    """Boolean mask keeping ``ceil(fraction * N)`` entries with the highest ``scores`` (ties: lower index
    first); ``protected`` entries are always kept and count towards the total."""
    scores = np.asarray(scores, np.float64)
    n = scores.shape[0]
    want = min(n, math.ceil(fraction * n - 1e-9))
    keep = np.zeros(n, bool) if protected is None else np.asarray(protected, bool).copy()
    order = np.lexsort((np.arange(n), -np.nan_to_num(scores, nan=-np.inf)))
    for i in order:
        if keep.sum() >= want:
            break
        keep[i] = True
    return keep


def importance_scores(
    world: WorldModel, object_views: int = 32, rings: int = 2, per_ring: int = 12, size: int | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Removal error per Gaussian (mean over views, :func:`train_world.compact.importance.gaussian_importance`): the
    background alone from its capture cameras plus an orbit (:func:`~train_world.compact.importance.scene_cameras`),
    each object alone from ``object_views`` cameras on a sphere, as ``dsg-compact`` scores them."""
    from train_world.compact.importance import gaussian_importance, scene_cameras, sphere_cameras

    cams = world.cameras if size is None else world.cameras.resized(size, size)
    bgc = tuple(float(c) for c in world.metadata.get("background", (0.0, 0.0, 0.0)))
    sc = scene_cameras(cams.viewmats, cams.Ks, cams.width, cams.height, rings=rings, per_ring=per_ring)
    imp = gaussian_importance(world.background, sc.viewmats, sc.Ks, sc.width, sc.height, background=bgc)
    bg = imp.error_sum / max(imp.num_cameras, 1)
    objs = []
    for o in world.objects:
        c = 0.5 * (o.means.min(0) + o.means.max(0)).astype(np.float64)
        vm = sphere_cameras(c, sc.radius, object_views, up=sc.up)
        imp = gaussian_importance(
            o, vm, sc.Ks[np.zeros(len(vm), np.int64)], sc.width, sc.height, background=bgc
        )
        objs.append(imp.error_sum / max(imp.num_cameras, 1))
    return bg, objs


def pruned_world(
    world: WorldModel, scores: tuple[np.ndarray, list[np.ndarray]], fraction: float
) -> WorldModel:
    """``world`` keeping the ``fraction`` of each part's Gaussians with the largest removal error, no refit;
    object collision-hull vertices are always kept (the physics proxy builds the same hulls)."""
    from train_world.compact.compaction import hull_vertices

    if fraction >= 1.0:
        return world
    bg_scores, obj_scores = scores
    bg = world.background.subset(keep_top(bg_scores, fraction))
    objs = tuple(o.subset(keep_top(s, fraction, hull_vertices(o))) for o, s in zip(world.objects, obj_scores))
    return dataclasses.replace(world, background=bg, objects=objs)


def world_variant(world: WorldModel, point: Point, scores=None) -> WorldModel:
    """The world a point renders: its own world file if it names one, else ``world`` pruned to its
    fraction; then stored as its storage says."""
    if point.world is not None:
        world = WorldModel.load(point.world).without_features()
    w = world if point.fraction >= 1.0 else pruned_world(world, scores, point.fraction)
    if point.storage != "float32":
        w = float16_world(w, all_fields=point.storage == "float16_all")
    return w


# ------------------------------------------------------------------------------------------- test states
@dataclass(frozen=True, eq=False)
class TestStates:
    """Ground truth of a capture's test states: per state ``images [V,H,W,3]`` float32 in [0, 1], ``classes
    [V,H,W]`` (0 background, k = the world's k-th object) and ``poses [K,4,4]``; the shared test cameras."""

    scene: str
    images: dict[str, np.ndarray]
    classes: dict[str, np.ndarray]
    poses: dict[str, np.ndarray]
    viewmats: np.ndarray
    Ks: np.ndarray
    width: int
    height: int


def load_test_states(
    capture: str | Path, object_ids: tuple[int, ...], max_views: int | None = None
) -> TestStates:
    """The ``test`` states of a ``dsg-synth`` capture (all of them; ``max_views``: the first views only)."""
    from train_world.capture import load_capture
    from train_world.single_state.data import class_map

    head = load_capture(capture, states=[], load_depth=False)
    names = sorted(s for s, split in head.splits.items() if split == "test")
    if not names:
        raise ValueError(f"{capture}: no test states")
    if tuple(head.object_ids) != tuple(object_ids):
        raise ValueError(f"{capture}: objects {head.object_ids} differ from the world's {object_ids}")
    cap = load_capture(capture, states=names, load_depth=False)
    lut = class_map(tuple(object_ids))
    sl = slice(None, max_views)
    imgs = {s: cap.states[s].images[sl].numpy() for s in names}
    cls = {s: lut[cap.states[s].masks[sl].numpy()].astype(np.uint8) for s in names}
    v0 = cap.states[names[0]]
    return TestStates(
        Path(capture).name,
        imgs,
        cls,
        {s: np.asarray(cap.poses[s], np.float64) for s in names},
        v0.viewmats[sl].numpy().astype(np.float64),
        v0.Ks[sl].numpy().astype(np.float64),
        v0.width,
        v0.height,
    )


def area_downsample(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """``[H,W]`` or ``[H,W,C]`` float image resized to ``width x height`` by area averaging
    (:func:`train_world.capture.files.area_resize`, as the capture loader downscales), float32."""
    from train_world.capture.files import area_resize

    a = np.asarray(img, np.float32)
    out = area_resize(a[..., None] if a.ndim == 2 else a, (width, height))
    return out[..., 0] if a.ndim == 2 else out


def downsample_classes(cls: np.ndarray, num_classes: int, width: int, height: int) -> np.ndarray:
    """Class map resized by area: the class covering most of each output pixel (ties: lower id)."""
    if cls.shape == (height, width):
        return cls
    onehot = (cls[..., None] == np.arange(num_classes)).astype(np.float32)
    return area_downsample(onehot, width, height).argmax(-1).astype(np.uint8)


def render_error(world: WorldModel, test: TestStates, point: Point) -> dict:
    """PSNR / SSIM / mask IoU of the env's renderer (:class:`SceneRenderer`, the point's settings, full
    render) at the test states' poses and cameras against the ground truth (area-downsampled to the point's
    size). PSNR and SSIM are ``dsg-eval``'s (:mod:`train_world.eval.metrics`), averaged over all views; mask
    IoU per object accumulated over a state's views, averaged over objects, then over states."""
    from train_world.eval.metrics import mask_iou, psnr, ssim

    s = point.size
    Ks = test.Ks.copy()
    Ks[:, 0] *= s / test.width
    Ks[:, 1] *= s / test.height
    bgc = tuple(float(c) for c in world.metadata.get("background", (0.0, 0.0, 0.0)))
    r = SceneRenderer(
        world.background,
        list(world.objects),
        test.viewmats,
        Ks,
        s,
        s,
        background_color=bgc,
        **world.splat_options,
        compositing=world.compositing,
        **point.render_settings.kwargs(),
    )
    k = world.num_objects
    psnrs, ssims, ious = [], [], []
    for state in sorted(test.poses):
        out = r.render(test.poses[state], rgb=True, mask=True, incremental=False)
        gtc = []
        for v in range(len(Ks)):
            gt = area_downsample(test.images[state][v], s, s)
            gtc.append(downsample_classes(test.classes[state][v], k + 1, s, s))
            ours = out.rgb[v].astype(np.float32) / 255.0
            psnrs.append(psnr(ours, gt))
            ssims.append(ssim(ours, gt))
        # stacking the views accumulates intersections and unions over them (dsg-eval's object IoU)
        vals = [v for v in mask_iou(out.mask, np.stack(gtc), range(1, k + 1)).values() if v is not None]
        if vals:
            ious.append(float(np.mean(vals)))
    return {
        "psnr": float(np.mean(psnrs)),
        "ssim": float(np.mean(ssims)),
        "mask_iou": float(np.mean(ious)) if ious else None,
        "views": len(psnrs),
        "gaussians": int(world.num_gaussians),
    }


# -------------------------------------------------------------------------------------------- step time
def _one_object_actions(rng: np.random.Generator, n: int, k: int, per: int = 4) -> np.ndarray:
    from benchmarks.env_step import _one_object_actions as f

    return f(rng, n, k, per)


class StepTimer:
    """``DSGWorld-v0`` envs (obs rgb + mask, one random object moved per step, ``collision="reject"``,
    incremental rendering, as ``benchmarks.env_step``) for several points, timed in interleaved rounds: each
    round runs the same seeded episode (same start, same actions) on every point's env, so the points do
    the same work apart from their settings and share the machine's load drifts."""

    def __init__(self, steps: int, seed: int = 0):
        self.steps, self.seed = int(steps), int(seed)
        self.envs: dict[str, object] = {}
        self.times: dict[str, list[float]] = {}
        self.tiles: dict[str, list[float]] = {}
        self.full: dict[str, list[float]] = {}

    def add(self, name: str, world: WorldModel, point: Point) -> None:
        from dsg_gym.envs.dsg_world import DSGWorldEnv

        bgc = tuple(float(c) for c in world.metadata.get("background", (0.0, 0.0, 0.0)))
        env = DSGWorldEnv(
            world=world,
            width=point.size,
            height=point.size,
            obs=("rgb", "mask"),
            incremental=True,
            collision="reject",
            background_color=bgc,
            render_settings=point.render_settings,
        )
        env.reset(seed=self.seed)
        rng = np.random.default_rng(self.seed + 1)
        for a in _one_object_actions(rng, 20, env.K):  # warm-up: numba load, caches
            env.step(a)
        self.envs[name] = env
        self.times[name], self.tiles[name], self.full[name] = [], [], []

    def round(self) -> None:
        for name, env in self.envs.items():
            env.reset(seed=self.seed)
            acts = _one_object_actions(np.random.default_rng(self.seed), self.steps, env.K)
            tiles = 0
            t0 = time.perf_counter()
            for a in acts:
                env.step(a)
                tiles += env.renderer.last_dirty_tiles
            self.times[name].append((time.perf_counter() - t0) / self.steps)
            self.tiles[name].append(tiles / self.steps)
            poses = pose7_to_matrix(env._poses)  # [K,4,4]: what every SceneRenderer version accepts
            t0 = time.perf_counter()
            for _ in range(3):  # the renderer alone: a full render of the env's camera
                env.renderer.render(poses, rgb=True, mask=True, incremental=False)
            self.full[name].append((time.perf_counter() - t0) / 3)

    def result(self, name: str) -> dict:
        t = self.times[name]
        return {
            "step_ms": 1e3 * float(np.median(t)),
            "steps_per_s": 1.0 / float(np.median(t)),
            "rounds_ms": [round(1e3 * x, 3) for x in t],
            "full_render_ms": 1e3 * float(np.median(self.full[name])),
            "mean_tiles_recomposited": float(np.mean(self.tiles[name])),
        }

    def close(self) -> None:
        for env in self.envs.values():
            env.close()
        self.envs.clear()


# ----------------------------------------------------------------------------------------------- front
def pareto_front(times: list[float], psnrs: list[float]) -> list[bool]:
    """Non-dominated flags: point ``i`` is dominated when another point is at least as fast and at least as
    accurate and strictly better in one of the two. Identical points do not dominate each other."""
    t = np.asarray(times, np.float64)
    p = np.asarray(psnrs, np.float64)
    out = []
    for i in range(len(t)):
        dom = (t <= t[i]) & (p >= p[i]) & ((t < t[i]) | (p > p[i]))
        out.append(not bool(dom.any()))
    return out


RECOMMEND_RULE = (
    "among the env-settable points (renderer settings only: full world, float32) at the env's "
    "default size: the fastest point on their Pareto front (step time, PSNR) whose mean PSNR is "
    "within {tol} dB of the most accurate of them"
)


def recommend(rows: list[dict], tol: float = 0.1, size: int = DEFAULT_SIZE) -> dict | None:
    """The recommended row (see :data:`RECOMMEND_RULE`); rows need ``point`` (a :class:`Point`),
    ``step_ms`` and ``psnr``. ``None`` when no row qualifies."""
    cand = [r for r in rows if r["point"].env_settable and r["point"].size == size]
    if not cand:
        return None
    front = pareto_front([r["step_ms"] for r in cand], [r["psnr"] for r in cand])
    best = max(r["psnr"] for r in cand)
    ok = [r for r, f in zip(cand, front) if f and r["psnr"] >= best - tol - 1e-12]
    return min(ok, key=lambda r: (r["step_ms"], -r["psnr"]))
