"""Procedural textures (uint8 RGB arrays) for the synthetic scenes; deterministic given their arguments.

The resting surface gets a high-frequency pattern (a colour-jittered checker overlaid with fine noise and
speckles) so that the patches of table uncovered when an object moves are easy to see and to learn. Objects
get simple two-colour patterns that MuJoCo maps onto every face through a cube texture.
"""

from __future__ import annotations

import numpy as np

__all__ = ["PATTERNS", "pattern_texture", "surface_texture"]

PATTERNS = ("solid", "stripes", "checker", "dots", "noise")


def _rgb255(c) -> np.ndarray:
    return np.clip(np.asarray(c, dtype=np.float64)[:3] * 255.0, 0.0, 255.0)


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Bilinearly upsampled random lattice in [0,1], shape [h,w], with ``cells`` lattice cells across."""
    gh = max(2, int(round(cells * h / max(w, 1))) + 2)
    gw = max(2, cells + 2)
    lattice = rng.random((gh, gw))
    ys = np.linspace(0.0, gh - 1.001, h)
    xs = np.linspace(0.0, gw - 1.001, w)
    y0 = np.floor(ys).astype(int)
    x0 = np.floor(xs).astype(int)
    fy = (ys - y0)[:, None]
    fx = (xs - x0)[None, :]
    a = lattice[y0][:, x0]
    b = lattice[y0][:, x0 + 1]
    c = lattice[y0 + 1][:, x0]
    d = lattice[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def surface_texture(
    seed: int, width_px: int, height_px: int, cells_x: int, cells_y: int, color1, color2, noise: float = 0.25
) -> np.ndarray:
    """High-frequency surface texture, uint8 [height_px, width_px, 3].

    A ``cells_x`` x ``cells_y`` checker between ``color1`` and ``color2`` (RGB in [0,1]) where every cell's
    colour is jittered, multiplied by low-frequency blotches and fine per-texel noise of amplitude ``noise``,
    plus sparse dark/light speckles.
    """
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7AB1E]))
    h, w = int(height_px), int(width_px)
    yy, xx = np.mgrid[0:h, 0:w]
    cx = (xx * cells_x) // w
    cy = (yy * cells_y) // h
    parity = ((cx + cy) % 2).astype(bool)
    c1, c2 = _rgb255(color1), _rgb255(color2)
    base = np.where(parity[..., None], c2, c1)
    # per-cell jitter: mostly brightness, a little hue
    jitter = rng.normal(0.0, 16.0, size=(cells_y, cells_x, 1)) + rng.normal(
        0.0, 5.0, size=(cells_y, cells_x, 3)
    )
    base = base + jitter[cy, cx]
    blotch = 0.75 + 0.5 * _smooth_noise(rng, h, w, max(cells_x // 3, 2))
    fine = 1.0 + noise * rng.uniform(-1.0, 1.0, size=(h, w, 1))
    img = base * blotch[..., None] * fine
    speck = rng.random((h, w))
    img[speck < 0.01] *= 0.35
    img[speck > 0.99] = img[speck > 0.99] * 0.4 + 150.0
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def pattern_texture(
    pattern: str, color1, color2, size_px: int = 64, cells: int = 4, seed: int = 0
) -> np.ndarray:
    """Two-colour pattern, uint8 [size_px, size_px, 3]; ``pattern`` is one of :data:`PATTERNS`."""
    if pattern not in PATTERNS:
        raise ValueError(f"unknown texture pattern {pattern!r}; expected one of {PATTERNS}")
    n = int(size_px)
    c1, c2 = _rgb255(color1), _rgb255(color2)
    yy, xx = np.mgrid[0:n, 0:n]
    cells = max(int(cells), 1)
    if pattern == "solid":
        sel = np.zeros((n, n), dtype=bool)
    elif pattern == "stripes":
        sel = ((xx * 2 * cells) // n) % 2 == 1
    elif pattern == "checker":
        sel = (((xx * cells) // n) + ((yy * cells) // n)) % 2 == 1
    elif pattern == "dots":
        period = n / cells
        fx = (xx + 0.5) % period - period / 2
        fy = (yy + 0.5) % period - period / 2
        sel = fx * fx + fy * fy < (0.3 * period) ** 2
    else:  # noise
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0B1EC7]))
        sel = _smooth_noise(rng, n, n, cells * 2) > 0.5
    img = np.where(sel[..., None], c2, c1)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
