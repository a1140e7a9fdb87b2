"""Sub-pixel refinement of a tracker's tracks by pyramidal Lucas-Kanade, frame to frame.

A small tracker trained for minutes on a CPU lands near the right point but not on it: on the
paper's D-ACC protocol (256x256, 24 frames) the demo's tracker is off by a median 1.5-2.1 px on
static points and 7 px on moving ones, which hides the epipolar motion cue
(`dynpt.track_mobility`) of a point moving 1-2 px a frame. The frames say where the point is more
precisely. Each track is followed from its query point outwards, forward and backward in time;
from the last frame s where it was trusted (at first the query frame) to the next frame t:
  1. Lucas-Kanade (OpenCV's pyramidal, `window` x `window` px, `levels` levels above the frame)
     matches the patch around the track's position at s in frame t, starting from that position
     moved by the tracker's own displacement from s to t;
  2. Lucas-Kanade back from the result to frame s must land within `max_backward_px` of where it
     started (forward-backward check), and the tracker must call the point visible at t; then the
     result is the track's position at t and t the frame the next step starts from; else the
     tracker's position stays, and the next frame is matched from s again (the last frame where
     the track was trusted: across an occlusion, the point it was on before).
Frame to frame the patch barely changes, so points on tumbling objects are followed where a
comparison with the query frame alone would fail. The query frame keeps the query point;
visibility, confidence and mobility are not touched. Deterministic (no sampling).

Besides the positions it says which of them Lucas-Kanade confirmed (both checks passed, and each
query frame): the others are the tracker's, a few px off, and a sub-pixel cue such as the fused
mobility (`dynpt.postprocess`) reads only the confirmed ones.
"""

from __future__ import annotations

from dataclasses import dataclass

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
    max_backward_px: float  # forward-backward check: largest distance back to the start


def refine_tracks(video: np.ndarray, tracks: np.ndarray, visible: np.ndarray,
                  queries: np.ndarray, settings: TrackRefinement) -> tuple[np.ndarray, np.ndarray]:
    """(refined float32 (T,N,2) px, confirmed bool (T,N)): `tracks` (T,N,2) (x, y) px of `video`
    uint8 (T,H,W,3), refined where `visible` (T,N) bool says visible, and the frames whose
    position Lucas-Kanade confirmed or that are the track's query frame (see the module); queries
    float (N,3) as (t, x, y)."""
    video = video.cpu().numpy() if hasattr(video, "cpu") else np.asarray(video)  # torch or numpy
    grey = [cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2GRAY) for frame in video]  # T x (H,W)
    tracks = np.asarray(tracks, np.float32)
    refined = tracks.copy()  # (T,N,2)
    query_frame = np.rint(queries[:, 0]).astype(int)  # (N,)
    confirmed = np.zeros(tracks.shape[:2], bool)  # (T,N)
    confirmed[query_frame, np.arange(len(query_frame))] = True
    lk = dict(winSize=(settings.window, settings.window), maxLevel=settings.levels,
              criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
              flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
    for q in np.unique(query_frame):
        tracked = np.flatnonzero(query_frame == q)  # (M,) the tracks queried at frame q
        for step in (1, -1):  # forward, then backward in time
            anchor = np.full(len(tracked), q)  # (M,) each track's last trusted frame
            position = queries[tracked, 1:].astype(np.float32)  # (M,2) its position there
            for t in range(q + step, len(grey) if step > 0 else -1, step):
                for a in np.unique(anchor):  # one Lucas-Kanade call per anchor frame
                    group = np.flatnonzero(anchor == a)  # (K,)
                    index = tracked[group]
                    start = position[group].reshape(-1, 1, 2)  # (K,1,2)
                    guess = start + (tracks[t, index] - tracks[a, index]).reshape(-1, 1, 2)
                    forward, ok, _ = cv2.calcOpticalFlowPyrLK(grey[a], grey[t], start, guess, **lk)
                    back, ok_back, _ = cv2.calcOpticalFlowPyrLK(grey[t], grey[a], forward.copy(),
                                                                start.copy(), **lk)
                    returned = np.linalg.norm((back - start)[:, 0], axis=1) <= settings.max_backward_px
                    good = ((ok[:, 0] == 1) & (ok_back[:, 0] == 1) & returned & visible[t, index]
                            & np.isfinite(forward[:, 0]).all(1))  # (K,)
                    refined[t, index[good]] = forward[good, 0]
                    confirmed[t, index[good]] = True
                    anchor[group[good]], position[group[good]] = t, forward[good, 0]
    return refined, confirmed

