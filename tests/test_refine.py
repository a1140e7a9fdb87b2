"""dynpt/refine.py and dynpt/postprocess.py: Lucas-Kanade, frame to frame, puts a tracker's noisy
tracks of a textured, sub-pixel translating video back on the true points (across an occlusion
too), keeps what it cannot check, and the post-processing reads the fused mobility from the
refined tracks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt.inference import TrackResult
from dynpt.postprocess import Postprocess, PostprocessedTracker
from dynpt.refine import TrackRefinement, refine_tracks
from dynpt.track_mobility import EpipolarMobility, fuse_mobility

H, W, T = 96, 128, 8
FLAT_X = 96  # columns from here on are one flat grey: nothing for Lucas-Kanade to lock onto


def translating_video(seed: int = 0):
    """uint8 (T,H,W,3) of a smooth random texture shifted by a sub-pixel offset each frame, and
    the offsets (T,2) px: a point (x, y) of frame 0 lies at (x, y) + offsets[t] in frame t."""
    rng = np.random.default_rng(seed)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 2.0)
    base = (base - base.min()) / (base.max() - base.min()) * 255
    offsets = np.cumsum(rng.uniform(-1.5, 1.5, (T, 2)), 0)
    offsets[0] = 0
    frames = []
    for dx, dy in offsets:
        frame = cv2.warpAffine(base, np.float32([[1, 0, dx], [0, 1, dy]]), (W, H),
                               flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
        frame[:, FLAT_X:] = 128
        frames.append(np.repeat(np.clip(frame, 0, 255).astype(np.uint8)[..., None], 3, -1))
    return np.stack(frames), offsets


def truth_and_noisy(offsets, seed: int = 1, num: int = 60):
    """True tracks (T,N,2) of points queried at frame 0 or 3, the tracker's stand-in (true + 1.5
    px noise, exact at the query frame) and the queries (N,3) as (t, x, y)."""
    rng = np.random.default_rng(seed)
    start = np.stack([rng.uniform(16, W - 16, num), rng.uniform(16, H - 16, num)], -1)  # frame-0 points
    truth = start[None] + offsets[:, None]  # (T,N,2)
    query_frame = np.where(np.arange(num) % 2 == 0, 0, 3)
    noisy = truth + rng.normal(0.0, 1.5, truth.shape)
    noisy[query_frame, np.arange(num)] = truth[query_frame, np.arange(num)]
    queries = np.concatenate([query_frame[:, None], truth[query_frame, np.arange(num)]], 1)
    return truth, noisy.astype(np.float32), queries.astype(np.float32)


def test_refinement_lands_on_the_true_points_and_keeps_what_it_cannot_check():
    video, offsets = translating_video()
    truth, noisy, queries = truth_and_noisy(offsets)
    visible = np.ones(noisy.shape[:2], bool)
    visible[5, :10] = False  # said occluded: left alone
    refined, confirmed = refine_tracks(video, noisy, visible, queries, TrackRefinement())
    textured = truth[0, :, 0] < FLAT_X - 12  # (N,) points whose window lies on the texture
    flat = truth[0, :, 0] > FLAT_X + 12
    before = np.linalg.norm(noisy - truth, axis=-1)[:, textured]
    after = np.linalg.norm(refined - truth, axis=-1)[:, textured]
    assert np.median(before) > 1.0 and np.median(after) < 0.1, (np.median(before), np.median(after))
    assert np.percentile(after, 95) < 0.3
    assert np.array_equal(refined[5, :10], noisy[5, :10])  # occluded frames
    # after the occlusion a track is matched from its last trusted frame, not from the tracker's
    # noisy guess in the occluded one: it is back on its point
    after_gap = np.linalg.norm(refined[6, :10] - truth[6, :10], axis=-1)[textured[:10]]
    assert len(after_gap) >= 3 and after_gap.max() < 0.2, after_gap
    query_frame = queries[:, 0].astype(int)
    assert np.array_equal(refined[query_frame, np.arange(len(queries))],
                          noisy[query_frame, np.arange(len(queries))])
    assert flat.any() and np.array_equal(refined[:, flat], noisy[:, flat])  # the check fails there
    # confirmed: the query frames and every position Lucas-Kanade set, nothing else
    assert confirmed[query_frame, np.arange(len(queries))].all()
    not_query = np.arange(len(confirmed))[:, None] != query_frame[None]  # (T,N)
    assert not confirmed[5, :10].any() and not (confirmed & not_query)[:, flat].any()
    assert confirmed[:, textured].mean() > 0.95
    assert not ((refined != noisy).any(-1) & ~confirmed).any()  # what moved was confirmed
    again = refine_tracks(torch.from_numpy(video), noisy, visible, queries, TrackRefinement())
    # deterministic, torch frames alike
    assert np.array_equal(again[0], refined) and np.array_equal(again[1], confirmed)


class FixedTracker:
    device = "cpu"

    def __init__(self, result: TrackResult):
        self.result = result

    def track(self, video, queries=None, **kwargs) -> TrackResult:
        return self.result


def test_the_post_processing_refines_then_fuses_and_the_config_is_checked():
    video, offsets = translating_video()
    _, noisy, queries = truth_and_noisy(offsets)
    visible = np.ones(noisy.shape[:2], bool)
    head = np.full(visible.shape, 0.5, np.float32)
    result = TrackResult(tracks=noisy, visible=visible, confidence=np.ones(visible.shape, np.float32),
                         moving=head, queries=queries)
    cfg = load_config("dynpt", "tiny-cpu", overrides=["eval.refine=lk", "eval.mobility=epipolar"]).eval
    post = Postprocess.from_config(cfg)
    assert post == Postprocess(TrackRefinement(), EpipolarMobility())
    wrapped = PostprocessedTracker(FixedTracker(result), post)
    out = wrapped.track(video)
    assert wrapped.device == "cpu"
    refined, confirmed = refine_tracks(video, noisy, visible, queries, TrackRefinement())
    assert np.array_equal(out.tracks, refined) and out.visible is visible
    # the geometry reads only the positions Lucas-Kanade confirmed
    assert not confirmed.all()
    assert np.array_equal(out.moving, fuse_mobility(refined, confirmed, head, EpipolarMobility()),
                          equal_nan=True)
    fused_only = PostprocessedTracker(FixedTracker(result), Postprocess(None, EpipolarMobility()))
    assert np.array_equal(fused_only.track(video).moving,  # unrefined: every visible position
                          fuse_mobility(noisy, visible, head, EpipolarMobility()), equal_nan=True)
    plain = PostprocessedTracker(FixedTracker(result), Postprocess.from_config(
        load_config("dynpt", "tiny-cpu").eval)).track(video)
    assert plain is result  # the defaults change nothing
    with pytest.raises(UserError, match="eval.refine"):
        load_config("dynpt", "tiny-cpu", overrides=["eval.refine=klt"])
    with pytest.raises(UserError, match="eval.lk.window"):
        load_config("dynpt", "tiny-cpu", overrides=["eval.lk.window=1"])
