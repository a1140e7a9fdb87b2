"""The frames a reconstruction works on: read a video or image folder, then DUSt3R preprocessing.

Reading (files, folders, stride, frame limit, corrupt or truncated files) is `c4d_core.video`'s;
this module adds DUSt3R's geometric preprocessing (dust3r `load_images`):
- size 512 (or any other long side S): resize so the long side is S (LANCZOS when shrinking,
  BICUBIC when enlarging; new size round(x * S / long side)), centre-crop each side down to a
  multiple of 16, and make square results 4:3 (e.g. 512x384) unless `square_ok`;
- size 224: resize so the long side is round(224 * aspect ratio) (the short side becomes 224),
  then centre-crop 224x224.
The resize-and-crop is also returned as an intrinsics transform, so ground truth and known
intrinsics (`intrinsics.known`, `read_intrinsics` and `network_intrinsics`) can follow it.
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


def read_intrinsics(spec: str) -> np.ndarray:
    """Known intrinsics `intrinsics.known` (--intrinsics) in the source video's pixels: "fx,fy,cx,cy"
    (every frame) or a text file (numbers split by spaces or commas, # comments) or .npy file with
    one row fx fy cx cy per source frame, or one row for all -> float64 (N,4). Checked before any
    heavy work: not 4 numbers a row, a non-finite value or a focal <= 0 is a one-line `UserError`."""
    what = f"--intrinsics {spec!r}"
    path = Path(spec)
    try:
        if path.is_file() and path.suffix == ".npy":
            rows = np.load(path, allow_pickle=False).astype(np.float64)
        elif path.is_file():
            lines = path.read_text(errors="replace").replace(",", " ").splitlines()
            rows = np.loadtxt(lines, ndmin=2)
        else:
            rows = np.array([float(x) for x in spec.split(",")])
    except (ValueError, OSError) as exc:
        hint = str(exc).splitlines()[0] if path.is_file() else "not a file, nor numbers fx,fy,cx,cy"
        raise UserError(f"{what}: {hint}; give fx,fy,cx,cy in the source video's pixels or a "
                        ".txt/.npy file with one row fx fy cx cy per source frame") from None
    rows = rows[None] if rows.ndim == 1 else rows
    if rows.ndim != 2 or rows.shape[1] != 4 or not len(rows):
        raise UserError(f"{what}: {'x'.join(map(str, rows.shape))} values; give 4 numbers a row: "
                        "fx fy cx cy (pixels of the source video)")
    bad = ~np.isfinite(rows).all(1) | (rows[:, :2] <= 0).any(1)
    if bad.any():
        n = int(np.flatnonzero(bad)[0])
        raise UserError(f"{what}: row {n} is {' '.join(f'{v:g}' for v in rows[n])}; every value must be "
                        "finite and the focal lengths fx, fy > 0 pixels")
    return rows


def network_intrinsics(rows: np.ndarray, video: VideoInput, read_whole: bool) -> np.ndarray:
    """Known intrinsics (N,4) from `read_intrinsics` -> float32 (T,4) fx, fy, cx, cy in the network
    frames' pixels: the one row for every frame, else the row of each frame's source index, scaled
    and shifted with the frames' resize and crop (`Preprocessing.intrinsics`, pixel centres kept as
    `c4d_core.geometry.rescale_pixels`). `read_whole`: the video was read to its end (not cut by
    --max-frames), so N may not exceed its frame count either; a wrong row count is a `UserError`."""
    indices = video.source_indices
    stride = int(indices[1] - indices[0]) if len(indices) > 1 else 1
    need = int(indices[-1]) + 1  # the source frames read reach this far
    if len(rows) != 1 and (len(rows) < need or (read_whole and len(rows) >= need + stride)):
        count = f"{need}" if stride == 1 or not read_whole else f"{need} to {need + stride - 1}"
        raise UserError(f"--intrinsics has {len(rows)} rows, but the video has {count} source frames"
                        f"{'' if read_whole else ' up to the last one read'}; give one row fx fy cx cy "
                        "per source frame (before --stride), or one row for every frame")
    known = rows[indices if len(rows) > 1 else np.zeros(len(indices), int)]  # (T,4)
    k = np.zeros((len(indices), 3, 3))
    k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2], k[:, 2, 2] = *known.T, 1.0
    k = video.preprocessing.intrinsics(k)  # (T,3,3)
    return np.stack([k[:, 0, 0], k[:, 1, 1], k[:, 0, 2], k[:, 1, 2]], -1).astype(np.float32)
