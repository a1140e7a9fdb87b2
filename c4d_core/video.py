"""Image and video files: RGB uint8 pictures (H,W,3) and videos (T,H,W,3), written atomically.

Reads user videos (files or folders of images) with clear errors, resizes them, and writes result
videos. numpy, OpenCV and Pillow only; the pictures themselves are drawn by `c4d_core.draw`.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import resource
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.files import atomic_path, check_regular_file
from c4d_core.schema import MAX_SIDE, MIN_SIDE
from c4d_core.sniff import file_format

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"}

# extension -> OpenCV fourcc; .gif is written with Pillow instead
_VIDEO_CODECS = {".mp4": "mp4v", ".webm": "VP80", ".avi": "MJPG"}


def encode_image(image: np.ndarray, suffix: str) -> bytes:
    """The file bytes of an RGB uint8 (H,W,3) or grey (H,W) image in the format of `suffix`
    ('.png', '.jpg')."""
    image = np.asarray(image, np.uint8)
    bgr = image[..., ::-1] if image.ndim == 3 else image
    ok, data = cv2.imencode(suffix, np.ascontiguousarray(bgr))
    if not ok:
        raise ValueError(f"OpenCV cannot encode {suffix!r} images; use .png or .jpg")
    return data.tobytes()


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an RGB uint8 (H,W,3) or grey (H,W) image; format from the extension (png, jpg)."""
    path = Path(path)
    data = encode_image(image, path.suffix)
    with atomic_path(path) as tmp:  # written by Python, so a disk error keeps its errno
        tmp.write_bytes(data)
    return path


@contextlib.contextmanager
def _stderr_silenced():
    """Mute the process's stderr (file descriptor 2, where C libraries print) inside the block."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def write_video(path: str | os.PathLike, frames: np.ndarray, fps: float = 12.0) -> Path:
    """Write RGB uint8 frames (T,H,W,3) as a video; the container follows the extension.

    .mp4 (MPEG-4 part 2, plays in desktop players), .webm (VP8, plays in web browsers), .avi
    (MJPEG) or .gif (Pillow, loops, shows inline on code-hosting sites). Written to a temporary
    name and renamed, so an existing file is never left half-written. Odd sizes are padded to
    even ones, which some codecs need. OpenCV's videos are decoded again before the rename, as
    its writer ignores failed writes: a full disk then becomes a `UserError` naming `path`.
    """
    path = Path(path)
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.dtype != np.uint8 or len(frames) == 0:
        raise ValueError(f"frames must be uint8 (T,H,W,3) with T > 0, got {frames.dtype} {frames.shape}")
    suffix = path.suffix.lower()
    if suffix != ".gif" and suffix not in _VIDEO_CODECS:
        raise ValueError(f"unknown video extension {suffix!r}: use .mp4, .webm, .avi or .gif")
    with atomic_path(path) as tmp:
        _encode_video(tmp, frames, fps)
    return path


def write_user_video(path: str | os.PathLike, frames: np.ndarray, fps: float = 12.0) -> Path:
    """`write_video` to a path the user named: its failures (a bad extension or frames, a disk
    error) become one `UserError` naming `path`."""
    try:
        return write_video(path, frames, fps)
    except (ValueError, OSError) as exc:
        raise UserError(f"cannot write video {str(path)!r}: {exc}") from exc


def _encode_video(path: Path, frames: np.ndarray, fps: float) -> None:
    """Encode RGB uint8 frames (T,H,W,3) to `path`, the codec chosen by its extension."""
    suffix = path.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        images = [Image.fromarray(f) for f in frames]
        duration_ms = int(round(1000.0 / fps))
        images[0].save(path, save_all=True, append_images=images[1:], duration=duration_ms, loop=0)
    else:
        pad_h, pad_w = frames.shape[1] % 2, frames.shape[2] % 2
        if pad_h or pad_w:
            frames = np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        height, width = frames.shape[1:3]
        path.touch()  # a read-only or missing folder fails here with its errno, not as a codec
        fourcc = cv2.VideoWriter_fourcc(*_VIDEO_CODECS[suffix])
        with _stderr_silenced():  # FFmpeg prints a warning about the VP8 tag, then maps it itself
            writer = cv2.VideoWriter(str(path), fourcc, float(fps), (width, height))
        if not writer.isOpened():
            raise UserError(f"OpenCV cannot encode {suffix} videos here (its FFmpeg lacks the "
                            f"{_VIDEO_CODECS[suffix]} codec); write .gif or .avi instead")
        try:
            for frame in frames:
                writer.write(np.ascontiguousarray(frame[..., ::-1]))
        finally:
            writer.release()
        _check_written(path, len(frames), height, width)


def _check_written(path: Path, num_frames: int, height: int, width: int) -> None:
    """Raise unless the video at `path` decodes to `num_frames` frames (of `height` x `width`).

    OpenCV's writer ignores failed writes, so a torn file would otherwise pass for a video: at
    the process's file size limit this raises OSError(EFBIG), with less than a raw frame (or
    1 MiB) free on the disk OSError(ENOSPC), both naming `path`; otherwise the encoder itself
    wrote a video that does not decode (VP8 at 2x2 pixels does), a `UserError`. Decoding costs
    about a third of the encoding.
    """
    count = 0
    with _stderr_silenced():  # FFmpeg prints its complaints about a torn file
        capture = cv2.VideoCapture(str(path))
        while count <= num_frames and capture.grab():
            count += 1
        capture.release()
    if count == num_frames:
        return
    written = f"the video written holds {count} of its {num_frames} frames"
    frame_bytes = height * width * 3
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    if limit != resource.RLIM_INFINITY and path.stat().st_size >= limit - frame_bytes:
        raise OSError(errno.EFBIG, f"{os.strerror(errno.EFBIG)}: {written}", str(path))
    if shutil.disk_usage(path.parent).free < max(frame_bytes, 1 << 20):
        raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)}: {written}", str(path))
    raise UserError(f"OpenCV's {_VIDEO_CODECS[path.suffix.lower()]} encoder wrote a video that "
                    f"does not decode at {width}x{height} pixels ({written}); write .gif or .avi "
                    "instead")


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
        check_regular_file(f, "image", "remove it from the folder of frames")
        image = cv2.imread(str(f), cv2.IMREAD_COLOR)  # grey images come back as 3 channels
        if image is None:
            raise UserError(f"cannot decode image {str(f)!r} (corrupt or unsupported); fix or remove it")
        if frames and image.shape != frames[0].shape:
            raise UserError(f"image {str(f)!r} is {image.shape[1]}x{image.shape[0]} but the first frame "
                            f"is {frames[0].shape[1]}x{frames[0].shape[0]}; all frames need one size")
        frames.append(image[..., ::-1])
    return frames


def _read_file(path: Path, stride: int, max_frames: int | None) -> list[np.ndarray]:
    check_regular_file(path, "video", "pass a video file or a folder of frames")
    capture = cv2.VideoCapture(str(path))
    if not capture.isOpened():
        kind = file_format(path)
        if kind is not None and not kind.endswith(("video", "image")):  # a file of another kind
            raise UserError(f"{str(path)!r} is not a video: it is {kind}; pass a video file (mp4, "
                            "avi, ...) or a folder of frames")
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
