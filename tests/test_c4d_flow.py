"""Optical flow behind one interface: shapes, exact ground truth for any pair, DIS on a known shift."""

import cv2
import numpy as np
import pytest

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_core.geometry import pixel_grid
from c4d_pipeline.flow import build_flow, compose_flows, fuse_flows
from c4d_pipeline.ground_truth import resize_nearest
from tests.synthetic_scenes import make_box_scene
from datagen.generate import generate_scene


@pytest.fixture(scope="module")
def scene():
    return make_box_scene(num_frames=6, height=48, width=64, num_tracks=200, seed=1)


def test_every_estimator_returns_one_flow_per_pair(scene):
    pairs = [(0, 1), (3, 2), (1, 5)]
    for spec in ("dis", "dis:fast", "dis:medium@2x", "dis+chain", "dis:fast@2x+chain", "gt"):
        flow = build_flow(spec, scene=scene).flow(scene.rgb, pairs)
        assert flow.shape == (3, 48, 64, 2) and flow.dtype == np.float32
        assert np.isfinite(flow).all()


@pytest.mark.parametrize(
    "spec, message",
    [("farneback", "unknown flow"), ("dis:slow", "unknown DIS preset"), ("gt", "needs a datagen scene"),
     ("raft", "needs weights"), ("raft:/no/such/raft.pth", "do not exist"),
     ("dis:medium@0x", "1x to 8x"), ("dis:medium@2", "1x to 8x"), ("dis:slow@2x", "unknown DIS preset"),
     ("dis:medium@2x+chains", "only option after"), ("gt+chain", "unknown flow")],
)
def test_bad_specs_are_user_errors(spec, message):
    with pytest.raises(UserError, match=message):
        build_flow(spec)


def test_bad_frames_and_pairs_are_user_errors(scene):
    dis = build_flow("dis")
    with pytest.raises(UserError, match="uint8 RGB"):
        dis.flow(scene.rgb.astype(np.float32), [(0, 1)])
    with pytest.raises(UserError, match="outside the video"):
        dis.flow(scene.rgb, [(0, 6)])
    with pytest.raises(UserError, match="got 5 frames"):
        build_flow("gt", scene=scene).flow(scene.rgb[:5], [(0, 1)])


def test_ground_truth_flow_of_adjacent_frames_is_the_scenes_flow(scene):
    gt = build_flow("gt", scene=scene)
    forward = gt.flow(scene.rgb, [(t, t + 1) for t in range(5)])
    backward = gt.flow(scene.rgb, [(t, t - 1) for t in range(1, 6)])
    np.testing.assert_allclose(forward, scene.flow_fwd[:5], atol=1e-3)
    np.testing.assert_allclose(backward, scene.flow_bwd[1:], atol=1e-3)


def test_ground_truth_flow_of_any_pair_follows_the_tracks(scene):
    """Tracks are queried at integer pixels and carried by the scene's own code: the flow from
    the query frame to any frame j, read at the query pixel, must land on the track at j."""
    pairs = [(i, j) for i in range(6) for j in range(6) if i != j]
    flow = build_flow("gt", scene=scene).flow(scene.rgb, pairs)
    checked = 0
    for p, (i, j) in enumerate(pairs):
        for n in np.flatnonzero(scene.query_frame == i):
            x, y = np.round(scene.tracks[n, i]).astype(int)
            np.testing.assert_allclose(scene.tracks[n, i] + flow[p, y, x], scene.tracks[n, j], atol=1e-3)
            checked += 1
    assert checked > 500


def test_ground_truth_flow_at_half_resolution_is_half_the_flow(scene):
    small = resize_nearest(scene.rgb.transpose(1, 2, 0, 3), (24, 32)).transpose(2, 0, 1, 3)  # (T,24,32,3)
    half = build_flow("gt", scene=scene).flow(small, [(0, 2)])[0]  # (24,32,2)
    full = build_flow("gt", scene=scene).flow(scene.rgb, [(0, 2)])[0]  # (48,64,2)
    # a small pixel (x', y') looks at the full-size pixel (2x' + 1, 2y' + 1), half a pixel off
    expected = resize_nearest(full, (24, 32)) / 2
    assert np.median(np.abs(half - expected)) < 0.05


def test_dis_recovers_a_known_shift():
    rng = np.random.default_rng(0)
    texture = rng.uniform(0, 255, (20, 28))
    big = np.kron(texture, np.ones((4, 4)))  # (80,112) blocky texture
    big = np.clip(big + rng.normal(0, 8, big.shape), 0, 255)
    big = cv2.GaussianBlur(big, (5, 5), 1.5)
    dx, dy = 3, -2
    frame0 = big[8:72, 8:104]  # (64,96)
    frame1 = big[8 - dy : 72 - dy, 8 - dx : 104 - dx]  # content moves by (+dx, +dy)
    frames = np.repeat(np.stack([frame0, frame1])[..., None], 3, -1).astype(np.uint8)
    inner = (slice(12, -12), slice(12, -12))
    for spec in ("dis", "dis:medium@2x"):  # on upsampled frames: the same shift in frame pixels
        flow = build_flow(spec).flow(frames, [(0, 1), (1, 0)])
        np.testing.assert_allclose(np.median(flow[0][inner].reshape(-1, 2), 0), [dx, dy], atol=0.1)
        np.testing.assert_allclose(np.median(flow[1][inner].reshape(-1, 2), 0), [-dx, -dy], atol=0.1)


def test_ground_truth_flow_matches_a_generated_movi_e_scene():
    """The contract's flow_fwd / flow_bwd of a real datagen scene (pybullet + pyrender)."""
    generated = generate_scene(load_config("datagen", "movi-e", overrides=["resolution=[48,48]", "frames=4", "objects.num_static=[3,3]"]), 0)
    gt = build_flow("gt", scene=generated)
    np.testing.assert_allclose(gt.flow(generated.rgb, [(0, 1), (1, 2), (2, 3)]), generated.flow_fwd[:3], atol=1e-3)
    np.testing.assert_allclose(gt.flow(generated.rgb, [(1, 0), (2, 1), (3, 2)]), generated.flow_bwd[1:], atol=1e-3)


def _drifting_texture(step_xy, num_frames, height=64, width=96, seed=0):
    """uint8 (T,H,W,3) frames of a blocky texture whose content moves by step_xy pixels a frame."""
    rng = np.random.default_rng(seed)
    margin = int(np.abs(step_xy).max() * num_frames) + 8
    cells = ((height + 2 * margin) // 4 + 1, (width + 2 * margin) // 4 + 1)
    big = np.kron(rng.uniform(0, 255, cells), np.ones((4, 4)))
    big = cv2.GaussianBlur(np.clip(big + rng.normal(0, 8, big.shape), 0, 255), (5, 5), 1.5)
    frames = []
    for t in range(num_frames):
        dx, dy = (round(v * t) for v in step_xy)
        frames.append(big[margin - dy : margin - dy + height, margin - dx : margin - dx + width])
    return np.repeat(np.stack(frames)[..., None], 3, -1).astype(np.uint8)


def test_flows_compose_exactly_where_they_are_affine():
    """A rotation about the centre then a shift: composed, the flow of the rotation-and-shift."""
    height, width = 40, 60
    grid = pixel_grid(height, width)
    centre = np.array([(width - 1) / 2, (height - 1) / 2])
    angle = np.deg2rad(3.0)
    rotate = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    rotation = (grid - centre) @ rotate.T + centre - grid  # (H,W,2)
    shift = np.broadcast_to(np.array([2.5, -1.25]), grid.shape)
    composed = compose_flows(rotation, shift)
    np.testing.assert_allclose(composed, rotation + shift, atol=1e-5)
    back = (grid - centre) @ rotate + centre - grid  # the inverse rotation: composed, no motion
    inside = np.all((grid + rotation > 0) & (grid + rotation < [width - 1, height - 1]), axis=-1)
    assert np.abs(compose_flows(rotation, back)[inside]).max() < 1e-3


def test_fusion_takes_per_pixel_the_flow_that_matches_the_frames():
    """Frame j = frame i shifted by (3, -2) px; candidates: the right shift on the left half and a
    wrong one on the right half, and the reverse. The fused flow is the right shift away from the
    seam (whose 7x7 patches mix both)."""
    frames = _drifting_texture((3.0, -2.0), 2, height=48, width=80)
    right = np.broadcast_to(np.array([3.0, -2.0], np.float32), (48, 80, 2))
    wrong = right + np.array([5.0, 4.0], np.float32)
    left_half = np.zeros((48, 80, 1), bool)
    left_half[:, :40] = True
    first, second = np.where(left_half, right, wrong), np.where(left_half, wrong, right)
    fused = fuse_flows(frames[0], frames[1], [first, second])
    inner = (slice(8, -8), np.r_[8:36, 44:72])  # away from the image's edges and the seam
    np.testing.assert_array_equal(fused[inner], right[inner])
    assert fused.dtype == np.float32 and fused.shape == (48, 80, 2)


def test_chained_dis_follows_a_large_displacement_that_one_search_loses():
    """Content drifting 7 px a frame: frames 0 and 6 lie 42 px apart, beyond DIS's search on
    64x96 frames; the chain of six 7-px steps, fused with the failed search, finds it. Consecutive
    pairs are searched directly, so they equal plain DIS's to the bit (the motion masks read only
    those)."""
    frames = _drifting_texture((7.0, 0.0), 7, width=128)
    pairs = [(0, 6), (6, 0), (0, 1), (3, 4), (2, 5)]
    chained = build_flow("dis:medium+chain").flow(frames, pairs)
    plain = build_flow("dis:medium").flow(frames, pairs)
    for p, (i, j) in enumerate(pairs):
        shift = 7.0 * (j - i)
        columns = slice(int(max(12, 12 - shift)), int(min(116, 116 - shift)))  # source, target in view
        measured = np.median(chained[p][12:-12, columns].reshape(-1, 2), 0)
        np.testing.assert_allclose(measured, [shift, 0.0], atol=0.25)
        if abs(j - i) == 6:
            assert np.abs(np.median(plain[p][12:-12, columns].reshape(-1, 2), 0) - [shift, 0.0]).max() > 5.0
    np.testing.assert_array_equal(chained[2:4], plain[2:4])


def test_run_chunks_the_pairs_by_frame_blocks_and_keeps_their_order():
    """`c4d run` computes flow in chunks (a progress bar): the chunks hold the pairs of blocks of 16
    frames, and the result is the whole call's, in the pairs' order, also for the chained DIS."""
    from c4d_pipeline.cli_run import _FlowWithProgress
    from c4d_pipeline.scene_graph import graph_from_config

    frames = _drifting_texture((1.5, -0.5), 40, height=32, width=48)
    pairs = [tuple(map(int, e)) for e in graph_from_config(40, load_config("c4d", "default").graph)]
    pairs = pairs[::-1]  # any order
    estimator = build_flow("dis:fast+chain")
    np.testing.assert_array_equal(_FlowWithProgress(estimator).flow(frames, pairs), estimator.flow(frames, pairs))
