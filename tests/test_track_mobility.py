"""dynpt/track_mobility.py: a track's epipolar residual pooled over time calls the points of a
sliding box moving through tracking noise that hides them frame by frame, and fuses with the head."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from benchmarks.mobility_cue import epipolar_cue, ranking
from c4d_core.config import load_config
from c4d_core.errors import UserError
from dynpt.inference import TrackResult
from dynpt.track_mobility import (EpipolarMobility, fuse_mobility, nanpercentile_columns,
                                  pair_distances)
from tests.synthetic_scenes import make_box_scene

UNDECIDED = 0.5  # a head that says nothing
GEOMETRY_ALONE = 2.0  # residual_sigmas for head_weight 0 (the config's comment)


def box_tracks(noise_px: float, moving: bool = True, seed: int = 3):
    scene = make_box_scene(num_frames=16, height=96, width=128, num_tracks=256, seed=seed, moving=moving)
    clip = scene.tracks_time_major()
    tracks = clip["tracks"].astype(np.float64)
    tracks = tracks + np.random.default_rng(seed).normal(0.0, noise_px, tracks.shape)
    return tracks, ~clip["occluded"], clip["moving"]


def balanced(called: np.ndarray, labels: np.ndarray) -> float:
    return (called[labels].mean() + (~called[~labels]).mean()) / 2


def test_pooling_over_time_sees_the_sliding_box_through_noise_the_per_frame_cue_does_not():
    tracks, visible, moving = box_tracks(noise_px=0.5)
    assert 0.02 < moving[visible].mean() < 0.6
    per_frame = ranking(epipolar_cue(tracks, visible)[visible], moving[visible])
    geometry = EpipolarMobility(head_weight=0.0, residual_sigmas=GEOMETRY_ALONE)
    fused = fuse_mobility(tracks, visible, np.full(visible.shape, UNDECIDED, np.float32), geometry)
    pooled = ranking(fused[visible], moving[visible])
    assert per_frame["auc"] < 0.75 and pooled["auc"] > 0.95, (per_frame, pooled)
    assert balanced(fused[visible] > 0.5, moving[visible]) > 0.85


def test_a_static_scene_is_called_static_and_the_head_weighs_in():
    tracks, visible, _ = box_tracks(noise_px=0.5, moving=False)
    head = np.full(visible.shape, UNDECIDED, np.float32)
    geometry = EpipolarMobility(head_weight=0.0, residual_sigmas=GEOMETRY_ALONE)
    assert (fuse_mobility(tracks, visible, head, geometry)[visible] < 0.5).mean() > 0.9
    static_head = np.full(visible.shape, 0.02, np.float32)  # a trained head on static points
    assert (fuse_mobility(tracks, visible, static_head, EpipolarMobility())[visible] < 0.5).mean() > 0.9
    sure = np.full(visible.shape, 0.999, np.float32)  # a head sure of motion outweighs geometry
    loud = EpipolarMobility(head_weight=2.0)
    assert (fuse_mobility(tracks, visible, sure, loud)[visible] > 0.5).all()


def test_frames_not_predicted_stay_nan_and_too_few_tracks_keep_the_head():
    tracks, visible, _ = box_tracks(noise_px=0.5)
    head = np.full(visible.shape, 0.8, np.float32)
    head[:3, :10] = np.nan  # not predicted (e.g. before the query frame without backward tracking)
    fused = fuse_mobility(tracks, visible, head, EpipolarMobility())
    assert np.isnan(fused[:3, :10]).all() and np.isfinite(fused[3:]).all()
    few = fuse_mobility(tracks[:, :5], visible[:, :5], head[:, :5], EpipolarMobility(head_weight=0.0))
    assert np.isnan(pair_distances(tracks[:, :5], visible[:, :5], 3)).all()  # no matrix from 5 tracks
    np.testing.assert_allclose(few[3:], 0.8, atol=1e-6)  # no geometry, no weight: the head's own


def test_the_settings_are_checked():
    with pytest.raises(UserError, match="eval.epipolar.offset"):
        load_config("dynpt", "tiny-cpu", overrides=["eval.epipolar.offset=0"])
    with pytest.raises(UserError, match="eval.mobility"):
        load_config("dynpt", "tiny-cpu", overrides=["eval.mobility=flow"])


def test_the_pooled_percentile_equals_numpys_nanpercentile_to_the_bit():
    """The vectorised percentile the pooling uses gives np.nanpercentile's values exactly: column
    lengths 1..29 after NaNs, all-NaN columns, quantiles at, between and beyond the samples."""
    rng = np.random.default_rng(0)
    for _ in range(400):
        values = rng.gamma(1.0, 2.0, (rng.integers(1, 30), rng.integers(1, 40)))
        values[rng.random(values.shape) < rng.uniform(0, 0.9)] = np.nan
        for q in (0.0, 33.3, 50.0, 75.0, 100.0, float(rng.uniform(0, 100))):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # "All-NaN slice encountered"
                expected = np.nanpercentile(values, q, axis=0)
            np.testing.assert_array_equal(nanpercentile_columns(values, q), expected)
