"""A set of 3D Gaussians with *activated* parameters, as plain numpy arrays.

``GaussianSet`` is the in-memory exchange format between the PLY reader/writer, the
world model and the renderer. Values are activated (what a renderer consumes):

============  =====================  ==========================================================
field         shape / dtype          meaning
============  =====================  ==========================================================
means         [N, 3] float32         centres, metres, world frame
quats         [N, 4] float32         rotations w, x, y, z, as stored (not renormalised)
scales        [N, 3] float32         standard deviations along the local axes, metres, >= 0
opacities     [N] float32            in [0, 1]
sh            [N, K, 3] float32      SH coefficients, K = (d + 1)^2, d in 0..3; ``sh[:, 0]`` is
                                     the DC term, ``rgb = 0.5 + SH_C0 * sh[:, 0]``
features      [N, F] float32         extra per-Gaussian features (e.g. Gaussian Grouping
                                     identity encodings); F may be 0
labels        [N] int32              object labels (0 when unknown)
============  =====================  ==========================================================

Two optional float32 fields, ``opacity_logits`` [N] and ``log_scales`` [N, 3], hold the
pre-activation values a set was read from. They exist because activation in float32
is lossy: many different stored logits map to the same float32 opacity, so without
them a file could not be rewritten bit for bit. They are only a hint:
``encoded_opacity_logits()`` / ``encoded_log_scales()`` use a stored value only where it
still activates to the current activated value, so editing the activated arrays (or
``dataclasses.replace``) can never write stale values.

Conversions run in float64: ``opacity = sigmoid(logit)``, ``scale = exp(log_scale)``;
and back ``logit(clip(opacity, 1e-7, 1 - 1e-7))``, ``log(max(scale, FLT_MIN))``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "SH_C0",
    "MAX_SH_DEGREE",
    "GaussianSet",
    "sh_degree_from_coeffs",
    "rgb_to_sh0",
    "sh0_to_rgb",
    "sigmoid",
    "logit",
]

SH_C0 = 0.28209479177387814
MAX_SH_DEGREE = 3
OPACITY_EPS = 1e-7
_F32_TINY = float(np.finfo(np.float32).tiny)


def sh_degree_from_coeffs(k: int) -> int:
    """Degree d with ``(d + 1)^2 == k``, d in 0..MAX_SH_DEGREE; ValueError otherwise."""
    for d in range(MAX_SH_DEGREE + 1):
        if (d + 1) ** 2 == k:
            return d
    raise ValueError(f"{k} SH coefficients per channel is not (d+1)^2 for a degree d in 0..{MAX_SH_DEGREE}")


def rgb_to_sh0(rgb: np.ndarray) -> np.ndarray:
    """DC SH coefficient of a colour: ``(rgb - 0.5) / SH_C0``. ``[..., 3] -> [..., 3]`` float32."""
    return ((np.asarray(rgb, dtype=np.float64) - 0.5) / SH_C0).astype(np.float32)


def sh0_to_rgb(sh0: np.ndarray) -> np.ndarray:
    """View-independent colour ``0.5 + SH_C0 * sh0`` (not clipped). ``[..., 3] -> [..., 3]`` float32."""
    return (0.5 + SH_C0 * np.asarray(sh0, dtype=np.float64)).astype(np.float32)


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Numerically stable logistic function in float64 (any shape)."""
    x = np.asarray(x, dtype=np.float64)
    e = np.exp(-np.abs(x))
    return np.where(x >= 0, 1.0 / (1.0 + e), e / (1.0 + e))


def logit(p: np.ndarray, eps: float = OPACITY_EPS) -> np.ndarray:
    """Inverse sigmoid in float64 of ``p`` clipped to ``[eps, 1 - eps]`` (any shape)."""
    p = np.clip(np.asarray(p, dtype=np.float64), eps, 1.0 - eps)
    return np.log(p) - np.log1p(-p)


def activate_opacity(logits: np.ndarray) -> np.ndarray:
    """float32 opacity from stored logits (float64 sigmoid, then rounded)."""
    return sigmoid(logits).astype(np.float32)


def activate_scale(log_scales: np.ndarray) -> np.ndarray:
    """float32 scales from stored log-scales (float64 exp, then rounded; may overflow to inf)."""
    with np.errstate(over="ignore"):
        return np.exp(np.asarray(log_scales, dtype=np.float64)).astype(np.float32)


def _as_float32(name: str, value, shape_tail: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu" and arr.dtype != np.bool_:
        raise ValueError(f"GaussianSet.{name}: expected a real numeric array, got dtype {arr.dtype}")
    with np.errstate(over="ignore"):
        arr = np.ascontiguousarray(arr, dtype=np.float32)
    if arr.ndim != 1 + len(shape_tail) or any(
        want is not None and got != want for got, want in zip(arr.shape[1:], shape_tail)
    ):
        tail = ", ".join("*" if w is None else str(w) for w in shape_tail)
        want = f"[N, {tail}]" if tail else "[N]"
        raise ValueError(f"GaussianSet.{name}: expected shape {want}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"GaussianSet.{name}: contains non-finite values")
    return arr


@dataclass(frozen=True, eq=False)
class GaussianSet:
    """N Gaussians with activated parameters (see the module docstring for fields/shapes).

    Inputs are converted to contiguous float32 (``labels`` to int32) and validated in
    ``__post_init__``; a ``ValueError`` names the offending field. ``features`` defaults
    to ``[N, 0]`` and ``labels`` to zeros. Arrays that already are contiguous float32
    (int32) are kept, not copied, so they share memory with the caller's arrays; frozen
    means the fields cannot be rebound, not that the arrays are read-only.
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray
    features: np.ndarray | None = None
    labels: np.ndarray | None = None
    opacity_logits: np.ndarray | None = field(default=None, repr=False)
    log_scales: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        put = lambda name, value: object.__setattr__(self, name, value)  # noqa: E731  (frozen)
        means = _as_float32("means", self.means, (3,))
        n = means.shape[0]
        put("means", means)
        for name, tail in (("quats", (4,)), ("scales", (3,)), ("opacities", ()), ("sh", (None, 3))):
            arr = _as_float32(name, getattr(self, name), tail)
            if arr.shape[0] != n:
                raise ValueError(f"GaussianSet.{name}: has {arr.shape[0]} rows, means has {n}")
            put(name, arr)
        try:
            sh_degree_from_coeffs(self.sh.shape[1])
        except ValueError as err:
            raise ValueError(f"GaussianSet.sh: {err}") from None
        if (self.opacities < 0).any() or (self.opacities > 1).any():
            raise ValueError("GaussianSet.opacities: values outside [0, 1]")
        if (self.scales < 0).any():
            raise ValueError("GaussianSet.scales: negative values")

        feats = np.zeros((n, 0), np.float32) if self.features is None else self.features
        feats = _as_float32("features", feats, (None,))
        if feats.shape[0] != n:
            raise ValueError(f"GaussianSet.features: has {feats.shape[0]} rows, means has {n}")
        put("features", feats)

        put("labels", _as_labels(self.labels, n))

        for name, tail in (("opacity_logits", ()), ("log_scales", (3,))):
            value = getattr(self, name)
            if value is None:
                continue
            arr = _as_float32(name, value, tail)
            if arr.shape[0] != n:
                raise ValueError(f"GaussianSet.{name}: has {arr.shape[0]} rows, means has {n}")
            put(name, arr)

    # ------------------------------------------------------------------ properties

    @property
    def num(self) -> int:
        """Number of Gaussians N."""
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def sh_degree(self) -> int:
        """SH degree d (``sh.shape[1] == (d + 1)^2``)."""
        return sh_degree_from_coeffs(self.sh.shape[1])

    @property
    def num_features(self) -> int:
        """F, the number of extra feature channels."""
        return int(self.features.shape[1])

    @property
    def colors(self) -> np.ndarray:
        """View-independent colour from the DC term, ``[N, 3]`` float32, not clipped."""
        return sh0_to_rgb(self.sh[:, 0])

    # ------------------------------------------------------------------ encodings

    def encoded_opacity_logits(self) -> np.ndarray:
        """Logits to store, ``[N]`` float32: ``opacity_logits`` where still consistent, else
        ``logit(opacities)`` computed in float64."""
        fresh = logit(self.opacities).astype(np.float32)
        if self.opacity_logits is None:
            return fresh
        ok = activate_opacity(self.opacity_logits) == self.opacities
        return np.where(ok, self.opacity_logits, fresh)

    def encoded_log_scales(self) -> np.ndarray:
        """Log-scales to store, ``[N, 3]`` float32: ``log_scales`` where still consistent, else
        ``log(max(scales, FLT_MIN))`` computed in float64."""
        fresh = np.log(np.maximum(self.scales.astype(np.float64), _F32_TINY)).astype(np.float32)
        if self.log_scales is None:
            return fresh
        ok = activate_scale(self.log_scales) == self.scales
        return np.where(ok, self.log_scales, fresh)

    # ------------------------------------------------------------------ constructors

    @classmethod
    def empty(cls, sh_degree: int = 0, num_features: int = 0) -> GaussianSet:
        """A set with N = 0."""
        k = (sh_degree + 1) ** 2
        z = np.zeros
        return cls(z((0, 3)), z((0, 4)), z((0, 3)), z(0), z((0, k, 3)), z((0, num_features)), z(0, np.int32))

    @classmethod
    def from_rgb(
        cls,
        means: np.ndarray,
        quats: np.ndarray,
        scales: np.ndarray,
        opacities: np.ndarray,
        rgb: np.ndarray,
        *,
        sh_degree: int = 0,
        features: np.ndarray | None = None,
        labels: np.ndarray | None = None,
    ) -> GaussianSet:
        """Build a set from view-independent colours ``rgb`` [N, 3] (higher SH bands zero)."""
        rgb = np.asarray(rgb)
        sh = np.zeros((rgb.shape[0], (sh_degree + 1) ** 2, 3), np.float32)
        sh[:, 0] = rgb_to_sh0(rgb)
        return cls(means, quats, scales, opacities, sh, features, labels)

    @classmethod
    def concat(cls, sets: Sequence[GaussianSet]) -> GaussianSet:
        """Concatenate sets in order. SH is zero-padded to the highest degree among them;
        feature widths must agree. Stored encodings are kept (so concatenating sets read
        from files still writes their original bytes)."""
        sets = list(sets)
        if not sets:
            raise ValueError("GaussianSet.concat: need at least one set")
        widths = {s.num_features for s in sets}
        if len(widths) != 1:
            raise ValueError(f"GaussianSet.concat: feature widths differ: {sorted(widths)}")
        k = max(s.sh.shape[1] for s in sets)

        def pad_sh(s: GaussianSet) -> np.ndarray:
            if s.sh.shape[1] == k:
                return s.sh
            out = np.zeros((s.num, k, 3), np.float32)
            out[:, : s.sh.shape[1]] = s.sh
            return out

        cat = np.concatenate
        keep = any(s.opacity_logits is not None or s.log_scales is not None for s in sets)
        return cls(
            means=cat([s.means for s in sets]),
            quats=cat([s.quats for s in sets]),
            scales=cat([s.scales for s in sets]),
            opacities=cat([s.opacities for s in sets]),
            sh=cat([pad_sh(s) for s in sets]),
            features=cat([s.features for s in sets]),
            labels=cat([s.labels for s in sets]),
            opacity_logits=cat([s.encoded_opacity_logits() for s in sets]) if keep else None,
            log_scales=cat([s.encoded_log_scales() for s in sets]) if keep else None,
        )

    def subset(self, idx) -> GaussianSet:
        """Rows selected by ``idx``: an integer index array, a boolean mask [N] or a slice."""
        if isinstance(idx, slice):
            sel = idx
        else:
            sel = np.asarray(idx)
            if sel.dtype == np.bool_:
                if sel.shape != (self.num,):
                    raise ValueError(
                        f"GaussianSet.subset: boolean mask of shape {sel.shape}, expected ({self.num},)"
                    )
            elif sel.dtype.kind not in "iu":
                raise ValueError(f"GaussianSet.subset: index dtype {sel.dtype} is neither integer nor bool")
            elif sel.ndim != 1:
                raise ValueError(f"GaussianSet.subset: index must be 1-D, got shape {sel.shape}")
        take = lambda a: None if a is None else a[sel]  # noqa: E731
        fields = {f.name: take(getattr(self, f.name)) for f in dataclasses.fields(self)}
        return dataclasses.replace(self, **fields)

    def without_encodings(self) -> GaussianSet:
        """The same set with ``opacity_logits`` / ``log_scales`` dropped."""
        return dataclasses.replace(self, opacity_logits=None, log_scales=None)


def _as_labels(value, n: int) -> np.ndarray:
    if value is None:
        return np.zeros(n, np.int32)
    arr = np.asarray(value)
    if arr.shape != (n,):
        raise ValueError(f"GaussianSet.labels: expected shape ({n},), got {arr.shape}")
    if arr.dtype.kind in "iub":
        info = np.iinfo(np.int32)
        if arr.size and (arr.min() < info.min or arr.max() > info.max):
            raise ValueError("GaussianSet.labels: values outside the int32 range")
        return np.ascontiguousarray(arr, dtype=np.int32)
    if arr.dtype.kind == "f":
        if not np.isfinite(arr).all() or (arr != np.round(arr)).any():
            raise ValueError("GaussianSet.labels: float values must be finite integers")
        if arr.size and (np.abs(arr).max() > 2**31 - 1):
            raise ValueError("GaussianSet.labels: values outside the int32 range")
        return np.ascontiguousarray(arr, dtype=np.int32)
    raise ValueError(f"GaussianSet.labels: expected an integer array, got dtype {arr.dtype}")
