"""Metric scale from an ArUco marker of known size lying in the scene.

Structure from motion recovers a scene up to scale. A printed ArUco marker (OpenCV's ``DICT_4X4_50``) whose black
square has a known edge length fixes it: :func:`detect_marker` finds the marker's four corners in each undistorted
photo (OpenCV's detector; corners refined by the AprilTag method, which fits the square's edges and is free of
the inward bias of the corner-window refinements on small, blurred markers), :func:`marker_scale` triangulates
each corner from every photo that saw it (linear least squares on the registered pinhole cameras) and divides
the known edge by the mean of the four triangulated edges. Needs OpenCV (the ``capture`` extra).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from train_world.capture.photos import PhotoCaptureError

__all__ = [
    "MarkerObservation",
    "MarkerScale",
    "detect_marker",
    "marker_detector",
    "marker_scale",
    "triangulate",
]

DICTIONARY = "DICT_4X4_50"
#: fewest photos that must see the marker
MIN_MARKER_VIEWS = 2


@dataclass(frozen=True)
class MarkerObservation:
    """One photo's view of the marker: its key, corners ``[4, 2]`` (pixels of the undistorted pinhole image, the
    marker's own corner order), intrinsics ``K [3, 3]`` and world-to-camera ``w2c [4, 4]``."""

    key: str
    marker_id: int
    corners: np.ndarray
    K: np.ndarray
    w2c: np.ndarray


@dataclass(frozen=True)
class MarkerScale:
    """Result of :func:`marker_scale`: ``metres_per_unit`` of the frame the cameras are in, the marker's mean
    edge in those units, the views used, the triangulated corners ``[4, 3]`` and their RMS reprojection error."""

    marker_id: int
    size_m: float
    edge_units: float
    metres_per_unit: float
    views: int
    corners: np.ndarray
    rms_px: float


def marker_detector():
    try:
        import cv2
    except ImportError as e:
        raise PhotoCaptureError(
            "a marker needs OpenCV: pip install 'dsg-gym[capture]' (or opencv-python-headless)"
        ) from e
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, DICTIONARY))
    return cv2.aruco.ArucoDetector(dictionary, params)


def detect_marker(
    rgb: np.ndarray, marker_id: int | None = None, detector=None
) -> tuple[int, np.ndarray] | None:
    """``(id, corners [4, 2])`` of the marker in ``rgb [H, W, 3]`` uint8 (``marker_id``, or the lowest id seen),
    ``None`` when it is not seen."""
    det = detector or marker_detector()
    grey = np.ascontiguousarray(rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)).round()
    corners, ids, _ = det.detectMarkers(grey.clip(0, 255).astype(np.uint8))
    if ids is None:
        return None
    found = {
        int(i): np.asarray(c, np.float64).reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)
    }
    want = min(found) if marker_id is None else int(marker_id)
    return (want, found[want]) if want in found else None


def triangulate(points: np.ndarray, Ks: np.ndarray, w2cs: np.ndarray) -> np.ndarray:
    """The 3D point ``[3]`` seen at pixels ``points [V, 2]`` by cameras ``Ks [V, 3, 3]``, ``w2cs [V, 4, 4]``
    (linear least squares: two equations per view, the smallest singular vector)."""
    rows = []
    for (u, v), K, w2c in zip(points, Ks, w2cs, strict=True):
        P = K @ w2c[:3]
        rows += [u * P[2] - P[0], v * P[2] - P[1]]
    A = np.asarray(rows)
    A /= np.linalg.norm(A, axis=1, keepdims=True)
    X = np.linalg.svd(A)[2][-1]
    return X[:3] / X[3]


def marker_scale(obs: list[MarkerObservation], size_m: float) -> MarkerScale:
    """Metres per unit of the cameras' frame from the marker observations ``obs`` (one id) and its black
    square's edge ``size_m`` in metres."""
    if not (np.isfinite(size_m) and size_m > 0):
        raise PhotoCaptureError(f"marker size must be a positive number of metres, got {size_m}")
    if len(obs) < MIN_MARKER_VIEWS:
        raise PhotoCaptureError(
            f"the ArUco marker ({DICTIONARY}) is seen in {len(obs)} registered photo(s); it must be seen whole "
            f"in at least {MIN_MARKER_VIEWS}: make it larger in the photos, or pass --metres-per-unit instead"
        )
    Ks = np.stack([o.K for o in obs])
    w2cs = np.stack([o.w2c for o in obs])
    X = np.stack([triangulate(np.stack([o.corners[c] for o in obs]), Ks, w2cs) for c in range(4)])
    edges = np.linalg.norm(X - np.roll(X, -1, axis=0), axis=1)
    errs = []
    for o in obs:
        cam = (o.w2c[:3, :3] @ X.T + o.w2c[:3, 3:4]).T
        px = (o.K @ cam.T).T
        errs.append(np.linalg.norm(px[:, :2] / px[:, 2:3] - o.corners, axis=1))
    edge = float(edges.mean())
    if not edge > 0:
        raise PhotoCaptureError("the ArUco marker's corners triangulate to one point; check the photos")
    return MarkerScale(
        marker_id=obs[0].marker_id,
        size_m=float(size_m),
        edge_units=edge,
        metres_per_unit=float(size_m) / edge,
        views=len(obs),
        corners=X,
        rms_px=float(np.sqrt(np.mean(np.concatenate(errs) ** 2))),
    )
