"""Augmentations keep point labels on the right pixels."""

import numpy as np
from omegaconf import OmegaConf

from dynpt.augment import apply_spatial, augment_clip, erase_boxes, resize_clip, spatial_matrix

CFG = OmegaConf.create({
    "scale_range": [0.8, 1.5], "hflip_prob": 0.5, "vflip_prob": 0.5,
    "jitter_prob": 0.0, "brightness": 0.2, "contrast": 0.2, "saturation": 0.2, "hue": 0.05,
    "blur_prob": 0.0, "blur_sigma": [0.1, 1.0],
    "eraser_prob": 0.0, "eraser_max_boxes": 4, "eraser_size_px": [4, 12],
})


def _dot_clip(T=5, H=48, W=64, N=6, seed=0):
    """Black frames with a white 3x3 dot painted at every track position."""
    rng = np.random.default_rng(seed)
    tracks = rng.integers(4, [W - 4, H - 4], size=(T, N, 2)).astype(np.float32)  # (T,N,2)
    rgb = np.zeros((T, H, W, 3), np.uint8)
    for t in range(T):
        for x, y in tracks[t].astype(int):
            rgb[t, y - 1:y + 2, x - 1:x + 2] = 255
    occluded = np.zeros((T, N), bool)
    return {"rgb": rgb, "tracks": tracks, "occluded": occluded, "moving": ~occluded}


def _brightness_at_tracks(clip):
    t, n = np.nonzero(~clip["occluded"])
    xy = np.round(clip["tracks"][t, n]).astype(int)
    return clip["rgb"][t, xy[:, 1], xy[:, 0]].min(-1)


def test_painted_dots_follow_tracks_through_crop_scale_flip():
    clip = _dot_clip()
    seen_flips = set()
    for seed in range(12):
        rng = np.random.default_rng(seed)
        matrix = spatial_matrix((48, 64), (32, 40), CFG, rng)
        seen_flips.add((matrix[0, 0] < 0, matrix[1, 1] < 0))
        out = apply_spatial(clip, matrix, (32, 40))
        assert out["rgb"].shape == (5, 32, 40, 3)
        values = _brightness_at_tracks(out)
        assert values.size > 0 and values.min() > 200, seed
        # Points reported outside the crop really are outside it.
        xy = out["tracks"][out["occluded"]]
        assert np.all((xy[:, 0] < 0) | (xy[:, 0] > 39) | (xy[:, 1] < 0) | (xy[:, 1] > 31))
    assert len(seen_flips) == 4  # all flip combinations exercised


def test_flip_and_resize_are_exact():
    cfg = OmegaConf.merge(CFG, {"scale_range": [1.0, 1.0], "hflip_prob": 1.0, "vflip_prob": 0.0})
    clip = _dot_clip(H=32, W=32)
    out = apply_spatial(clip, spatial_matrix((32, 32), (32, 32), cfg, np.random.default_rng(0)), (32, 32))
    np.testing.assert_allclose(out["tracks"][..., 0], 31 - clip["tracks"][..., 0], atol=1e-5)
    np.testing.assert_array_equal(out["rgb"], clip["rgb"][:, :, ::-1])
    up = resize_clip(clip, (64, 64))  # pixel centres: x -> 2x + 0.5
    np.testing.assert_allclose(up["tracks"], 2 * clip["tracks"] + 0.5, atol=1e-5)
    assert _brightness_at_tracks(up).min() > 200


def test_eraser_marks_covered_points_occluded_and_keeps_frame_zero():
    clip = _dot_clip(T=6, N=40, seed=3)
    cfg = OmegaConf.merge(CFG, {"eraser_max_boxes": 6, "eraser_size_px": [10, 30]})
    out = erase_boxes(clip, cfg, np.random.default_rng(1))
    np.testing.assert_array_equal(out["rgb"][0], clip["rgb"][0])
    assert not out["occluded"][0].any() and out["occluded"][1:].any()
    # Every still-visible point keeps its dot; erased ones lost it (box is filled uniformly).
    assert _brightness_at_tracks(out).min() > 200


def test_full_augmentation_is_deterministic_by_seed():
    cfg = OmegaConf.merge(CFG, {"jitter_prob": 1.0, "blur_prob": 1.0, "eraser_prob": 1.0})
    clip = _dot_clip()
    a = augment_clip(clip, cfg, (32, 32), np.random.default_rng(7))
    b = augment_clip(clip, cfg, (32, 32), np.random.default_rng(7))
    for key in ("rgb", "tracks", "occluded"):
        np.testing.assert_array_equal(a[key], b[key])
    assert a["rgb"].dtype == np.uint8


# --- clip and track sampling, the shard stream ---------------------------------------------------

import pytest  # noqa: E402

from c4d_core.errors import UserError  # noqa: E402
from dynpt.data import ShardStream, StreamPosition, choose_clip, merge_positions, sample_tracks  # noqa: E402
from tests.dynpt_testdata import synthetic_scene, synthetic_shards  # noqa: E402

DATA = OmegaConf.create({
    "num_frames": 6, "max_stride": 2, "crop_size": [32, 32], "num_tracks": 8,
    "random_query_fraction": 0.5, "moving_track_fraction": 0.0, "shuffle_buffer": 4,
    "max_offscreen_px": 1000.0,
    "augment": OmegaConf.merge(CFG, {"scale_range": [1.0, 1.0], "hflip_prob": 0.0, "vflip_prob": 0.0}),
})


def test_sampled_queries_are_visible_first_or_random():
    rng = np.random.default_rng(0)
    occluded = rng.random((8, 30)) < 0.6
    occluded[:, 29] = True  # never visible: never sampled
    clip = {"rgb": np.zeros((8, 4, 4, 3), np.uint8), "tracks": rng.random((8, 30, 2)),
            "occluded": occluded, "moving": np.zeros((8, 30), bool)}
    first = sample_tracks(clip, 20, 0.0, rng)
    t = first["queries"][:, 0].astype(int)
    n = np.arange(20)
    assert first["visible"][t, n].all()
    assert np.all(t == first["visible"].argmax(axis=0))  # first visible frame
    np.testing.assert_allclose(first["queries"][:, 1:], first["tracks"][t, n])
    rand = sample_tracks(clip, 200, 1.0, rng)  # more than available: drawn with replacement
    t = rand["queries"][:, 0].astype(int)
    assert rand["visible"][t, np.arange(200)].all()
    assert np.any(t != rand["visible"].argmax(axis=0))  # some later than the first visible frame
    none = dict(clip, occluded=np.ones_like(occluded))
    assert sample_tracks(none, 4, 0.0, rng) is None


def test_moving_fraction_balances_the_mobility_classes():
    rng = np.random.default_rng(0)
    moving = np.zeros((6, 50), bool)
    moving[2:4, :5] = True  # 5 of 50 tracks move, in frames 2-3 only
    clip = {"rgb": np.zeros((6, 4, 4, 3), np.uint8), "tracks": rng.random((6, 50, 2)),
            "occluded": np.zeros((6, 50), bool), "moving": moving}
    uniform = [sample_tracks(clip, 20, 0.0, rng)["moving"].any(axis=0).sum() for _ in range(200)]
    assert 1.5 < np.mean(uniform) < 2.5  # 20 of 50 drawn: 2 movers expected
    balanced = sample_tracks(clip, 20, 0.0, rng, moving_fraction=0.2)
    assert balanced["moving"].any(axis=0).sum() >= 4  # 4 movers asked, plus any drawn uniformly
    short = sample_tracks(clip, 20, 0.0, rng, moving_fraction=0.5)  # 10 asked, only 5 exist
    ids = short["tracks"][0]  # tracks are distinct random points: equal rows = the same track
    assert short["moving"].any(axis=0).sum() == 5 and len(np.unique(ids, axis=0)) == 20


def test_clip_choice_and_too_short_scenes():
    scene = synthetic_scene(3, T=10)
    clip = choose_clip(scene, 6, 2, np.random.default_rng(1))
    assert clip["rgb"].shape == (6, 32, 32, 3) and clip["tracks"].shape == (6, 20, 2)
    with pytest.raises(UserError, match="num_frames"):
        choose_clip(scene, 12, 1, np.random.default_rng(1))


def _take(stream, count):
    it = iter(stream)
    return [next(it) for _ in range(count)]


def test_stream_is_deterministic_and_resumes_exactly():
    shards = synthetic_shards(12, 3)
    samples = _take(ShardStream([shards], [1.0], DATA, seed=5), 20)  # > one epoch of 12
    again = _take(ShardStream([shards], [1.0], DATA, seed=5), 20)
    scenes = [int(s["video"][0, 0, 0, 0]) for s in samples]
    assert scenes == [int(s["video"][0, 0, 0, 0]) for s in again]
    assert sorted(scenes[:12]) == list(range(12))  # one epoch sees every scene once, shuffled
    assert scenes[:12] != list(range(12))
    # Resume after sample 13 (mid second epoch) from the position it carries.
    position = StreamPosition()
    position.update(torch_rows([s["position"] for s in samples[:13]]))
    start = merge_positions([position.state_dict()], num_splits=1)
    resumed = _take(ShardStream([shards], [1.0], DATA, seed=5, start=start), 7)
    for a, b in zip(resumed, samples[13:]):
        for key in ("video", "queries", "tracks", "visible", "moving", "position"):
            np.testing.assert_array_equal(a[key], b[key])


def torch_rows(rows):
    import torch

    return torch.as_tensor(np.stack(rows))


def test_ranks_read_disjoint_shards_and_mixing_follows_weights():
    shards = synthetic_shards(12, 3)
    seen = [{int(s["video"][0, 0, 0, 0]) for s in _take(
        ShardStream([shards], [1.0], DATA, seed=0, rank=r, world_size=2), 6)} for r in (0, 1)]
    assert not seen[0] & seen[1] and len(seen[0] | seen[1]) == 12
    other = synthetic_shards(6, 3, first=100)
    only_first = _take(ShardStream([shards, other], [1.0, 0.0], DATA, seed=0), 8)
    assert all(s["video"][0, 0, 0, 0] < 100 for s in only_first)
    mixed = _take(ShardStream([shards, other], [1.0, 1.0], DATA, seed=0), 16)
    from_other = sum(s["video"][0, 0, 0, 0] >= 100 for s in mixed)
    assert 3 <= from_other <= 13
    with pytest.raises(UserError, match="weights"):
        ShardStream([shards], [1.0, 2.0], DATA, seed=0)
