"""OpenCV pinhole cameras (``viewmat``, ``K``, image size) <-> ``UsdGeom.Camera``.

Conversion (documented once, tested by projecting points both ways):

* Pose. USD cameras look down ``-Z`` with ``+Y`` up (OpenGL axes); OpenCV cameras look down
  ``+Z`` with ``+Y`` down. The camera prim gets one ``xformOp:transform`` holding the
  camera-to-world matrix ``inv(viewmat) @ diag(1, -1, -1, 1)`` (y and z axes flipped).
* Intrinsics. USD has no pixels: ``focalLength`` and the apertures share one length unit
  (millimetres by convention). We fix the horizontal aperture to ``SENSOR_WIDTH_MM`` (USD's
  default, 20.955 mm) so one pixel is ``p = SENSOR_WIDTH_MM / width`` mm wide, and set

  ====================================  ===========================================
  ``focalLength``                       ``fx * p``
  ``horizontalAperture``                ``width * p``  (= ``SENSOR_WIDTH_MM``)
  ``verticalAperture``                  ``height * p * fx / fy``  (non-square pixels)
  ``horizontalApertureOffset``          ``(width / 2 - cx) * p``
  ``verticalApertureOffset``            ``(cy - height / 2) * p * fx / fy``
  ``clippingRange``                     ``(near, far)`` in stage units
  ====================================  ===========================================

  so that a point's OpenCV pixel ``(u, v)`` (pixel centres at ``+0.5``) equals the USD
  projection's NDC mapped as ``u = (x + 1) / 2 * width``, ``v = (1 - y) / 2 * height``. Skew is
  not representable and is refused. The image size is kept in the prim's customData
  (``dsg:width``, ``dsg:height``) so ``K`` can be recovered exactly up to float32 rounding of
  the USD lens attributes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom

from dsg_gym.poses import check_rigid, rigid_inverse
from dsg_gym.usd.transforms import from_gf_matrix, to_gf_matrix

__all__ = [
    "SENSOR_WIDTH_MM",
    "UsdCamera",
    "cameras_from_arrays",
    "check_camera",
    "write_camera",
    "read_camera",
    "usd_lens_from_K",
    "K_from_usd_lens",
]

SENSOR_WIDTH_MM = 20.955
_FLIP_YZ = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True, eq=False)
class UsdCamera:
    """A capture camera: OpenCV world-to-camera ``viewmat [4, 4]``, intrinsics ``K [3, 3]``
    (pixels), image ``width`` x ``height``; ``clipping_range`` (near, far) in stage units."""

    name: str
    viewmat: np.ndarray
    K: np.ndarray
    width: int
    height: int
    clipping_range: tuple[float, float] = (0.01, 100.0)


def cameras_from_arrays(
    viewmats,
    Ks,
    width: int,
    height: int,
    prefix: str = "cam",  # noqa: N803
    clipping_range: tuple[float, float] = (0.01, 100.0),
) -> list[UsdCamera]:
    """``UsdCamera`` list named ``{prefix}_{i:03d}`` from batched ``viewmats [V, 4, 4]`` and
    ``Ks [V, 3, 3]`` sharing one image size (e.g. a world's capture cameras)."""
    viewmats, Ks = np.asarray(viewmats, np.float64), np.asarray(Ks, np.float64)  # noqa: N806
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (viewmats.shape[0], 3, 3):
        raise ValueError(f"cameras_from_arrays: bad shapes viewmats {viewmats.shape}, Ks {Ks.shape}")
    return [
        UsdCamera(f"{prefix}_{i:03d}", v, k, int(width), int(height), clipping_range)
        for i, (v, k) in enumerate(zip(viewmats, Ks))
    ]


def check_camera(cam: UsdCamera) -> tuple[np.ndarray, np.ndarray]:
    """``(viewmat, K)`` as float64 after validation; ``ValueError`` naming the camera and field."""
    what = f"UsdCamera {cam.name!r}"
    viewmat = check_rigid(f"{what}.viewmat", cam.viewmat)
    k = np.asarray(cam.K, dtype=np.float64)
    if k.shape != (3, 3) or not np.isfinite(k).all():
        raise ValueError(f"{what}.K: expected a finite [3, 3] matrix, got shape {k.shape}")
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"{what}.K: focal lengths must be positive, got fx={k[0, 0]}, fy={k[1, 1]}")
    if k[0, 1] != 0 or k[1, 0] != 0 or not np.array_equal(k[2], [0.0, 0.0, 1.0]):
        raise ValueError(f"{what}.K: must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
    for field in ("width", "height"):
        value = getattr(cam, field)
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
            raise ValueError(f"{what}.{field}: expected a positive integer, got {value!r}")
    near, far = (float(x) for x in cam.clipping_range)
    if not (np.isfinite(near) and np.isfinite(far) and 0 < near < far):
        raise ValueError(f"{what}.clipping_range: need 0 < near < far, got {cam.clipping_range}")
    return viewmat, k


def usd_lens_from_K(k: np.ndarray, width: int, height: int) -> dict[str, float]:
    """USD camera lens attributes (see the module docstring) from OpenCV ``K``."""
    fx, fy, cx, cy = float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    p = SENSOR_WIDTH_MM / width
    py = p * fx / fy
    return {
        "focalLength": fx * p,
        "horizontalAperture": width * p,
        "verticalAperture": height * py,
        "horizontalApertureOffset": (0.5 * width - cx) * p,
        "verticalApertureOffset": (cy - 0.5 * height) * py,
    }


def K_from_usd_lens(lens: dict[str, float], width: int, height: int) -> np.ndarray:  # noqa: N802
    """Inverse of ``usd_lens_from_K``: ``K [3, 3]`` float64."""
    p = lens["horizontalAperture"] / width
    py = lens["verticalAperture"] / height
    f = lens["focalLength"]
    fx, fy = f / p, f / py
    cx = 0.5 * width - lens["horizontalApertureOffset"] / p
    cy = 0.5 * height + lens["verticalApertureOffset"] / py
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def write_camera(
    stage: Usd.Stage, path: str | Sdf.Path, cam: UsdCamera, name: str | None = None
) -> UsdGeom.Camera:
    """Define a ``UsdGeom.Camera`` at ``path`` for ``cam`` (validated with ``check_camera``)."""
    viewmat, k = check_camera(cam)
    usd_cam = UsdGeom.Camera.Define(stage, Sdf.Path(str(path)))
    c2w_gl = rigid_inverse(viewmat) @ _FLIP_YZ
    usd_cam.AddTransformOp(UsdGeom.XformOp.PrecisionDouble).Set(to_gf_matrix(c2w_gl))
    usd_cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    lens = usd_lens_from_K(k, int(cam.width), int(cam.height))
    usd_cam.CreateFocalLengthAttr(lens["focalLength"])
    usd_cam.CreateHorizontalApertureAttr(lens["horizontalAperture"])
    usd_cam.CreateVerticalApertureAttr(lens["verticalAperture"])
    usd_cam.CreateHorizontalApertureOffsetAttr(lens["horizontalApertureOffset"])
    usd_cam.CreateVerticalApertureOffsetAttr(lens["verticalApertureOffset"])
    usd_cam.CreateClippingRangeAttr(Gf.Vec2f(*(float(x) for x in cam.clipping_range)))
    prim = usd_cam.GetPrim()
    prim.SetCustomDataByKey("dsg:width", int(cam.width))
    prim.SetCustomDataByKey("dsg:height", int(cam.height))
    prim.SetCustomDataByKey("dsg:name", name if name is not None else cam.name)
    return usd_cam


def read_camera(prim: Usd.Prim, time: Usd.TimeCode = Usd.TimeCode.Default()) -> UsdCamera:  # noqa: B008  (an immutable value)
    """A ``UsdCamera`` from a camera prim written by ``write_camera`` (world transform included)."""
    usd_cam = UsdGeom.Camera(prim)
    if not usd_cam:
        raise ValueError(f"USD camera {prim.GetPath()}: not a Camera (type {prim.GetTypeName()!r})")
    width, height = prim.GetCustomDataByKey("dsg:width"), prim.GetCustomDataByKey("dsg:height")
    if width is None or height is None:
        raise ValueError(f"USD camera {prim.GetPath()}: customData lacks dsg:width / dsg:height")
    width, height = int(width), int(height)
    c2w_gl = from_gf_matrix(usd_cam.ComputeLocalToWorldTransform(time))
    viewmat = rigid_inverse(c2w_gl @ _FLIP_YZ)
    names = (
        "focalLength",
        "horizontalAperture",
        "verticalAperture",
        "horizontalApertureOffset",
        "verticalApertureOffset",
    )
    lens = {n: float(prim.GetAttribute(n).Get(time)) for n in names}
    near, far = usd_cam.GetClippingRangeAttr().Get(time)
    return UsdCamera(
        name=str(prim.GetCustomDataByKey("dsg:name") or prim.GetName()),
        viewmat=viewmat,
        K=K_from_usd_lens(lens, width, height),
        width=width,
        height=height,
        clipping_range=(float(near), float(far)),
    )
