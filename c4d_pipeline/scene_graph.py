"""The scene graph: which frame pairs the pointmap source sees and global alignment connects.

Videos use a strided sliding window (MonST3R's `swinstride-5-noncyclic`): frame i is paired with
frames i + o for offsets o in {start, start + stride, ..., start + stride * (window - 1)}, i.e.
{1, 3, 5, 7, 9} by default, then every pair is also added reversed (symmetric graph).
"""

from __future__ import annotations

import numpy as np

from c4d_core.errors import UserError


def window_offsets(window: int, stride: int, start: int = 1) -> list[int]:
    """Frame offsets of the strided window: start, start + stride, ... (`window` of them)."""
    if window < 1 or stride < 1 or start < 1:
        raise UserError(
            f"scene graph: window ({window}), stride ({stride}) and start ({start}) must be >= 1"
        )
    return list(range(start, start + stride * window, stride))


def strided_window_pairs(
    num_frames: int, window: int = 5, stride: int = 2, start: int = 1, symmetric: bool = True
) -> np.ndarray:
    """Edges of the strided sliding-window graph over `num_frames` frames.

    Returns int64 (E,2) pairs (i, j): first every forward pair sorted by (i, j), then (if
    `symmetric`) the same pairs reversed in the same order, so edge e + E/2 is edge e reversed.
    Raises `UserError` when the video is too short to give a connected graph (fewer than 2
    frames, or no pair of offset 1 when start > 1 leaves frames unconnected).
    """
    if num_frames < 2:
        raise UserError(
            f"the video has {num_frames} frame(s); the scene graph needs at least 2 frames "
            "(use a longer video)"
        )
    offsets = window_offsets(window, stride, start)
    forward = [(i, i + o) for i in range(num_frames) for o in offsets if i + o < num_frames]
    forward.sort()
    if not forward or not is_connected(num_frames, forward):
        raise UserError(
            f"the scene graph with offsets {offsets} does not connect all {num_frames} frames; "
            "use a longer video or set graph.start=1"
        )
    pairs = forward + [(j, i) for i, j in forward] if symmetric else forward
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def is_connected(num_frames: int, pairs) -> bool:
    """True when the undirected graph of `pairs` over frames 0..num_frames-1 is connected."""
    parent = list(range(num_frames))

    def root(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for i, j in pairs:
        parent[root(int(i))] = root(int(j))
    return len({root(a) for a in range(num_frames)}) == 1


def graph_from_config(num_frames: int, cfg) -> np.ndarray:
    """Edges from the `graph` section of a c4d config (window, stride, start, symmetric)."""
    return strided_window_pairs(num_frames, cfg.window, cfg.stride, cfg.start, cfg.symmetric)


def frame_neighbours(edges: np.ndarray, num_frames: int) -> list[list[int]]:
    """For every frame, the sorted frames it is paired with in the graph (either direction)."""
    neighbours: list[set[int]] = [set() for _ in range(num_frames)]
    for i, j in np.asarray(edges):
        neighbours[int(i)].add(int(j))
        neighbours[int(j)].add(int(i))
    return [sorted(n) for n in neighbours]
