"""Optical flow behind one interface: shapes, exact ground truth for any pair, DIS on a known shift."""

import cv2
import numpy as np
import pytest

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.flow import build_flow
from c4d_pipeline.ground_truth import resize_nearest
from tests.synthetic_scenes import make_box_scene
from datagen.generate import generate_scene


@pytest.fixture(scope="module")
def scene():
    return make_box_scene(num_frames=6, height=48, width=64, num_tracks=200, seed=1)


def test_every_estimator_returns_one_flow_per_pair(scene):
    pairs = [(0, 1), (3, 2), (1, 5)]
    for spec in ("dis", "dis:fast", "dis:medium@2x", "gt"):
        flow = build_flow(spec, scene=scene).flow(scene.rgb, pairs)
        assert flow.shape == (3, 48, 64, 2) and flow.dtype == np.float32
        assert np.isfinite(flow).all()


@pytest.mark.parametrize(
    "spec, message",
    [("farneback", "unknown flow"), ("dis:slow", "unknown DIS preset"), ("gt", "needs a datagen scene"),
     ("raft", "needs weights"), ("raft:/no/such/raft.pth", "do not exist"),
     ("dis:medium@0x", "1x to 8x"), ("dis:medium@2", "1x to 8x"), ("dis:slow@2x", "unknown DIS preset")],
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
