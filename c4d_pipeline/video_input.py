"""The frames a reconstruction works on: read a video or image folder, then DUSt3R preprocessing.

Reading (files, folders, stride, frame limit, corrupt or truncated files) is `c4d_core.video`'s;
this module adds DUSt3R's geometric preprocessing (dust3r `load_images`):
- size 512 (or any other long side S): resize so the long side is S (LANCZOS when shrinking,
  BICUBIC when enlarging; new size round(x * S / long side)), centre-crop each side down to a
  multiple of 16, and make square results 4:3 (e.g. 512x384) unless `square_ok`;
- size 224: resize so the long side is round(224 * aspect ratio) (the short side becomes 224),
  then centre-crop 224x224.
The resize-and-crop is also returned as an intrinsics transform, so ground truth can follow it.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from c4d_core.errors import UserError
from c4d_core.video import read_video, video_fps

log = logging.getLogger(__name__)
PATCH = 16


@dataclass(frozen=True)
class Preprocessing:
    """How source pixels map to network pixels: x_net = scale * (x_src + 0.5) - 0.5 - crop_x.

    source_hw, resized_hw and output_hw are (H, W); crop_xy is the top-left corner of the crop in
    the resized image.
    """

    source_hw: tuple[int, int]
    resized_hw: tuple[int, int]
    crop_xy: tuple[int, int]
    output_hw: tuple[int, int]

    def intrinsics(self, K: np.ndarray) -> np.ndarray:
        """Source intrinsics (...,3,3) -> network-resolution intrinsics (pixel centres at integers)."""
        sy = self.resized_hw[0] / self.source_hw[0]
        sx = self.resized_hw[1] / self.source_hw[1]
        A = np.array([[sx, 0, 0.5 * sx - 0.5 - self.crop_xy[0]],
                      [0, sy, 0.5 * sy - 0.5 - self.crop_xy[1]], [0, 0, 1]])
        return (A @ np.asarray(K, np.float64)).astype(np.float32)


def plan_preprocessing(source_hw: tuple[int, int], size: int, square_ok: bool = False) -> Preprocessing:
    """The resize and centre crop DUSt3R applies to an image of `source_hw` (H, W) for `size`."""
    H, W = source_hw
    if size < PATCH:
        raise UserError(f"network image size {size} is smaller than one {PATCH}-pixel patch; use 512 or 224")
    if min(H, W) < PATCH:  # enlarged, a few flat colours: nothing to match (the optimisation diverges)
        raise UserError(f"the video's frames are {W}x{H} pixels, smaller than one {PATCH}-pixel "
                        f"patch of the pointmap network; give frames of at least {PATCH}x{PATCH} pixels")
    # The long side's new length first, then each side as round(side * long / max(H, W)), in this
    # order of operations, as dust3r's: at exact .5 ties (a 402x384 image at 224) another order
    # rounds the other way and the resized image gains a column.
    long_side = round(224 * max(W / H, H / W)) if size == 224 else size
    rh, rw = round(H * long_side / max(H, W)), round(W * long_side / max(H, W))
    cy, cx = rh // 2, rw // 2
    if size == 224:  # short side to (about) 224, then the centre square
        half_h = half_w = min(cx, cy)
    else:
        half_w, half_h = ((2 * cx) // PATCH) * PATCH // 2, ((2 * cy) // PATCH) * PATCH // 2
        if rw == rh and not square_ok:
            half_h = (3 * half_w // 4) // (PATCH // 2) * (PATCH // 2)  # 4:3, whole patches
    if half_h < PATCH // 2 or half_w < PATCH // 2:
        raise UserError(f"a {W}x{H} video at size {size} leaves no full {PATCH}-pixel patch; "
                        "use a larger size or a less elongated video")
    crop = (cx - half_w, cy - half_h)
    return Preprocessing((H, W), (rh, rw), crop, (2 * half_h, 2 * half_w))


def dust3r_resize(frames: np.ndarray, size: int = 512, square_ok: bool = False
                  ) -> tuple[np.ndarray, Preprocessing]:
    """uint8 (T,H,W,3) -> uint8 (T,h,w,3) DUSt3R-preprocessed frames, and the mapping used."""
    plan = plan_preprocessing(frames.shape[1:3], size, square_ok)
    rh, rw = plan.resized_hw
    shrink = max(frames.shape[1:3]) > max(rh, rw)  # dust3r: LANCZOS when the long side shrinks
    method = Image.Resampling.LANCZOS if shrink else Image.Resampling.BICUBIC
    x0, y0 = plan.crop_xy
    oh, ow = plan.output_hw
    out = np.empty((len(frames), oh, ow, 3), np.uint8)
    for t, frame in enumerate(frames):
        image = Image.fromarray(frame)
        if (rh, rw) != frame.shape[:2]:
            image = image.resize((rw, rh), method)
        out[t] = np.asarray(image.crop((x0, y0, x0 + ow, y0 + oh)))
    return out, plan


@dataclass(frozen=True)
class VideoInput:
    """Preprocessed frames uint8 (T,h,w,3), the source frame index of each, the mapping, and the
    source's frame rate (None for a folder of frames)."""

    frames: np.ndarray
    source_indices: np.ndarray
    preprocessing: Preprocessing
    path: Path
    fps: float | None = None

    @property
    def timestamps(self) -> np.ndarray:
        """float64 (T,): each frame's time in the source, seconds (its source index without a
        frame rate)."""
        return self.source_indices / (self.fps or 1.0)


def load_video_input(path: str | Path, size: int = 512, stride: int = 1, max_frames: int | None = None,
                     square_ok: bool = False) -> VideoInput:
    """Read a video file or image folder (every `stride`-th frame, at most `max_frames`) and apply
    DUSt3R preprocessing for network size `size`. Bad or unreadable input raises `UserError`."""
    raw = read_video(path, stride=stride, max_frames=max_frames)  # (T,H,W,3) uint8
    frames, plan = dust3r_resize(raw, size, square_ok)
    (H, W), (rh, rw), (x0, y0), (oh, ow) = plan.source_hw, plan.resized_hw, plan.crop_xy, plan.output_hw
    if size != 224 and rh == rw and not square_ok:
        log.info("square %dx%d frames cropped to 4:3: the source's box x %.0f-%.0f, y %.0f-%.0f, "
                 "network frames %dx%d (DUSt3R's rule for a square input at size %d)", W, H,
                 x0 * W / rw, (x0 + ow) * W / rw, y0 * H / rh, (y0 + oh) * H / rh, ow, oh, size)
    return VideoInput(frames, np.arange(len(raw)) * stride, plan, Path(path), video_fps(path))
