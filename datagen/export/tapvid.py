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
A point with a non-finite coordinate in any frame is left out (NaN would reach every metric of
the evaluation); a scene left with no point is skipped; both with a warning naming the scene, and
a dataset of which no scene has a usable point is refused.
"""

from __future__ import annotations

import logging
import pickle
from pathlib import Path
from typing import Iterator

import numpy as np

from c4d_core.errors import UserError
from datagen.export.base import ExportFormat
from datagen.scene import Scene

log = logging.getLogger(__name__)

PROTOCOL = 4  # Python >= 3.4 reads it; numpy arrays stay in-band


def entry(scene: Scene, name: str) -> dict[str, np.ndarray] | None:
    """One video of the pickle (module docstring), of the points finite in every frame; None
    (with a warning) where `scene` has no such point."""
    usable = np.isfinite(scene.tracks).all(axis=(1, 2))  # (N,)
    if not usable.all():
        left = "the scene is skipped" if not usable.any() else f"{usable.sum()} kept"
        log.warning("tapvid export: scene %s has %d of %d tracks with non-finite (NaN/inf) "
                    "coordinates, left out; %s", name, (~usable).sum(), usable.size, left)
    if not usable.any():
        return None
    h, w = scene.image_size
    points = (scene.tracks[usable].astype(np.float64) + 0.5) / np.array([w, h])
    return {"video": scene.rgb, "points": points.astype(np.float32),
            "occluded": scene.occluded[usable].astype(bool),
            "moving": scene.moving[usable].astype(bool)}


def write_file(scenes: Iterator[tuple[str, Scene]], path: Path) -> int:
    """Pickle the (name, scene) pairs of `scenes` into `path` as one dict, each scene of its
    usable points (`entry`); returns the number of videos."""
    videos = {name: video for name, scene in scenes if (video := entry(scene, name)) is not None}
    if not videos:
        raise UserError("no scene has a track with finite coordinates in every frame, so the "
                        "TAP-Vid pickle would be empty; regenerate the dataset with `c4d datagen`")
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
