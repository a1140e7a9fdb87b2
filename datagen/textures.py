"""Procedural textures rich enough to track, and UV coordinates for meshes that have none.

A texture is a uint8 (S,S,3) image that tiles (it is sampled with wrap-around). It mixes a random
colour palette through multi-scale value noise and one random pattern (checks, stripes, dots,
cells), so that every patch has gradients at several scales, as real scanned objects do.
"""

from __future__ import annotations

import cv2
import numpy as np

PATTERNS = ("checks", "stripes", "dots", "cells", "noise")


def value_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth tileable noise in [0, 1], (size,size): a random cells x cells grid, upsampled."""
    grid = rng.random((cells, cells)).astype(np.float32)
    # Pad by wrapping so the upsampled image tiles seamlessly.
    padded = np.pad(grid, 2, mode="wrap")
    scale = size / cells
    big = cv2.resize(padded, None, fx=scale, fy=scale, interpolation=cv2.INTER_CUBIC)
    offset = int(round(2 * scale))
    return np.clip(big[offset:offset + size, offset:offset + size], 0.0, 1.0)


def fractal_noise(rng: np.random.Generator, size: int, octaves: int = 5,
                  base_cells: int = 4) -> np.ndarray:
    """Sum of value noise octaves (cells doubling, amplitude halving), normalised to [0, 1]."""
    total = np.zeros((size, size), np.float32)
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        cells = min(base_cells * 2**octave, size)
        total += amplitude * value_noise(rng, size, cells)
        norm += amplitude
        amplitude *= 0.5
    total /= norm
    return (total - total.min()) / max(float(np.ptp(total)), 1e-6)


def pattern(rng: np.random.Generator, size: int, kind: str) -> np.ndarray:
    """A tileable (size,size) pattern in [0, 1] of the given kind (one of PATTERNS)."""
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float32) / size  # (S,S) in [0,1)
    repeats = int(rng.integers(2, 9))
    if kind == "checks":
        return ((np.floor(xs * repeats) + np.floor(ys * repeats)) % 2).astype(np.float32)
    if kind == "stripes":
        a, b = rng.integers(-3, 4, size=2)
        a = a if (a, b) != (0, 0) else 1
        return (0.5 + 0.5 * np.sin(2 * np.pi * repeats * (a * xs + b * ys))).astype(np.float32)
    if kind == "dots":
        fx, fy = (xs * repeats) % 1.0 - 0.5, (ys * repeats) % 1.0 - 0.5
        radius = rng.uniform(0.15, 0.4)
        return (np.hypot(fx, fy) < radius).astype(np.float32)
    if kind == "cells":  # Voronoi cells with wrap-around distances, one random value per cell
        centres = rng.random((repeats * repeats, 2)).astype(np.float32)
        values = rng.random(repeats * repeats).astype(np.float32)
        nearest = np.zeros((size, size), np.intp)  # the first nearest centre, as argmin picks
        best = np.full((size, size), np.inf, np.float32)
        for c, (cx, cy) in enumerate(centres):  # one (S,S) slice at a time, not (S,S,C)
            dx, dy = np.abs(xs - cx), np.abs(ys - cy)
            dist = np.minimum(dx, 1 - dx) ** 2 + np.minimum(dy, 1 - dy) ** 2  # (S,S)
            closer = dist < best
            nearest[closer], best[closer] = c, dist[closer]
        return values[nearest]
    if kind == "noise":
        return fractal_noise(rng, size, octaves=3, base_cells=16)
    raise ValueError(f"unknown pattern {kind!r}; choose one of {PATTERNS}")


def random_palette(rng: np.random.Generator, num_colors: int) -> np.ndarray:
    """(num_colors,3) float colours in [0,1], from random hues, saturations and values."""
    hsv = np.stack(
        [rng.uniform(0, 180, num_colors), rng.uniform(60, 255, num_colors),
         rng.uniform(60, 255, num_colors)], axis=-1,
    ).astype(np.uint8)[None]  # (1,n,3) OpenCV HSV
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0].astype(np.float32) / 255.0


def procedural_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A random tileable texture, uint8 (size,size,3)."""
    palette = random_palette(rng, 3)  # (3,3)
    base = fractal_noise(rng, size)  # (S,S) large-scale colour variation
    detail = pattern(rng, size, PATTERNS[rng.integers(len(PATTERNS))])  # (S,S)
    grain = fractal_noise(rng, size, octaves=2, base_cells=size // 8)  # (S,S) fine grain
    weight = rng.uniform(0.35, 0.8) * detail  # (S,S) float32
    # Per colour channel: ((p0 (1 - base) + p1 base) (1 - weight) + p2 weight) (0.8 + 0.4 grain),
    # clipped to [0, 1], x 255; all float32, each channel a contiguous (S,S) plane (the same
    # operations as on (S,S,3) arrays broadcast against the palette: 0.5 against 2.8 ms at 256).
    keep, shade = 1 - weight, 0.8 + 0.4 * grain  # (S,S) float32 each
    colour = np.empty((size, size, 3), np.uint8)
    for c in range(3):
        plane = palette[0, c] * (1 - base)  # (S,S) float32
        plane += palette[1, c] * base
        plane *= keep
        plane += palette[2, c] * weight
        plane *= shade
        np.clip(plane, 0, 1, out=plane)
        plane *= 255
        colour[..., c] = plane  # truncated to uint8, as astype
    return colour


def box_uv(vertices: np.ndarray, faces: np.ndarray, tiles: float = 1.0):
    """UVs by box projection for a mesh that has none.

    Every face is projected along the axis its normal points most along, so the texture is never
    stretched by more than sqrt(3). Vertices are split per face, so faces on different sides can
    hold different UVs. `vertices` (V,3) should lie in about [-0.5, 0.5]^3.
    Returns (vertices (3F,3), faces (F,3), uv (3F,2)).
    """
    corners = vertices[faces]  # (F,3,3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])  # (F,3)
    axis = np.argmax(np.abs(normals), axis=1)  # (F,)
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # (F,2) the two other axes
    uv = np.take_along_axis(corners, keep[:, None, :].repeat(3, axis=1), axis=2)  # (F,3,2)
    # Offset each projection direction differently so opposite sides do not look mirrored.
    uv = (uv + 0.5 + 0.37 * axis[:, None, None]) * tiles
    new_faces = np.arange(3 * len(faces)).reshape(-1, 3)
    return corners.reshape(-1, 3), new_faces, uv.reshape(-1, 2)
