"""What may be done to a tracker's result before it is scored or shown: refine its tracks
photometrically (`dynpt.refine`, the dynpt configs' `eval.refine`) and fuse its head's mobility
with the tracks' epipolar geometry (`dynpt.track_mobility`, `eval.mobility`), in that order: the
geometry is read from the refined tracks. Neither needs weights or changes the network's output
otherwise; `c4d eval`, `c4d track` and `c4d demo` apply them as their settings say.

The geometry reads only positions it can trust: without refinement every visible one; with it,
those Lucas-Kanade confirmed (the others are the tracker's, a few px off: a static point whose
track went astray would read as a moving one)."""

from __future__ import annotations

from dataclasses import dataclass, replace

from dynpt.inference import check_video
from dynpt.refine import TrackRefinement, refine_tracks
from dynpt.track_mobility import EpipolarMobility, fuse_mobility


@dataclass(frozen=True)
class Postprocess:
    """refinement: None (the tracker's tracks) or the Lucas-Kanade settings; mobility: None (the
    head's) or the fused mobility's settings."""

    refinement: TrackRefinement | None = None
    mobility: EpipolarMobility | None = None

    @classmethod
    def from_config(cls, eval_cfg) -> "Postprocess":
        """As a dynpt config's `eval` says: `refine` (none | lk, with `lk`'s settings) and
        `mobility` (head | epipolar, with `epipolar`'s)."""
        return cls(TrackRefinement(**eval_cfg.lk) if eval_cfg.refine == "lk" else None,
                   EpipolarMobility(**eval_cfg.epipolar) if eval_cfg.mobility == "epipolar" else None)

    def __call__(self, result, video):
        """`result` (a `dynpt.inference.TrackResult` of `video` uint8 (T,H,W,3)) post-processed:
        its tracks refined and its `moving` fused as the settings say; visibility and confidence
        unchanged."""
        trusted = result.visible  # (T,N) bool: the positions the fused mobility's geometry reads
        if self.refinement is not None:
            tracks, trusted = refine_tracks(video, result.tracks, result.visible, result.queries,
                                            self.refinement)
            result = replace(result, tracks=tracks)
        if self.mobility is not None:
            result = replace(result, moving=fuse_mobility(result.tracks, trusted, result.moving,
                                                          self.mobility))
        return result


class PostprocessedTracker:
    """A tracker whose results are `post`-processed; everything else is the wrapped tracker's."""

    def __init__(self, tracker, post: Postprocess):
        self.tracker, self.post = tracker, post

    def __getattr__(self, name: str):  # the wrapped tracker's device, model, ...
        return getattr(self.tracker, name)

    def track(self, video, *args, **kwargs):
        video = check_video(video)  # a path is read once, here
        return self.post(self.tracker.track(video, *args, **kwargs), video)

