"""``GaussianSet`` <-> ``UsdVol.ParticleField3DGaussianSplat`` prim.

Attribute mapping (all in the prim's local frame, values as activated in ``GaussianSet``):

===========================================  ============================  =====================
USD attribute                                type                          from
===========================================  ============================  =====================
``positions``                                point3f[N]                    ``means``
``orientations``                             quatf[N] (w, x, y, z as text) ``quats`` (as stored)
``scales``                                   float3[N], linear             ``scales``
``opacities``                                float[N], linear 0..1         ``opacities``
``radiance:sphericalHarmonicsDegree``        int                           ``sh_degree``
``radiance:sphericalHarmonicsCoefficients``  float3[N * (d+1)^2]           ``sh`` (per particle
                                                                           contiguous, 3DGS order
                                                                           ``k = l^2 + l + m``)
``primvars:dsg:features``                    float[N * F], vertex,         ``features`` (omitted
                                             elementSize F                 when F = 0)
``primvars:dsg:labels``                      int[N], vertex                ``labels``
``extent``                                   float3[2]                     3-sigma box (below)
===========================================  ============================  =====================

Arrays go through ``Vt.*Array.FromNumpy`` (one copy, no Python loop), so float32 values are
stored and read back bit for bit. ``Vt.QuatfArray`` numpy buffers are ``x, y, z, w``; the
reorder happens here. The extent is the axis-aligned box of every Gaussian's 3-sigma
ellipsoid (half-width ``3 * sqrt(sum_j (R_ij s_j)^2)`` along axis i).
"""

from __future__ import annotations

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdVol, Vt

from dsg_gym.gaussians import GaussianSet
from dsg_gym.poses import quat_to_rotmat
from dsg_gym.usd.transforms import usd_to_wxyz, wxyz_to_usd

__all__ = [
    "FEATURES_PRIMVAR",
    "LABELS_PRIMVAR",
    "EXTENT_SIGMAS",
    "write_splats",
    "read_splats",
    "splat_extent",
]

FEATURES_PRIMVAR = "dsg:features"
LABELS_PRIMVAR = "dsg:labels"
EXTENT_SIGMAS = 3.0


def splat_extent(g: GaussianSet, sigmas: float = EXTENT_SIGMAS) -> np.ndarray:
    """``[2, 3]`` float32 min/max corners of the boxes around each Gaussian's ``sigmas`` ellipsoid
    (zeros for an empty set)."""
    if g.num == 0:
        return np.zeros((2, 3), np.float32)
    quats = g.quats.astype(np.float64)
    norm = np.linalg.norm(quats, axis=-1, keepdims=True)
    quats = np.where(norm > 0, quats, np.array([1.0, 0.0, 0.0, 0.0]))  # zero quaternion = identity
    rs = quat_to_rotmat(quats) * g.scales.astype(np.float64)[:, None, :]  # R diag(s)
    half = sigmas * np.sqrt((rs * rs).sum(axis=-1))
    means = g.means.astype(np.float64)
    lo, hi = (means - half).min(axis=0), (means + half).max(axis=0)
    # Round outwards so the float32 box still contains the float64 one.
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32)
    return np.stack([lo32, hi32]).astype(np.float32)


def write_splats(
    stage: Usd.Stage, path: str | Sdf.Path, g: GaussianSet
) -> UsdVol.ParticleField3DGaussianSplat:
    """Define a ``ParticleField3DGaussianSplat`` at ``path`` holding ``g`` (local frame)."""
    prim = UsdVol.ParticleField3DGaussianSplat.Define(stage, Sdf.Path(str(path)))
    n = g.num
    prim.CreatePositionsAttr(Vt.Vec3fArray.FromNumpy(g.means))
    prim.CreateOrientationsAttr(Vt.QuatfArray.FromNumpy(wxyz_to_usd(g.quats)))
    prim.CreateScalesAttr(Vt.Vec3fArray.FromNumpy(g.scales))
    prim.CreateOpacitiesAttr(Vt.FloatArray.FromNumpy(g.opacities))
    prim.CreateRadianceSphericalHarmonicsDegreeAttr(int(g.sh_degree))
    sh = np.ascontiguousarray(g.sh.reshape(n * g.sh.shape[1], 3))
    prim.CreateRadianceSphericalHarmonicsCoefficientsAttr(Vt.Vec3fArray.FromNumpy(sh))
    prim.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(splat_extent(g)))

    pv = UsdGeom.PrimvarsAPI(prim.GetPrim())
    f = g.num_features
    if f > 0:
        feat = pv.CreatePrimvar(FEATURES_PRIMVAR, Sdf.ValueTypeNames.FloatArray, UsdGeom.Tokens.vertex, f)
        feat.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(g.features.reshape(-1))))
    labels = pv.CreatePrimvar(LABELS_PRIMVAR, Sdf.ValueTypeNames.IntArray, UsdGeom.Tokens.vertex, 1)
    labels.Set(Vt.IntArray.FromNumpy(g.labels))
    return prim


def _array(attr: Usd.Attribute, dtype, what: str) -> np.ndarray:
    value = attr.Get() if attr else None
    if value is None:
        raise ValueError(f"{what}: missing attribute {attr.GetName() if attr else '?'}")
    return np.array(value, dtype=dtype)


def read_splats(prim: Usd.Prim) -> GaussianSet:
    """Read a ``ParticleField3DGaussianSplat`` written by ``write_splats`` back into a ``GaussianSet``
    (float32 arrays identical to the ones written). ``ValueError`` on a missing attribute or
    inconsistent lengths."""
    what = f"USD splats {prim.GetPath()}"
    splat = UsdVol.ParticleField3DGaussianSplat(prim)
    if not splat:
        raise ValueError(f"{what}: not a ParticleField3DGaussianSplat (type {prim.GetTypeName()!r})")
    means = _array(splat.GetPositionsAttr(), np.float32, what).reshape(-1, 3)
    n = means.shape[0]
    quats = usd_to_wxyz(_array(splat.GetOrientationsAttr(), np.float32, what).reshape(-1, 4))
    scales = _array(splat.GetScalesAttr(), np.float32, what).reshape(-1, 3)
    opacities = _array(splat.GetOpacitiesAttr(), np.float32, what).reshape(-1)
    degree = splat.GetRadianceSphericalHarmonicsDegreeAttr().Get()
    k = (int(degree) + 1) ** 2
    coeffs = _array(splat.GetRadianceSphericalHarmonicsCoefficientsAttr(), np.float32, what)
    if coeffs.size != n * k * 3:
        raise ValueError(f"{what}: {coeffs.size // 3} SH coefficients for {n} particles of degree {degree}")
    sh = coeffs.reshape(n, k, 3)

    pv = UsdGeom.PrimvarsAPI(prim)
    feat_pv = pv.GetPrimvar(FEATURES_PRIMVAR)
    if feat_pv and feat_pv.HasAuthoredValue():
        f = int(feat_pv.GetElementSize())
        flat = np.array(feat_pv.Get(), dtype=np.float32)
        if flat.size != n * f:
            raise ValueError(
                f"{what}: primvars:{FEATURES_PRIMVAR} has {flat.size} values, expected {n} x {f}"
            )
        features = flat.reshape(n, f)
    else:
        features = np.zeros((n, 0), np.float32)
    label_pv = pv.GetPrimvar(LABELS_PRIMVAR)
    labels = np.array(label_pv.Get(), dtype=np.int32) if label_pv and label_pv.HasAuthoredValue() else None
    try:
        return GaussianSet(means, quats, scales, opacities, sh, features, labels)
    except ValueError as err:
        raise ValueError(f"{what}: {err}") from None
