"""Training augmentations for a clip, keeping point labels on the right pixels.

A clip is a dict of numpy arrays: `rgb` uint8 (T,H,W,3), `tracks` float32 (T,N,2) as (x, y)
pixels with pixel centres at integers, `occluded` bool (T,N), `moving` bool (T,N). Spatial
augmentation is one affine map per clip (random scale, crop, horizontal/vertical flips) applied
to the frames with `cv2.remap` and to the tracks with the same matrix; points that leave
the crop become occluded. Photometric augmentation (colour jitter, Gaussian blur) leaves labels
unchanged; eraser boxes fill rectangles with their mean colour on frames after the first and mark
the points they cover occluded. All randomness comes from the `numpy.random.Generator` given.
"""

from __future__ import annotations

import cv2
import numpy as np


def spatial_matrix(in_hw: tuple[int, int], out_hw: tuple[int, int], cfg,
                   rng: np.random.Generator) -> np.ndarray:
    """A random 2x3 affine map from input to output pixels: scale, crop and flips.

    The base scale makes the input cover the output; it is multiplied by U(scale_range).
    """
    (h, w), (oh, ow) = in_hw, out_hw
    scale = max(oh / h, ow / w) * rng.uniform(*cfg.scale_range)
    # Random crop offset of the scaled image (centred when it is smaller than the crop).
    tx = -rng.uniform(0.0, max(w * scale - ow, 0.0)) if w * scale > ow else (ow - w * scale) / 2
    ty = -rng.uniform(0.0, max(h * scale - oh, 0.0)) if h * scale > oh else (oh - h * scale) / 2
    # Pixel centres sit at integers, so x -> s*x + t maps centre (0,0) to (t,t) + (s-1)/2 offset.
    tx += (scale - 1.0) / 2.0
    ty += (scale - 1.0) / 2.0
    matrix = np.array([[scale, 0.0, tx], [0.0, scale, ty]])
    if rng.random() < cfg.hflip_prob:  # x -> (ow - 1) - x
        matrix = np.array([[-1.0, 0.0, ow - 1.0], [0.0, 1.0, 0.0]]) @ np.vstack([matrix, [0, 0, 1]])
    if rng.random() < cfg.vflip_prob:  # y -> (oh - 1) - y
        matrix = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, oh - 1.0]]) @ np.vstack([matrix, [0, 0, 1]])
    return matrix


def apply_spatial(clip: dict, matrix: np.ndarray, out_hw: tuple[int, int]) -> dict:
    """Warp frames and tracks by the 2x3 `matrix`; points outside the output become occluded."""
    oh, ow = out_hw
    # The input position of every output pixel, computed once for all frames and converted to
    # OpenCV's fixed-point maps: `remap` with them is ~1.5x faster than `warpAffine` per frame.
    inverse = cv2.invertAffineTransform(matrix)  # (2,3) output -> input pixels
    x, y = np.meshgrid(np.arange(ow, dtype=np.float32), np.arange(oh, dtype=np.float32))  # (oh,ow)
    map_x = inverse[0, 0] * x + inverse[0, 1] * y + inverse[0, 2]  # (oh,ow)
    map_y = inverse[1, 0] * x + inverse[1, 1] * y + inverse[1, 2]  # (oh,ow)
    whole, fraction = cv2.convertMaps(map_x.astype(np.float32), map_y.astype(np.float32),
                                      cv2.CV_16SC2)
    rgb = np.empty((len(clip["rgb"]), oh, ow, 3), np.uint8)  # (T,oh,ow,3)
    for frame, out in zip(clip["rgb"], rgb):
        cv2.remap(frame, whole, fraction, cv2.INTER_LINEAR, dst=out,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    tracks = clip["tracks"] @ matrix[:, :2].T + matrix[:, 2]  # (T,N,2)
    inside = (tracks[..., 0] >= 0) & (tracks[..., 0] <= ow - 1) \
        & (tracks[..., 1] >= 0) & (tracks[..., 1] <= oh - 1)  # (T,N)
    return {**clip, "rgb": rgb, "tracks": tracks.astype(np.float32),
            "occluded": clip["occluded"] | ~inside}


def colour_jitter(rgb: np.ndarray, cfg, rng: np.random.Generator) -> np.ndarray:
    """Brightness, contrast, saturation and hue jitter with one draw per clip; uint8 in and out.

    Brightness and contrast (around the clip's mean grey level) form one lookup table;
    saturation blends each frame with its grey image; hue rotates the HSV hue channel.
    """
    brightness = rng.uniform(1 - cfg.brightness, 1 + cfg.brightness)
    contrast = rng.uniform(1 - cfg.contrast, 1 + cfg.contrast)
    saturation = rng.uniform(1 - cfg.saturation, 1 + cfg.saturation)
    shift = int(round(rng.uniform(-cfg.hue, cfg.hue) * 180.0))  # OpenCV hue range is [0, 180)
    mean = float(rgb[::4, ::4, ::4].mean()) * brightness
    levels = np.arange(256, dtype=np.float32) * brightness
    lut = np.clip((levels - mean) * contrast + mean, 0, 255).astype(np.uint8)  # (256,)
    out = np.empty_like(rgb)
    for t, frame in enumerate(rgb):
        x = cv2.LUT(frame, lut)
        grey = cv2.cvtColor(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
        x = cv2.addWeighted(x, saturation, grey, 1.0 - saturation, 0.0)
        if shift:
            hsv = cv2.cvtColor(x, cv2.COLOR_RGB2HSV)
            hsv[..., 0] = cv2.LUT(hsv[..., 0], ((np.arange(256) + shift) % 180).astype(np.uint8))
            x = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        out[t] = x
    return out


def gaussian_blur(rgb: np.ndarray, sigma: float) -> np.ndarray:
    """Blur every frame with a Gaussian of `sigma` pixels."""
    out = np.empty_like(rgb)
    for frame, blurred in zip(rgb, out):
        cv2.GaussianBlur(frame, (0, 0), sigmaX=sigma, dst=blurred)
    return out


def erase_boxes(clip: dict, cfg, rng: np.random.Generator) -> dict:
    """Fill 1..`eraser_max_boxes` random boxes per frame (not frame 0) with their mean colour.

    Points inside a box on that frame are marked occluded.
    """
    rgb, tracks = clip["rgb"].copy(), clip["tracks"]
    occluded = clip["occluded"].copy()
    T, h, w, _ = rgb.shape
    k = cfg.eraser_max_boxes
    count = rng.integers(1, k + 1, size=T)  # boxes per frame
    size = rng.integers(cfg.eraser_size_px[0], cfg.eraser_size_px[1] + 1, size=(T, k, 2))
    x0 = (rng.random((T, k)) * np.maximum(w - size[..., 0] + 1, 1)).astype(int)  # (T,k)
    y0 = (rng.random((T, k)) * np.maximum(h - size[..., 1] + 1, 1)).astype(int)
    x1, y1 = np.minimum(x0 + size[..., 0], w), np.minimum(y0 + size[..., 1], h)
    used = np.arange(k)[None] < count[:, None]  # (T,k)
    used[0] = False  # the first frame is never erased
    for t, b in zip(*np.nonzero(used)):
        box = rgb[t, y0[t, b]:y1[t, b], x0[t, b]:x1[t, b]]  # (h_b,w_b,3) view
        sums = np.array(cv2.sumElems(box)[:3])  # exact integer sums per channel
        box[:] = (sums // (box.shape[0] * box.shape[1])).astype(np.uint8)  # the mean, truncated
    # A point is covered when its pixel (centre at integers) lies in a used box: (T,N,k).
    x, y = tracks[..., 0:1], tracks[..., 1:2]  # (T,N,1)
    inside = (x >= x0[:, None] - 0.5) & (x < x1[:, None] - 0.5) \
        & (y >= y0[:, None] - 0.5) & (y < y1[:, None] - 0.5) & used[:, None]
    return {**clip, "rgb": rgb, "occluded": occluded | inside.any(axis=-1)}


def augment_clip(clip: dict, cfg, out_hw: tuple[int, int], rng: np.random.Generator) -> dict:
    """All augmentations of the `augment:` config in order: spatial, jitter, blur, eraser."""
    clip = apply_spatial(clip, spatial_matrix(clip["rgb"].shape[1:3], out_hw, cfg, rng), out_hw)
    if rng.random() < cfg.jitter_prob:
        clip = {**clip, "rgb": colour_jitter(clip["rgb"], cfg, rng)}
    if rng.random() < cfg.blur_prob:
        clip = {**clip, "rgb": gaussian_blur(clip["rgb"], rng.uniform(*cfg.blur_sigma))}
    if rng.random() < cfg.eraser_prob:
        clip = erase_boxes(clip, cfg, rng)
    return clip


def resize_clip(clip: dict, out_hw: tuple[int, int]) -> dict:
    """Deterministic resize to `out_hw` (evaluation): the scale part of the spatial map only."""
    h, w = clip["rgb"].shape[1:3]
    sx, sy = out_hw[1] / w, out_hw[0] / h
    matrix = np.array([[sx, 0.0, (sx - 1) / 2], [0.0, sy, (sy - 1) / 2]])
    return apply_spatial(clip, matrix, out_hw)
