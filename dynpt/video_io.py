"""Reading user videos (files or folders of images) and writing result videos, with clear errors.

Frames are RGB uint8 (T,H,W,3). Writing delegates to `c4d_core.video.write_video` (atomic,
container by extension) and only turns its failures into `UserError`s.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import cv2
import numpy as np

from c4d_core import video
from c4d_core.errors import UserError
from c4d_core.schema import MAX_SIDE, MIN_SIDE

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}


def _natural_key(path: Path):
    """Sort frame_2.png before frame_10.png."""
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", path.name)]


def _read_folder(folder: Path, stride: int, max_frames: int | None) -> list[np.ndarray]:
    files = sorted((p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES), key=_natural_key)
    if not files:
        raise UserError(f"folder {str(folder)!r} holds no images ({', '.join(sorted(IMAGE_SUFFIXES))}); "
                        "pass a video file or a folder of frames")
    files = files[::stride][:max_frames]
    frames = []
    for f in files:
        image = cv2.imread(str(f), cv2.IMREAD_COLOR)  # grey images come back as 3 channels
        if image is None:
            raise UserError(f"cannot decode image {str(f)!r} (corrupt or unsupported); fix or remove it")
        if frames and image.shape != frames[0].shape:
            raise UserError(f"image {str(f)!r} is {image.shape[1]}x{image.shape[0]} but the first frame "
                            f"is {frames[0].shape[1]}x{frames[0].shape[0]}; all frames need one size")
        frames.append(image[..., ::-1])
    return frames


def _read_file(path: Path, stride: int, max_frames: int | None) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        raise UserError(f"cannot open video {str(path)!r} (corrupt, truncated or an unsupported format); "
                        "re-encode it as .mp4 or pass a folder of frames")
    reported = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    frames, index = [], 0
    try:
        while max_frames is None or len(frames) < max_frames:
            ok, frame = capture.read()
            if not ok:
                break
            if index % stride == 0:
                frames.append(frame[..., ::-1])
            index += 1
    finally:
        capture.release()
    if not frames:
        raise UserError(f"no frame could be decoded from {str(path)!r} (empty, corrupt or truncated "
                        "video); re-encode it or pass a folder of frames")
    if max_frames is None and reported > 0 and index < reported:
        log.warning("%s: decoded %d of the %d frames the file announces (truncated?)", path, index, reported)
    return frames


def read_video(path_or_image_folder: str | os.PathLike, stride: int = 1, max_frames: int | None = None) -> np.ndarray:
    """Frames of a video file or of a folder of images (sorted by name): uint8 (T,H,W,3) RGB.

    Keeps every `stride`-th frame, at most `max_frames` of them.
    """
    path = Path(path_or_image_folder)
    if stride < 1 or (max_frames is not None and max_frames < 1):
        raise UserError(f"stride ({stride}) and max_frames ({max_frames}) must be at least 1")
    if not path.exists():
        raise UserError(f"video {str(path)!r} does not exist; pass a video file or a folder of frames")
    frames = _read_folder(path, stride, max_frames) if path.is_dir() else _read_file(path, stride, max_frames)
    return np.ascontiguousarray(np.stack(frames))


def video_fps(path: str | os.PathLike) -> float | None:
    """Frame rate recorded in a video file; None for a folder of frames or a file without one."""
    path = Path(path)
    if path.is_dir():
        return None
    capture = cv2.VideoCapture(str(path))
    fps = capture.get(cv2.CAP_PROP_FPS) if capture.isOpened() else 0.0
    capture.release()
    return float(fps) if 0 < fps < 1000 else None


def resize_long_side(video: np.ndarray, size: int | None = None, max_size: int | None = None) -> np.ndarray:
    """`video` uint8 (T,H,W,3) resized (area / bilinear) so that its long side is `size` pixels, or
    at most `max_size` (never enlarged); both None: unchanged. Aspect ratio kept."""
    T, H, W = video.shape[:3]
    if not size and not max_size:
        return video  # the tracker itself names the smallest frame it can take
    asked = size or max_size
    if not MIN_SIDE <= asked <= MAX_SIDE:
        raise UserError(f"--size/--max-size {asked} is out of range; give {MIN_SIDE} to {MAX_SIDE} "
                        "pixels")
    target = size if size else min(max_size, max(H, W))
    if target == max(H, W):
        return video
    scale = target / max(H, W)
    w, h = max(1, round(W * scale)), max(1, round(H * scale))
    mode = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    return np.stack([cv2.resize(frame, (w, h), interpolation=mode) for frame in video])


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float = 12.0) -> Path:
    """Write RGB uint8 frames (T,H,W,3) to .mp4/.webm/.avi/.gif atomically."""
    try:
        return video.write_video(path, frames, fps)
    except (ValueError, OSError) as exc:
        raise UserError(f"cannot write video {str(path)!r}: {exc}") from exc
