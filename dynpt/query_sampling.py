"""The paper's query sampling: per grid cell, the max-gradient pixel plus one random pixel."""

from __future__ import annotations

import cv2
import numpy as np


def sample_queries(frame: np.ndarray, grid_size: int = 20, seed: int = 0, frame_index: int = 0) -> np.ndarray:
    """Query points on one RGB uint8 frame (H,W,3): float32 (N,3) as (t, x, y) pixels.

    The image is cut into `grid_size` x `grid_size` cells (partial cells at the right and bottom
    borders included); each cell contributes the pixel of maximum image-gradient magnitude (Sobel
    on grey levels; the first one in row-major order on ties) and one uniformly random pixel
    (seeded by `seed`). N = 2 * number of cells; the points of a cell are consecutive.
    """
    H, W = frame.shape[:2]
    g = grid_size
    grey = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY).astype(np.float32)
    grad = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3))
    rows, cols = -(-H // g), -(-W // g)
    padded = np.full((rows * g, cols * g), -1.0, np.float32)  # padding never wins the argmax
    padded[:H, :W] = grad
    cells = padded.reshape(rows, g, cols, g).transpose(0, 2, 1, 3).reshape(rows, cols, g * g)
    best = cells.argmax(axis=-1)  # (rows, cols) index inside each cell
    cy, cx = np.meshgrid(np.arange(rows) * g, np.arange(cols) * g, indexing="ij")  # cell corners
    max_x, max_y = cx + best % g, cy + best // g

    rng = np.random.default_rng(seed)
    width = np.minimum(g, W - cx)  # (rows, cols) extent of the (possibly partial) cell
    height = np.minimum(g, H - cy)
    rand_x = cx + (rng.random(cx.shape) * width).astype(np.int64)
    rand_y = cy + (rng.random(cy.shape) * height).astype(np.int64)

    xy = np.stack([np.stack([max_x, max_y], -1), np.stack([rand_x, rand_y], -1)], axis=2)  # (r,c,2,2)
    xy = xy.reshape(-1, 2).astype(np.float32)
    t = np.full((len(xy), 1), frame_index, np.float32)
    return np.concatenate([t, xy], axis=1)
