"""Sub-pixel refinement of a tracker's tracks by pyramidal Lucas-Kanade against the query frame.

A small tracker trained for minutes on a CPU lands near the right point but not on it: on the
paper's D-ACC protocol (256x256, 24 frames) the demo's tracker is off by a median 1.8 px on static
points, which hides the epipolar motion cue (`dynpt.track_mobility`) of a point moving 1-2 px a
frame. The image around the query point says where the point is more precisely. For each track
and each frame t where the tracker calls it visible:
  1. Lucas-Kanade (OpenCV's pyramidal, `window` x `window` px, `levels` levels above the frame)
     moves the tracker's position at t onto the patch around the query point in the query frame;
  2. Lucas-Kanade back from that position to the query frame must land within `max_backward_px`
     of the query point (forward-backward check), or the tracker's position stays.
Occluded frames, the query frame and tracks whose check fails keep the tracker's positions;
visibility, confidence and mobility are not touched. Deterministic (no sampling).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from c4d_core.config import defaults_from


@dataclass(frozen=True)
@defaults_from("dynpt", "eval.lk")
class TrackRefinement:
    """Settings of the refinement: the keys of the dynpt configs' `eval.lk`, where each is
    explained; the defaults are that file's (the schema's)."""

    window: int  # px, side of the patch Lucas-Kanade matches
    levels: int  # pyramid levels above the frame (0: the frame only)
    max_backward_px: float  # forward-backward check: largest distance back to the query point


def refine_tracks(video: np.ndarray, tracks: np.ndarray, visible: np.ndarray,
                  queries: np.ndarray, settings: TrackRefinement) -> np.ndarray:
    """float32 (T,N,2) px: `tracks` (T,N,2) (x, y) px of `video` uint8 (T,H,W,3), refined where
    `visible` (T,N) bool says visible (see the module); queries float (N,3) as (t, x, y)."""
    video = video.cpu().numpy() if hasattr(video, "cpu") else np.asarray(video)  # torch or numpy
    grey = [cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY) for frame in video]  # T x (H,W)
    refined = np.array(tracks, np.float32, copy=True)  # (T,N,2)
    size, levels = (settings.window, settings.window), settings.levels
    stop = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    query_frame = np.rint(queries[:, 0]).astype(int)  # (N,)
    for q in np.unique(query_frame):
        tracked = np.flatnonzero(query_frame == q)  # (M,) the tracks queried at frame q
        start = queries[tracked, 1:].astype(np.float32).reshape(-1, 1, 2)  # (M,1,2)
        for t in range(len(grey)):
            shown = tracked[visible[t, tracked]] if t != q else tracked[:0]  # (K,)
            if len(shown) == 0:
                continue
            origin = start[visible[t, tracked]]  # (K,1,2)
            guess = refined[t, shown].reshape(-1, 1, 2).copy()  # (K,1,2)
            forward, ok, _ = cv2.calcOpticalFlowPyrLK(
                grey[q], grey[t], origin, guess, winSize=size, maxLevel=levels, criteria=stop,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            back, ok_back, _ = cv2.calcOpticalFlowPyrLK(
                grey[t], grey[q], forward.copy(), origin.copy(), winSize=size, maxLevel=levels,
                criteria=stop, flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            returned = np.linalg.norm((back - origin)[:, 0], axis=1) <= settings.max_backward_px  # (K,)
            good = (ok[:, 0] == 1) & (ok_back[:, 0] == 1) & returned & np.isfinite(forward[:, 0]).all(1)
            refined[t, shown[good]] = forward[good, 0]
    return refined


def refined_result(result, video: np.ndarray, settings: TrackRefinement):
    """`result` (a `dynpt.inference.TrackResult` of `video` uint8 (T,H,W,3)) with
    `refine_tracks`'s positions; visibility, confidence and mobility unchanged."""
    return replace(result, tracks=refine_tracks(video, result.tracks, result.visible,
                                                result.queries, settings))
