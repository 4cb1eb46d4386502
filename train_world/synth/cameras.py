"""Camera trajectories: a smooth orbit around the surface that looks like a handheld video.

Cameras are returned as camera-to-world matrices in **OpenGL axes** (x right, y up, looking down -z), which is
both MuJoCo's camera frame and the ``transform_matrix`` convention of ``transforms.json``.
"""

from __future__ import annotations

import numpy as np

from dsg_gym.cameras import look_at
from train_world.synth.spec import OrbitSpec

__all__ = ["look_at_opengl", "orbit_c2w", "smooth_wobble"]


def look_at_opengl(eye, target, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """4x4 OpenGL camera-to-world matrix at ``eye`` looking at ``target`` (``roll`` radians about the view
    axis, positive turns the image clockwise): the axes of :func:`dsg_gym.cameras.look_at` with y and z
    flipped, then rolled."""
    eye = np.asarray(eye, dtype=np.float64)
    rows = look_at(eye, target, up)[
        :3, :3
    ]  # OpenCV camera axes in world coordinates: x, y (down), z (forward)
    x, y, f = rows[0], -rows[1], rows[2]
    c, s = np.cos(roll), np.sin(roll)
    x, y = c * x + s * y, -s * x + c * y
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, y, -f, eye
    return m


def smooth_wobble(rng: np.random.Generator, s: np.ndarray, harmonics: int = 3) -> np.ndarray:
    """A smooth random signal over ``s`` in [0,1) (periodic with period 1) with values in about [-1, 1]."""
    out = np.zeros_like(s, dtype=np.float64)
    amp_total = 0.0
    for k in range(1, harmonics + 1):
        a = rng.uniform(0.5, 1.0) / k
        out += a * np.sin(2.0 * np.pi * (k * s + rng.uniform()))
        amp_total += a
    return out / amp_total


def orbit_c2w(
    orbit: OrbitSpec, n: int, rng: np.random.Generator, azimuth_phase_deg: float = 0.0
) -> np.ndarray:
    """``n`` cameras [n,4,4] (OpenGL camera-to-world) along one orbit around ``orbit.target``.

    Azimuth advances evenly (with slight speed jitter) over ``azimuth_span_deg`` starting at
    ``azimuth_offset_deg + azimuth_phase_deg``; radius, elevation, aim point and roll wobble smoothly.
    """
    if n < 1:
        raise ValueError("orbit_c2w: need at least one camera")
    s = np.arange(n) / n
    speed = 0.25 / max(n, 1) * smooth_wobble(rng, s)
    az = np.deg2rad(orbit.azimuth_offset_deg + azimuth_phase_deg) + np.deg2rad(orbit.azimuth_span_deg) * (
        s + speed
    )
    el = np.deg2rad(orbit.elevation_deg + orbit.elevation_wobble_deg * smooth_wobble(rng, s))
    radius = orbit.radius + orbit.radius_wobble * smooth_wobble(rng, s)
    target = np.asarray(orbit.target, dtype=np.float64)[None, :] + orbit.target_jitter * np.stack(
        [smooth_wobble(rng, s) for _ in range(3)], axis=1
    )
    roll = np.deg2rad(orbit.roll_wobble_deg) * smooth_wobble(rng, s, harmonics=4)
    eye = target + radius[:, None] * np.stack(
        [np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1
    )
    return np.stack([look_at_opengl(eye[i], target[i], roll=roll[i]) for i in range(n)])
