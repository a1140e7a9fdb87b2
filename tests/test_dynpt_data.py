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
