"""benchmarks/mobility_cue.py's epipolar cue: on exact tracks of a scene with a sliding box it
ranks the moving point-frames (the labels follow from geometry); noise in the tracks blurs it."""

from __future__ import annotations

import numpy as np

from benchmarks.mobility_cue import best_balanced, epipolar_cue, image_motion, ranking
from tests.synthetic_scenes import make_box_scene


def test_the_epipolar_cue_separates_moving_points_of_exact_tracks_and_noise_blurs_it():
    scene = make_box_scene(num_frames=12, height=96, width=128, num_tracks=256, seed=3)
    clip = scene.tracks_time_major()
    tracks, visible, moving = clip["tracks"].astype(np.float64), ~clip["occluded"], clip["moving"]
    assert 0.02 < moving[visible].mean() < 0.6  # the sliding box
    exact = ranking(epipolar_cue(tracks, visible)[visible], moving[visible])
    assert exact["auc"] > 0.97 and exact["best_balanced"] > 0.93, exact
    noisy = tracks + np.random.default_rng(0).normal(0.0, 2.0, tracks.shape)
    blurred = ranking(epipolar_cue(noisy, visible)[visible], moving[visible])
    assert blurred["auc"] < exact["auc"] - 0.05, (exact, blurred)


def test_best_balanced_and_image_motion():
    labels = np.array([True, True, False, False, False])
    assert best_balanced(np.array([0.9, 0.8, 0.1, 0.2, 0.3]), labels) == 1.0
    assert best_balanced(np.zeros(5), labels) == 0.5
    tracks = np.zeros((3, 1, 2))
    tracks[:, 0, 0] = [0.0, 2.0, 4.0]  # 2 px a frame
    np.testing.assert_allclose(image_motion(tracks)[:, 0], [2.0, 2.0, 2.0])
