"""Trivial trackers that give the metrics a floor: what a number means next to doing nothing."""

from __future__ import annotations

import numpy as np

from dynpt.inference import TrackResult


class ZeroMotionBaseline:
    """Every point stays at its query position, always visible, never moving in the world.

    This is TAP-Vid's zero-motion baseline and, for D-ACC, the "everything is static" answer.
    Same `track(video, queries)` interface as `dynpt.inference.Tracker`.
    """

    def track(self, video, queries) -> TrackResult:
        """video (T,H,W,3); queries float (N,3) as (t, x, y) pixels."""
        num_frames = len(video)
        queries = np.asarray(queries, np.float32)  # (N,3)
        tracks = np.broadcast_to(queries[None, :, 1:], (num_frames, len(queries), 2))  # (T,N,2)
        ones = np.ones((num_frames, len(queries)), np.float32)
        return TrackResult(tracks=tracks.copy(), visible=ones.astype(bool), confidence=ones,
                           moving=np.zeros_like(ones), queries=queries)
