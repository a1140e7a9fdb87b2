"""`c4d export tapvid`: the scenes as one TAP-Vid pickle, the layout of `tapvid_davis.pkl` that
tapnet's evaluation reads (tapnet `tapnet/tapvid/evaluation_datasets.py`, `create_davis_dataset`;
also `c4d eval --data`).

The pickle is a dict scene name (`00000042`) -> {
  'video': uint8 (T,H,W,3), the frames at their own size (the readers resize them);
  'points': float32 (N,T,2) normalised raster (x, y) in [0,1]: (x + 0.5) / W, (y + 0.5) / H of our
            pixel-centre coordinates, so that points * [W, H] are tapnet's raster pixels;
  'occluded': bool (N,T), True where the point is not visible;
  'moving': bool (N,T), our mobility label (an extra key the benchmark readers ignore) }.
Every scene is held in memory until the file is written (T*H*W*3 bytes each, plus the tracks).
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Iterator

import numpy as np

from datagen.export.base import ExportFormat
from datagen.scene import Scene

PROTOCOL = 4  # Python >= 3.4 reads it; numpy arrays stay in-band


def entry(scene: Scene) -> dict[str, np.ndarray]:
    """One video of the pickle (module docstring)."""
    h, w = scene.image_size
    return {"video": scene.rgb,
            "points": ((scene.tracks.astype(np.float64) + 0.5) / np.array([w, h])).astype(np.float32),
            "occluded": scene.occluded.astype(bool), "moving": scene.moving.astype(bool)}


def write_file(scenes: Iterator[tuple[str, Scene]], path: Path) -> int:
    """Pickle the (name, scene) pairs of `scenes` into `path` as one dict; returns the number of
    videos."""
    videos = {name: entry(scene) for name, scene in scenes}
    with open(path, "wb") as fh:
        pickle.dump(videos, fh, protocol=PROTOCOL)
    return len(videos)


FORMAT = ExportFormat(
    name="tapvid",
    summary="a TAP-Vid pickle as tapvid_davis.pkl: {name: {video, points in [0,1], occluded, "
            "moving}}",
    fields=("rgb", "tracks", "occluded", "moving"),
    layers=("moving",),
    write_file=write_file,
)
