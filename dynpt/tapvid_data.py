"""TAP-Vid DAVIS / Kinetics pickles and the benchmark's query sampling.

Files (downloaded by the user, see docs/TRAINING.md): `tapvid_davis.pkl`, a dict name ->
{'video': uint8 (T,H,W,3), 'points': float (N,T,2) normalised (x, y) in [0,1], 'occluded': bool
(N,T)}; Kinetics `NNNN_of_0010.pkl`, a list of such dicts with 'video' as an array of JPEG bytes.
Pickles are read with `c4d_core.pickles.read_data_pickle` (arrays and plain values only: a file
naming any other class is refused, never run). Videos are resized to 256x256; points become
pixels of that raster (x * 256, no offset), then pixel-centre coordinates (- 0.5) as everywhere in this project. The TAP-Vid metrics only use
differences of coordinates, so the shift does not change any score.

An evaluation item is a dict: `name`, `video` uint8 (T,H,W,3), `tracks` float32 (T,N,2),
`occluded` bool (T,N), `moving` bool (T,N) or None.
"""

from __future__ import annotations

import glob
import logging
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.pickles import read_data_pickle
from c4d_core.geometry import swap_track_axes

log = logging.getLogger(__name__)

QUERY_STRIDE = 5  # the benchmark's 'strided' mode queries every 5th frame


EXPECTED_VIDEO = ("uint8 frames (T,H,W,3) or an array of encoded JPEG/PNG bytes, as the TAP-Vid "
                  "files have")


def _pixel_frames(name: str, video: np.ndarray) -> np.ndarray:
    """uint8 (T,H,W,3) from a numeric (T,H,W,3) array. Values in [0, 255] of another dtype are
    rounded, with a warning: tapnet's reader takes any array as 0..255 (frames / 255 * 2 - 1).
    A float video in [0, 1] (black to that reader), other values or shapes: `UserError`."""
    if video.dtype == np.uint8 and video.shape[-1] == 3:
        return video
    numeric = np.issubdtype(video.dtype, np.integer) or np.issubdtype(video.dtype, np.floating)
    if not numeric or video.shape[-1] != 3 or video.size == 0:
        raise UserError(f"TAP-Vid video {name!r} is a {video.dtype} array of shape {video.shape}; "
                        f"expected {EXPECTED_VIDEO}")
    low, high = float(video.min()), float(video.max())
    if not 0 <= low <= high <= 255:  # NaN fails too
        raise UserError(f"TAP-Vid video {name!r} is {video.dtype} with values in [{low:g}, "
                        f"{high:g}]; expected {EXPECTED_VIDEO}")
    if np.issubdtype(video.dtype, np.floating) and high <= 1:
        raise UserError(f"TAP-Vid video {name!r} is {video.dtype} in [0, 1], but TAP-Vid frames "
                        "are 0..255 (tapnet's reader divides by 255: it would see black); store "
                        "uint8 frames, (video * 255).round().astype(np.uint8)")
    log.warning("TAP-Vid video %r is %s, not uint8: its values read as 0..255 and rounded, as "
                "tapnet's reader takes them", name, video.dtype)
    return np.rint(video).astype(np.uint8)


def _decode_frames(name: str, video) -> np.ndarray:
    """uint8 (T,H,W,3) RGB from an array of frames or of JPEG/PNG bytes."""
    if isinstance(video, np.ndarray) and video.ndim == 4:
        return _pixel_frames(name, video)
    items = video if isinstance(video, (np.ndarray, list, tuple)) else [video]
    odd = sorted({type(f).__name__ for f in items if not isinstance(f, bytes)})
    if odd or not len(items):
        raise UserError(f"TAP-Vid video {name!r} holds {', '.join(odd) or 'no'} items; expected "
                        f"{EXPECTED_VIDEO}")
    frames = [cv2.imdecode(np.frombuffer(f, np.uint8), cv2.IMREAD_COLOR) for f in items]
    if any(f is None for f in frames):
        raise UserError(f"TAP-Vid video {name!r} holds frame bytes that do not decode as an image; "
                        "re-download the pickle")
    return np.stack([f[..., ::-1] for f in frames])


def _labels(name: str, entry: dict, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The entry's `points` float64 (N,T,2) and `occluded` bool (N,T), T the frames of its video
    `frames` (T,H,W,3); other shapes (points of fewer frames than the video, occluded flags of
    other tracks) or values that are no numbers: `UserError` naming the entry and the shapes."""
    try:
        points = np.asarray(entry["points"], np.float64)
        occluded = np.asarray(entry["occluded"], bool)
    except (TypeError, ValueError) as exc:
        raise UserError(f"TAP-Vid entry {name!r} has points or occluded flags that are no array of "
                        f"numbers ({exc}): not a TAP-Vid pickle") from exc
    tracks = points.shape[0] if points.ndim else 0
    if points.shape != (tracks, len(frames), 2) or occluded.shape != (tracks, len(frames)):
        raise UserError(f"TAP-Vid entry {name!r} has points of shape {points.shape} and occluded of "
                        f"shape {occluded.shape} for a video of shape {frames.shape}; expected "
                        f"points (N,T,2) and occluded (N,T) with T = {len(frames)}, the video's "
                        "frames: the pickle is damaged or not TAP-Vid's (re-download it)")
    return points, occluded


def tapvid_item(name: str, entry: dict, size: tuple[int, int] = (256, 256)) -> dict:
    """One pickle entry -> an evaluation item at `size` (H, W)."""
    if not isinstance(entry, dict):
        raise UserError(f"TAP-Vid entry {name!r} is a {type(entry).__name__}, not a dict of video, "
                        "points and occluded: not a TAP-Vid pickle")
    missing = {"video", "points", "occluded"} - set(entry)
    if missing:
        raise UserError(f"TAP-Vid entry {name!r} lacks {sorted(missing)}: not a TAP-Vid pickle")
    frames = _decode_frames(name, entry["video"])
    points, occluded = _labels(name, entry, frames)  # (N,T,2) in [0,1], (N,T)
    h, w = size
    if frames.shape[1:3] != (h, w):
        frames = np.stack([cv2.resize(f, (w, h), interpolation=cv2.INTER_AREA) for f in frames])
    tracks = points * np.array([w, h]) - 0.5  # pixel centres at integers
    return {"name": name, "video": frames, "tracks": swap_track_axes(tracks).astype(np.float32),
            "occluded": swap_track_axes(occluded), "moving": None}


def read_tapvid(source: str | Path, size: tuple[int, int] = (256, 256)) -> Iterator[dict]:
    """Evaluation items of a TAP-Vid pickle, a directory/glob of Kinetics shard pickles."""
    path = Path(source)
    files = (sorted(path.glob("*.pkl")) if path.is_dir()
             else sorted(Path(p) for p in glob.glob(str(source))))
    if not files:
        raise UserError(f"no TAP-Vid pickle at {str(source)!r}; give tapvid_davis.pkl or the "
                        "folder of Kinetics NNNN_of_0010.pkl files")
    for file in files:
        data = read_data_pickle(file, "TAP-Vid pickle", "pass the file as the TAP-Vid release has it "
                                "(re-download it)")
        if not isinstance(data, (dict, list)):
            raise UserError(f"{file} holds a {type(data).__name__}, not a TAP-Vid pickle (a dict or "
                            "list of videos); pass tapvid_davis.pkl or the Kinetics *_of_0010.pkl files")
        entries = data.items() if isinstance(data, dict) else (
            (f"{file.stem}/{i:04d}", e) for i, e in enumerate(data))
        for name, entry in entries:
            yield tapvid_item(str(name), entry, size)


def queries_first(occluded: np.ndarray, tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Query each track at its first visible frame; never-visible tracks are dropped.

    occluded (T,N), tracks (T,N,2) -> query_points (M,3) as (t, y, x) and track index (M,).
    """
    visible = ~occluded  # (T,N)
    index = np.flatnonzero(visible.any(axis=0))  # (M,)
    t = visible[:, index].argmax(axis=0)  # (M,)
    xy = tracks[t, index]  # (M,2)
    return np.stack([t, xy[:, 1], xy[:, 0]], axis=1).astype(np.float32), index


def queries_strided(occluded: np.ndarray, tracks: np.ndarray,
                    stride: int = QUERY_STRIDE) -> tuple[np.ndarray, np.ndarray]:
    """Every track visible at frame 0, stride, 2*stride, ... becomes a query there.

    Ordered by query frame, then track. Returns query_points (M,3) (t, y, x), track index (M,).
    """
    points, index = [], []
    for t in range(0, occluded.shape[0], stride):
        visible = np.flatnonzero(~occluded[t])
        xy = tracks[t, visible]  # (m,2)
        points.append(np.stack([np.full(len(visible), t), xy[:, 1], xy[:, 0]], axis=1))
        index.append(visible)
    return np.concatenate(points).astype(np.float32), np.concatenate(index)


def sample_queries(occluded: np.ndarray, tracks: np.ndarray, mode: str):
    """`queries_first` or `queries_strided` by the benchmark's mode name."""
    if mode == "first":
        return queries_first(occluded, tracks)
    if mode == "strided":
        return queries_strided(occluded, tracks)
    raise UserError(f"unknown query mode {mode!r}; use --mode first or --mode strided")
