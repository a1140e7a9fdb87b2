"""Motion masks: Sampson distance by hand, C4D's correspondence-guided mask separating a moving box,
the fallbacks, the flow-only (ego-flow) baseline and the ground-truth masks."""

import logging

import numpy as np
import pytest
import torch

from c4d_core.epipolar import sampson_distance
from c4d_core.errors import UserError
from c4d_core.geometry import pixel_grid
from c4d_pipeline.eval_metrics import mask_iou
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import GroundTruthPointmaps, ground_truth_motion_masks, oracle_tracks
from c4d_pipeline.motion_mask import (
    MotionMaskConfig,
    correspondence_motion_masks,
    ego_flow,
    flow_only_motion_masks,
    guided_filter,
    pair_motion_mask,
    pairwise_ego_flow,
)
from c4d_pipeline.scene_graph import strided_window_pairs
from tests.synthetic_scenes import make_box_scene

MOVING_BOX = 3  # make_box_scene's sliding box is its third object


@pytest.fixture(scope="module")
def scene():
    return make_box_scene(num_frames=6, height=48, width=64, num_tracks=300, seed=2)


@pytest.fixture(scope="module")
def graph(scene):
    pairs = [tuple(p) for p in strided_window_pairs(scene.num_frames, window=2, stride=2)]
    return pairs, build_flow("gt", scene=scene).flow(scene.rgb, pairs)


def test_sampson_distance_of_a_sideways_translation():
    # camera translating along x with K = I: F = [e]x with e = (1, 0, 0); epipolar lines are rows
    fundamental = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    x1 = np.array([[10.0, 5.0], [3.0, 7.0], [0.0, 0.0]])
    x2 = np.array([[14.0, 5.0], [3.0, 9.0], [-5.0, -3.0]])  # along the row, 2 px off, 3 px off
    np.testing.assert_allclose(sampson_distance(fundamental, x1, x2), [0.0, 2 / np.sqrt(2), 3 / np.sqrt(2)])
    np.testing.assert_allclose(sampson_distance(7.0 * fundamental, x1, x2), sampson_distance(fundamental, x1, x2))


def test_ground_truth_masks_are_the_sliding_box(scene):
    masks = ground_truth_motion_masks(scene)
    np.testing.assert_array_equal(masks, scene.segmentation == MOVING_BOX)


def test_correspondence_mask_separates_the_moving_box(scene, graph):
    pairs, flows = graph
    result = correspondence_motion_masks(oracle_tracks(scene), flows, pairs)
    assert {info["method"] for info in result.pair_info} == {"static"}
    truth = ground_truth_motion_masks(scene)
    assert mask_iou(result.masks, truth)["iou"] > 0.95
    static_boxes = (scene.segmentation == 1) | (scene.segmentation == 2)
    assert result.masks[static_boxes].mean() < 0.01


def test_correspondence_mask_survives_flow_noise(scene, graph):
    pairs, flows = graph
    noisy = flows + np.random.default_rng(0).normal(0, 0.15, flows.shape).astype(np.float32)
    result = correspondence_motion_masks(oracle_tracks(scene), noisy, pairs, MotionMaskConfig(sampson_threshold_px=0.6))
    assert mask_iou(result.masks, ground_truth_motion_masks(scene))["iou"] > 0.6


def test_torch_tracker_output_with_a_batch_dimension_gives_the_same_masks(scene, graph):
    pairs, flows = graph
    oracle = oracle_tracks(scene)

    class Batched:  # what a torch tracker returns: (1,T,N,...) tensors
        tracks = torch.from_numpy(oracle.tracks)[None]
        visible = torch.from_numpy(oracle.visible)[None]
        confidence = torch.from_numpy(oracle.confidence)[None]
        moving = torch.from_numpy(oracle.moving)[None]

    np.testing.assert_array_equal(
        correspondence_motion_masks(Batched(), flows, pairs).masks, correspondence_motion_masks(oracle, flows, pairs).masks
    )


def test_too_few_static_points_falls_back_to_all_flow_and_warns(scene, graph, caplog):
    pairs, flows = graph
    tracks = oracle_tracks(scene)
    tracks.moving = np.ones_like(tracks.moving)  # the tracker calls everything moving
    with caplog.at_level(logging.WARNING):
        result = correspondence_motion_masks(tracks, flows, pairs)
    assert {info["method"] for info in result.pair_info} == {"all-flow"}
    assert "fewer than 16 static points" in caplog.text
    # the box covers a few percent of the frame, so LMedS on all correspondences still finds it
    assert mask_iou(result.masks, ground_truth_motion_masks(scene))["iou"] > 0.8


def test_degenerate_inputs_never_crash():
    flow = np.zeros((32, 40, 2), np.float32)
    mask, info = pair_motion_mask(flow, np.zeros((0, 2)))  # no static points, no motion at all
    assert mask.shape == (32, 40) and info["method"] in ("all-flow", "failed")
    flow[10:20, 5:15] = (3.0, 0.0)  # a still camera and one moving patch
    static = np.stack(np.meshgrid(np.arange(20, 40, 2.0), np.arange(0, 32, 2.0)), -1).reshape(-1, 2)
    mask, info = pair_motion_mask(flow, static)
    assert info["method"] == "still"
    expected = np.zeros((32, 40), bool)
    expected[10:20, 5:15] = True
    np.testing.assert_array_equal(mask, expected)


def test_mismatched_inputs_are_user_errors(scene, graph):
    pairs, flows = graph
    with pytest.raises(UserError, match="for 3 pairs"):
        correspondence_motion_masks(oracle_tracks(scene), flows, pairs[:3])
    with pytest.raises(UserError, match="outside"):
        correspondence_motion_masks(oracle_tracks(scene), flows[:1], [(0, 9)])
    bad = flows.copy()
    bad[0, 0, 0, 0] = np.nan
    with pytest.raises(UserError, match="NaN"):
        correspondence_motion_masks(oracle_tracks(scene), bad, pairs)


def test_ego_flow_is_the_flow_of_static_pixels(scene):
    flow = build_flow("gt", scene=scene).flow(scene.rgb, [(1, 4)])[0]
    ego = ego_flow(scene.depth[1], scene.intrinsics[1], scene.intrinsics[4], scene.cam_to_world[1], scene.cam_to_world[4])
    static = scene.segmentation[1] != MOVING_BOX
    np.testing.assert_allclose(ego[static], flow[static], atol=1e-3)
    assert np.abs(ego[~static] - flow[~static]).max() > 1.0


def test_flow_only_baseline_with_exact_geometry_finds_the_box(scene, graph):
    pairs, flows = graph
    sc = scene
    egos = np.stack([ego_flow(sc.depth[i], sc.intrinsics[i], sc.intrinsics[j], sc.cam_to_world[i], sc.cam_to_world[j]) for i, j in pairs])
    result = flow_only_motion_masks(flows, egos, pairs, sc.num_frames)
    assert mask_iou(result.masks, ground_truth_motion_masks(sc))["iou"] > 0.95
    with pytest.raises(UserError, match="one per pair"):
        flow_only_motion_masks(flows, egos[:, :10], pairs, sc.num_frames)


def test_pairwise_ego_flow_from_clean_pointmaps_is_the_static_flow(scene):
    source = GroundTruthPointmaps(scene, depth_noise=0.0, smooth_noise=0.0, static_bias=False)
    pw = source.pointmaps(scene.rgb, np.array([[1, 4]]))
    ego = pairwise_ego_flow(pw.pts_i[0], pw.pts_j[0], pw.conf_j[0], scene.intrinsics[4])
    flow = build_flow("gt", scene=scene).flow(scene.rgb, [(1, 4)])[0]
    static = scene.segmentation[1] != MOVING_BOX
    np.testing.assert_allclose(ego[static], flow[static], atol=0.05)


def test_max_pair_offset_keeps_only_pairs_of_near_frames(scene, graph):
    pairs, flows = graph
    result = correspondence_motion_masks(oracle_tracks(scene), flows, pairs, MotionMaskConfig(max_pair_offset=1))
    used = [tuple(info["pair"]) for info in result.pair_info]
    assert used == [p for p in pairs if abs(p[0] - p[1]) == 1] and len(used) < len(pairs)
    assert mask_iou(result.masks, ground_truth_motion_masks(scene))["iou"] > 0.9


def test_flow_leaving_the_frame_is_not_judged_and_noise_raises_the_threshold(scene, graph):
    pairs, flows = graph
    flow, (i, _) = flows[0].copy(), pairs[0]
    flow[:, :6] = (-40.0, 13.0)  # nonsense flow pointing out of the frame on the left border
    static = oracle_tracks(scene).tracks[i][oracle_tracks(scene).moving[i] < 0.5]
    static = static[static[:, 0] > 8]  # the static points themselves are fine
    judged, _ = pair_motion_mask(flow, static, MotionMaskConfig(judge_out_of_view=True))
    skipped, info = pair_motion_mask(flow, static, MotionMaskConfig(judge_out_of_view=False))
    assert judged[:, :6].all() and not skipped[:, :6].any()
    assert info["threshold_px"] == MotionMaskConfig().sampson_threshold_px  # exact flow: no noise
    noisy = flows[0] + np.random.default_rng(1).normal(0, 1.0, flows[0].shape)
    _, info = pair_motion_mask(noisy, static, MotionMaskConfig(noise_sigmas=4.0))
    assert info["threshold_px"] == pytest.approx(4.0 * info["sigma_px"]) and info["threshold_px"] > 1.0


def test_forward_backward_check_leaves_broken_flow_unjudged(scene, graph):
    """A patch of nonsense flow in one direction breaks the epipolar constraint: the union marks it
    dynamic, the forward-backward check (the pair's reverse flow does not bring it back) does not."""
    from c4d_pipeline.motion_mask import forward_backward_error

    pairs, flows = graph
    tracks = oracle_tracks(scene)
    truth = ground_truth_motion_masks(scene)
    exact = correspondence_motion_masks(tracks, flows, pairs, MotionMaskConfig(forward_backward_px=1.0))
    assert mask_iou(exact.masks, truth)["iou"] > 0.9, "exact flow is consistent: nothing is dropped"
    p = pairs.index(next(pq for pq in pairs if (pq[1], pq[0]) in pairs))
    reverse = pairs.index((pairs[p][1], pairs[p][0]))
    assert np.median(forward_backward_error(flows[p], flows[reverse])) < 0.05
    broken = flows.copy()
    broken[p, 30:40, 5:15] += (6.0, -5.0)  # a flow failure on static floor pixels
    static_floor = ~truth[pairs[p][0], 30:40, 5:15]
    union = correspondence_motion_masks(tracks, broken, pairs, MotionMaskConfig())
    checked = correspondence_motion_masks(tracks, broken, pairs, MotionMaskConfig(forward_backward_px=1.0))
    assert union.masks[pairs[p][0], 30:40, 5:15][static_floor].mean() > 0.9
    assert not checked.masks[pairs[p][0], 30:40, 5:15][static_floor].any()
    assert any("inconsistent_fraction" in info for info in checked.pair_info)
    assert checked.masks[truth].mean() > 0.9, "the moving box stays"


def test_opening_removes_specks_and_closing_fills_holes(scene, graph):
    from dataclasses import replace

    pairs, flows = graph
    tracks, truth = oracle_tracks(scene), ground_truth_motion_masks(scene)
    speck = flows.copy()
    speck[:, 35, 8] += (5.0, -4.0)  # one pixel of nonsense flow on the floor, in every pair
    plain = correspondence_motion_masks(tracks, speck, pairs, MotionMaskConfig()).masks
    cleaned = correspondence_motion_masks(tracks, speck, pairs, replace(MotionMaskConfig(), open_px=3, close_px=3)).masks
    assert plain[:, 35, 8].any() and not cleaned[:, 35, 8].any()
    assert mask_iou(cleaned, truth)["iou"] > 0.9


def test_guided_filter_moves_a_spilled_mask_onto_the_object():
    """A mask that spills 3 px onto a textured floor around a coloured object and misses a bite
    inside it (what DIS's smoothed flow gives) is brought back to the object's outline."""
    import cv2

    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.standard_normal((96, 128)).astype(np.float32), (0, 0), 2.0)
    frame = np.clip(110 + 60 * texture[..., None] * np.array([1.0, 0.9, 1.1]), 0, 255)  # (H,W,3)
    obj = np.zeros((96, 128), np.uint8)
    cv2.ellipse(obj, (64, 48), (28, 16), 20, 0, 360, 1, -1)
    obj = obj > 0
    frame[obj] = (200, 60, 40)
    spilled = cv2.dilate(obj.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
    spilled[44:52, 60:68] = False  # a hole inside the object
    refined = guided_filter(frame / 255, spilled.astype(np.float32), radius=11, eps=1e-3) >= 0.5
    assert mask_iou(spilled, obj)["iou"] < 0.7
    assert mask_iou(refined, obj)["iou"] > 0.95
    assert refined[44:52, 60:68].all(), "the hole inside the object is filled"


def test_temporal_vote_drops_a_one_frame_speck_and_restores_a_missed_frame(scene):
    """With the neighbouring frames voting (their masks brought over by exact flow), a speck of
    nonsense flow in one frame goes, and a frame whose own pairs missed the box gets it back."""
    from dataclasses import replace

    from c4d_pipeline.motion_mask import refine_masks

    pairs = [(t, t + d) for t in range(scene.num_frames) for d in (-1, 1) if 0 <= t + d < scene.num_frames]
    flows = build_flow("gt", scene=scene).flow(scene.rgb, pairs)
    tracks, truth = oracle_tracks(scene), ground_truth_motion_masks(scene)
    cfg = replace(MotionMaskConfig(), temporal_neighbours=1)
    speck = flows.copy()
    for p, (i, _) in enumerate(pairs):
        if i == 2:
            speck[p, 35:37, 8:10] += (5.0, -4.0)  # nonsense flow on the floor, in frame 2's pairs only
    plain = correspondence_motion_masks(tracks, speck, pairs).masks
    voted = correspondence_motion_masks(tracks, speck, pairs, cfg).masks
    assert plain[2, 35:37, 8:10].all() and not voted[2, 35:37, 8:10].any()
    assert mask_iou(voted, truth)["iou"] > 0.9

    missed = truth.copy()
    missed[3] = False  # frame 3's own pairs saw nothing
    index = {pair: p for p, pair in enumerate(pairs)}
    restored = refine_masks(missed, flows, index, None, cfg)
    assert mask_iou(restored[3], truth[3])["iou"] > 0.85
    assert mask_iou(restored, truth)["iou"] > 0.85


def test_guided_refinement_needs_the_frames(scene, graph):
    from dataclasses import replace

    pairs, flows = graph
    cfg = replace(MotionMaskConfig(), guided_radius_px=4)
    with pytest.raises(UserError, match="needs the video's frames"):
        correspondence_motion_masks(oracle_tracks(scene), flows, pairs, cfg)
    masks = correspondence_motion_masks(oracle_tracks(scene), flows, pairs, cfg, scene.rgb).masks
    assert mask_iou(masks, ground_truth_motion_masks(scene))["iou"] > 0.9


def test_flow_is_sampled_at_any_number_of_points():
    """cv2.remap's maps hold fewer than 32767 columns: the forward-backward check of a 256x256
    pair samples 65,536 points, and a rotation's flow and its inverse cancel there."""
    from c4d_pipeline.flow import sample_flow
    from c4d_pipeline.motion_mask import forward_backward_error

    height = width = 256
    grid = pixel_grid(height, width)  # (H,W,2)
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    angle = np.deg2rad(2.0)
    rotate = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    forward = (grid - centre) @ rotate.T + centre - grid  # (H,W,2)
    back = (grid - centre) @ rotate + centre - grid  # the inverse rotation's flow
    error = forward_backward_error(forward, back)  # (H,W)
    inside = np.all((grid + forward > 0) & (grid + forward < width - 1), axis=-1)
    assert error.shape == (height, width) and np.abs(error[inside]).max() < 1e-3
    xy = np.random.default_rng(0).uniform(0, width - 1, (40_000, 2))  # not a multiple of the rows
    exact = (xy - centre) @ rotate.T + centre - xy
    assert np.abs(sample_flow(forward, xy) - exact).max() < 1e-3
